"""A model written as a yaml beside an SBML file, with no Python (``model=sbml``).

The yaml (``model.spec``, or the same keys in the model config itself) names

* ``network`` (required): the SBML file (a path relative to the yaml);
* ``inputs`` (required, at least one): which of its parameters are the agent's inputs and
  where each comes from. A parameter is a global one by its id (``inducer``) or a reaction's
  local (kinetic-law) one as ``<reaction id>.<parameter id>`` (``Transcription.k2``); its
  source is a variable of the body (``L``, the field's value where the agent is, in every body;
  ``m``, ``F``, ``activity`` in the chemotaxis body) or a formula over them
  (``"1 / (1 + exp(F))"``); a formula may also live in the SBML file as an assignment rule over
  an input parameter;
* ``lump`` (required): the property phi as a condition on species counts
  (``"N >= 2 and S == 0"``), and ``lump_names`` (phi = 0, phi = 1);
* ``body`` (required): a body of the library (:mod:`surrogate.models.bodies`) by ``kind`` with
  its parameters;
* optionally ``name``, ``substance_units`` (``items``: read the file's amounts as molecule
  counts whatever substance units it declares, e.g. a StochSS export's ``mole``),
  ``species_in_laws`` (``counts``: a species symbol in the file's formulas is its count, as
  StochSS and GillesPy2 write propensities; ``concentrations``: SBML's reading; required where
  the two differ in a file read with ``substance_units: items``), ``reactant_guard``
  (default true: a kinetic law that does not read a species its reaction uses up, ``I -> A``
  at ``alpha``, is read as 0 while that species lacks the molecules; false: as written, and a
  count it drives negative is refused when simulated; one warning names such laws), ``ssa``
  (auto|compiled|batched), ``burn_in`` (s), ``max_states``, ``signal_bounds``
  (``{input: [lo, hi]}``, lets the exact psi be tabulated), ``collect`` (the model's default
  collection budget: ``n_per_state``, ``n_cells``, ``record_every``) and ``classes``: classes
  finer than phi for the K-lumps chain (``gp=classes``), each lump split into bins of a count,
  ``{species: P2, edges: [10, 30]}`` (or ``expression: "P + 2 * P2"``; edges shared by both
  lumps or ``{<lump name>: [...]}``), or chosen by a short simulation
  (:mod:`surrogate.models.count_classes`): ``auto`` at the file's parameter values, or
  ``{auto: {over: {Transcription.k2: [0.007, 0.036]}, bins: 4}}`` over the inputs' range the
  fields give (what ``scripts/inspect_model.py`` recommends, with the range it measured).

The file is read by :func:`surrogate.sbml.read_sbml` (its module docstring has the rules: local
inputs, shadowing, one-way reversible laws, substance units). Formulas are parsed by libsbml's
formula parser (:mod:`surrogate.sbml.formula`), never evaluated as Python; everything is
checked when the model is built, before any simulation: a missing required key, a key of the
wrong type, an unknown species in the lump, an input that is not a parameter of the file, a
body parameter of the wrong type are each refused with a message naming the setting and the
yaml.

Example (``examples/gene_switch/model.yaml``)::

    network: gene_switch.xml
    inputs: {inducer: L}
    lump: "D >= 2"
    lump_names: [off, on]
    body: {kind: walker, speed_on: 0.02, speed_off: 0.005}

    python3 scripts/reproduce.py model=sbml model.spec=examples/gene_switch/model.yaml
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Mapping
from functools import partial
from pathlib import Path
from typing import Any

import torch
import yaml
from torch import Tensor

from surrogate.ctmc.kinetics import Expr, input_ref, torch_function
from surrogate.errors import ConfigError
from surrogate.fields import Field
from surrogate.models.base import (
    CellKernel,
    Model,
    burn_in_seconds,
)
from surrogate.models.bodies import LibraryBody, build_body
from surrogate.models.capabilities import lump_expr_of
from surrogate.models.count_classes import (
    CountBinning,
    CountClasses,
    choose_count_classes,
    impossible_classes,
    is_auto,
    parse_auto_classes,
    parse_classes,
    shared_auto,
    spread_inputs,
    threshold_of,
)
from surrogate.models.network import SSA_BACKENDS, NetworkInternalModel
from surrogate.models.packed import PackedDecision
from surrogate.sbml import SbmlError, read_sbml
from surrogate.sbml.formula import parse_formula
from surrogate.sbml.reader import SPECIES_IN_LAWS, SUBSTANCE_UNITS
from surrogate.validation import known_keys, yaml_hint

log = logging.getLogger(__name__)

__all__ = ["REQUIRED_KEYS", "SPEC_DEFAULTS", "SbmlAgentModel", "load_spec"]

#: every key of a spec and its default (None: required, or optional without a default)
SPEC_DEFAULTS: dict[str, Any] = {
    "name": None,
    "network": None,
    "inputs": None,
    "lump": None,
    "lump_names": ["off", "on"],
    "body": None,
    "substance_units": None,
    "species_in_laws": None,
    "reactant_guard": None,
    "ssa": "auto",
    "burn_in": 50.0,
    "max_states": 5000,
    "signal_bounds": None,
    "collect": None,
    "classes": None,
}
#: keys added after artefacts were stored: left out of the spec's digests (the full model's
#: law, the artefacts' sources) while unset, so those artefacts keep their identity
LATER_KEYS = ("species_in_laws", "reactant_guard")
#: the keys a spec must give, and what each is (for the message when one is missing)
REQUIRED_KEYS: dict[str, str] = {
    "network": "the SBML file, a path relative to the yaml",
    "inputs": "which SBML parameters are the agent's inputs and where each comes from, e.g. "
    "`inputs: {k: L}` (a global parameter) or `inputs: {Transcription.k2: L}` (a local one)",
    "lump": 'the property phi as a condition on species counts, e.g. `lump: "P >= 20"`',
    "body": "a body of the library by kind, e.g. `body: {kind: walker}`",
}
#: the classes=auto choices this process has logged (by digest)
_LOGGED_CHOICES: set[str] = set()
#: the window (s) ``classes: auto`` scores the candidate classes over (the default dt)
AUTO_CLASSES_DT = 0.05
#: the cells ``classes: auto`` simulates (at one input each where it spreads them over ranges)
AUTO_CLASSES_CELLS = 200
#: spec keys that shape only the abstraction, not the full model's law
ABSTRACTION_KEYS = ("classes", "collect")
#: spec keys a collection's rows leave to their reader (the bins; the rows store the count)
BINS_KEYS = ("classes",)
#: collection settings a model may carry as its default budget (positive integers) and
#: perturbation (non-negative seconds or rates: a network slow to settle after a jump)
COLLECT_KEYS = ("n_per_state", "n_cells", "record_every")
COLLECT_PERTURBATION_KEYS = ("perturb_rate", "blackout_time")


def load_spec(spec: str | Path | None, settings: Mapping[str, Any]) -> tuple[dict, Path]:
    """The spec yaml's keys with ``settings`` merged over them (mappings key by key), and the
    directory relative paths are read from (the yaml's, else the working directory)."""
    data: dict[str, Any] = {}
    base = Path.cwd()
    if spec is not None:
        path = Path(str(spec)).expanduser()
        if not path.is_file():
            raise ConfigError(f"model.spec={spec}: no such file (a yaml beside the SBML file)")
        try:
            loaded = yaml.safe_load(path.read_text())
        except yaml.YAMLError as error:
            raise ConfigError(f"model.spec={spec}: not valid yaml ({error})") from None
        if not isinstance(loaded, Mapping):
            raise ConfigError(f"model.spec={spec}: expected a mapping of settings, got "
                              f"{type(loaded).__name__}")  # fmt: skip
        data, base = dict(loaded), path.resolve().parent
    for key, value in settings.items():
        if isinstance(value, Mapping) and isinstance(data.get(key), Mapping):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return {**SPEC_DEFAULTS, **known_keys(data, sorted(SPEC_DEFAULTS), "model")}, base


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _column(x: Tensor, index: int) -> Tensor:
    return x[:, index]


class FormulaFeature:
    """``x (n x d) -> (n,)`` in x's dtype: a formula over a body's variables (the columns
    ``getters`` compute from ``x``, by the formula's input index); compiled from its expression
    on first use and picklable (the expression, not the code)."""

    def __init__(self, expr: Expr, n_variables: int, getters: Mapping[int, Any]) -> None:
        self.expr, self.n_variables, self.getters = expr, n_variables, dict(getters)
        self._function: Any = None

    def __call__(self, x: Tensor) -> Tensor:
        if self._function is None:
            self._function = torch_function([self.expr])
        columns = x.new_zeros((x.shape[0], self.n_variables), dtype=torch.float64)
        for j, get in self.getters.items():
            columns[:, j] = get(x).to(torch.float64)
        return self._function(x.new_zeros((x.shape[0], 0)), columns)[:, 0].to(x.dtype)

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_function": None}


def _possible(classes: CountClasses, internal: Any) -> CountClasses:
    """``classes``, refused (naming them) where some cannot occur
    (:func:`~surrogate.models.count_classes.impossible_classes`): bins of the lump's own
    threshold count on the other lump's side of the threshold."""
    threshold = threshold_of(lump_expr_of(internal))
    empty = impossible_classes(classes, threshold)
    if empty:
        assert threshold is not None  # only a threshold lump has impossible classes
        species, edge, upper = threshold
        low, high = internal.lump_names if upper else internal.lump_names[::-1]
        raise ConfigError(
            f"model.classes: the class(es) {empty} cannot occur: {low} is {species} < {edge} "
            f"and {high} is {species} >= {edge}, so no cell is ever in them and no "
            f"collection can give them rows; give each lump edges on its own side of {edge} "
            f"(edges: {{{low!r}: [...], {high!r}: [...]}}), or bins of another count"
        )
    return classes


class SbmlAgentModel(Model):
    """An agent model from a yaml spec and an SBML file (see the module docstring).

    Args:
        spec: the yaml file (None: every key given as keyword arguments).
        **settings: spec keys, merged over the yaml's (e.g. ``model.body.speed_on=0.03``).

    Example:
        >>> model = SbmlAgentModel("examples/gene_switch/model.yaml")
        >>> model.internal.input_names, model.internal.signal_names, model.internal.lump_names
        (('L',), ('inducer',), ('off', 'on'))
    """

    internal: NetworkInternalModel
    body: LibraryBody

    def __init__(self, spec: str | None = None, **settings: Any) -> None:
        self.spec = None if spec is None else Path(str(spec)).expanduser()
        try:
            self._build(*load_spec(spec, settings))
        except ConfigError as error:
            where = f" (model.spec={spec})" if spec is not None else ""
            raise type(error)(f"{error}{where}") from None

    @staticmethod
    def relaxation_config(config: Mapping[str, Any]) -> dict[str, Any]:
        """The model's config for ``gp.class_moves=relaxation``: ``classes: auto``, in the
        yaml or the config, then asks its chooser for bins both lumps share
        (:func:`~surrogate.models.count_classes.shared_auto`), rather than bins the relaxation
        check refuses after the choice; other classes as they are. Every stage builds the model
        from the same config, so they all see the same classes.

        Args:
            config: the ``model`` config (``_target_``, ``spec`` and keys over the yaml's).

        Returns:
            The config, with ``classes: {auto: {..., shared: true}}`` where it was auto.
        """
        settings = {k: v for k, v in config.items() if k not in ("_target_", "spec")}
        spec = config.get("spec")
        value = load_spec(None if spec is None else str(spec), settings)[0]["classes"]
        if not is_auto(value):
            return dict(config)
        shared = shared_auto(value)
        if shared != value:
            log.info("gp.class_moves=relaxation: model.classes=%s chooses bins both lumps "
                     "share (%s)", value, shared)  # fmt: skip
        return {**config, "classes": shared}

    def _build(self, s: dict[str, Any], base: Path) -> None:
        self._check_types(s)
        network = Path(s["network"]).expanduser()
        self.network_path = network if network.is_absolute() else base / network
        if not self.network_path.is_file():
            raise ConfigError(f"model.network={s['network']}: no such SBML file "
                              f"({self.network_path})")  # fmt: skip
        inputs = s["inputs"]
        try:
            sbml = read_sbml(
                self.network_path,
                inputs=list(inputs),
                substance_units=s["substance_units"],
                species_in_laws=s["species_in_laws"],
                reactant_guard=s["reactant_guard"] is not False,
            )
        except SbmlError as error:
            raise SbmlError(f"model.network / model.inputs: {error}") from None
        self.body = build_body(s["body"])
        features = {**self.body.derived, **self._mapped_inputs(inputs)}
        names = s["lump_names"]
        if not (
            isinstance(names, list | tuple)
            and len(names) == 2
            and all(isinstance(n, str) and n for n in names)
            and names[0] != names[1]
        ):
            hint = (" (write them in quotes: YAML reads bare off/on, yes/no as booleans)"
                    if isinstance(names, list | tuple) and any(isinstance(n, bool) for n in names)
                    else "")  # fmt: skip
            raise ConfigError(f"model.lump_names must be two different names (phi = 0, phi = 1), "
                              f"got {names!r}{hint}")  # fmt: skip
        if s["ssa"] not in SSA_BACKENDS:
            raise ConfigError(f"model.ssa must be one of {list(SSA_BACKENDS)}, got {s['ssa']!r}")
        burn_in = burn_in_seconds(s["burn_in"])
        max_states = s["max_states"]
        if (
            isinstance(max_states, bool)
            or not isinstance(max_states, int | float)
            or not (math.isfinite(max_states) and max_states == int(max_states) >= 0)
        ):
            raise ConfigError(f"model.max_states must be a non-negative integer (the most states "
                              f"enumerated for the exact law), got {max_states!r}"
                              f"{yaml_hint(max_states)}")  # fmt: skip
        self.internal = NetworkInternalModel(
            sbml,
            self.body.variable_names,
            s["lump"],
            lump_names=(names[0], names[1]),
            features=features,
            signal_names=sbml.input_names or None,
            ssa=s["ssa"],
            burn_in=burn_in,
            max_states=int(max_states),
            signal_bounds=self._bounds(s["signal_bounds"], sbml.input_names),
            input_labels={
                str(k): f"model.inputs.{k} ({str(v).strip()!r})" for k, v in inputs.items()
            },
        )
        self.class_report: dict[str, Any] | None = None
        if s["classes"] is not None:
            self.internal.set_classes(self._classes(s["classes"], sbml))
        self.perturbation_options = self.body.perturbation_options
        self.perturbation_key = "model.body.perturbation"
        self.name = str(s["name"] or sbml.id or "sbml")
        self._collect_budget = self._collect(s["collect"])
        self.settings = s

    def _classes(self, value: Any, sbml: Any) -> CountClasses:
        """``classes``: declared (``{species|expression: ..., edges: ...}``) or chosen by
        :func:`~surrogate.models.count_classes.choose_count_classes`: ``auto`` at the file's
        parameter values, ``{auto: {over: {<input>: [lo, hi]}, bins: K}}`` with those inputs
        spread over their ranges (its report is kept in :attr:`class_report` and logged)."""
        internal = self.internal
        if not is_auto(value):
            return _possible(parse_classes(value, internal.species, internal.lump_names),
                             internal)  # fmt: skip
        ranges, bins, placement, shared = parse_auto_classes(value, internal.kinetics.input_names)
        names = internal.kinetics.input_names
        values = [sbml.input_defaults.get(n, math.nan) for n in names]
        unset = [n for j, (n, v) in enumerate(zip(names, values, strict=True))
                 if v != v and j not in ranges]  # fmt: skip
        if unset:
            raise ConfigError(f"model.classes=auto chooses the classes at the SBML file's "
                              f"parameter values, but {unset} have none in the file; give "
                              f"their range (model.classes={{auto: {{over: {{{unset[0]}: "
                              f"[lo, hi]}}}}}}) or declare model.classes={{species: ..., "
                              f"edges: [...]}} instead")  # fmt: skip
        cells = AUTO_CLASSES_CELLS
        kinetic = (spread_inputs([0.0 if v != v else v for v in values], ranges, cells)
                   if ranges else torch.tensor(values, dtype=torch.float64))  # fmt: skip
        binning = CountBinning(bins, placement, shared)
        classes, report = choose_count_classes(internal, kinetic, AUTO_CLASSES_DT, cells=cells,
                                               binning=binning)  # fmt: skip
        self.class_report = report
        if classes.digest() in _LOGGED_CHOICES:  # once per process: models are rebuilt often
            return classes
        _LOGGED_CHOICES.add(classes.digest())
        gains = ", ".join(f"{c['species']} {c['gain_nats_per_window']:.2e}"
                          for c in report["candidates"])  # fmt: skip
        where = (", ".join(f"{names[j]} over [{lo:g}, {hi:g}]" for j, (lo, hi) in ranges.items())
                 if ranges else "the file's parameter values")  # fmt: skip
        log.info("model.classes=auto: bins of %s (%s) at %s, chosen by held-out log-likelihood "
                 "gain per window over phi alone (%s)%s", classes.variable,
                 classes.to_config()["edges"], where, gains, "" if report["significant"] else
                 "; the gain is within two standard errors: the two-state chain holds about as "
                 "much")  # fmt: skip
        return classes

    @staticmethod
    def _check_types(s: Mapping[str, Any]) -> None:
        """The required keys are given and the plain keys have their types (the body, lump
        names, signal bounds and collection budget are checked where they are built)."""
        missing = [key for key in REQUIRED_KEYS if s[key] is None]
        if missing:
            what = "; ".join(f"model.{key} is required ({REQUIRED_KEYS[key]})" for key in missing)
            raise ConfigError(f"{what}; see surrogate/models/sbml_agent.py")
        for key in ("network", "lump"):
            if not isinstance(s[key], str) or not s[key].strip():
                raise ConfigError(f"model.{key} must be a non-empty string ({REQUIRED_KEYS[key]}), "
                                  f"got {s[key]!r}")  # fmt: skip
        inputs = s["inputs"]
        if not isinstance(inputs, Mapping) or not inputs:
            raise ConfigError(f"model.inputs must map at least one SBML parameter to its source "
                              f"({REQUIRED_KEYS['inputs']}), got {inputs!r}")  # fmt: skip
        bad = [k for k in inputs if not isinstance(k, str) or not k]
        if bad:
            raise ConfigError(f"model.inputs: parameter names must be SBML ids (strings), got "
                              f"{bad}")  # fmt: skip
        if s["name"] is not None and (not isinstance(s["name"], str) or not s["name"]):
            raise ConfigError(f"model.name must be a non-empty string, got {s['name']!r}")
        if s["substance_units"] not in SUBSTANCE_UNITS:
            raise ConfigError(f"model.substance_units must be items (read the file's amounts "
                              f"as molecule counts) or unset, got "
                              f"{s['substance_units']!r}")  # fmt: skip
        if s["reactant_guard"] not in (None, True, False):
            raise ConfigError(f"model.reactant_guard must be true (a kinetic law that does not "
                              f"read a species its reaction uses up is 0 while that species "
                              f"lacks the molecules; the default), false (the laws as written) "
                              f"or unset, got {s['reactant_guard']!r}")  # fmt: skip
        if s["species_in_laws"] not in SPECIES_IN_LAWS:
            raise ConfigError(f"model.species_in_laws must be counts (a species symbol in the "
                              f"file's formulas is its count, as StochSS and GillesPy2 write "
                              f"propensities), concentrations (SBML's reading) or unset, got "
                              f"{s['species_in_laws']!r}")  # fmt: skip

    def _mapped_inputs(self, inputs: Mapping[str, Any]) -> dict[str, Any]:
        """The features that supply the SBML input parameters: a body variable under another
        name, or a formula over the body's variables (compiled from its expression tree)."""
        body = self.body
        variables = (*body.variable_names, *body.derived)
        out: dict[str, Any] = {}
        for param, source in inputs.items():
            where = f"model.inputs.{param}"
            if isinstance(source, int | float) and not isinstance(source, bool):
                source = repr(float(source))
            if not isinstance(source, str):
                hint = (" (a reaction's local parameter is one key, `reaction.parameter`, in the "
                        "yaml's inputs)" if isinstance(source, Mapping) else "")  # fmt: skip
                raise ConfigError(f"{where} must be a body variable {list(variables)} or a "
                                  f"formula over them, got {source!r}{hint}")  # fmt: skip
            name = source.strip()
            if name in variables:
                if param != name:
                    out[param] = self._variable(name)
                continue
            if param in variables:
                raise ConfigError(f"{where}: the body already has a variable {param!r}; map the "
                                  f"parameter to it ({param}: {param}) or rename it in the "
                                  "SBML file")  # fmt: skip
            symbols = {v: input_ref(j, v) for j, v in enumerate(variables)}
            expr = parse_formula(source, symbols, where, "real", what="body variable")
            out[param] = self._formula(expr, variables)
        return out

    def _variable(self, name: str) -> Any:
        body = self.body
        if name in body.derived:
            return body.derived[name]
        return partial(_column, index=body.variable_names.index(name))

    def _formula(self, expr: Any, variables: tuple[str, ...]) -> Any:
        """``x (n x d) -> (n,)`` in x's dtype: the formula at the body's variables."""
        getters = {j: self._variable(variables[j]) for j in sorted(expr.inputs_used())}
        return FormulaFeature(expr, len(variables), getters)

    @staticmethod
    def _bounds(bounds: Any, names: tuple[str, ...]) -> dict[str, tuple[float, float]] | None:
        if bounds is None:
            return None
        ok = isinstance(bounds, Mapping) and set(bounds) == set(names) and all(
            isinstance(v, list | tuple) and len(v) == 2
            and all(isinstance(b, int | float) and not isinstance(b, bool) and math.isfinite(b)
                    for b in v)
            and v[0] < v[1] for v in bounds.values())  # fmt: skip
        if not ok:
            values = bounds.values() if isinstance(bounds, Mapping) else []
            hints = [yaml_hint(b) for v in values if isinstance(v, list | tuple) for b in v]
            raise ConfigError(f"model.signal_bounds must give finite [lo, hi] (lo < hi) for each "
                              f"input {list(names)}, got {bounds!r}"
                              f"{next((h for h in hints if h), '')}")  # fmt: skip
        return {k: (float(v[0]), float(v[1])) for k, v in bounds.items()}

    @staticmethod
    def _collect(options: Any) -> dict[str, float]:
        if options is None:
            return {}
        checked = known_keys(options, (*COLLECT_KEYS, *COLLECT_PERTURBATION_KEYS), "model.collect")
        for key, value in checked.items():
            if key in COLLECT_PERTURBATION_KEYS:
                if (isinstance(value, bool) or not isinstance(value, int | float)
                        or not math.isfinite(value) or value < 0):  # fmt: skip
                    raise ConfigError(f"model.collect.{key} must be a non-negative number, got "
                                      f"{value!r}")  # fmt: skip
                checked[key] = float(value)
            elif isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"model.collect.{key} must be a positive integer, got {value!r}")
        return checked

    # -- the model's hooks -----------------------------------------------------------------------
    def validate(self, dt: float) -> None:
        """The body's check of the time step (e.g. dt below the adaptation time)."""
        self.body.validate(dt)

    def cell_kernel(self, decision: PackedDecision, field: Field, dt: float) -> CellKernel:
        """The body's compiled per-cell step (for lookup-table abstractions over its
        variables), where the body has one; the body refuses (KernelUnsupported) an internal
        model its kernel cannot run."""
        kernel = getattr(self.body, "cell_kernel", None)
        if kernel is None:
            return super().cell_kernel(decision, field, dt)
        return kernel(self.internal, decision, field, dt)

    def kernel_precompiler(self) -> str | None:
        """The body's kernel precompile, where it has one."""
        precompiler = getattr(self.body, "kernel_precompiler", None)
        return precompiler() if precompiler is not None else None

    def collect_defaults(self, dt: float) -> dict[str, float]:
        """The yaml's ``collect`` budget and perturbation over the defaults for the network's
        cost."""
        return {**super().collect_defaults(dt), **self._collect_budget}

    def sources(self) -> dict[str, str]:
        """sha256 of the network file, of the spec's settings as read (comments and layout do
        not count), and the digest of its K-lumps classes where it has any (``classes: auto``
        resolves them by a measurement): part of every artefact's identity."""
        out = {"network": _sha256(self.network_path)}
        if self.spec is not None:
            # the yaml's settings as read, not its bytes: editing a comment keeps every artefact
            blob = json.dumps(self._settings_as_read(), sort_keys=True, default=str)
            out["spec"] = hashlib.sha256(blob.encode()).hexdigest()
        classes = self.internal.count_classes
        if classes is not None:
            out["classes"] = classes.digest()
        return out

    def _settings_as_read(self) -> dict[str, Any]:
        """The spec's settings for digests: :data:`LATER_KEYS` left out while unset, so the
        artefacts of yamls written before those keys keep their identity."""
        return {k: v for k, v in self.settings.items() if not (k in LATER_KEYS and v is None)}

    def full_model_identity(self, config: Mapping[str, Any]) -> dict[str, Any]:
        """The full model's law: the network file's digest and the spec's settings without
        the abstraction-only keys (:data:`ABSTRACTION_KEYS`), so changing the classes or the
        collection budget keeps a stored reference (the yaml's comments never counted)."""
        law = {k: v for k, v in self._settings_as_read().items() if k not in ABSTRACTION_KEYS}
        blob = json.dumps(law, sort_keys=True, default=str)
        sources = {"network": _sha256(self.network_path),
                   "settings": hashlib.sha256(blob.encode()).hexdigest()}  # fmt: skip
        kept = {k: v for k, v in config.items() if k not in ABSTRACTION_KEYS}
        return {"model": kept, "model_sources": sources}

    def rows_identity(self, config: Mapping[str, Any]) -> dict[str, Any]:
        """A collection's rows, which store the count its classes bin: the sources with the
        spec's settings read without ``classes`` and the count (the variable the rows hold) in
        place of the classes' digest; ``config`` without ``classes``. Changing only the bins
        (or ``classes: auto``'s settings, where it picks the same count) reuses the rows."""
        settings = {k: v for k, v in self._settings_as_read().items() if k not in BINS_KEYS}
        sources = {"network": _sha256(self.network_path)}
        if self.spec is not None:
            blob = json.dumps(settings, sort_keys=True, default=str)
            sources["spec"] = hashlib.sha256(blob.encode()).hexdigest()
        classes = self.internal.count_classes
        if classes is not None:
            sources["class_count"] = classes.variable
        kept = {k: v for k, v in config.items() if k not in BINS_KEYS}
        return {"model": kept, "model_sources": sources}

    def observable_label(self, name: str) -> str:
        """The body's figure labels."""
        return self.body.observable_label(name)

    def describe(self) -> str:
        """One line for reports."""
        internal = self.internal
        return (
            f"{self.name}: SBML network {self.network_path.name} ({len(internal.species)} "
            f"species, {internal.reactions.n_reactions} reactions, inputs "
            f"{list(internal.signal_names)}) in a {self.settings['body'].get('kind')} body; "
            f"{internal.lump_names[1]} iff {self.settings['lump']}"
        )

    def to_config(self) -> dict[str, Any]:
        """The resolved spec (for manifests)."""
        return {"name": self.name, **{k: v for k, v in self.settings.items() if k != "name"},
                "network": str(self.network_path)}  # fmt: skip
