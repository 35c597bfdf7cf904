"""The chain kinds (``gp.lumps``, ``gp.history``, ``gp.class_moves``) looked up by their config
strings: :func:`chain_kind` (the strings -> the registered kind), :func:`fit_chain` (the gp
group's chain, validated), :func:`exact_clock` and :func:`exact_chain` (``decision=exact``'s,
validated) and :func:`resolve_auto_lumps` (``gp.lumps=auto``). The kinds are one module each,
registered when this module imports them (:data:`KIND_MODULES`): :class:`TwoStateChain`
(:mod:`~surrogate.kinds.two_state`), :class:`SwitchClock` (:mod:`~surrogate.kinds.clock`) and
:class:`KLumps` (:mod:`~surrogate.kinds.klumps`), on :class:`ChainKind`
(:mod:`~surrogate.kinds.base`); their names stay importable from here."""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

from surrogate.config import group_config, non_negative, positive
from surrogate.errors import ConfigError
from surrogate.gp.class_relaxation import DEFAULT_CELLS, DEFAULT_LAGS, relaxation_cells
from surrogate.gp.classes import DEFAULT_MAX_LABEL_WEIGHT
from surrogate.gp.model import DEFAULT_MEAN as DEFAULT_MEAN
from surrogate.gp.training import GPSettings

# the chain kinds, each one module that registers its kind (register_chain_kind) when imported
# here: a new kind adds its module to this import and to KIND_MODULES (and its recipe,
# conf/gp/<name>.yaml; docs/architecture.md)
from surrogate.kinds import clock, klumps, phases, two_state
from surrogate.kinds.base import AUTO_RECIPES as AUTO_RECIPES
from surrogate.kinds.base import (
    CHAIN_KINDS,
    ChainKind,
    find_kind,
    kind_values,
    kinds_with,
)
from surrogate.kinds.base import LayerRequest as LayerRequest
from surrogate.kinds.base import register_chain_kind as register_chain_kind
from surrogate.kinds.clock import GP_CLOCK as GP_CLOCK
from surrogate.kinds.clock import SwitchClock as SwitchClock
from surrogate.kinds.decision import DecisionMode
from surrogate.kinds.klumps import GP_CLASSES as GP_CLASSES
from surrogate.kinds.klumps import KLumps as KLumps
from surrogate.kinds.two_state import TwoStateChain as TwoStateChain
from surrogate.models.capabilities import class_bins_of, lump_classes_of
from surrogate.simulate.memory import history_setting
from surrogate.validation import known_keys

#: the modules of the chain kinds (imported above, which registers their kinds)
KIND_MODULES = (two_state, clock, klumps, phases)


def chain_kind(
    lumps: str = "phi", history: str = "none", class_moves: str = "learned"
) -> ChainKind:
    """The registered kind named by the config's strings, already validated (:func:`fit_chain`,
    :func:`exact_chain`): one instance per kind and ``class_moves``.

    Raises:
        ValueError: a combination no kind has (classes with a clock, relaxing two-state bins).
    """
    kind = find_kind(lumps, history, class_moves)
    if kind is None:
        raise ValueError(f"no chain kind with lumps={lumps!r}, history={history!r}, "
                         f"class_moves={class_moves!r}")  # fmt: skip
    return kind


TWO_STATE = chain_kind()
SWITCH_CLOCK = chain_kind(history=SwitchClock.history)


class FitChain(NamedTuple):
    """The gp group's chain, validated (:func:`fit_chain`): its kind, the GP settings and the
    inputs it fits (a clock adds its axis), the clock's cap and the K-lumps law's options
    (validated for every fit, read by K lumps only)."""

    kind: ChainKind
    gp: GPSettings
    inputs: tuple[str, ...]
    max_age: float
    min_events: float | None
    max_label_weight: float
    relaxation_cells: int
    relaxation_lags: tuple[float, ...]


