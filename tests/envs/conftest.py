"""Fixtures shared by the environment tests."""

from __future__ import annotations

import pytest
from medc_training.envs import ENV_NAMES


@pytest.fixture(params=ENV_NAMES)
def name(request: pytest.FixtureRequest) -> str:
    """Each application in turn."""
    return request.param
