"""Where a command may write: the checks every command runs on its outputs before any work.

The rules, the same for every command:

- A folder output (a dataset, a run) is created new, or fills an empty folder. An existing folder
  with files in it is replaced only with ``overwrite`` and only when it holds an adnerf folder of
  the same kind (its marker file: ``meta.json`` of format ``adnerf-dataset``, ``run.json`` of
  format ``adnerf-run``). A folder that holds one of the command's inputs, the current folder
  and the folders above it are never replaced.
- A file output never names one of the command's inputs, and an existing file is replaced only
  with ``overwrite``.
- The place an output goes must be writable; this is probed before the work starts, so a long
  render does not fail at its end.

Every refusal is an :class:`OutputError` whose message names the path and the way out.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from pathlib import Path
from typing import Iterable, Literal

__all__ = ["MARKERS", "OutputError", "check_file_output", "check_folder_output", "check_frames_folder", "ensure_writable", "folder_kind"]

FolderKind = Literal["dataset", "run"]
MARKERS: dict[str, tuple[str, str]] = {"dataset": ("meta.json", "adnerf-dataset"), "run": ("run.json", "adnerf-run")}


class OutputError(ValueError):
    """An output path that a command must not write (it would lose a user's file or cannot be written)."""


def folder_kind(folder: str | Path) -> str | None:
    """``"dataset"`` or ``"run"`` when ``folder`` holds that adnerf folder's marker file, else ``None``."""
    for kind, (name, fmt) in MARKERS.items():
        try:
            doc = json.loads((Path(folder) / name).read_text())
        except (OSError, ValueError):
            continue
        if isinstance(doc, dict) and doc.get("format") == fmt:
            return kind
    return None


def _inside(path: Path, folder: Path) -> bool:
    """Whether ``path`` is ``folder`` or lies below it (both already resolved)."""
    return path == folder or folder in path.parents


def ensure_writable(folder: str | Path) -> None:
    """Raise :class:`OutputError` unless files can be created in ``folder`` (or, when it does not
    exist yet, in its nearest existing ancestor, which must be a folder).

    Probes by creating and removing a temporary file, so read-only file systems and missing
    permissions are found the same way for root and other users.
    """
    target = Path(folder)
    probe = target
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        raise OutputError(f"{target}: cannot create it, {probe} is a file, not a folder")
    try:
        fd, name = tempfile.mkstemp(prefix=".adnerf-probe", dir=probe)
    except OSError as exc:
        raise OutputError(f"{target}: cannot write there ({exc.strerror or exc}); choose a writable folder") from exc
    os.close(fd)
    os.unlink(name)


def check_folder_output(out: str | Path, kind: FolderKind, *, inputs: Iterable[str | Path] = (), overwrite: bool = False, flag: str | None = "--overwrite") -> None:
    """Refuse a destination folder that the command must not create or replace.

    Args:
        out: The destination folder.
        kind: What will be written there: ``"dataset"`` or ``"run"``.
        inputs: The command's input paths; a folder holding one is never replaced.
        overwrite: Whether the user asked to replace an existing adnerf folder of this kind.
        flag: The option that asks for replacement, named in the messages; ``None`` for a
            command that never replaces a folder.

    Raises:
        OutputError: ``out`` is a file; is the current folder or above it; holds an input; holds
            files and ``overwrite`` is off; holds files but no adnerf ``kind``; or is not writable.
    """
    out = Path(out)
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise OutputError(f"{out}: is a file, not a folder; give a new folder for the {kind}")
        real = out.resolve()
        if _inside(Path.cwd().resolve(), real):
            raise OutputError(f"{out}: is the current folder or one above it; give a new folder for the {kind}")
        for item in inputs:
            if _inside(Path(item).resolve(), real):
                raise OutputError(f"{out}: holds this command's input {item}; give another folder for the {kind}")
        if any(real.iterdir()):
            marker, fmt = MARKERS[kind]
            if not overwrite:
                how = f" (or {flag} to replace the adnerf {kind} there)" if flag else ""
                raise OutputError(f"{out}: already exists and is not empty; choose a new or empty folder{how}")
            if folder_kind(real) != kind:
                raise OutputError(
                    f"{out}: is not an adnerf {kind} (no {marker} of format {fmt!r}); {flag} only replaces a folder adnerf made, so choose another folder"
                )
    ensure_writable(out.parent if not out.exists() else out)


def check_file_output(out: str | Path, *, inputs: Iterable[str | Path | None] = (), overwrite: bool = False, flag: str = "--overwrite") -> None:
    """Refuse an output file that would replace an input, or an existing file without ``overwrite``.

    Raises:
        OutputError: ``out`` is a folder, is one of ``inputs`` (by path or by inode), exists and
            ``overwrite`` is off, or its folder is not writable.
    """
    out = Path(out)
    if out.is_dir():
        raise OutputError(f"{out}: is a folder; give a file name")
    for item in inputs:
        if item is None:
            continue
        src = Path(item)
        same = out.resolve() == src.resolve() or (out.exists() and src.exists() and os.path.samefile(out, src))
        if same:
            raise OutputError(f"{out}: is also an input of this command ({item}); choose another output name")
    if out.exists() and not overwrite:
        raise OutputError(f"{out}: already exists; choose another name, or pass {flag} to replace it")
    ensure_writable(out.parent)


def check_frames_folder(folder: str | Path, pattern: str = r"\d{6}\.png", *, overwrite: bool = False, flag: str = "--overwrite") -> None:
    """Refuse a folder for numbered frame images that would replace files it must not.

    Args:
        folder: Where the images go (created if missing).
        pattern: Regular expression of the file names that will be written (whole name).
        overwrite: Whether existing files matching ``pattern`` may be replaced.

    Raises:
        OutputError: ``folder`` is a file; belongs to an adnerf dataset or run (e.g. a dataset's
            ``frames/``); already holds a file matching ``pattern`` and ``overwrite`` is off; or
            is not writable.
    """
    d = Path(folder)
    if d.exists() and not d.is_dir():
        raise OutputError(f"{d}: is a file, not a folder")
    real = d.resolve()
    for owner in [real, *real.parents]:
        kind = folder_kind(owner)
        if kind is not None:
            raise OutputError(f"{d}: lies inside the adnerf {kind} {owner}; write the frames to a folder of their own")
    if d.is_dir() and not overwrite:
        clash = sorted(name for name in os.listdir(d) if re.fullmatch(pattern, name))
        if clash:
            raise OutputError(f"{d}: already holds {clash[0]} (and {len(clash) - 1} more frame images); choose an empty folder, or pass {flag} to replace them")
    ensure_writable(d)
