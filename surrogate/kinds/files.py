"""The fit's file names that the kinds read and write: imported by
:mod:`surrogate.stages.artefacts` alone, so this module imports nothing (the rest of the
kinds import torch, gpytorch and the simulator)."""

#: the fit's files that the kinds read and write (stages/artefacts.py re-exports them): the
#: classifiers psi, which every kind fits, and the K-lumps chain's learned law (gp.lumps=classes),
#: a ClassTable's state
PSI = "psi.pt"
CLASS_CHAIN = "class_chain.pt"
#: the hidden-phase chain (gp.lumps=phases): its table's and its law's states
PHASE_CHAIN = "phase_chain.pt"
