"""What every command part shares: argument types, the help format, the option groups several
commands declare alike, and how a command reports to the user.

Each command is a module of this room (or of ``bench/`` for the benchmarks) with
``register(subparsers)`` and ``run(args)``; :mod:`adnerf.cli` only lists them.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any, Callable

__all__ = [
    "CliError",
    "HelpFormatter",
    "add_device",
    "add_json",
    "add_metric_weights",
    "add_overwrite",
    "angle",
    "checked_device",
    "config_file",
    "count",
    "emit",
    "head_torso_iters",
    "log",
    "number",
    "positive",
    "positive_float_list",
    "positive_int_list",
    "with_formatter",
]


class CliError(Exception):
    """An error with a message meant for the user (printed without a traceback)."""


def positive_list(cast: type, what: str) -> Callable[[str], tuple]:
    """An argparse type: comma-separated positive values of type ``cast``."""

    def parse(text: str) -> tuple:
        try:
            values = tuple(cast(v) for v in text.split(","))
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"expected comma-separated {what}, got {text!r}") from exc
        if not values or any(not v > 0 for v in values):
            raise argparse.ArgumentTypeError(f"expected positive {what}, got {text!r}")
        return values

    return parse


positive_int_list = positive_list(int, "integers")
positive_float_list = positive_list(float, "numbers")


def head_torso_iters(text: str) -> tuple[int, int]:
    """An argparse type: ``HEAD,TORSO`` positive iteration counts."""
    values = positive_int_list(text)
    if len(values) != 2:
        raise argparse.ArgumentTypeError(f"expected HEAD,TORSO iterations, got {text!r}")
    return values


def number(cast: type, lo: float | None = None, hi: float | None = None, *, open_lo: bool = False) -> Callable[[str], Any]:
    """An argparse type: a finite ``cast`` (int or float) in ``[lo, hi]`` (``(lo, hi]`` with ``open_lo``)."""

    def parse(text: str) -> Any:
        try:
            value = cast(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if cast is int else 'a number'}, got {text!r}") from exc
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        if lo is not None and (value <= lo if open_lo else value < lo):
            raise argparse.ArgumentTypeError(f"must be {'>' if open_lo else '>='} {lo:g}; got {text}")
        if hi is not None and value > hi:
            raise argparse.ArgumentTypeError(f"must be <= {hi:g}; got {text}")
        return value

    parse.__name__ = "integer" if cast is int else "number"  # argparse names the type in its message
    return parse


positive = number(float, 0.0, open_lo=True)
count = number(int, 0)


def angle(text: str) -> Any:
    """An argparse type: degrees, a ``.npy`` of per-frame angles or ``sway:A,P`` (:func:`adnerf.commands.pose_edits.parse_angle`)."""
    from .pose_edits import parse_angle

    try:
        return parse_angle(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


class HelpFormatter(argparse.HelpFormatter):
    """Help lines end with the option's default (where it has a meaningful one)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "%(default)" in text or "default" in text or any(action.default is v for v in (None, False, argparse.SUPPRESS)) or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


def with_formatter(subparsers: Any) -> Any:
    """Make every parser ``subparsers.add_parser`` creates show defaults in its help; returns ``subparsers``."""
    add_parser = subparsers.add_parser

    def add(*args: Any, **kwargs: Any) -> argparse.ArgumentParser:
        kwargs.setdefault("formatter_class", HelpFormatter)
        return add_parser(*args, **kwargs)

    subparsers.add_parser = add
    return subparsers


def add_device(parser: argparse.ArgumentParser, help: str = "cpu or cuda") -> None:
    parser.add_argument("--device", default="cpu", help=help)


def add_json(parser: argparse.ArgumentParser, help: str = "one JSON object on stdout") -> None:
    parser.add_argument("--json", action="store_true", help=help)


def add_overwrite(parser: argparse.ArgumentParser, help: str) -> None:
    parser.add_argument("--overwrite", action="store_true", help=help)


def add_metric_weights(parser: argparse.ArgumentParser) -> None:
    """The local weights of the learned metrics (LPIPS, SyncNet): nothing is downloaded."""
    parser.add_argument("--lpips-backbone", default=None, help="AlexNet weights for LPIPS (default: the torch hub cache's alexnet-owt-7be5be79.pth, if there)")
    parser.add_argument("--lpips-linear", default=None, help="LPIPS linear layers (default: those the lpips package ships, if installed)")
    parser.add_argument("--syncnet", default=None, metavar="CHECKPOINT", help="SyncNet checkpoint (syncnet_v2.model of the public release) for LSE-D / LSE-C; without it they read \"no weights\" (nothing is downloaded)")


def checked_device(name: str) -> str:
    """``--device``: ``cpu``, or ``cuda`` when a CUDA device is there."""
    import torch  # lazy: the parser is built (and --help answered) without loading torch

    if name == "cuda" and not torch.cuda.is_available():
        raise CliError("--device cuda was requested but no CUDA device is available (torch.cuda.is_available() is False)")
    if name not in ("cpu", "cuda"):
        raise CliError(f"unknown device {name!r}; use cpu or cuda")
    return name


def config_file(path: str | None) -> dict:
    """``--config``: a JSON object of :class:`TrainConfig` fields (empty without the option)."""
    if not path:
        return {}
    try:
        with open(path) as f:
            doc = json.loads(f.read())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CliError(f"{path}: not a readable JSON training config ({exc})") from exc
    if not isinstance(doc, dict):
        raise CliError(f"{path}: a training config is a JSON object of TrainConfig fields (e.g. {{\"rays\": 2048}}); got a {type(doc).__name__}")
    return dict(doc)


def log(message: str) -> None:
    """Step messages of long commands: on stderr, so that --json output stays clean."""
    print(message, file=sys.stderr)


def emit(rows: list[dict], table: str, as_json: bool) -> None:
    """Benchmark output: JSON lines on stdout and the table on stderr, or the table alone on stdout."""
    if as_json:
        for row in rows:
            print(json.dumps(row), flush=True)
        print(table, file=sys.stderr)
    else:
        print(table)
