"""Shared constants and helpers of the registry tests (imported by name; not a test module)."""

from __future__ import annotations

import pytest
from medc_registry.chain import ContractRevert

APP = "target_localization"
PRICE = 10**15  # 0.001 ETH


def revert_of(excinfo: pytest.ExceptionInfo) -> ContractRevert:
    """The ContractRevert of a pytest.raises block."""
    assert isinstance(excinfo.value, ContractRevert)
    return excinfo.value
