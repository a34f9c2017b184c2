"""The ``adnerf`` command line."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Sequence

__all__ = ["main"]


class CliError(Exception):
    """An error with a message meant for the user (printed without a traceback)."""


def _positive_int_list(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from exc
    if not values or any(v < 1 for v in values):
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return values


def _device(name: str) -> str:
    import torch

    if name == "cuda" and not torch.cuda.is_available():
        raise CliError("--device cuda was requested but no CUDA device is available (torch.cuda.is_available() is False)")
    if name not in ("cpu", "cuda"):
        raise CliError(f"unknown device {name!r}; use cpu or cuda")
    return name


def _cmd_bench_render(args: argparse.Namespace) -> int:
    import torch

    from .bench import bench_render, format_table, rows_as_dicts

    rows = bench_render(args.samples, size=args.size, repeats=args.repeats, device=_device(args.device), dtype=getattr(torch, args.dtype), sigma=args.sigma)
    table = format_table(rows)
    if args.json:
        for row in rows_as_dicts(rows):
            print(json.dumps(row), flush=True)
        print(table, file=sys.stderr)
    else:
        print(table)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``adnerf`` command."""
    parser = argparse.ArgumentParser(prog="adnerf", description="Audio-driven neural radiance fields for talking heads.")
    sub = parser.add_subparsers(dest="command", required=True)

    bench = sub.add_parser("bench", help="benchmarks: error against run time")
    bench_sub = bench.add_subparsers(dest="bench_command", required=True)
    render = bench_sub.add_parser("render", help="quadrature error of rendering an analytic sphere vs samples per ray, and time")
    render.add_argument("--json", action="store_true", help="print one JSON line per configuration (the table goes to stderr)")
    render.add_argument("--samples", type=_positive_int_list, default=(8, 16, 32, 64, 128, 256), help="comma-separated samples per ray")
    render.add_argument("--size", type=int, default=128, help="image side in pixels (default 128)")
    render.add_argument("--repeats", type=int, default=3, help="timed repeats; the best is reported")
    render.add_argument("--device", default="cpu", help="cpu or cuda")
    render.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    render.add_argument("--sigma", type=float, default=10.0, help="density of the analytic sphere (default 10: surface-like)")
    render.set_defaults(func=_cmd_bench_render)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``adnerf`` command; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except CliError as exc:
        print(f"adnerf: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("adnerf: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
