"""Contract tests as a library (as GPyTorch's ``BaseKernelTestCase``): base test classes that a
plug-in's tests inherit, so every chain kind, internal model, body and field, shipped or a
user's, is held to the same contract by construction.

Each class is a plain class whose ``test_*`` methods pytest runs once a test module subclasses
it under a ``Test*`` name and fills its factory (``make_kind``, ``make_internal``,
``make_body``, ``make_field``); the classes import neither pytest nor a stage, and no module of
the package imports them.

Example:
    >>> from surrogate.fields import GaussianField
    >>> from surrogate.testing import FieldContract
    >>> class TestGaussianField(FieldContract):
    ...     def make_field(self):
    ...         return GaussianField()
    >>> TestGaussianField().test_values_are_per_cell_finite_and_non_negative()
"""

from surrogate.testing.body import BodyContract
from surrogate.testing.field import FieldContract
from surrogate.testing.internal import InternalModelContract
from surrogate.testing.kind import ChainKindContract, telegraph_sequences

__all__ = [
    "BodyContract",
    "ChainKindContract",
    "FieldContract",
    "InternalModelContract",
    "telegraph_sequences",
]