def fit_chain(
    gp_config: Mapping[str, Any],
    gp: GPSettings,
    inputs: tuple[str, ...],
    internal: object,
    model_name: str,
) -> FitChain:
    """The chain a fit's gp group asks for (``gp.history``, ``gp.max_age``, ``gp.lumps``,
    ``gp.class_moves`` and the K-lumps law's options), checked against the model's
    ``internal`` model (``model_name`` for the messages), with the GP settings ``gp`` over the
    model's abstraction ``inputs`` as the kind fits them (:meth:`ChainKind.configure`: a switch
    clock is psi's last input, with its own bin count, ``gp.clock_bins``). The kind-specific
    refusals are the kinds' (:meth:`ChainKind.check_fit`, :meth:`ChainKind.configure`)."""
    history, max_age = _history(gp_config, "gp")
    lumps = gp_config.get("lumps", "phi")
    lumpings = kind_values("lumps")
    if lumps not in lumpings:
        raise ConfigError(f"gp.lumps must be one of {lumpings}, got {lumps!r}")
    for owner in kinds_with(lumps=lumps):
        owner.check_fit(history, internal, model_name)
    min_events = gp_config.get("min_events")  # null: by the labels
    if min_events is not None:
        min_events = non_negative(gp_config, "min_events", "gp.")
    max_label_weight = positive({"max_label_weight": DEFAULT_MAX_LABEL_WEIGHT, **gp_config},
                                "max_label_weight", "gp.")  # fmt: skip
    if max_label_weight < 1:
        raise ConfigError(f"gp.max_label_weight must be >= 1, got {max_label_weight!r}")
    moves, cells, lags = _class_moves(gp_config)
    kind = find_kind(str(lumps), history, moves)
    if kind is None:
        raise _no_kind(str(lumps), history, moves)
    gp, inputs = kind.configure(gp_config, gp, inputs, internal, model_name)
    # the stationary sample grows with the bins it estimates a law over (null n_cells); only
    # a relaxing kind asks for the bins (classes: auto may simulate to choose them)
    bins = class_bins_of(internal) if kind.relaxation else None
    cells = relaxation_cells(len(set(bins or ())), cells)
    return FitChain(kind, gp, inputs, max_age, None if min_events is None else float(min_events),
                    float(max_label_weight), cells, lags)  # fmt: skip


def _history(config: Mapping[str, Any], group: str) -> tuple[str, float]:
    """``<group>.history`` (one of the registered kinds') and ``<group>.max_age`` validated."""
    return history_setting(config.get("history"), config.get("max_age", 5.0), group,
                           kind_values("history"))  # fmt: skip


def _no_kind(lumps: str, history: str, moves: str) -> ConfigError:
    """Why no registered kind has these gp strings (each is some kind's): ``gp.class_moves``
    names another kind's option, or the combination is no kind's."""
    owners = [k for k in CHAIN_KINDS if moves in k.class_moves_choices]
    if owners and kinds_with(lumps=lumps, history=history):
        return ConfigError(f"gp.class_moves={moves} is a {owners[0].title} option: use "
                           f"gp={owners[0].recipe}")  # fmt: skip
    kinds = [f"{k.__name__} (gp.lumps={k.lumps}, gp.history={k.history}, gp.class_moves in "
             f"{list(k.class_moves_choices)})" for k in CHAIN_KINDS]  # fmt: skip
    return ConfigError(f"no chain kind has gp.lumps={lumps}, gp.history={history} and "
                       f"gp.class_moves={moves}; the kinds: {', '.join(kinds)}")  # fmt: skip


def _class_moves(gp_config: Mapping[str, Any]) -> tuple[str, int | None, tuple[float, ...]]:
    """``gp.class_moves`` and ``gp.relaxation`` ({n_cells, lags}) validated."""
    moves = gp_config.get("class_moves") or "learned"
    choices = kind_values("class_moves_choices")
    if moves not in choices:
        raise ConfigError(f"gp.class_moves must be one of {choices}, got {moves!r}")
    options = known_keys(gp_config.get("relaxation") or {}, ("n_cells", "lags"), "gp.relaxation")
    cells = options.get("n_cells")  # null: by the bins (relaxation_cells)
    if cells is not None and (isinstance(cells, bool) or not isinstance(cells, int) or cells < 10):
        raise ConfigError(f"gp.relaxation.n_cells must be an integer >= 10 or null (150 per "
                          f"bin, at least {DEFAULT_CELLS}), got {cells!r}")  # fmt: skip
    lags = options.get("lags", DEFAULT_LAGS)
    if (not isinstance(lags, Sequence) or isinstance(lags, str) or len(lags) < 2
            or any(isinstance(v, bool) or not isinstance(v, int | float) or not v > 0
                   or not math.isfinite(v) for v in lags)
            or any(b <= a for a, b in itertools.pairwise(lags))):  # fmt: skip
        raise ConfigError(f"gp.relaxation.lags must be at least two positive, increasing "
                          f"seconds, got {lags!r}")  # fmt: skip
    return str(moves), cells, tuple(float(v) for v in lags)


