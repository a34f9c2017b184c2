"""Shared fixtures of the geometry-correctness suite.

Error tables that a check measures are added with the ``report`` fixture and printed at the end
of the pytest run (``pytest_terminal_summary``; under pytest-xdist each worker hands its lines to
the main process), so every CI log carries them.
"""

from __future__ import annotations

from typing import Callable

import pytest
import torch

_REPORT: list[str] = []

# Tolerances per dtype: (relative, absolute) for quantities of order one.
TOLERANCES = {torch.float32: (2e-5, 1e-6), torch.float64: (1e-12, 1e-14)}


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request: pytest.FixtureRequest) -> torch.dtype:
    """Run a check in float32 and in float64."""
    return request.param


@pytest.fixture
def tol(dtype: torch.dtype) -> dict[str, float]:
    """``rtol`` / ``atol`` for ``torch.testing.assert_close`` at the current dtype."""
    rtol, atol = TOLERANCES[dtype]
    return {"rtol": rtol, "atol": atol}


@pytest.fixture
def report() -> Callable[[str], None]:
    """Append a line to the error report printed after the run."""
    return _REPORT.append


def pytest_sessionfinish(session: pytest.Session) -> None:
    """A worker process of pytest-xdist hands its lines to the process that prints the summary."""
    output = getattr(session.config, "workeroutput", None)
    if output is not None:
        output["geometry_report"] = list(_REPORT)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error) -> None:  # noqa: ANN001
    """The summary's process collects the lines of each pytest-xdist worker as it finishes."""
    _REPORT.extend(getattr(node, "workeroutput", {}).get("geometry_report", []))


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:  # noqa: ANN001
    if _REPORT:
        terminalreporter.section("geometry error report")
        for line in _REPORT:
            terminalreporter.write_line(line)
