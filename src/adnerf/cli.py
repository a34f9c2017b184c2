"""The ``adnerf`` command line: the list of commands, and how their errors reach the user.

Each command is a part with ``register(subparsers)`` and ``run(args)``: the user's commands in
:mod:`adnerf.commands` (options and shared option groups in :mod:`adnerf.commands.options`), the
benchmarks in :mod:`adnerf.bench.command`.
"""

from __future__ import annotations

import argparse
import errno
import signal
import sys
import threading
import warnings
from contextlib import contextmanager
from typing import Iterator, Sequence

from . import allocator, subnormals
from .atomic import DiskFullError, disk_full
from .audio.features import FeatureError
from .bench import command as bench
from .commands import check_preprocess, demo, evaluate, features, import_adnerf, lip_signal, preprocess, render, stream, synth, train
from .commands.options import CliError, HelpFormatter, with_formatter
from .formats.dataset import DatasetError
from .formats.outputs import OutputError
from .formats.run_folder import RunError
from .io import MediaError
from .lock import FolderBusyError
from .memory import MemoryNeedError
from .model.render_clip import RenderError
from .model.train import TrainingInterrupted
from .preprocess.pipeline import PreprocessError

__all__ = ["CliError", "build_parser", "main"]

# In the order `adnerf --help` lists them.
COMMANDS = (bench, features, demo, synth, preprocess, import_adnerf, check_preprocess, lip_signal, train, render, stream, evaluate)
# Exceptions whose message is for the user (bad input), printed without a traceback.
USER_ERRORS = (CliError, DatasetError, DiskFullError, FeatureError, FolderBusyError, MediaError, MemoryNeedError, OutputError, PreprocessError, RenderError, RunError)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``adnerf`` command."""
    parser = argparse.ArgumentParser(prog="adnerf", description="Audio-driven neural radiance fields for talking heads.", formatter_class=HelpFormatter)
    sub = with_formatter(parser.add_subparsers(dest="command", required=True))
    for part in COMMANDS:
        part.register(sub)
    return parser


class _Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler's notice before it kills), raised where the process is, so that a
    command stops as on Ctrl-C: atomic writes leave nothing half-written, preprocessing keeps its
    finished steps. Training handles both signals itself (it finishes its step first)."""


@contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():  # signals reach the main thread only
        yield
        return

    def terminate(signum: int, frame: object) -> None:
        raise _Terminated()

    before = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``adnerf`` command; returns the exit status."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # argparse: a refused argument (2, message printed) or --help (0)
        return int(exc.code or 0)
    allocator.tune_allocator()  # keeps freed tensor memory for reuse: fewer page faults (ADNERF_TUNE_MALLOC=0: off)
    subnormals.flush_subnormals()  # before torch starts its worker threads, which take the setting (ADNERF_FLUSH_SUBNORMALS=0: off)
    try:
        with _sigterm_as_interrupt(), warnings.catch_warnings():
            warnings.showwarning = lambda message, *rest, **kw: print(f"adnerf: warning: {message}", file=sys.stderr)
            return int(args.func(args))
    except USER_ERRORS as exc:
        print(f"adnerf: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        # a write outside atomic_path (frames of a dataset, PNGs)
        message = disk_full(exc.filename) if exc.filename else "the disk is full (no space left on the device); free some space and run the same command again"
        print(f"adnerf: error: {message}", file=sys.stderr)
        return 2
    except TrainingInterrupted as exc:
        print(f"adnerf: {exc}", file=sys.stderr)
        return 128 + exc.signum  # 130 for SIGINT, 143 for SIGTERM, as the shell reports a signal
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (_Terminated): what was finished is kept
        print(f"adnerf: {str(exc) or 'interrupted'}", file=sys.stderr)
        return 143 if isinstance(exc, _Terminated) else 130


if __name__ == "__main__":
    sys.exit(main())
