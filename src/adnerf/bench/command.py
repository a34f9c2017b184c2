"""``adnerf bench ...``: the benchmarks' command parts (a ``register`` and a ``run`` each).

They live in this room because they call the benchmarks, which sit above the commands.
"""

from __future__ import annotations

import argparse
from typing import Callable

import torch

from ..audio.features import BUILTIN_KINDS
from ..commands.options import (
    CliError,
    add_device,
    add_json,
    add_metric_weights,
    checked_device,
    config_file,
    count,
    emit,
    head_torso_iters,
    log,
    number,
    positive,
    positive_float_list,
    positive_int_list,
    with_formatter,
)
from ..io import MediaError
from .fields import bench_fields, format_fields_table, plot_fields
from .real import bench_real, plot_mouth_opening
from .render import bench_features, bench_render, format_table, rows_as_dicts
from .scale import bench_scale, format_scale_table
from .voices import bench_voices, format_voices_table

__all__ = ["register"]

JSON_LINES = "JSON lines on stdout, table on stderr"
JSON_ROW = "one JSON line on stdout, the table on stderr"
VIDEO = "the clip (one person, static camera, with audio)"


def register(sub: argparse._SubParsersAction) -> None:
    """``adnerf bench`` and its benchmarks."""
    bench = sub.add_parser("bench", help="benchmarks: error against run time")
    benches = with_formatter(bench.add_subparsers(dest="bench_command", required=True))
    for part in (_register_render, _register_fields, _register_real, _register_scale, _register_voices, _register_features):
        part(benches)


def _output(rows: list[dict], table: str, args: argparse.Namespace, plot: Callable[[str], None]) -> int:
    """A benchmark's rows and table (:func:`emit`), and its plot where ``--plot`` asks for one."""
    emit(rows, table, args.json)
    if args.plot:
        plot(args.plot)
        log(f"plot: {args.plot}")
    return 0


def _register_render(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="quadrature error of rendering an analytic sphere vs samples per ray, and time")
    add_json(p, "print one JSON line per configuration (the table goes to stderr)")
    p.add_argument("--samples", type=positive_int_list, default=(8, 16, 32, 64, 128, 256), help="comma-separated samples per ray")
    p.add_argument("--size", type=number(int, 1, 4096), default=128, help="image side in pixels, 1 to 4096")
    p.add_argument("--repeats", type=number(int, 1), default=3, help="timed repeats (>= 1); the best is reported")
    add_device(p)
    p.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    p.add_argument("--sigma", type=positive, default=10.0, help="density of the analytic sphere (> 0; 10 is surface-like)")
    p.set_defaults(func=_run_render)


def _run_render(args: argparse.Namespace) -> int:
    rows = bench_render(args.samples, size=args.size, repeats=args.repeats, device=checked_device(args.device), dtype=getattr(torch, args.dtype), sigma=args.sigma)
    emit(rows_as_dicts(rows), format_table(rows), args.json)
    return 0


