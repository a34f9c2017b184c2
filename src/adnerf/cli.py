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


def _emit(rows: list[dict], table: str, as_json: bool) -> None:
    """Benchmark output: JSON lines on stdout and the table on stderr, or the table alone on stdout."""
    if as_json:
        for row in rows:
            print(json.dumps(row), flush=True)
        print(table, file=sys.stderr)
    else:
        print(table)


def _cmd_bench_render(args: argparse.Namespace) -> int:
    import torch

    from .bench import bench_render, format_table, rows_as_dicts

    rows = bench_render(args.samples, size=args.size, repeats=args.repeats, device=_device(args.device), dtype=getattr(torch, args.dtype), sigma=args.sigma)
    _emit(rows_as_dicts(rows), format_table(rows), args.json)
    return 0


def _cmd_bench_features(args: argparse.Namespace) -> int:
    from .bench import bench_features
    from .io import MediaError

    try:
        rows = bench_features(args.media, seconds=args.seconds, repeats=args.repeats)
    except MediaError as exc:
        raise CliError(str(exc)) from exc
    lines = [f"{'extractor':<10}  {'audio s':>8}  {'wall s':>7}  {'x real time':>11}"]
    lines += [f"{r['kind']:<10}  {r['audio_seconds']:>8.1f}  {r['wall_seconds']:>7.2f}  {r['realtime_factor']:>11.1f}" for r in rows]
    _emit(rows, "\n".join(lines), args.json)
    return 0


def _cmd_features(args: argparse.Namespace) -> int:
    import math
    from pathlib import Path

    import numpy as np
    from tqdm import tqdm

    from .features import MODEL_RATE, FeatureError, FeatureSpec, save_npy_atomic, speech_windows
    from .io import MediaError, frame_times, probe, read_audio

    media, out = Path(args.media), Path(args.output)
    if out.suffix != ".npy":
        raise CliError(f"{out}: the output must be a .npy file")
    try:
        audio = read_audio(media)  # raises "has no audio track" itself
        if args.fps is None and probe(media)["video"]:
            times = frame_times(media)
            source = "video timestamps"
        else:
            fps = args.fps or 25.0
            if fps <= 0:
                raise CliError(f"--fps must be positive; got {fps}")
            times = np.arange(max(1, math.ceil(audio.duration * fps))) / fps + audio.start
            source = f"{fps:g} fps"
        with tqdm(total=round(audio.duration, 1), unit="s", desc=f"{args.kind} features", disable=audio.duration < 30 or None) as bar:
            spec = FeatureSpec(args.kind, model_dir=args.model_dir)
            windows = speech_windows(audio, times, spec, progress=lambda n: bar.update(round(n / MODEL_RATE, 2)))
    except (MediaError, FeatureError) as exc:
        raise CliError(str(exc)) from exc
    save_npy_atomic(out, windows)
    print(f"{out}: {windows.shape[0]} frames ({source}) x {windows.shape[1]} x {windows.shape[2]} {args.kind} features from {audio.duration:.2f} s of audio")
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
    fbench = bench_sub.add_parser("features", help="speech feature extraction speed (seconds of audio per second)")
    fbench.add_argument("--media", default=None, help="audio/video file to use (default: 60 s of synthetic voiced audio)")
    fbench.add_argument("--seconds", type=float, default=60.0, help="length of the synthetic audio")
    fbench.add_argument("--repeats", type=int, default=2)
    fbench.add_argument("--json", action="store_true", help="JSON lines on stdout, table on stderr")
    fbench.set_defaults(func=_cmd_bench_features)

    feats = sub.add_parser("features", help="per-frame speech feature windows (N, 16, D) of a video or audio file")
    feats.add_argument("media", help="video (frames timed by its timestamps) or audio file (wav, mp3, m4a, flac, ...)")
    feats.add_argument("-o", "--output", required=True, help="output .npy file")
    feats.add_argument("--kind", choices=("phonemes", "logmel", "wav2vec2"), default="phonemes", help="extractor (default: phonemes, hama's IPA log-probs)")
    feats.add_argument("--model-dir", default=None, help="local wav2vec2 / HuBERT model directory for --kind wav2vec2")
    feats.add_argument("--fps", type=float, default=None, help="frame rate for audio-only input (default 25); overrides a video's timestamps")
    feats.set_defaults(func=_cmd_features)
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
