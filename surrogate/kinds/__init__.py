"""The kinds of an abstraction and of a run's decision layer, as objects (issue 40).

The configs still name a chain by strings (``gp.lumps``, ``gp.history``, ``gp.class_moves``;
``decision.name``, ``decision.mode``), and this package is the one place that reads them: each
string is looked up here once, where the settings are made, and everything after that asks the
kind object (``kind.clock``, ``kind.classes``, ``kind.fit_identity(...)``) instead of comparing
names. A chain kind owns what the settings used to decide about it by string: which
combinations it refuses (with the messages users know), the keys it adds to or drops from a
fit's identity (identities are hashed into directory names, so every stored fit is still
found), what train must record for it (switch clocks, class labels) and the shipped recipe its
commands name. It also owns what train and simulate do with it, which they ask of it instead of
branching on its flags: :meth:`ChainKind.training_rows` (the transitions its fit reads),
:meth:`~ChainKind.fit` (what it fits beyond the classifiers psi, which every kind fits),
:meth:`~ChainKind.write` and :meth:`~ChainKind.load` (its own artefact, its
:attr:`~ChainKind.files`), :meth:`~ChainKind.decision_layer` (its learned layer) and
:meth:`~ChainKind.exact_layer` (decision=exact's), both asked with a :class:`LayerRequest`.

The chain kinds are plug-ins: each is one module that defines its :class:`ChainKind` subclass
with :func:`register_chain_kind` and declares the config strings that select it (its
``lumps``, ``history`` and ``class_moves_choices``) and the gp keys only it reads
(``gp_keys``). :func:`chain_kind` looks the strings up in the registry (:data:`CHAIN_KINDS`),
and the settings' messages list the registered values (``gp.lumps must be one of ['phi',
'classes']``). The kind-specific checks are hooks the kind overrides (``check_fit``,
``configure``, ``check_exact_history``, ``check_exact``, ``check_mode``, ``check_start``), so
:func:`fit_chain`, :func:`exact_clock` and :func:`exact_chain` compare no kind's name.

The config's ``gp.lumps``/``gp.history``/``gp.class_moves`` stay strings read by
:func:`chain_kind`, not a ``_target_`` in ``conf/gp/``: those strings are keys of every stored
fit's identity (hashed into its directory name, pinned in tests/test_kinds.py) and the words of
the commands (``gp.history=age``, ``gp.lumps=auto``, ``decision.lumps=classes``), so a kind built
by ``_target_`` would either enter the identities (new directories for every stored fit) or
have to be mapped back to the same strings, which is what the registry does.

* :class:`ChainKind` and its three kinds: :class:`TwoStateChain` (``gp.lumps=phi``,
  ``gp.history=none``), :class:`SwitchClock` (``gp.history=age``) and :class:`KLumps`
  (``gp.lumps=classes``, with ``gp.class_moves`` learned or relaxation).
* :func:`chain_kind` (the strings -> the kind), :func:`fit_chain` (the gp group's chain,
  validated), :func:`exact_clock` and :func:`exact_chain` (``decision=exact``'s, validated),
  :func:`resolve_auto_lumps` (``gp.lumps=auto``: the best measured chain for a model).
* :class:`DecisionKind` and :class:`DecisionMode`: ``decision.name`` (full, abstract, exact)
  and ``decision.mode`` (lookup, classifier, direct), :func:`decision_kind`.

The modules: :mod:`~surrogate.kinds.base` (:class:`ChainKind`, the chain over phi's behaviour
that every kind inherits; the registry, :func:`register_chain_kind`; :class:`LayerRequest`),
one module per kind (:mod:`~surrogate.kinds.two_state`, :mod:`~surrogate.kinds.clock` with
:func:`exact_clock_decision`, :mod:`~surrogate.kinds.klumps` with
:func:`learned_class_decision` and :func:`exact_class_decision`),
:mod:`~surrogate.kinds.chains` (imports the kinds' modules, :data:`KIND_MODULES`, which
registers them; :func:`chain_kind`, :func:`fit_chain`, :func:`exact_clock`,
:func:`exact_chain`, :func:`resolve_auto_lumps`), :mod:`~surrogate.kinds.decision` (the
decision layers and modes, :func:`decision_identity`), :mod:`~surrogate.kinds.fits` (the
K-lumps chain's fit and :func:`load_class_chain`), :mod:`~surrogate.kinds.layers` (the layers
the kinds share: :func:`psi_decision`, :func:`abstract_decision`, :func:`exact_decision`) and
:mod:`~surrogate.kinds.files` (the fit's file names :data:`PSI` and :data:`CLASS_CHAIN`, which
import nothing: this package imports the others, and torch, gpytorch and the simulator with
them, only when one of their names is first used, so that :mod:`surrogate.stages.artefacts`
stays cheap to import).

A new chain kind is one module and one yaml: ``surrogate/kinds/<name>.py`` (its class with
:func:`register_chain_kind`: its strings, flags, gp keys and checks; its fit, artefact and
layers where it has its own), ``conf/gp/<name>.yaml`` (its recipe), and its module's name in
:data:`KIND_MODULES` (the import above it in :mod:`~surrogate.kinds.chains`);
docs/architecture.md counts the files. tests/kinds/ registers one from outside the package.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from surrogate.kinds.files import CLASS_CHAIN as CLASS_CHAIN
from surrogate.kinds.files import PSI as PSI

if TYPE_CHECKING:
    from surrogate.kinds.base import CHAIN_KINDS as CHAIN_KINDS
    from surrogate.kinds.base import FIT_GP_KEYS as FIT_GP_KEYS
    from surrogate.kinds.base import JUMP_ROWS as JUMP_ROWS
    from surrogate.kinds.base import LayerRequest as LayerRequest
    from surrogate.kinds.base import kind_gp_keys as kind_gp_keys
    from surrogate.kinds.base import register_chain_kind as register_chain_kind
    from surrogate.kinds.chains import (
        AUTO_RECIPES,
        DEFAULT_MEAN,
        GP_CLASSES,
        GP_CLOCK,
        KIND_MODULES,
        SWITCH_CLOCK,
        TWO_STATE,
        ChainKind,
        FitChain,
        KLumps,
        SwitchClock,
        TwoStateChain,
        chain_kind,
        exact_chain,
        exact_clock,
        fit_chain,
        is_auto,
        resolve_auto_lumps,
    )
    from surrogate.kinds.clock import exact_clock_decision as exact_clock_decision
    from surrogate.kinds.decision import (
        DECISION_KINDS,
        LOOKUP,
        DecisionKind,
        DecisionMode,
        decision_identity,
        decision_kind,
        mode_kind,
    )
    from surrogate.kinds.fits import RELAXATION_SEED_OFFSET as RELAXATION_SEED_OFFSET
    from surrogate.kinds.fits import load_class_chain as load_class_chain
    from surrogate.kinds.klumps import exact_class_decision as exact_class_decision
    from surrogate.kinds.klumps import learned_class_decision as learned_class_decision
    from surrogate.kinds.layers import abstract_decision as abstract_decision
    from surrogate.kinds.layers import exact_decision as exact_decision
    from surrogate.kinds.layers import psi_decision as psi_decision

__all__ = [
    "AUTO_RECIPES",
    "CHAIN_KINDS",
    "DECISION_KINDS",
    "DEFAULT_MEAN",
    "FIT_GP_KEYS",
    "GP_CLASSES",
    "GP_CLOCK",
    "JUMP_ROWS",
    "KIND_MODULES",
    "LOOKUP",
    "SWITCH_CLOCK",
    "TWO_STATE",
    "ChainKind",
    "DecisionKind",
    "DecisionMode",
    "FitChain",
    "KLumps",
    "LayerRequest",
    "SwitchClock",
    "TwoStateChain",
    "chain_kind",
    "decision_identity",
    "decision_kind",
    "exact_chain",
    "exact_clock",
    "fit_chain",
    "is_auto",
    "kind_gp_keys",
    "mode_kind",
    "register_chain_kind",
    "resolve_auto_lumps",
]


def __getattr__(name: str) -> Any:
    """A name of the kinds' modules (every name :mod:`surrogate.kinds` had as one module),
    imported when first used: importing the package (as :mod:`surrogate.kinds.files` does)
    imports neither them nor torch, gpytorch and the simulator they import (~2 s)."""
    if name.startswith("__") or (Path(__file__).parent / f"{name}.py").exists():  # a module
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from surrogate.kinds import base, chains, clock, decision, fits, klumps, layers

    for module in (chains, base, clock, klumps, decision, fits, layers):
        if hasattr(module, name):
            return getattr(module, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
