"""The exception types live in surrogate.errors; older import paths keep working."""

from __future__ import annotations

from surrogate import errors
from surrogate.models import base


def test_kernel_unsupported_is_a_config_error_reexported_by_models_base() -> None:
    assert issubclass(errors.KernelUnsupported, errors.ConfigError)
    assert base.KernelUnsupported is errors.KernelUnsupported
    assert "KernelUnsupported" in base.__all__
