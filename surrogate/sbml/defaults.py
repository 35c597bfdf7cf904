"""Attributes SBML Level 3 requires and a file omits, read with Level 2's defaults.

SBML Level 2 gave the boolean attributes of compartments, species, parameters, reactions,
species references, events and triggers default values; Level 3 made them required. Exporters
that write Level 3 with Level 2's habits omit them (every model of Wilkinson's *Stochastic
Modelling for Systems Biology* collection at its repository's head: 7-82 libsbml errors each,
all of this kind), and libsbml reports each omission as an error. Where an omitted attribute had
a Level 2 default, the file is read with that default (the value libsbml's own Level 2 -> 3
conversion writes), with one :class:`~surrogate.sbml.errors.SbmlWarning` listing every attribute
filled and the elements concerned; every other error still refuses the file.

The defaults (SBML L2V4 and libsbml's conversion): compartment ``constant=true``; species
``hasOnlySubstanceUnits=false``, ``boundaryCondition=false``, ``constant=false``; parameter
``constant=true`` (``false`` where a rule assigns it); reaction ``reversible=true`` (then the
reader's one-way rule applies: a one-way law is read as irreversible, with its own warning),
``fast=false``; species reference ``constant=true``; event ``useValuesFromTriggerTime=true``;
trigger ``initialValue=true``, ``persistent=true``.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import libsbml

__all__ = ["LEVEL2_DEFAULTS", "fill_level2_defaults"]

#: libsbml's error id for an element's required attributes -> the element, and each omitted
#: attribute's Level 2 default
LEVEL2_DEFAULTS: dict[int, tuple[str, dict[str, bool]]] = {
    20517: ("compartment", {"constant": True}),
    20623: (
        "species",
        {"hasOnlySubstanceUnits": False, "boundaryCondition": False, "constant": False},
    ),
    20706: ("parameter", {"constant": True}),
    21110: ("reaction", {"reversible": True, "fast": False}),
    21116: ("speciesReference", {"constant": True}),
    21225: ("event", {"useValuesFromTriggerTime": True}),
    21226: ("trigger", {"initialValue": True, "persistent": True}),
}

_MISSING = re.compile(r"required attribute '(\w+)' is missing", re.IGNORECASE)


def _omitted(error: libsbml.SBMLError) -> tuple[str, str] | None:
    """(element, attribute) where ``error`` is a required attribute with a Level 2 default
    that the file omits, else None."""
    entry = LEVEL2_DEFAULTS.get(error.getErrorId())
    found = _MISSING.search(error.getMessage())
    if entry is None or found is None:
        return None
    element, defaults = entry
    # libsbml spells one of them 'useValuesfromTriggerTime' in its message
    names = {name.lower(): name for name in defaults}
    name = names.get(found.group(1).lower())
    return None if name is None else (element, name)


def _elements(model: libsbml.Model, element: str) -> Iterator[tuple[str, Any]]:
    """(label, object) of every element of one kind (a species reference labelled by its
    reaction, a trigger by its event)."""
    if element == "compartment":
        yield from ((c.getId(), c) for c in model.getListOfCompartments())
    elif element == "species":
        yield from ((s.getId(), s) for s in model.getListOfSpecies())
    elif element == "parameter":
        yield from ((p.getId(), p) for p in model.getListOfParameters())
    elif element == "reaction":
        yield from ((r.getId(), r) for r in model.getListOfReactions())
    elif element == "speciesReference":
        for r in model.getListOfReactions():
            for ref in [*r.getListOfReactants(), *r.getListOfProducts()]:
                yield f"{r.getId()}:{ref.getSpecies()}", ref
    elif element == "event":
        yield from ((e.getId() or f"event {i}", e) for i, e in enumerate(model.getListOfEvents()))
    elif element == "trigger":
        for i, e in enumerate(model.getListOfEvents()):
            if e.isSetTrigger():
                yield e.getId() or f"event {i}", e.getTrigger()


def _accessors(obj: Any, name: str) -> tuple[Callable[[], bool], Callable[[bool], int]]:
    attribute = name[0].upper() + name[1:]
    return getattr(obj, f"isSet{attribute}"), getattr(obj, f"set{attribute}")


def fill_level2_defaults(
    document: libsbml.SBMLDocument, errors: Sequence[libsbml.SBMLError]
) -> tuple[list[libsbml.SBMLError], str | None]:
    """Set every omitted attribute that ``errors`` report and Level 2 gave a default (on the
    document's model, in place).

    Args:
        document: the document libsbml read.
        errors: its errors (severity error or above).

    Returns:
        The errors left (every other one), and the warning's text listing what was filled
        (None where nothing was).
    """
    model = document.getModel()
    omitted = {pair for pair in map(_omitted, errors) if pair is not None}
    if model is None or document.getLevel() < 3 or not omitted:
        return list(errors), None
    assigned = {rule.getVariable() for rule in model.getListOfRules()}
    assigned |= {a.getVariable() for e in model.getListOfEvents()
                 for a in e.getListOfEventAssignments()}  # fmt: skip
    # (element, the elements' labels) -> the attributes filled on all of them
    filled: dict[tuple[str, tuple[str, ...]], list[str]] = {}
    for element, name in sorted(omitted):
        default = LEVEL2_DEFAULTS_BY_ELEMENT[element][name]
        labels: dict[bool, list[str]] = {}
        for label, obj in _elements(model, element):
            is_set, setter = _accessors(obj, name)
            if is_set():
                continue
            value = default
            if element == "parameter" and name == "constant" and label in assigned:
                value = False  # a parameter a rule or event assigns is not constant
            setter(value)
            labels.setdefault(value, []).append(label)
        for value, where in labels.items():
            filled.setdefault((element, tuple(where)), []).append(f"{name}={str(value).lower()}")
    listed = []
    for (element, ids), settings in filled.items():
        shown = ", ".join(ids[:6]) + (f", ... ({len(ids)} in all)" if len(ids) > 6 else "")
        listed.append(f"{element} {', '.join(settings)} ({shown})")
    left = [error for error in errors if _omitted(error) is None]
    text = (
        "read with SBML Level 2's defaults for attributes Level 3 requires and the file omits "
        "(libsbml reports each as an error; add them to the file to silence this): "
        + "; ".join(listed)
    )
    return left, text


#: element -> attribute -> its Level 2 default
LEVEL2_DEFAULTS_BY_ELEMENT: dict[str, dict[str, bool]] = dict(LEVEL2_DEFAULTS.values())
