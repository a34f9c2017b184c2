"""Subnormal floats flushed to zero: in the calling thread, in the worker threads torch starts
after it, off when asked, and by the ``adnerf`` command (the trainer's call: tests/test_devices.py)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

import adnerf.subnormals as subnormals
from adnerf.cli import main
from adnerf.subnormals import ENV_VAR, flush_subnormals

TINY = 1e-30  # times 1e-10: 1e-40, a subnormal float32 (the smallest normal one is 1.2e-38)


def _product() -> float:
    return float(torch.tensor(TINY) * torch.tensor(1e-10))


def test_flushing_turns_subnormal_results_into_zero(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_VAR, raising=False)
    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU cannot flush subnormals")
    assert 0.0 < _product() < 1.2e-38
    assert flush_subnormals() is True
    assert _product() == 0.0


def test_opt_out(monkeypatch: pytest.MonkeyPatch) -> None:
    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU cannot flush subnormals")
    for value in ("0", "off", "False"):
        monkeypatch.setenv(ENV_VAR, value)
        assert flush_subnormals() is False
        assert _product() > 0.0
    monkeypatch.setenv(ENV_VAR, "1")
    assert flush_subnormals() is True and _product() == 0.0


# Two worker threads multiply a long tensor into the subnormal range; prints how many results
# are not zero. Flushed before torch's first parallel operation, none is.
_WORKERS = """
import sys, torch
from adnerf.subnormals import flush_subnormals
torch.set_num_threads(2)
if sys.argv[1] == "flush":
    flush_subnormals()
x = torch.full((1 << 22,), {tiny}) * 1e-10
print(int((x != 0).sum()))
"""


def test_worker_threads_started_after_it_flush_too() -> None:
    if not torch.set_flush_denormal(True):
        pytest.skip("this CPU cannot flush subnormals")
    code = _WORKERS.format(tiny=TINY)
    env = {k: v for k, v in __import__("os").environ.items() if k not in (ENV_VAR, "OMP_NUM_THREADS")}
    counts = {how: int(subprocess.run([sys.executable, "-c", code, how], capture_output=True, text=True, check=True, env=env).stdout) for how in ("flush", "keep")}
    assert counts == {"flush": 0, "keep": 1 << 22}


def test_the_command_flushes_subnormals(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    monkeypatch.setattr(subnormals, "flush_subnormals", lambda: calls.append(1) or True)
    assert main(["bench", "render", "--samples", "4", "--size", "8", "--repeats", "1"]) == 0
    assert calls == [1]
