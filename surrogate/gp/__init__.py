"""GP classifiers psi_phi(z) = p(phi' = 1 | phi, z) that replace the internal model, over the
abstraction's declared inputs z (e.g. the signal the internal network sees, or the paper's (m, L)).

Train with :func:`fit_psi` (or :func:`fit_classifier` per origin state), persist with
:func:`save_psi` / :func:`load_psi`, and tabulate with :class:`PsiLookupTable` for fast
simulation.
"""

from __future__ import annotations

from surrogate.gp.figures import binned_frequencies, plot_psi, plot_training_history, psi_grid_frame
from surrogate.gp.fitted import FittedClassifier, Normalizer
from surrogate.gp.lookup import PsiFunction, PsiLookupTable, StackedPsiLookup
from surrogate.gp.metrics import classification_metrics, last_tenth_drop
from surrogate.gp.model import KERNELS, PsiGP, make_kernel
from surrogate.gp.predictor import PsiClassifier, data_domain, fit_psi, load_psi, save_psi
from surrogate.gp.settings import GPSettings
from surrogate.gp.training import fit_classifier

__all__ = [
    "KERNELS",
    "FittedClassifier",
    "GPSettings",
    "Normalizer",
    "PsiClassifier",
    "PsiFunction",
    "PsiGP",
    "PsiLookupTable",
    "StackedPsiLookup",
    "binned_frequencies",
    "classification_metrics",
    "data_domain",
    "fit_classifier",
    "fit_psi",
    "last_tenth_drop",
    "load_psi",
    "make_kernel",
    "plot_psi",
    "plot_training_history",
    "psi_grid_frame",
    "save_psi",
]
