"""How much memory a clip needs, and a refusal before work that would not fit.

A clip of minutes at 512 px is gigabytes even as uint8 frames; a process that runs out of memory is
killed by the kernel with no word. Commands that hold a whole clip check first
(:func:`require`): what they would hold against what the machine has available, and refuse in one
line that gives both.
"""

from __future__ import annotations

import os

__all__ = ["MemoryNeedError", "available_bytes", "gib", "peak_rss_bytes", "require"]

HEADROOM = 0.9
"""Share of the available memory a clip may take: the rest is for the model, the batch and the
libraries."""


class MemoryNeedError(ValueError):
    """A clip would not fit in the memory this machine (or device) has available."""


def gib(n: float) -> str:
    """Bytes as ``"1.23 GiB"``."""
    return f"{n / 2**30:.2f} GiB"


def _proc_kib(path: str, key: str) -> int | None:
    """Bytes of a ``KEY:  N kB`` line of a Linux ``/proc`` file; ``None`` where there is none."""
    try:
        with open(path) as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def peak_rss_bytes() -> int | None:
    """This process's peak resident memory since it started its program: Linux's ``VmHWM``
    (``/proc/self/status``), else ``getrusage``'s ``ru_maxrss``; ``None`` when unknown.

    ``VmHWM`` belongs to the address space that ``exec`` created, so a child process started from a
    large parent reports its own peak; ``ru_maxrss`` (the fallback) also counts the pages the child
    shared with its parent between ``fork`` and ``exec``.
    """
    peak = _proc_kib("/proc/self/status", "VmHWM")
    if peak is not None:
        return peak
    try:
        import resource
        import sys

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return int(peak) if sys.platform == "darwin" else int(peak) * 1024  # macOS: bytes; Linux: KiB
    except (ImportError, OSError):  # pragma: no cover - no resource module (Windows)
        return None


def available_bytes() -> int | None:
    """Memory available to a new allocation without swapping: Linux's ``MemAvailable``
    (``/proc/meminfo``), else free physical pages (``os.sysconf``); ``None`` when unknown."""
    available = _proc_kib("/proc/meminfo", "MemAvailable")
    if available is not None:
        return available
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def require(need: int, what: str, *, available: int | None = None, where: str = "this machine") -> None:
    """Raise :class:`MemoryNeedError` when ``need`` bytes exceed :data:`HEADROOM` of the memory
    available (``available``, default :func:`available_bytes`; nothing is checked when unknown).

    Args:
        need: Bytes the work would hold.
        what: What needs them, for the message (e.g. ``"data/me: 9000 frames of 512x512"``).
        available: Bytes available (a GPU's free memory, say); ``None``: this machine's.
        where: Whose memory ``available`` is, for the message.
    """
    have = available_bytes() if available is None else available
    if have is not None and need > HEADROOM * have:
        raise MemoryNeedError(f"{what} need {gib(need)} of memory; {where} has {gib(have)} available (use a shorter clip or a smaller frame size)")
