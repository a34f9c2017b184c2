"""Allocator tuning: it must cut the page faults of a renderer-like allocation pattern, stay off
when asked, and be applied by the ``adnerf`` command."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

import adnerf.allocator as allocator
from adnerf.allocator import ENV_VAR, _glibc, tune_allocator
from adnerf.cli import main

# A renderer's chunk: a few layers' activations of a varying packed batch live at once (about
# 190 MB here), all freed at the end of the chunk. Prints whether tuning applied, the minor page
# faults of the 30 chunks after the first (which finds fresh memory either way), and the pages
# one chunk's tensors span.
_WORKLOAD = """
import resource, torch
from adnerf.allocator import tune_allocator
ok = tune_allocator()
g = torch.Generator().manual_seed(0)
w = torch.ones(96, 64)
for i in range(31):
    if i == 1:
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    live = []
    for _ in range(6):
        n = int(torch.randint(40000, 60000, (1,), generator=g))
        live.append(torch.ones(n, 96))
        live.append(torch.relu(live[-1] @ w))
    pages = sum(t.numel() * t.element_size() for t in live) // 4096
    del live
print(ok, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before, pages)
"""


def _run_workload(tune: bool) -> tuple[bool, int, int]:
    env = {**os.environ, ENV_VAR: "1" if tune else "0", "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", _WORKLOAD], capture_output=True, text=True, env=env, check=True).stdout.split()
    return out[0] == "True", int(out[1]), int(out[2])


@pytest.mark.skipif(_glibc() is None, reason="allocator tuning applies to glibc only")
def test_tuning_cuts_page_faults_of_varying_batches() -> None:
    tuned_ok, tuned, chunk_pages = _run_workload(tune=True)
    off_ok, off, _ = _run_workload(tune=False)
    assert tuned_ok and not off_ok
    # Tuned, freed memory is reused: the 30 chunks together fault in less than one chunk's pages
    # (measured here: 7 to 27 k faults against 45 k pages). Untuned, or with only the mmap
    # threshold fixed (trim then stays at 128 KiB), they took 0.16 to 1.5 M.
    assert tuned < chunk_pages < off, (tuned, chunk_pages, off)


def test_opt_out_and_bad_values(monkeypatch: pytest.MonkeyPatch) -> None:
    for value in ("0", "off", "False"):
        monkeypatch.setenv(ENV_VAR, value)
        assert tune_allocator() is False
    monkeypatch.setenv(ENV_VAR, "1")
    with pytest.raises(ValueError):
        tune_allocator(mmap_threshold=-1)
    assert tune_allocator(mmap_threshold=2**40) is False  # beyond mallopt's int: refused, not wrapped


def test_the_command_tunes_the_allocator(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    calls = []
    monkeypatch.setattr(allocator, "tune_allocator", lambda: calls.append(1) or True)
    assert main(["bench", "render", "--samples", "4", "--size", "8", "--repeats", "1"]) == 0
    assert calls == [1]
