"""Atomic file writing: readers never see a half-written file, failures leave none behind."""

from __future__ import annotations

import errno
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["DiskFullError", "atomic_path", "disk_full"]

FULL = (errno.ENOSPC, errno.EDQUOT)


class DiskFullError(OSError):
    """A write ran out of disk space (or quota); the file it would have replaced is intact."""

    def __str__(self) -> str:
        return str(self.strerror)


def disk_full(path: str | Path, written: int | None = None) -> DiskFullError:
    """The one-line error for a write to ``path`` that found the disk full: the folder, the space
    free there and, when known, how far the write had got (``written`` bytes)."""
    folder = Path(path).absolute().parent
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        free = None
    got = f"; the write had reached {written / 2**20:.1f} MiB when it stopped, so it needs more than that" if written else ""
    room = f" ({free / 2**20:.1f} MiB free there)" if free is not None else ""
    return DiskFullError(errno.ENOSPC, f"{folder}: the disk is full{room} writing {Path(path).name}{got}; the previous file, if any, is kept: free some space and run the same command again")


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` to write; on success it is renamed onto ``path``.

    The temporary name keeps the suffix (some writers choose the format by it) and is removed if
    the block raises. The parent folder is created when missing. A write that finds the disk full
    raises :class:`DiskFullError` (see :func:`disk_full`), leaving the existing ``path`` as it was.
    """
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.tmp{os.getpid()}{out.suffix}")
    try:
        yield tmp
        os.replace(tmp, out)
    except OSError as exc:
        if exc.errno in FULL and not isinstance(exc, DiskFullError):
            raise disk_full(out, tmp.stat().st_size if tmp.exists() else None) from exc
        raise
    finally:
        tmp.unlink(missing_ok=True)
