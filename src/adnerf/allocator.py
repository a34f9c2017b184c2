"""Process-wide tuning of the C allocator (glibc ``malloc``) for PyTorch on CPU.

PyTorch allocates CPU tensors with ``malloc``. glibc serves blocks above its *mmap threshold*
with fresh ``mmap`` pages and gives freed memory at the top of the heap back to the kernel once
it exceeds the *trim threshold*. Both thresholds adapt (the mmap threshold rises to the largest
block freed so far, up to 32 MiB), but a renderer whose batches vary in size from one chunk to
the next (occupancy packing, rays that miss a layer) keeps crossing them: every few calls a
multi-megabyte activation lands on pages the kernel must fault in and zero again (dear in a
virtual machine; ``docs/decisions.md`` has the measurement).

:func:`tune_allocator` fixes the mmap threshold at glibc's 64-bit ceiling (32 MiB; larger
blocks are still mapped and unmapped directly) and the trim threshold at 1 GiB, so freed memory
below those sizes is kept and reused. The cost is that the process keeps its peak heap: the
resident size stays near the high-water mark instead of shrinking between batches.

The ``adnerf`` command calls it at start-up (and ``adnerf bench fields`` in each worker
process); library users may call it themselves. Setting the environment variable
``ADNERF_TUNE_MALLOC=0`` turns it off. It does nothing, and returns ``False``, where the C
library is not glibc (macOS, Windows, musl) or refuses a setting.
"""

from __future__ import annotations

import ctypes
import os
import sys

__all__ = ["ENV_VAR", "MMAP_THRESHOLD", "TRIM_THRESHOLD", "tune_allocator"]

ENV_VAR = "ADNERF_TUNE_MALLOC"
"""Environment variable; ``0`` (or ``false``, ``no``, ``off``) disables :func:`tune_allocator`."""

MMAP_THRESHOLD = 32 << 20
"""Bytes; blocks at least this large are mapped directly (glibc's maximum on 64-bit systems)."""

TRIM_THRESHOLD = 1 << 30
"""Bytes of free memory at the top of the heap kept before any is returned to the kernel."""

# mallopt parameter numbers from glibc's <malloc.h>.
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def _glibc() -> ctypes.CDLL | None:
    """The process's C library if it is glibc, else ``None``."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None)  # the symbols already loaded into this process
    except OSError:
        return None
    # gnu_get_libc_version exists only in glibc; musl has a mallopt that ignores everything.
    if not hasattr(libc, "gnu_get_libc_version") or not hasattr(libc, "mallopt"):
        return None
    return libc


def tune_allocator(mmap_threshold: int = MMAP_THRESHOLD, trim_threshold: int = TRIM_THRESHOLD) -> bool:
    """Fix glibc's mmap and trim thresholds for this process (see the module docs).

    Args:
        mmap_threshold: Bytes; larger blocks get their own mapping. glibc refuses more than
            32 MiB on 64-bit systems.
        trim_threshold: Bytes of free heap top kept rather than returned to the kernel.

    Returns:
        ``True`` when both settings were applied; ``False`` when turned off by
        ``ADNERF_TUNE_MALLOC=0``, when the C library is not glibc, or when glibc refused a value
        (then nothing, or only the mmap threshold, was changed).
    """
    if os.environ.get(ENV_VAR, "1").strip().lower() in ("0", "false", "no", "off"):
        return False
    if mmap_threshold < 0 or trim_threshold < 0:
        raise ValueError("allocator thresholds must be >= 0 bytes")
    libc = _glibc()
    if libc is None:
        return False
    mallopt = libc.mallopt
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    limit = 2**31 - 1
    if mmap_threshold > limit or trim_threshold > limit:
        return False
    if mallopt(_M_MMAP_THRESHOLD, mmap_threshold) != 1:
        return False
    return mallopt(_M_TRIM_THRESHOLD, trim_threshold) == 1