def _register_fields(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fields", help="held-out PSNR against training time per field configuration (paper MLP, fast grids, skipping, fine pass)")
    p.add_argument("--dataset", default=None, help="dataset folder (default: synthesise the built-in scene at --size)")
    p.add_argument("--configs", default=None, help="comma-separated: paper, fast, fast-no-skip, fast-coarse-only (default: all)")
    p.add_argument("--budget", type=positive, default=300.0, help="seconds of training per configuration (> 0)")
    p.add_argument("--checkpoints", type=positive_float_list, default=(5, 10, 20, 30, 60, 120, 300), help="training times (s) to measure PSNR at")
    p.add_argument("--size", type=number(int, 16, 1024), default=128, help="frame size of the synthesised scene, 16 to 1024")
    add_device(p)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--plot", default=None, help="write a PNG of PSNR against training time")
    add_json(p, JSON_LINES)
    p.set_defaults(func=_run_fields)


def _run_fields(args: argparse.Namespace) -> int:
    try:
        rows = bench_fields(
            args.dataset, configs=args.configs.split(",") if args.configs else None, budget=args.budget, checkpoints=args.checkpoints,
            size=args.size, device=checked_device(args.device), seed=args.seed,
            progress=True,  # bars go to stderr; --json output stays clean on stdout
        )  # fmt: skip
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    return _output(rows, format_fields_table(rows), args, lambda path: plot_fields(rows, path))


def _register_real(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("real", help="a real clip: preprocess, train within a budget, render its held-out tail, measure (PSNR, SSIM, LMD, lip sync, LPIPS)")
    p.add_argument("video", help=VIDEO)
    p.add_argument("--size", type=number(int, 0, 2048), default=256, help="longer side in pixels the clip is resized to first, 0 to keep it")
    p.add_argument("--minutes", type=number(float, 0.0, 10000.0, open_lo=True), default=10.0, help="training budget for both stages, minutes of training time")
    add_device(p)
    p.add_argument("--cut", choices=("jaw", "neck-row"), default="jaw", help="head / torso cut of the preprocessing (neck-row: the earlier cut, to compare)")
    p.add_argument("--clothes", choices=("grabcut", "none"), default="grabcut", help="clothes completion of the preprocessing (none: as before it existed, to compare)")
    p.add_argument("--features", choices=("auto", *BUILTIN_KINDS), default="auto", help="audio features of the dataset (auto: preprocessing's choice, see adnerf preprocess --help)")
    p.add_argument("--test-fraction", type=number(float, 0.0, 0.5, open_lo=True), default=0.15, help="fraction of the clip held out at its end, in (0, 0.5]")
    p.add_argument("--focal", type=positive, default=None, help="focal length in pixels at --size (default: preprocessing's guess)")
    p.add_argument("--work", default="adnerf_bench_real", help="folder for the cached video, dataset and run")
    add_metric_weights(p)
    p.add_argument("--seed", type=number(int, 0), default=0, help="training seed")
    p.add_argument("--iters", type=head_torso_iters, default=None, help="HEAD,TORSO iterations instead of the schedule fitted to --minutes (equal schedules for comparisons)")
    p.add_argument("--config", default=None, help="JSON file of TrainConfig fields other than the iterations and seed (a variant, e.g. {\"pose_refit\": 2}); its run folder's name carries a hash of them, and the fitted schedule counts pose refits in the budget")
    p.add_argument("--drive", action="append", default=[], metavar="AUDIO", help="another speech file to drive the trained run with (repeat for more); reports how its lips follow that speech")
    p.add_argument("--sweep", type=count, default=6, metavar="FRAMES", help="held-out frames rendered with the head turned by 0, 5, 10, 15 and 20 degrees of yaw (face geometry, sharpness, neck, torso against the un-edited render; a contact sheet); 0 skips it")
    p.add_argument("--plot", default=None, help="write a PNG of the true and rendered mouth opening over the held-out frames")
    add_json(p, JSON_ROW)
    p.set_defaults(func=_run_real)


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.2f}"


REAL_KEYS = ("poses", "psnr", "ssim", "psnr_head", "ssim_head", "psnr_mouth", "ssim_mouth", "psnr_eyes", "lmd_mouth_px", "lmd_mouth", "lmd_all_px", "lmd_all", "lmd_mouth_shape_px", "lmd_mouth_still_px", "mouth_open_corr", "av_offset_frames", "mouth_open_slope", "mouth_open_std_ratio", "lpips", "lse_d", "lse_c", "lse_d_true", "lse_c_true", "train_seconds")


def _real_table(row: dict) -> str:
    """``bench real``'s row as the lines it prints."""
    table = "\n".join(f"{k:>18}: {row.get(k, row['syncnet'] if k.startswith('lse') else None)}" for k in REAL_KEYS) + f"\n{'contact sheet':>18}: {row['sheet']}"
    lips = row["lip_signal"]
    ceiling = lips.get("unavailable") or f"audio -> true opening, ridge corr held out {_fmt(lips['ridge_tail_corr'])}, cross-validated {_fmt(lips['ridge_cv_corr'])} (adnerf lip-signal)"
    table += f"\n{'clip lip signal':>18}: {ceiling}"
    for r in (row["pose_sweep"] or {}).get("rows", []):
        table += f"\n{'yaw ' + format(r['yaw'], '+g'):>18}: face landmarks {_fmt(r['identity_px'])} px off a rigid turn, sharpness x{_fmt(r['sharpness'])}, neck gap {_fmt(r['neck_gap'])}, torso change {_fmt(r['torso_change'])} (past the taught yaw by {r.get('yaw_past_range')} deg)"
    for d in row["driven"]:
        table += f"\n{'driven':>18}: {d['audio']} ({d['lips']}): lips vs speech activity corr {d['corr']}, best shift {d['offset']} frames ({d['corr_at_offset']})"
        if "lse_d" in d:
            table += f"; SyncNet LSE-D {d['lse_d']:.3f}, LSE-C {d['lse_c']:.3f}, offset {d['syncnet_offset_frames']}"
    return table


def _run_real(args: argparse.Namespace) -> int:
    try:
        row = bench_real(
            args.video, size=args.size or None, minutes=args.minutes, device=checked_device(args.device), cut=args.cut, clothes=args.clothes,
            features=args.features, test_fraction=args.test_fraction, focal=args.focal, work=args.work, lpips_backbone=args.lpips_backbone,
            lpips_linear=args.lpips_linear, syncnet=args.syncnet, seed=args.seed, iterations=args.iters, config=config_file(args.config), drive=tuple(args.drive), sweep=args.sweep, log=log,
        )  # fmt: skip
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    return _output([row], _real_table(row), args, lambda path: plot_mouth_opening(row, path))


def _register_scale(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scale", help="a clip looped or cut to several lengths: preprocessing time per step and per frame, training speed and peak memory of each")
    p.add_argument("video", help=VIDEO)
    p.add_argument("--seconds", type=positive_float_list, default=(10.0, 50.0, 300.0), help="comma-separated clip lengths in seconds, each made from the clip by looping it (frames and audio) or cutting it")
    p.add_argument("--size", type=number(int, 0, 2048), default=512, help="longer side in pixels the clip is resized to first, 0 to keep it")
    p.add_argument("--steps", type=number(int, 1), default=40, help="head iterations of each timed training run (the torso gets half)")
    add_device(p, "cpu or cuda (training)")
    p.add_argument("--work", default="adnerf_bench_scale", help="folder for the clips, datasets, runs and logs")
    add_json(p, JSON_ROW)
    p.set_defaults(func=_run_scale)


def _run_scale(args: argparse.Namespace) -> int:
    try:
        result = bench_scale(args.video, seconds=args.seconds, size=args.size or None, steps=args.steps, device=checked_device(args.device), work=args.work, log=log)
    except (ValueError, RuntimeError) as exc:
        raise CliError(str(exc)) from exc
    emit([result], format_scale_table(result), args.json)
    return 0


def _register_voices(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("voices", help="train on one espeak-ng voice, drive with others: how the rendered mouth follows the viseme truth, per feature kind")
    p.add_argument("--kinds", nargs="+", choices=("logmel", "phonemes"), default=["logmel", "phonemes"], help="feature kinds to compare (one scene and run each)")
    p.add_argument("--seconds", type=number(float, 5.0, 600.0), default=30.0, help="length of the training scene, 5 to 600 s")
    p.add_argument("--drive-seconds", type=number(float, 1.0, 120.0), default=8.0, help="length of each driving clip, 1 to 120 s")
    p.add_argument("--size", type=number(int, 32, 512), default=128, help="frame size in pixels, 32 to 512")
    p.add_argument("--iters", type=head_torso_iters, default=None, help="HEAD,TORSO iterations (default: the demo's 3600,3000)")
    p.add_argument("--seed", type=number(int, 0), default=0, help="seed of the scene, the training and the sentence order")
    add_device(p)
    p.add_argument("--work", default="adnerf_bench_voices", help="folder for the cached scenes, runs and the plot")
    add_json(p, JSON_ROW)
    p.set_defaults(func=_run_voices)


def _run_voices(args: argparse.Namespace) -> int:
    try:
        result = bench_voices(
            args.work, kinds=args.kinds, seconds=args.seconds, drive_seconds=args.drive_seconds, size=args.size, iterations=args.iters,
            seed=args.seed, device=checked_device(args.device), log=log,
        )  # fmt: skip
    except (ValueError, RuntimeError) as exc:
        raise CliError(str(exc)) from exc
    emit([result], format_voices_table(result) + f"\nplot: {result['plot']}", args.json)
    return 0


def _register_features(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("features", help="speech feature extraction speed (seconds of audio per second)")
    p.add_argument("--media", default=None, help="audio/video file to use (default: 60 s of synthetic voiced audio)")
    p.add_argument("--seconds", type=number(float, 1.0, 3600.0), default=60.0, help="length of the synthetic audio, 1 to 3600 s")
    p.add_argument("--repeats", type=number(int, 1), default=2, help="timed repeats (>= 1)")
    add_json(p, JSON_LINES)
    p.set_defaults(func=_run_features)


def _run_features(args: argparse.Namespace) -> int:
    try:
        rows = bench_features(args.media, seconds=args.seconds, repeats=args.repeats)
    except MediaError as exc:
        raise CliError(str(exc)) from exc
    lines = [f"{'extractor':<10}  {'audio s':>8}  {'wall s':>7}  {'x real time':>11}"]
    lines += [f"{r['kind']:<10}  {r['audio_seconds']:>8.1f}  {r['wall_seconds']:>7.2f}  {r['realtime_factor']:>11.1f}" for r in rows]
    emit(rows, "\n".join(lines), args.json)
    return 0
