"""Settings of the collect stage: perturbed full-model runs -> transitions table (and the
sequential design's fits, where ``collect.design.target_error`` is set).

The design's fits are train settings, which read collect's: they are built by the train
settings' module, which the caller names (``fits=TrainSettings.design_fits``); this module
knows them only by what the design reads of them (:class:`DesignFits`)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from surrogate.config import non_negative, positive, to_dict
from surrogate.errors import ConfigError
from surrogate.grid.coupled import is_coupled
from surrogate.io import MANIFEST, artefact_dir
from surrogate.models.capabilities import (
    class_count_of,
    expected_class_next_of,
    expected_phi_next_of,
    feature_names_of,
    lump_classes_of,
)
from surrogate.stages.settings.common import (
    COLLECT_CMD,
    TRAIN_CMD,
    Job,
    ModelSetup,
    check_table_memory,
    command_line,
    group_overrides,
)
from surrogate.validation import known_keys

if TYPE_CHECKING:
    from surrogate.gp.training import GPSettings
    from surrogate.stages.settings.occupancy import OccupancySettings

#: seconds of ``collect.probe_seconds`` where a config does not give it (conf/collect/default.yaml)
PROBE_SECONDS = 3.0
#: collect keys that change how a collection is checked, not the table: kept out of its identity
#: (and so of its directory's name and of every identity built on it)
NOT_IDENTITY = ("probe_seconds",)
#: ``collect.keep_switches``: auto is true where the rows are thinned (``record_every`` > 1),
#: carry no expected labels (the model gives none, or ``collect.expected_labels=false``) and no
#: sequential design is asked for
KEEP_SWITCHES = ("auto", True, False)
#: what a collection that keeps every switch keeps besides, where the model declares classes:
#: every window where the class changed (in its identity: tables kept otherwise before it)
KEPT_CLASS_MOVES = "class_moves"
#: ``collect.top_up``: where rows lag a jump within the measured window, record settled rows
#: until each origin has ``n_per_state`` of them (auto), or keep the table as collected (off)
TOP_UP = ("auto", "off")


class DesignFits(Protocol):
    """What a sequential design reads of its fits' settings (the train settings of the
    collection without its design: :meth:`~surrogate.stages.settings.TrainSettings.design_fits`
    builds them)."""

    @property
    def inputs(self) -> tuple[str, ...]: ...

    @property
    def gp(self) -> GPSettings: ...

    @property
    def fit_threads(self) -> int: ...

    @property
    def diagnostic(self) -> dict[str, Any]: ...

    def fit_identity(self) -> dict[str, Any]: ...

    def label_column(self, columns: Sequence[str]) -> str: ...

    def input_warps(self) -> dict[str, float]: ...

    def occupancy(self) -> OccupancySettings: ...


#: builds a design's fits from the collection without its design and the gp group (as given)
DesignBuilder = Callable[["CollectSettings", dict[str, Any]], DesignFits]


@dataclass(frozen=True, eq=False)
class CollectSettings:
    """The collect stage: perturbed full-model runs -> transitions table."""

    setup: ModelSetup
    options: dict[str, Any]
    job: Job
    #: the collect settings as given (null: the model's default budget), for the command
    given: dict[str, Any] | None = None
    #: the fits of a sequential design (``collect.design.target_error`` set), else None
    design: DesignFits | None = None

    @classmethod
    def from_config(
        cls,
        cfg: Mapping[str, Any],
        setup: ModelSetup | None = None,
        job: Job | None = None,
        fits: DesignBuilder | None = None,
    ) -> CollectSettings:
        """Validate the collect group (and the model's perturbation options); the budget left
        null (``n_per_state``, ``n_cells``, ``record_every``) is the model's default, which
        fits its cost, and so is the perturbation left null (``perturb_rate``,
        ``blackout_time``) (``Model.collect_defaults``).

        Args:
            cfg: The job's config (its ``collect`` group; ``gp`` for a sequential design).
            setup: The model setup, built once at the stage's entry (None: built from ``cfg``).
            job: The job, likewise.
            fits: Builds a sequential design's fits (``TrainSettings.design_fits``); needed
                where ``collect.design.target_error`` is set.
        """
        setup = ModelSetup.from_config(cfg) if setup is None else setup
        if is_coupled(setup.field):  # the perturbed cells would shape the field they read
            raise ConfigError(
                f"collect runs in a given field; field={setup.field_name} "
                f"({type(setup.field).__name__}) is coupled (the cells change it): collect and "
                f"train in a given field (e.g. field=gaussian, experiment=band's "
                f"decision.train_field) and run the abstraction in the coupled one"
            )
        given = to_dict(cfg["collect"])
        c = dict(given)
        defaults = setup.model.collect_defaults(setup.dt)
        for key in ("n_per_state", "n_cells", "record_every", "perturb_rate", "blackout_time"):
            if c.get(key) is None:
                c[key] = defaults[key]
        for key in ("n_per_state", "n_cells", "record_every"):
            positive(c, key, "collect.", integer=True)
        positive(c, "max_time", "collect.")
        non_negative(c, "equilibration_time", "collect.")
        non_negative(c, "blackout_time", "collect.")
        c.setdefault("probe_seconds", PROBE_SECONDS)
        c.setdefault("top_up", "auto")
        if c["top_up"] not in TOP_UP:
            raise ConfigError(f"collect.top_up must be one of {list(TOP_UP)} (auto: where rows "
                              f"lag a jump, record settled rows until each origin has "
                              f"n_per_state of them), got {c['top_up']!r}")  # fmt: skip
        non_negative(c, "probe_seconds", "collect.")  # 0: no cost probe
        rate = non_negative(c, "perturb_rate", "collect.")
        if rate * setup.dt > 1.0:
            raise ConfigError(
                f"collect.perturb_rate={rate:g}/s cannot be met with dt={setup.dt:g} s: at most "
                f"one perturbation per step, so the rate must be <= 1/dt = {1 / setup.dt:g}/s"
            )
        expected = c.get("expected_labels", False)
        if not isinstance(expected, bool):
            raise ConfigError(f"collect.expected_labels must be true or false, got {expected!r}")
        keep = c.get("keep_switches", "auto")
        if keep not in KEEP_SWITCHES or (keep in (0, 1) and not isinstance(keep, bool)):
            raise ConfigError(f"collect.keep_switches must be auto, true or false (true: every "
                              f"window where phi changes recorded besides the thinned ones, "
                              f"each row weighted by the windows it stands for; auto: true "
                              f"where the rows are thinned and carry no expected labels), got "
                              f"{keep!r}")  # fmt: skip
        if keep == "auto":
            keep = (int(c["record_every"]) > 1 and not _design_asked(c)
                    and not (expected and expected_phi_next_of(setup.model.internal) is not None))  # fmt: skip
        c["keep_switches"] = keep
        # the body checks its own perturbation options now, not after simulating
        setup.model.body.perturbation(setup.field, setup.model.perturbation_options)
        out = cls(setup, c, Job.from_config(cfg) if job is None else job, given=given)
        design = _design_options(cfg, c, rate)
        if design is not None and keep:
            raise ConfigError("collect.keep_switches=true with a sequential design "
                              "(collect.design.target_error): its rounds' fits weigh every row "
                              "once; use one or the other")  # fmt: skip
        if design is not None:
            if fits is None:
                raise TypeError("collect.design.target_error is set: build the collect settings "
                                "with fits=TrainSettings.design_fits (its rounds fit psi)")  # fmt: skip
            # the rounds fit on the collection without its design (as the fixed design
            # identifies it), psi's two-state chain (gp.lumps=auto: the design needs psi)
            options = {**c, "design": {**design, "target_error": None}}
            plain = replace(out, options=options, given=options)
            gp = to_dict(cfg["gp"])
            if gp.get("lumps") == "auto":
                gp = {**gp, "lumps": "phi"}
            out = replace(out, design=fits(plain, gp))
        out.check_memory()  # on the directory the settings name (a design's is its own)
        return out

    def check_memory(self) -> None:
        """Refuse a collection whose table cannot fit in the free memory while it is collected
        (:func:`~surrogate.stages.settings.common.check_table_memory`). One already made is
        read, not collected: not refused (a fidelity run was, after its own choice's fits on
        12.7 million rows per origin had left 5.4 GiB free). A collection that keeps every
        switch is priced at its thinned rows plus the weights' column: its extra switch rows,
        ``record_every`` x phi's switching share per window of them (+30 % at 3 % and 10), are
        not known before it runs, so for it the check is a floor, not a bound."""
        if (self.directory / MANIFEST).exists():
            return
        internal = self.setup.model.internal
        columns = len(internal.input_names) + len(feature_names_of(internal)) + 7
        check_table_memory(int(self.options["n_per_state"]), columns + self.keep_switches)

    @property
    def expected_labels(self) -> bool:
        """Whether the table gets the expected labels (``collect.expected_labels`` and a model
        whose internal model gives them)."""
        wanted = bool(self.options.get("expected_labels", False))
        return (wanted and not self.keep_switches
                and expected_phi_next_of(self.setup.model.internal) is not None)  # fmt: skip

    @property
    def thinned(self) -> bool:
        """Whether the table records one window in several (``record_every`` > 1) without
        keeping every switch and class move besides (:attr:`keep_switches`)."""
        return int(self.options["record_every"]) > 1 and not self.keep_switches

    @property
    def keep_switches(self) -> bool:
        """Whether every window where phi changes is recorded besides the thinned ones
        (``collect.keep_switches``; its rows then carry the windows each stands for,
        :mod:`surrogate.gp.windows`, and no expected labels: a window's law given its state
        is not what the switches are kept for)."""
        return bool(self.options.get("keep_switches", False))

    @property
    def target_error(self) -> float | None:
        """The sequential design's target (``collect.design.target_error``), or None."""
        return None if self.design is None else float(self.options["design"]["target_error"])

    @property
    def bins_at_train(self) -> bool:
        """Whether the rows leave the classes' bins to their reader: the model's classes are
        bins of a count, which the rows store (train applies the bins,
        :func:`~surrogate.simulate.classes.reclassify`), with no expected class law (its
        columns would be the bins' law) and no sequential design (its rounds' fits would use
        the bins)."""
        internal = self.setup.model.internal
        return (self.design is None and class_count_of(internal) is not None
                and expected_class_next_of(internal) is None)  # fmt: skip

    def bins_identity(self) -> dict[str, Any]:
        """The classes' bins (a digest) where the rows leave them to their reader
        (:attr:`bins_at_train`): part of the identity of what is fitted on the rows, not of the
        rows; else nothing."""
        count = class_count_of(self.setup.model.internal)
        return {"classes": count.digest} if self.bins_at_train and count is not None else {}

    def identity(self) -> dict[str, Any]:
        """Everything that defines a transitions table: the device too (its random stream), and
        the design's fits where it has one (a switched-off design leaves the fixed design's
        identity as it was); not the checks of :data:`NOT_IDENTITY`, nor the classes' bins
        where the rows store the count they bin (:attr:`bins_at_train`: the model's
        :meth:`~surrogate.models.base.Model.rows_identity`; a table that keeps every class
        move keeps those of the bins it was collected with, and its weighted rows read
        unbiased under any bins)."""
        options = {k: v for k, v in identity_options(self.options).items()
                   if k != "design" or self.design}  # fmt: skip
        model = self.setup.identity()
        if self.bins_at_train:
            model = {**model, **self.setup.model.rows_identity(self.setup.model_config)}
        out = {**model, "collect": options, "device": self.job.device_type}
        if self.keep_switches and lump_classes_of(self.setup.model.internal) is not None:
            # every class move kept besides the switches (surrogate.simulate.transitions)
            out["kept"] = KEPT_CLASS_MOVES
        if self.design is not None:
            # its rounds fit psi and score it on the diagnostic's occupancy run
            out["design_fit"] = {**self.design.fit_identity(), "occupancy": self.design.diagnostic}
        return out

    @functools.cached_property
    def directory(self) -> Path:
        """``data/collect/model=..._field=..._dt=..._seed=...-<hash>``."""
        label = {**self.setup.label(), "seed": self.setup.seed}
        return artefact_dir(self.job.data_dir, "collect", label, self.identity())

    def command(self) -> str:
        """The command that makes this artefact."""
        return command_line(COLLECT_CMD, self.setup.overrides(), self._overrides(),
                            self.job.device_overrides())  # fmt: skip

    def _overrides(self) -> list[str]:
        given = self.options if self.given is None else self.given
        return group_overrides("collect", given, "default")[1:]


def identity_options(options: Mapping[str, Any]) -> dict[str, Any]:
    """The collect ``options`` that define a table: all but :data:`NOT_IDENTITY`, and
    ``top_up`` at its default (a collection whose rows did not lag is the same table with it;
    one that lagged, made before the key, is read as it was: delete it to top it up), nor
    ``keep_switches`` at its default (false: the tables made before the key)."""
    return {k: v for k, v in options.items()
            if k not in NOT_IDENTITY and not (k == "top_up" and v == "auto")
            and not (k == "keep_switches" and v is False)}  # fmt: skip


def _design_asked(options: Mapping[str, Any]) -> bool:
    """Whether ``options`` ask for a sequential design (``design.target_error`` set)."""
    design = options.get("design")
    return isinstance(design, Mapping) and design.get("target_error") is not None


#: keys of ``collect.design`` (the sequential design; surrogate/stages/design.py)
DESIGN_KEYS = ("target_error", "max_rounds", "candidates", "explore")


def _design_options(
    cfg: Mapping[str, Any], options: dict[str, Any], perturb_rate: float
) -> dict[str, Any] | None:
    """Validate ``collect.design``; its options where ``target_error`` is set, else None."""
    d = options.get("design")
    if d is None:
        return None
    d = known_keys(d, DESIGN_KEYS, "collect.design")
    if d.get("target_error") is None:
        return None
    target = positive(d, "target_error", "collect.design.")
    if target >= 1.0:
        raise ConfigError(
            f"collect.design.target_error={target:g} is a relative error of psi: give a value "
            f"in (0, 1), e.g. 0.02"
        )
    positive(d, "max_rounds", "collect.design.", integer=True)
    positive(d, "candidates", "collect.design.", integer=True)
    explore = non_negative(d, "explore", "collect.design.")
    if explore > 1.0:
        raise ConfigError(f"collect.design.explore={explore:g} is a share: give a value in [0, 1]")
    if perturb_rate <= 0.0:
        raise ConfigError(
            "collect.design needs perturbations to guide: set collect.perturb_rate > 0"
        )
    if "gp" not in cfg:
        raise ConfigError(
            "collect.design.target_error needs the gp group (its rounds fit psi): run "
            f"{TRAIN_CMD} collect.design.target_error={target:g} or add gp=svgp"
        )
    return dict(d)