def exact_clock(
    config: Mapping[str, Any], mode: DecisionMode, internal: Any, model_name: str
) -> tuple[str, float]:
    """``decision=exact``'s ``decision.history`` and ``decision.max_age`` (of the decision group
    ``config``, run in ``mode``), checked against the model's ``internal`` model by the kinds
    with that history (:meth:`ChainKind.check_exact_history`: an exact psi with a clock needs
    a table and the model's ``exact_age_psi``)."""
    history, max_age = _history(config, "decision")
    for owner in kinds_with(history=history):
        owner.check_exact_history(mode, internal, model_name)
    return history, max_age


def exact_chain(
    config: Mapping[str, Any], history: str, mode: DecisionMode, internal: Any, model_name: str
) -> ChainKind:
    """The chain ``decision=exact`` drives with the model's exact law: ``decision.lumps`` of the
    decision group ``config`` with the clock :func:`exact_clock` validated (``history``), run
    in ``mode``, checked against the model's ``internal`` model by the kinds with that lumps
    (:meth:`ChainKind.check_exact`)."""
    lumps = config.get("lumps", "phi")
    lumpings = kind_values("lumps")
    if lumps not in lumpings:
        raise ConfigError(f"decision.lumps must be one of {lumpings}, got {lumps!r}")
    for owner in kinds_with(lumps=lumps):
        owner.check_exact(history, mode, internal, model_name)
    return chain_kind(str(lumps), history)


#: a gp key's value that leaves it to the recipe (conf/gp/auto.yaml: ``lumps`` and the keys the
#: recipes set apart from gp=svgp's)
AUTO = "auto"


def resolve_auto_lumps(gp_config: Mapping[str, Any], model: Any) -> dict[str, Any]:
    """``gp_config`` with ``lumps: auto`` resolved to the best measured chain for ``model``: the
    K-lumps chain (``gp=classes``'s recipe) where its internal model declares classes finer than
    phi and no switch clock is asked for (``gp.history=none``), else the two-state chain
    (``gp=svgp``). A key given a value is the user's, and kept; a key absent, or one that
    conf/gp/auto.yaml leaves ``auto`` (those the recipes set apart from ``gp=svgp``'s, so that a
    value given is told from the default even where it equals ``gp=svgp``'s), takes the chosen
    recipe's value: ``gp=auto`` on E. coli is the same fit (the same directory) as
    ``gp=classes``. With a chain named (any other ``lumps``), the keys left ``auto`` take
    ``gp=svgp``'s values (what ``gp=auto`` is based on) and the rest is returned unchanged.

    Example:
        >>> resolve_auto_lumps({**group_config("gp", "auto")}, ecoli)["n_inducing"]  # doctest: +SKIP
        32
    """
    config = dict(gp_config)
    auto = is_auto(gp_config)
    name = AUTO_RECIPES[1]
    if auto and lump_classes_of(model.internal) is not None:
        name = AUTO_RECIPES[0] if config.get("history", "none") == "none" else name
    recipe, left = group_config("gp", name), _left_to_recipe()
    for key, value in recipe.items():
        if (key in left and _is_auto_value(config.get(key))) or (auto and key not in config):
            config[key] = value
    if auto:
        config["lumps"] = recipe.get("lumps", "phi")
    return config


def _left_to_recipe() -> set[str]:
    """The keys conf/gp/auto.yaml leaves to the recipe: ``auto`` there, not in ``gp=svgp``
    (whose ``labels: auto`` is a choice of its own)."""
    auto, base = group_config("gp", "auto"), group_config("gp", AUTO_RECIPES[1])
    return {k for k, v in auto.items() if _is_auto_value(v) and base.get(k) != v}


def _is_auto_value(value: Any) -> bool:
    """Whether a gp key's ``value`` is :data:`AUTO`."""
    return isinstance(value, str) and value == AUTO


def is_auto(gp_config: Mapping[str, Any]) -> bool:
    """Whether the gp group leaves the chain to :func:`resolve_auto_lumps` (``gp.lumps=auto``)."""
    return _is_auto_value(gp_config.get("lumps"))
