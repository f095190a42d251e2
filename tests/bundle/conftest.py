"""Fixtures shared by the bundle tests."""

import pytest
from bundle_forge import valid_parts


@pytest.fixture(scope="module")
def parts():
    """The tensors and manifest of a valid LeNet-5 bundle on a 10x10 grid (tests edit copies)."""
    return valid_parts("lenet5", grid=10)
