"""Options shared by both test suites (``tests/`` and ``geometry/``).

``pytest --device cuda`` runs the device-marked tests (those taking the ``device`` fixture) on the
GPU; the default is ``cpu``. On a machine without CUDA those tests skip with a reason, and nothing
else changes.

The run spreads its test files over worker processes (pytest-xdist: ``-n auto --dist loadfile``
in ``setup.cfg``; ``pytest -n 0`` runs them in one process). Each worker computes on one thread
unless the caller chose otherwise: two workers of two torch threads each on two cores run about
three times slower than one, not twice as fast.
"""

from __future__ import annotations

import os

if os.environ.get("PYTEST_XDIST_WORKER"):  # set before this worker imports torch
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import pytest  # noqa: E402
import torch  # noqa: E402

MAX_WORKERS = 4
"""``-n auto`` starts at most this many workers: each one holds a few GiB at its peak."""


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device", default="cpu", choices=("cpu", "cuda"), help="device of the device-marked tests (default cpu)")


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: one worker a core, at most :data:`MAX_WORKERS`."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, min(MAX_WORKERS, cores))


@pytest.fixture
def device(request: pytest.FixtureRequest) -> torch.device:
    """The device chosen with ``--device``; skips when it is CUDA and none is available."""
    name = request.config.getoption("--device")
    if name == "cuda" and not torch.cuda.is_available():
        pytest.skip("--device cuda: no CUDA device available (torch.cuda.is_available() is False)")
    return torch.device(name)
