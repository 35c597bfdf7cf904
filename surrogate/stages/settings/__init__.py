"""Typed settings of every stage, built once from a Hydra config at the stage's edge.

Each settings object validates its part of the config on construction (so a bad setting is
refused by name before any work starts), builds the objects the stage needs (model, field, GP
settings) and knows, in one place, its artefact directory (a function of its ``identity``:
exactly the settings that change the output, including ones that change the random stream such
as ``compile``) and the command that makes it. Stages receive these objects, never raw configs.

One module per stage, each importing only those before it:

* ``common``: :class:`Job`, :class:`ModelSetup`, the scripts' commands, :func:`group_overrides`;
* ``collect``: :class:`CollectSettings` (and the sequential design's fits, built lazily by
  ``train``, whose settings read collect's);
* ``occupancy``: :class:`OccupancySettings` (the train diagnostic's population);
* ``train``: :class:`TrainSettings`, :class:`ExternalTable`, the gp group's keys;
* ``decision``: :class:`DecisionSettings` (full, abstract, exact);
* ``simulate``: :class:`SimulateSettings`, :func:`check_memory`, :func:`validate_backend`;
* ``evaluate``: :class:`EvaluateSettings`;
* ``reproduce``: :class:`ReproduceSettings`, :func:`batchable`;
* ``inspection``: :class:`InspectSettings` (a model checked before collection; its costs are
  reproduce's).

Every public name is re-exported here: ``from surrogate.stages.settings import X``.
"""

from __future__ import annotations

from surrogate.kinds import GP_CLOCK  # the clock's gp keys, where they were before kinds
from surrogate.stages.settings.collect import DESIGN_KEYS, CollectSettings
from surrogate.stages.settings.common import (
    COLLECT_CMD,
    EVALUATE_CMD,
    FIDELITY_CMD,
    REPRODUCE_CMD,
    SIMULATE_CMD,
    TRAIN_CMD,
    Job,
    ModelSetup,
    command_line,
    group_overrides,
)
from surrogate.stages.settings.decision import (
    DECISION_MODES,
    DECISIONS,
    DecisionSettings,
    resolve_start,
)
from surrogate.stages.settings.evaluate import EvaluateSettings
from surrogate.stages.settings.inspection import INSPECT_CMD, InspectSettings
from surrogate.stages.settings.occupancy import OccupancySettings
from surrogate.stages.settings.reproduce import BATCH_MAX_CELLS, ReproduceSettings, batchable
from surrogate.stages.settings.simulate import (
    BYTES_PER_CELL,
    SimulateSettings,
    check_memory,
    validate_backend,
)
from surrogate.stages.settings.train import (
    DIAGNOSTIC_DEFAULTS,
    GP_EXTRA,
    GP_NOT_FIT,
    LABEL_CHOICES,
    LABEL_COLUMNS,
    ExternalTable,
    TrainSettings,
)

__all__ = [
    "BATCH_MAX_CELLS",
    "BYTES_PER_CELL",
    "COLLECT_CMD",
    "DECISIONS",
    "DECISION_MODES",
    "DESIGN_KEYS",
    "DIAGNOSTIC_DEFAULTS",
    "EVALUATE_CMD",
    "FIDELITY_CMD",
    "GP_CLOCK",
    "GP_EXTRA",
    "GP_NOT_FIT",
    "INSPECT_CMD",
    "LABEL_CHOICES",
    "LABEL_COLUMNS",
    "REPRODUCE_CMD",
    "SIMULATE_CMD",
    "TRAIN_CMD",
    "CollectSettings",
    "DecisionSettings",
    "EvaluateSettings",
    "ExternalTable",
    "InspectSettings",
    "Job",
    "ModelSetup",
    "OccupancySettings",
    "ReproduceSettings",
    "SimulateSettings",
    "TrainSettings",
    "batchable",
    "check_memory",
    "command_line",
    "group_overrides",
    "resolve_start",
    "validate_backend",
]
