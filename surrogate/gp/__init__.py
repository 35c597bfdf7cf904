"""GP classifiers psi_phi(m, L) = p(phi' = RUN | phi, m, L) that replace the internal model.

Train with :func:`fit_psi` (or :func:`fit_classifier` per origin state), persist with
:func:`save_psi` / :func:`load_psi`, and tabulate with :class:`PsiLookupTable` for fast
simulation.
"""

from __future__ import annotations

from surrogate.gp.figures import plot_psi_surfaces, plot_training_history, psi_grid_frame
from surrogate.gp.lookup import PsiFunction, PsiLookupTable
from surrogate.gp.metrics import classification_metrics
from surrogate.gp.model import KERNELS, PsiGP, make_kernel
from surrogate.gp.predictor import PsiClassifier, data_domain, fit_psi, load_psi, save_psi
from surrogate.gp.training import FittedClassifier, GPSettings, Normalizer, fit_classifier

__all__ = [
    "KERNELS",
    "FittedClassifier",
    "GPSettings",
    "Normalizer",
    "PsiClassifier",
    "PsiFunction",
    "PsiGP",
    "PsiLookupTable",
    "classification_metrics",
    "data_domain",
    "fit_classifier",
    "fit_psi",
    "load_psi",
    "make_kernel",
    "plot_psi_surfaces",
    "plot_training_history",
    "psi_grid_frame",
    "save_psi",
]
