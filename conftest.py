"""Options shared by both test suites (``tests/`` and ``geometry/``).

``pytest --device cuda`` runs the device-marked tests (those taking the ``device`` fixture) on the
GPU; the default is ``cpu``. On a machine without CUDA those tests skip with a reason, and nothing
else changes.
"""

from __future__ import annotations

import pytest
import torch


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device", default="cpu", choices=("cpu", "cuda"), help="device of the device-marked tests (default cpu)")


@pytest.fixture
def device(request: pytest.FixtureRequest) -> torch.device:
    """The device chosen with ``--device``; skips when it is CUDA and none is available."""
    name = request.config.getoption("--device")
    if name == "cuda" and not torch.cuda.is_available():
        pytest.skip("--device cuda: no CUDA device available (torch.cuda.is_available() is False)")
    return torch.device(name)
