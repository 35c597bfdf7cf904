"""Settings of the measured choice of the chain kind (``gp=auto``, ``gp.choice``; issue 52).

``gp=auto`` (the default) leaves the chain to a measurement: the candidate kinds are fitted on
one collection and scored on a held-out full-model run (:mod:`surrogate.stages.choice`). Its
settings are resolved when the train settings are made
(:meth:`~surrogate.stages.settings.train.TrainSettings.from_config`): where the choice of this
collection is stored, ``gp=auto`` *is* the chosen candidate (its fit, its directory); where it
is not, the entries that train make it first (:func:`surrogate.stages.choice.settle`) and an
entry that only reads (``simulate.py``) is refused naming the command that makes it.

* :class:`ChoiceSettings`: ``gp.choice`` validated (how, the clock's caps, the held-out run,
  the tie and duration rules, the candidates' optimiser);
* :func:`candidate_groups`: the candidates' gp groups;
* :class:`PendingChoice`, :func:`collecting_pending`: a choice to make, gathered while the
  settings are checked.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from surrogate.config import field_config, group_config
from surrogate.diagnosis.remedies import RELAXING_CANDIDATE
from surrogate.errors import ConfigError, MissingArtefactError
from surrogate.gp.class_relaxation import CLASS_MOVES, check_shared_bins
from surrogate.io import read_json
from surrogate.kinds import CHAIN_KINDS, SWITCH_CLOCK
from surrogate.kinds.scoring import FIRST_SWITCH, FROM_START, LIKELIHOOD_FROM, clock_name
from surrogate.models.capabilities import class_bins_of, lump_classes_of
from surrogate.validation import known_keys

#: the record of a made choice, in its directory (``data/choice/...``)
CHOICE = "choice.json"
SCORES = "scores.csv"
#: gp.choice.by: measure (fit and score the candidates) | rule (the rule of issue 40: K lumps
#: where the model declares classes, else the two-state chain)
BY = ("measure", "rule")
#: gp.choice.optimizer: lbfgs (every candidate fitted by L-BFGS, 200 iterations: ~5x faster
#: than the recipes' Adam, docs/performance.md) | newton (by Newton's q*, 200 steps: the
#: binned fit solved exactly, gp.optimizer=newton) | recipe (each recipe's own optimiser)
OPTIMIZERS = ("lbfgs", "newton", "recipe")
#: what gp.choice.optimizer=lbfgs sets in each candidate (L-BFGS takes no natural gradient)
LBFGS = {"optimizer": "lbfgs", "epochs": 200, "natural_gradient": False}
#: what gp.choice.optimizer=newton sets in each candidate (gp=classes' recipe, for every kind)
NEWTON = {"optimizer": "newton", "epochs": 200, "natural_gradient": False}
#: the candidates' scoring keys per gp.choice.optimizer (recipe: none)
SCORING_KEYS = {"lbfgs": LBFGS, "newton": NEWTON}
#: every fit the choice makes (the candidates' to score them, the chosen one's with its recipe)
#: runs on one torch thread, in as many processes as ``gp.choice.workers`` says: the same fits
#: whatever the worker count and the machine's cores (a fit's float reductions depend on its
#: threads), and these small fits gain little from a second thread (E. coli's K-lumps step:
#: 27 ms on two, 26 ms of CPU on one)
FIT_THREADS = 1
#: gp.choice.kinds: the candidates' families (each clock cap is one ``clock`` candidate; K lumps
#: only where the model declares classes, and K lumps whose bins relax, ``relaxation``, only
#: where they are bins both lumps share; the registered candidate kinds by their recipe)
FAMILIES = ("two-state", "clock", "classes", "relaxation", "phases")
#: the family of K lumps whose bins relax (its cost: a stationary full-model sample)
RELAXING_FAMILY = FAMILIES[3]
#: the candidates trained ahead with their recipe (``gp.choice.ahead``): K lumps, the rule's
#: chain where the model declares classes (chosen on E. coli for every seed measured). Not the
#: two-state chain, the rule's elsewhere: chosen on none of the networks with memory measured,
#: its fit ahead cost the toggle switch ~70 s of a worker per choice for nothing
AHEAD_CANDIDATES = ("classes",)
DEFAULTS: dict[str, Any] = {
    "by": "measure",
    "kinds": list(FAMILIES),
    "max_ages": [1.0, 2.0, 5.0],
    "n_cells": 1000,
    "t_end": 50.0,
    "equilibration_time": 10.0,
    "tie_se": 1.0,
    "duration_tolerance": 0.03,
    "optimizer": "lbfgs",
    "refit": True,
    "ahead": True,
    "clock_inducing": 64,
    "extend": 2,
    "workers": "auto",
    "fields": None,
    "spread_tolerance": None,
    "likelihood_from": FROM_START,
    "draws": 4,
    "closed_loop": False,
    "max_cells": "auto",
}


@dataclass(frozen=True)
class ChoiceSettings:
    """``gp.choice`` validated: how (``by``), the clock's caps, the held-out run, the tie rule
    (``tie_se`` standard errors), the durations a candidate must hold to be chosen
    (``duration_tolerance``: the means' relative difference per lump) and the candidates'
    optimiser."""

    by: str
    kinds: tuple[str, ...]
    max_ages: tuple[float, ...]
    n_cells: int
    t_end: float
    equilibration_time: float
    tie_se: float
    duration_tolerance: float
    optimizer: str
    #: clocks the choice may add, each at twice the largest cap, while the best is a clock at
    #: the largest cap tried (the memory reaches past it: Tyson's oscillator, period 3.5 s)
    extend: int = 2
    #: the chosen candidate trained with its recipe's own optimiser (gp.choice.optimizer=lbfgs
    #: scores the candidates; E. coli's K lumps by L-BFGS left one seed of two off the noise
    #: floor at 1e5 cells, by Adam none)
    refit: bool = True
    #: processes fitting the candidates side by side (``gp.choice.workers``; "auto": one per
    #: usable core up to the candidates' count on the CPU, one on a GPU). Not in the identity:
    #: each fit is the same whichever process makes it (:data:`FIT_THREADS`)
    workers: int | str = "auto"
    #: with ``refit`` and more than one worker, K lumps (where the model declares classes:
    #: :data:`AHEAD_CANDIDATES`) is also trained with its recipe while the candidates are
    #: scored, in a worker of its own: where it is chosen, the train that follows finds that
    #: fit made (the same fit: its settings and one thread). Not in the identity: it changes
    #: when a fit is made, not which
    ahead: bool = True
    #: inducing points of the clocks' scoring fits (None: the recipe's 200); their trained
    #: fit keeps the recipe's. A clock's psi is a smooth surface over (inputs, age): on E.
    #: coli 64 points score within 1e-5 per window of 200's (well inside the SE, 1.2e-5) at
    #: 2-3x less fitting
    clock_inducing: int | None = 64
    #: the fields the held-out cells move in, ``gp.choice.n_cells`` split evenly among them
    #: (None: the training field). The held-out run at the training inputs cannot see a kind
    #: that is off where only another field takes the cells: the dimerisation's K lumps,
    #: +7.5 to +9.0 % on L2's high inputs with every fit, within 0.2 % at the training
    #: field's (docs/choice.md, session 18)
    fields: tuple[str, ...] | None = None
    #: the occupancy spread's relative difference a candidate holding its durations must also
    #: hold (:func:`~surrogate.kinds.scoring.holds_spread`: its own population's, closed loop,
    #: where it was run) where one of them does; None: not asked. CERENA's gene-expression
    #: network: every clock +7 to +10 %, the three phases +5.4 to +5.7 % over four draws, the
    #: phases (3, 2) +2.8 %, which fail at scale (opt-in, docs/choice.md)
    spread_tolerance: float | None = None
    #: the windows the held-out likelihood ranks the candidates and decides the added clocks
    #: by (:func:`~surrogate.kinds.scoring.scored_windows`): every window (``start``, the
    #: default), or those after each cell's first switch (``first_switch``, opt-in: Vilar's
    #: clock caps stop growing past its segments; but the dimerisation's clock at 2 s then
    #: ties its phases and fails 4 of 24 checks, docs/choice.md, session 35)
    likelihood_from: str = FROM_START
    #: simulated sequences per held-out cell the durations and the spread are scored from:
    #: one draw left the three phases' spread on CERENA's network 0.4 points either side of
    #: the screen with the seed alone (docs/choice.md)
    draws: int = 4
    #: each candidate's own population run as the held-out cells were (closed loop: its cells
    #: moved by their own phi), its durations screened too and its spread read: open loop,
    #: driven by the full model's inputs, a kind whose moves take its cells elsewhere is not
    #: seen. Opt-in: against 1,000 held-out cells one population's means moved by up to 5
    #: points from draw to draw on CERENA's network, and told none of its kinds apart
    #: (docs/choice.md, session 38)
    closed_loop: bool = False
    #: the most held-out cells the run grows to where its means' standard error is over half
    #: the duration tolerance (:func:`~surrogate.kinds.scoring.grown_cells`; "auto" in the
    #: config: four times ``n_cells``, the SE halved; ``n_cells``: it never grows): above that
    #: the screen reads 2 SE, not the tolerance. The immigration-death network's segments,
    #: few and long, gave 2.5 % at 1,000 cells; its K lumps read -4.9 and -6.3 % there and
    #: -0.3 and -0.1 % at 4,000 (docs/choice.md)
    max_cells: int = 4000

    @classmethod
    def from_config(cls, options: Mapping[str, Any] | None) -> ChoiceSettings:
        """The ``gp.choice`` group checked, each bad value refused with its key and a value
        that passes."""
        options = {**DEFAULTS, **known_keys(options or {}, sorted(DEFAULTS), "gp.choice")}
        if options["by"] not in BY:
            raise ConfigError(f"gp.choice.by must be one of {list(BY)}, got {options['by']!r}")
        if options["likelihood_from"] not in LIKELIHOOD_FROM:
            raise ConfigError(f"gp.choice.likelihood_from must be one of "
                              f"{list(LIKELIHOOD_FROM)} (the windows after each held-out cell's "
                              f"first switch, or every window), got "
                              f"{options['likelihood_from']!r}; e.g. "
                              f"gp.choice.likelihood_from={FIRST_SWITCH}")  # fmt: skip
        if options["optimizer"] not in OPTIMIZERS:
            raise ConfigError(f"gp.choice.optimizer must be one of {list(OPTIMIZERS)}, got "
                              f"{options['optimizer']!r}")  # fmt: skip
        kinds = options["kinds"]
        families = sorted({*FAMILIES, *(k.recipe for k in CHAIN_KINDS if k.candidate)})
        if (isinstance(kinds, str) or not isinstance(kinds, Sequence) or not kinds
                or any(k not in families for k in kinds) or len(set(kinds)) != len(kinds)):  # fmt: skip
            raise ConfigError(f"gp.choice.kinds must list candidates among {families}, each "
                              f"once, got {kinds!r}; e.g. gp.choice.kinds=[two-state,clock]")  # fmt: skip
        ages = options["max_ages"]
        if (isinstance(ages, str) or not isinstance(ages, Sequence) or not ages
                or any(isinstance(a, bool) or not isinstance(a, int | float) or not a > 0
                       or not math.isfinite(a) for a in ages)):  # fmt: skip
            raise ConfigError(f"gp.choice.max_ages must be a non-empty list of seconds > 0, got "
                              f"{ages!r}; e.g. gp.choice.max_ages=[1,2,5]")  # fmt: skip
        caps = [float(a) for a in ages]
        if len(set(caps)) != len(caps):
            # one candidate per cap: a repeat would be fitted once and listed once, silently
            unique = list(dict.fromkeys(caps))
            raise ConfigError(f"gp.choice.max_ages={list(ages)!r} names a cap twice; each is one "
                              f"candidate: use gp.choice.max_ages={unique!r}")  # fmt: skip
        n_cells = _number(options, "n_cells", integer=True)
        if n_cells < 2:
            # the tie rule reads the SE of the paired per-cell difference: one cell has none
            raise ConfigError(f"gp.choice.n_cells={n_cells} held-out cell gives the paired "
                              f"difference no standard error (the tie rule's): use "
                              f"gp.choice.n_cells=2 or more (default 1000)")  # fmt: skip
        return cls(str(options["by"]), tuple(str(k) for k in kinds), tuple(caps), n_cells, _number(options, "t_end"),
                   _number(options, "equilibration_time", zero=True),
                   _number(options, "tie_se"), _number(options, "duration_tolerance"),
                   str(options["optimizer"]), _count(options, "extend"),
                   _flag(options, "refit"), _workers(options["workers"]),
                   _flag(options, "ahead"), _inducing(options["clock_inducing"]),
                   _fields(options["fields"], n_cells),
                   None if options["spread_tolerance"] is None
                   else _number(options, "spread_tolerance"),
                   str(options["likelihood_from"]), _number(options, "draws", integer=True),
                   _flag(options, "closed_loop"), _max_cells(options["max_cells"], n_cells))  # fmt: skip

    def check_windows(self, dt: float) -> None:
        """Refuse a held-out run or a clock cap shorter than one window of ``dt`` s: both are
        counted in whole windows, at least one, so either would silently be one window.

        Raises:
            ConfigError: ``gp.choice.t_end`` or a cap in ``gp.choice.max_ages`` below ``dt``,
                named with the value that passes.
        """
        if self.t_end < dt:
            raise ConfigError(f"gp.choice.t_end={self.t_end:g} s is shorter than one window "
                              f"(dt={dt:g} s): the held-out run would record one window of "
                              f"{dt:g} s; use gp.choice.t_end={max(dt, 50.0):g} (the default) "
                              f"or any value >= {dt:g}")  # fmt: skip
        short = [a for a in self.max_ages if a < dt]
        if short:
            kept = [a for a in self.max_ages if a >= dt] or [max(1.0, dt)]
            raise ConfigError(f"gp.choice.max_ages has cap(s) {short} below one window "
                              f"(dt={dt:g} s): the clock counts whole windows, so its layer "
                              f"would cap it at one window, not as asked; use caps >= {dt:g}, "
                              f"e.g. gp.choice.max_ages={kept!r}")  # fmt: skip

    def worker_count(self, candidates: int, device: str) -> int:
        """Processes to fit ``candidates`` candidates on ``device`` with: ``workers``, or for
        "auto" one per usable core (at most ``candidates``) on the CPU and one on a GPU (its
        fits are short, and each process would hold its own CUDA context)."""
        if isinstance(self.workers, int):
            return max(1, min(self.workers, candidates))
        if not str(device).startswith("cpu"):
            return 1
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
        return max(1, min(cores // FIT_THREADS, candidates))

    def identity(self) -> dict[str, Any]:
        """What the held-out run and the choice depend on (not ``by``: the rule makes none)."""
        return {"kinds": list(self.kinds), "max_ages": list(self.max_ages), "n_cells": self.n_cells, "t_end": self.t_end,
                "equilibration_time": self.equilibration_time, "tie_se": self.tie_se,
                "duration_tolerance": self.duration_tolerance, "extend": self.extend,
                "refit": self.refit, "clock_inducing": self.clock_inducing,
                # the clocks added and compared with each other by the score with a clock's
                # unknown first age marginalised (session 36): choices made before are made
                # again (their fits are reused)
                "clocks_by": "marginal",
                **({} if self.fields is None else {"fields": list(self.fields)}),
                **({} if self.spread_tolerance is None
                   else {"spread_tolerance": self.spread_tolerance}),
                # every window, the choice before the key: its records read again
                **({} if self.likelihood_from == FROM_START
                   else {"likelihood_from": self.likelihood_from}),
                # each candidate's draws seeded by its name (session 38): choices made before
                # are made again
                "draws": self.draws, "seeds": "by_name",
                "closed_loop": self.closed_loop,
                # the means held within the tolerance or 2 SE open loop too, the held-out
                # run grown where that SE is over half the tolerance (session 39): choices
                # made before are made again
                "means": "tolerance_or_2se", "max_cells": self.max_cells,
                "grows": "adding_cells"}  # fmt: skip


#: ``gp.choice.max_cells: auto``: this many times ``gp.choice.n_cells`` (the SE halved)
AUTO_GROWTH = 4


def _max_cells(value: Any, n_cells: int) -> int:
    """``gp.choice.max_cells``: ``auto`` (:data:`AUTO_GROWTH` x ``gp.choice.n_cells``) or an
    integer at least ``gp.choice.n_cells`` (equal: the held-out run never grows)."""
    if value == "auto":
        return AUTO_GROWTH * n_cells
    if isinstance(value, bool) or not isinstance(value, int) or value < n_cells:
        raise ConfigError(f"gp.choice.max_cells must be auto or an integer >= gp.choice.n_cells "
                          f"({n_cells}): the most held-out cells the run grows to where its "
                          f"means' SE is over half the tolerance (gp.choice.max_cells="
                          f"{n_cells} never grows it), got {value!r}")  # fmt: skip
    return value


def _fields(value: Any, n_cells: int) -> tuple[str, ...] | None:
    """``gp.choice.fields``: null or a list of shipped field names, each once, with at least
    one held-out cell per field (each name checked as the field stage checks it)."""
    if value is None:
        return None
    if (isinstance(value, str) or not isinstance(value, Sequence) or not value
            or any(not isinstance(f, str) for f in value)):  # fmt: skip
        raise ConfigError(f"gp.choice.fields must be null (the training field) or a list of "
                          f"field names, got {value!r}; e.g. "
                          f"gp.choice.fields=[gaussian,linear]")  # fmt: skip
    if len(set(value)) != len(value):
        unique = list(dict.fromkeys(value))
        raise ConfigError(f"gp.choice.fields={list(value)!r} names a field twice; use "
                          f"gp.choice.fields=[{','.join(unique)}]")  # fmt: skip
    for name in value:
        try:
            field_config(name)
        except ConfigError as error:  # an unknown name, with the available fields
            raise ConfigError(f"gp.choice.fields: {error}") from None
    if n_cells < len(value):
        raise ConfigError(f"gp.choice.n_cells={n_cells} cannot give each of the "
                          f"{len(value)} fields in gp.choice.fields a held-out cell: use "
                          f"gp.choice.n_cells={max(2, len(value))} or more (default "
                          f"{DEFAULTS['n_cells']})")  # fmt: skip
    return tuple(value)


def _workers(value: Any) -> int | str:
    """``gp.choice.workers``: "auto" or an integer >= 1."""
    if value == "auto":
        return "auto"
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"gp.choice.workers must be auto or an integer >= 1 (processes "
                          f"fitting the candidates side by side), got {value!r}; e.g. "
                          f"gp.choice.workers=1 to fit them one after the other")  # fmt: skip
    return value


def _inducing(value: Any) -> int | None:
    """``gp.choice.clock_inducing``: null or an integer >= 1."""
    if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
        raise ConfigError(f"gp.choice.clock_inducing must be null (the clock recipe's inducing "
                          f"points) or an integer >= 1, got {value!r}; default "
                          f"{DEFAULTS['clock_inducing']}")  # fmt: skip
    return value


def _flag(options: Mapping[str, Any], key: str) -> bool:
    """``gp.choice.<key>``: true or false."""
    value = options[key]
    if not isinstance(value, bool):
        raise ConfigError(f"gp.choice.{key} must be true or false, got {value!r}; default "
                          f"{DEFAULTS[key]!r}")  # fmt: skip
    return value


def _count(options: Mapping[str, Any], key: str) -> int:
    """``gp.choice.<key>``: an integer >= 0."""
    value = options[key]
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ConfigError(f"gp.choice.{key} must be an integer >= 0, got {value!r}; default "
                          f"{DEFAULTS[key]!r}")  # fmt: skip
    return value


def _number(options: Mapping[str, Any], key: str, integer: bool = False, zero: bool = False) -> Any:
    """``gp.choice.<key>``: a positive number (an integer, or >= 0 where ``zero``)."""
    value = options[key]
    kind = int if integer else int | float
    if isinstance(value, bool) or not isinstance(value, kind) or not (
            value >= 0 if zero else value > 0) or not math.isfinite(value):  # fmt: skip
        what = "an integer" if integer else "a number"
        raise ConfigError(f"gp.choice.{key} must be {what} {'>=' if zero else '>'} 0, got "
                          f"{value!r}; default {DEFAULTS[key]!r}")  # fmt: skip
    return int(value) if integer else float(value)


def user_keys(raw_gp: Mapping[str, Any]) -> dict[str, Any]:
    """The gp keys of ``raw_gp`` (``gp=auto``'s group as composed) whose value differs from
    conf/gp/auto.yaml's: the user's, carried into every candidate (``gp.threads=1``,
    ``gp.inputs=...``); ``choice`` and the keys auto.yaml leaves ``auto`` are the choice's."""
    default = group_config("gp", "auto")
    return {k: v for k, v in raw_gp.items()
            if k != "choice" and default.get(k) != v and v != "auto"}  # fmt: skip


def candidate_groups(
    raw_gp: Mapping[str, Any], settings: ChoiceSettings, internal: Any, scoring: bool = True
) -> dict[str, dict[str, Any]]:
    """The candidates' names and gp groups (those of ``gp.choice.kinds``): the two-state chain
    (``gp=svgp``), the switch clock at each cap (``gp=clock gp.max_age=...``), K lumps
    (``gp=classes``) where the model's ``internal`` model declares classes, K lumps whose bins
    relax (``gp=classes gp.class_moves=relaxation``, scored as its recipe trains it: its cost is
    a stationary full-model sample, not the fit) where they are bins both lumps share, and each
    registered candidate kind's recipe (the hidden phases, ``gp=phases``) with its variants
    (:meth:`~surrogate.kinds.base.ChainKind.candidate_variants`: the phases at the most
    counts); each the shipped recipe with the user's keys (:func:`user_keys`) and, to score
    them (``scoring``), those of ``gp.choice.optimizer`` (:data:`LBFGS` or :data:`NEWTON`)
    unless the user set them
    (``scoring=False``: the recipes' own optimisers, what ``gp.choice.refit`` trains the chosen
    with); each on :data:`FIT_THREADS` unless the user set ``gp.threads``; the clocks scored
    with ``gp.choice.clock_inducing`` inducing points unless the user set ``gp.n_inducing``."""
    user = user_keys(raw_gp)
    keys = SCORING_KEYS.get(settings.optimizer, {}) if scoring else {}
    choice_keys = {k: v for k, v in keys.items() if k not in user}
    if "threads" not in user:
        choice_keys["threads"] = FIT_THREADS

    def group(recipe: str, **extra: Any) -> dict[str, Any]:
        shipped = group_config("gp", recipe)
        # a kind's own block (gp.phases) given in part keeps the recipe's other keys
        nested = {k: {**shipped[k], **v} for k, v in user.items()
                  if isinstance(v, Mapping) and isinstance(shipped.get(k), Mapping)}  # fmt: skip
        return {**shipped, **extra, **choice_keys, **user, **nested}

    families: list[tuple[str, str, dict[str, Any]]] = [("two-state", "two-state", group("svgp"))]
    light = ({"n_inducing": settings.clock_inducing}
             if scoring and settings.clock_inducing is not None else {})  # fmt: skip
    families += [("clock", clock_name(age), group("clock", max_age=age, **light))
                 for age in settings.max_ages]  # fmt: skip
    declared = lump_classes_of(internal)
    if declared is not None:
        families.append(("classes", "classes", group("classes")))
        if _shared_bins(internal, declared.lumps):
            # scored as its recipe trains it, never refitted: its cost is the stationary
            # sample's full-model cells (minutes on a slow network), paid once
            recipe = {k: v for k, v in choice_keys.items() if k not in keys}
            relaxing = {**group_config("gp", "classes"), "class_moves": CLASS_MOVES[1],
                        **recipe, **user}  # fmt: skip
            families.append((RELAXING_FAMILY, RELAXING_CANDIDATE, relaxing))
    shipped = {"svgp", "clock", "classes"}
    for kind in CHAIN_KINDS:
        if kind.candidate and kind.recipe not in shipped:
            base = group(kind.recipe)
            families.append((kind.recipe, kind.recipe, base))
            families += [
                (kind.recipe, name, gp) for name, gp in kind.candidate_variants(base).items()
            ]
            shipped.add(kind.recipe)
    out = {name: gp for family, name, gp in families if family in settings.kinds}
    if not out:
        raise ConfigError(f"gp.choice.kinds={list(settings.kinds)} leaves no candidate for this "
                          f"model (K lumps need classes the model declares): add two-state")  # fmt: skip
    return out


def _shared_bins(internal: Any, lumps: Sequence[int]) -> bool:
    """Whether ``internal``'s classes are bins of one count both lumps share (what K lumps
    whose bins relax needs, :func:`~surrogate.gp.class_relaxation.check_shared_bins`)."""
    try:
        check_shared_bins(class_bins_of(internal), lumps)
    except ConfigError:
        return False
    return True


class Candidate(Protocol):
    """What a choice reads of a candidate's train settings (a
    :class:`~surrogate.stages.settings.train.TrainSettings`; typed by what it offers, since
    those settings are made from this module's)."""

    def fit_identity(self) -> dict[str, Any]: ...

    def command(self) -> str: ...


@dataclass(frozen=True)
class PendingChoice:
    """A choice to make: its settings, the candidates' train settings (by name, on one
    collection) and the directory its record goes to."""

    settings: ChoiceSettings
    candidates: dict[str, Any]  # name -> TrainSettings (a Candidate)
    directory: Path
    #: the candidates' gp groups (by name), and what makes a candidate's train settings of a
    #: gp group on the same collection (a clock at a longer cap, :meth:`longer_clock`)
    groups: dict[str, dict[str, Any]] = field(default_factory=dict)
    make: Callable[[dict[str, Any]], Any] | None = None
    #: each candidate's gp group as trained once chosen (``gp.choice.refit``: its recipe's own
    #: optimiser; else its scoring group)
    finals: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: the train command that makes it, with ``gp=auto`` and its choice keys
    made_by: str | None = None

    def reach_clock(
        self, horizon: float | None, groups: Mapping[str, dict[str, Any]]
    ) -> tuple[str, dict[str, Any]] | None:
        """A clock candidate at the held-out sequences' memory ``horizon`` (s,
        :func:`~surrogate.kinds.scoring.memory_horizon`, to two significant figures), where it
        is more than twice the largest cap among ``groups``' clocks in seconds: what the
        inspector's pilot adds from the hazard it measures, here from the run the candidates
        are scored on. Doubling from the caps asked for stops at the first cap that scores
        worse than the one below it, short of a long period's memory (the Vilar oscillator's
        segments of 16 s: the clock at 10 s below the one at 5 s for one training seed, every
        candidate's `a_low` mean 11-42 % short, docs/choice.md). Its age axis keeps the width
        of that largest clock's bins."""
        largest = largest_clock(groups)
        if horizon is None or largest is None or self.make is None:
            return None
        base = groups[largest]
        cap, age = float(base["max_age"]), float(f"{horizon:.2g}")
        if age <= 2.0 * cap:
            return None
        axis = wider_clock_axis(base)
        if axis:  # as wide as the base's bins: its count scaled with the cap
            axis = {"clock_bins": max(1, round(axis["clock_bins"] / 2 * age / cap))}
        return clock_name(age), {**base, "max_age": age, **axis}

    def longer_clock(
        self, name: str, groups: Mapping[str, dict[str, Any]], reached: int = 0
    ) -> tuple[str, dict[str, Any]] | None:
        """A clock candidate at twice ``name``'s cap, where ``name`` is a clock at the largest
        cap among ``groups`` (the candidates so far) and extensions are left
        (``gp.choice.extend``, counted past the caps asked for and the ``reached`` ones
        :meth:`reach_clock` added): the memory may reach past it. Its age axis keeps the
        width of ``name``'s bins (twice the ``gp.clock_bins``): at the same count a longer cap
        blurs what the shorter one resolved (Tyson's oscillator: 20 bins over 10 s, 0.5 s
        each, miss a 3.5-s period's means that 20 over 5 s hold)."""
        gp = groups.get(name)
        if gp is None or gp.get("history") != SWITCH_CLOCK.history or self.make is None:
            return None
        caps = [g["max_age"] for g in groups.values() if g.get("history") == SWITCH_CLOCK.history]
        extended = len(caps) - len(self.settings.max_ages) - reached
        if gp["max_age"] < max(caps) or extended >= self.settings.extend:
            return None
        age = 2.0 * float(gp["max_age"])
        return clock_name(age), {**gp, "max_age": age, **wider_clock_axis(gp)}

    def log_clock(
        self, name: str, groups: Mapping[str, dict[str, Any]], dt: float
    ) -> tuple[str, dict[str, Any]] | None:
        """A clock on a log axis (``gp.clock_knee``, :func:`log_clock_axis`) at twice the cap
        of ``name``, where ``name`` is the likelihood's best and a clock in seconds, and no
        log clock is among ``groups`` yet: it keeps the short ages ``name`` resolves and
        reaches twice as far (Tyson's oscillator, seed 1: the clock at 10 s held L2's
        `y_high` mean -10.8 % off, the log clock at 20 s +1.5 %)."""
        gp = groups.get(name)
        if (gp is None or gp.get("history") != SWITCH_CLOCK.history or self.make is None
                or gp.get("clock_knee") is not None
                or any(g.get("clock_knee") is not None for g in groups.values())):  # fmt: skip
            return None
        axis = log_clock_axis(gp, dt)
        if not axis:
            return None
        return clock_name(axis["max_age"], log_axis=True), {**gp, **axis}

    def ahead(self) -> tuple[str, Any] | None:
        """The candidate to train with its recipe while the candidates are scored
        (``gp.choice.ahead``; :data:`AHEAD_CANDIDATES`: K lumps where the model declares
        classes) and the train settings it is trained with once chosen; None where it is not
        asked, there is no such candidate, or it is trained as scored."""
        if not self.settings.ahead or self.make is None:
            return None
        name = next((n for n in AHEAD_CANDIDATES if n in self.finals), None)
        if name is None or self.finals[name] == self.groups.get(name):
            return None
        return name, self.make(self.finals[name])

    def command(self) -> str:
        """The train command that makes it (:attr:`made_by`; else the first candidate's)."""
        if self.made_by is not None:
            return self.made_by
        return str(next(iter(self.candidates.values())).command())


def largest_clock(groups: Mapping[str, dict[str, Any]]) -> str | None:
    """The name of the clock in seconds (not on a log axis) at the largest cap among
    ``groups``; None where there is none."""
    clocks = [n for n, g in groups.items()
              if g.get("history") == SWITCH_CLOCK.history and g.get("clock_knee") is None]  # fmt: skip
    return max(clocks, key=lambda n: float(groups[n]["max_age"]), default=None)


def wider_clock_axis(gp: Mapping[str, Any]) -> dict[str, Any]:
    """The ``gp.clock_bins`` of a clock at twice ``gp``'s cap with bins as wide as ``gp``'s
    (empty where ``gp.bins`` is not one count for every axis: unbinned, or the user's per
    axis).

    Example:
        >>> wider_clock_axis({"max_age": 5.0, "bins": 200, "clock_bins": 20})
        {'clock_bins': 40}
        >>> wider_clock_axis({"max_age": 5.0, "bins": 200})  # the clock's axis takes gp.bins
        {'clock_bins': 400}
    """
    bins = gp.get("bins")
    if isinstance(bins, bool) or not isinstance(bins, int) or bins <= 0:
        return {}
    return {"clock_bins": 2 * int(gp.get("clock_bins", bins))}


#: a log clock's knee in windows: the first window moves the axis by log(1.2), so the first
#: ages are resolved window by window
KNEE_WINDOWS = 5


def log_clock_axis(gp: Mapping[str, Any], dt: float) -> dict[str, Any]:
    """The axis of a clock on a log axis at twice ``gp``'s cap (a clock in seconds with
    ``gp.clock_bins`` bins, or ``gp.bins`` where it has none): knee :data:`KNEE_WINDOWS`
    windows, and bins as wide as ``gp``'s at a third of its cap (finer below, coarser
    above); empty where ``gp`` has no single bin count.

    Example:
        >>> log_clock_axis({"max_age": 10.0, "bins": 200, "clock_bins": 40}, 0.05)
        {'max_age': 20.0, 'clock_knee': 0.25, 'clock_bins': 63}
    """
    bins = gp.get("clock_bins", gp.get("bins"))
    if isinstance(bins, bool) or not isinstance(bins, int) or bins <= 0:
        return {}
    cap, knee = float(gp["max_age"]), KNEE_WINDOWS * dt
    width = cap / bins / (knee + cap / 3.0)  # log units at a third of the cap
    return {"max_age": 2.0 * cap, "clock_knee": knee,
            "clock_bins": max(1, round(math.log1p(2.0 * cap / knee) / width))}  # fmt: skip


_PENDING: contextvars.ContextVar[list[PendingChoice] | None] = contextvars.ContextVar(
    "pending_choices", default=None
)


@contextlib.contextmanager
def collecting_pending() -> Iterator[list[PendingChoice]]:
    """While open, train settings whose measured choice is not stored resolve ``gp=auto`` by
    the rule and add the choice to the yielded list (the entries that train check every setting
    this way first, make the choices, then build the settings again)."""
    pending: list[PendingChoice] = []
    token = _PENDING.set(pending)
    try:
        yield pending
    finally:
        _PENDING.reset(token)


def stored_choice(plan: PendingChoice) -> tuple[str, dict[str, Any]] | None:
    """The chosen candidate's name and gp group where ``plan``'s record exists (None: not made
    yet); a clock the choice added at a longer cap is in the record, not among the plan's."""
    path = plan.directory / CHOICE
    if not path.is_file():
        return None
    record = read_json(path, made_by=plan.command())
    chosen, gp = str(record.get("chosen")), record.get("gp")
    if chosen not in plan.candidates and not isinstance(gp, dict):
        raise ConfigError(f"{path} chose {chosen!r}, not one of the candidates "
                          f"{sorted(plan.candidates)}: remove the directory and run "
                          f"`{plan.command()}` again")  # fmt: skip
    return chosen, dict(gp) if isinstance(gp, dict) else plan.finals.get(
        chosen, plan.groups[chosen]
    )


def pending(plan: PendingChoice) -> None:
    """Record ``plan`` where the settings are being checked (:func:`collecting_pending`);
    elsewhere refuse, naming the command that makes it."""
    gathered = _PENDING.get()
    if gathered is not None:
        gathered.append(plan)
        return
    raise MissingArtefactError(
        f"gp=auto chooses the chain kind by a held-out measurement, not made yet for this "
        f"collection ({plan.directory}): make it with `{plan.command()}` (it fits and scores "
        f"the candidates {sorted(plan.candidates)} and trains the best), or name a kind "
        f"(gp=svgp, gp=clock, gp=classes, gp=phases) or gp.choice.by=rule"
    )
