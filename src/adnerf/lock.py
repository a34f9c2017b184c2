"""One writer per output folder: a lock file beside the folder, taken before any write.

Two trainings of one run folder, or two preprocessings into one dataset, would interleave their
checkpoints and logs. A command that writes a folder holds :class:`FolderLock` on it for its whole
run. The lock is a file ``.NAME.adnerf-lock`` in the folder's parent (beside it, so it exists
before the folder does and survives the folder's atomic replacement), created with ``O_EXCL``
(atomic: of two processes only one creates it), holding the owner's process id, host, start
time and command line as JSON.

A second writer is refused with one line that names the owner. A lock whose owner is gone (killed
with ``kill -9``, a crash, a reboot: same host and no such process, or a process of that id
started after the lock was taken) is taken over with a warning. A lock of another host cannot be
checked and is refused; the message says which file to remove if that process is gone.
Readers of a folder (rendering a run that is being trained) do not take the lock:
:func:`lock_owner` tells them who writes it.
"""

from __future__ import annotations

import functools
import inspect
import json
import os
import socket
import sys
import time
import warnings
from pathlib import Path
from typing import Callable, TypeVar

__all__ = ["FolderBusyError", "FolderLock", "lock_owner", "lock_path", "writes_folder"]

F = TypeVar("F", bound=Callable)


class FolderBusyError(ValueError):
    """Another live process writes the folder."""


def lock_path(folder: str | Path) -> Path:
    """The lock file of ``folder``: ``.NAME.adnerf-lock`` beside it."""
    folder = Path(folder).absolute()
    return folder.with_name(f".{folder.name}.adnerf-lock")


def _boot_ticks(pid: int) -> int | None:
    """When process ``pid`` started, in clock ticks since boot (Linux ``/proc``), or ``None``."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[19])
    except (OSError, ValueError, IndexError):
        return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by another user
        return True
    return True


def _read(path: Path) -> dict | None:
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        return {}  # written halfway (a crash between create and write): no owner to honour
    return doc if isinstance(doc, dict) else {}


def lock_owner(folder: str | Path) -> dict | None:
    """The live process that holds ``folder``'s lock (its JSON: ``pid``, ``host``, ``started``,
    ``command``), or ``None`` when no lock is held or its owner is gone."""
    doc = _read(lock_path(folder))
    if not doc:
        return None
    return doc if not _stale(doc) else None


def _stale(doc: dict) -> bool:
    """Whether a lock's owner is certainly gone (only decidable on the same host)."""
    if doc.get("host") != socket.gethostname():
        return False
    pid = doc.get("pid")
    if not isinstance(pid, int) or not _alive(pid):
        return True
    ticks = doc.get("boot_ticks")
    now = _boot_ticks(pid)
    return ticks is not None and now is not None and now != ticks  # the id was reused


def _describe(doc: dict) -> str:
    since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(doc["started"])) if isinstance(doc.get("started"), (int, float)) else "?"
    return f"process {doc.get('pid')} on {doc.get('host')} ({doc.get('command', '?')}, since {since})"


class FolderLock:
    """Hold ``folder``'s lock while the ``with`` block runs (see the module docstring).

    Args:
        folder: The folder to be written (it need not exist yet).
        what: What is written, for messages (``"run"``, ``"dataset"``, ``"frames folder"``).

    A process that holds the lock may enter it again (nested): only the outermost holder
    releases it.

    Raises:
        FolderBusyError: On entry, when a live process (or one of another host) holds the lock.
    """

    def __init__(self, folder: str | Path, what: str = "folder") -> None:
        self.folder, self.what = Path(folder), what
        self.path = lock_path(folder)
        self.held = False

    def __enter__(self) -> "FolderLock":
        me = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time(), "boot_ticks": _boot_ticks(os.getpid()), "command": " ".join(Path(sys.argv[0]).name.split() + sys.argv[1:])[:200]}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(3):  # a stale lock taken over, then created anew; a race lost is re-read
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                doc = _read(self.path)
                if doc is None:
                    continue  # released meanwhile
                if doc and doc.get("pid") == os.getpid() and doc.get("host") == me["host"]:
                    return self  # this process holds it already (a command around a library call): nested, released by the outer holder
                if doc and not _stale(doc):
                    hint = "" if doc.get("host") == me["host"] else f"; if that process is gone, remove {self.path}"
                    raise FolderBusyError(f"{self.folder}: another adnerf writes this {self.what}: {_describe(doc)}; wait for it to finish or stop it{hint}")
                warnings.warn(f"{self.folder}: took over the lock of {_describe(doc) if doc else 'a process'} that is gone (killed or crashed)", stacklevel=2)
                try:
                    os.unlink(self.path)
                except FileNotFoundError:
                    pass
                continue
            with os.fdopen(fd, "w") as f:
                json.dump(me, f)
            self.held = True
            return self
        raise FolderBusyError(f"{self.folder}: could not take the lock {self.path}; another writer keeps taking it")

    def __exit__(self, *exc: object) -> None:
        if self.held:
            doc = _read(self.path)
            if doc and doc.get("pid") == os.getpid():
                self.path.unlink(missing_ok=True)
            self.held = False


def writes_folder(argument: str, what: str) -> Callable[[F], F]:
    """Decorate a function that writes the folder passed as its parameter ``argument``: it runs
    holding that folder's :class:`FolderLock` (a second call on the same folder, from another
    process, is refused with :class:`FolderBusyError` before the function starts); an optional
    folder left ``None`` takes no lock."""

    def decorate(fn: F) -> F:
        signature = inspect.signature(fn)

        @functools.wraps(fn)
        def locked(*args: object, **kwargs: object) -> object:
            folder = signature.bind(*args, **kwargs).arguments.get(argument)
            if folder is None:
                return fn(*args, **kwargs)
            with FolderLock(folder, what):
                return fn(*args, **kwargs)

        return locked  # type: ignore[return-value]

    return decorate
