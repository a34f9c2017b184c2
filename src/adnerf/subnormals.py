"""Subnormal floats flushed to zero on the CPU.

A float32 below 1.2e-38 is *subnormal*, and x86 cores compute with subnormals tens of times more
slowly than with normal numbers. Training makes them in numbers: Adam's first moment of a
tri-plane cell that no ray reached for a while decays by 0.9 a step and falls below that bound
after about 830 steps, and a density far below zero gives a softplus in that range. On two CPU
cores a demo step of 512 rays took 65-70 ms for the first 700 steps and 100-125 ms after 800
(``docs/decisions.md``, *Subnormal floats are flushed to zero*). Flushed to zero they cost
nothing; no result of adnerf depends on a number that small (transmittance, weights and their
sums are handled at zero explicitly).

:func:`flush_subnormals` turns the flushing on for the calling thread (``torch.set_flush_denormal``:
results and inputs below the bound become zero). A new thread takes the setting of the thread
that creates it, so it must come before torch's first parallel operation starts its worker
threads: the ``adnerf`` command calls it at start-up, before any work, and so do
:func:`~adnerf.model.train.train`, :func:`~adnerf.commands.demo.run_demo` and the trainer when they
start. In a process that already ran parallel torch work (a notebook that rendered first), the
worker threads keep subnormals and a long training runs up to twice as slowly: call it first.
Setting the environment variable ``ADNERF_FLUSH_SUBNORMALS=0`` turns it off. It does nothing, and
returns ``False``, where the CPU cannot flush (``torch.set_flush_denormal`` says so).
"""

from __future__ import annotations

import os

__all__ = ["ENV_VAR", "flush_subnormals"]

ENV_VAR = "ADNERF_FLUSH_SUBNORMALS"
"""Environment variable; ``0`` (or ``false``, ``no``, ``off``) disables :func:`flush_subnormals`."""


def flush_subnormals() -> bool:
    """Flush subnormal floats to zero in this thread and the threads it creates from now on.

    Returns:
        Whether flushing is on: ``False`` when turned off by :data:`ENV_VAR` or not supported.
    """
    if os.environ.get(ENV_VAR, "").strip().lower() in ("0", "false", "no", "off"):
        return False
    import torch

    return bool(torch.set_flush_denormal(True))
