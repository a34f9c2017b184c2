"""The ``adnerf`` command line."""

from __future__ import annotations

import argparse
import errno
import json
import math
import os
import signal
import sys
import threading
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Sequence

__all__ = ["main"]


class CliError(Exception):
    """An error with a message meant for the user (printed without a traceback)."""


def _positive_list(cast: type, what: str):
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


_positive_int_list = _positive_list(int, "integers")
_positive_float_list = _positive_list(float, "numbers")


def _head_torso_iters(text: str) -> tuple[int, int]:
    """An argparse type: ``HEAD,TORSO`` positive iteration counts."""
    values = _positive_int_list(text)
    if len(values) != 2:
        raise argparse.ArgumentTypeError(f"expected HEAD,TORSO iterations, got {text!r}")
    return values


def _log(message: str) -> None:
    """Step messages of long commands: on stderr, so that --json output stays clean."""
    print(message, file=sys.stderr)


def _number(cast: type, lo: float | None = None, hi: float | None = None, *, open_lo: bool = False):
    """An argparse type: a finite ``cast`` (int or float) in ``[lo, hi]`` (``(lo, hi]`` with ``open_lo``)."""

    def parse(text: str):
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


def _angle(text: str):
    """An argparse type: degrees, a ``.npy`` of per-frame angles or ``sway:A,P`` (:func:`adnerf.commands.pose_edits.parse_angle`)."""
    from .commands.pose_edits import parse_angle

    try:
        return parse_angle(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


_positive = _number(float, 0.0, open_lo=True)
_count = _number(int, 0)


class _HelpFormatter(argparse.HelpFormatter):
    """Help lines end with the option's default (where it has a meaningful one)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "%(default)" in text or "default" in text or any(action.default is v for v in (None, False, argparse.SUPPRESS)) or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


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

    from .bench.render import bench_render, format_table, rows_as_dicts

    rows = bench_render(args.samples, size=args.size, repeats=args.repeats, device=_device(args.device), dtype=getattr(torch, args.dtype), sigma=args.sigma)
    _emit(rows_as_dicts(rows), format_table(rows), args.json)
    return 0


def _cmd_bench_fields(args: argparse.Namespace) -> int:
    from .bench.fields import bench_fields, format_fields_table, plot_fields

    try:
        rows = bench_fields(
            args.dataset,
            configs=args.configs.split(",") if args.configs else None,
            budget=args.budget,
            checkpoints=args.checkpoints,
            size=args.size,
            device=_device(args.device),
            seed=args.seed,
            progress=True,  # bars go to stderr; --json output stays clean on stdout
        )
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    _emit(rows, format_fields_table(rows), args.json)
    if args.plot:
        plot_fields(rows, args.plot)
        _log(f"plot: {args.plot}")
    return 0


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.2f}"


def _cmd_bench_real(args: argparse.Namespace) -> int:
    from .bench.real import bench_real, plot_mouth_opening

    try:
        row = bench_real(
            args.video,
            size=args.size or None,
            minutes=args.minutes,
            device=_device(args.device),
            cut=args.cut,
            clothes=args.clothes,
            features=args.features,
            test_fraction=args.test_fraction,
            focal=args.focal,
            work=args.work,
            lpips_backbone=args.lpips_backbone,
            lpips_linear=args.lpips_linear,
            syncnet=args.syncnet,
            seed=args.seed,
            iterations=args.iters,
            drive=tuple(args.drive),
            sweep=args.sweep,
            log=_log,
        )
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    keys = ("psnr", "ssim", "psnr_head", "ssim_head", "psnr_mouth", "ssim_mouth", "lmd_mouth_px", "lmd_mouth", "lmd_all_px", "lmd_all", "lmd_mouth_shape_px", "lmd_mouth_still_px", "mouth_open_corr", "av_offset_frames", "mouth_open_slope", "mouth_open_std_ratio", "lpips", "lse_d", "lse_c", "lse_d_true", "lse_c_true", "train_seconds")
    table = "\n".join(f"{k:>18}: {row.get(k, row['syncnet'] if k.startswith('lse') else None)}" for k in keys) + f"\n{'contact sheet':>18}: {row['sheet']}"
    lips = row["lip_signal"]

    ceiling = lips.get("unavailable") or f"audio -> true opening, ridge corr held out {_fmt(lips['ridge_tail_corr'])}, cross-validated {_fmt(lips['ridge_cv_corr'])} (adnerf lip-signal)"
    table += f"\n{'clip lip signal':>18}: {ceiling}"
    for r in (row["pose_sweep"] or {}).get("rows", []):
        table += f"\n{'yaw ' + format(r['yaw'], '+g'):>18}: face landmarks {_fmt(r['identity_px'])} px off a rigid turn, sharpness x{_fmt(r['sharpness'])}, neck gap {_fmt(r['neck_gap'])}, torso change {_fmt(r['torso_change'])} (past the taught yaw by {r.get('yaw_past_range')} deg)"
    for d in row["driven"]:
        table += f"\n{'driven':>18}: {d['audio']} ({d['lips']}): lips vs speech activity corr {d['corr']}, best shift {d['offset']} frames ({d['corr_at_offset']})"
        if "lse_d" in d:
            table += f"; SyncNet LSE-D {d['lse_d']:.3f}, LSE-C {d['lse_c']:.3f}, offset {d['syncnet_offset_frames']}"
    _emit([row], table, args.json)
    if args.plot:
        plot_mouth_opening(row, args.plot)
        _log(f"plot: {args.plot}")
    return 0


def _cmd_bench_scale(args: argparse.Namespace) -> int:
    from .bench.scale import bench_scale, format_scale_table

    try:
        result = bench_scale(args.video, seconds=args.seconds, size=args.size or None, steps=args.steps, device=_device(args.device), work=args.work, log=_log)
    except (ValueError, RuntimeError) as exc:
        raise CliError(str(exc)) from exc
    _emit([result], format_scale_table(result), args.json)
    return 0


def _cmd_bench_voices(args: argparse.Namespace) -> int:
    from .bench.voices import bench_voices, format_voices_table

    try:
        result = bench_voices(
            args.work,
            kinds=args.kinds,
            seconds=args.seconds,
            drive_seconds=args.drive_seconds,
            size=args.size,
            iterations=args.iters,
            seed=args.seed,
            device=_device(args.device),
            log=_log,
        )
    except (ValueError, RuntimeError) as exc:
        raise CliError(str(exc)) from exc
    _emit([result], format_voices_table(result) + f"\nplot: {result['plot']}", args.json)
    return 0


def _cmd_bench_features(args: argparse.Namespace) -> int:
    from .bench.render import bench_features
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

    from .audio.features import (
        MODEL_RATE,
        FeatureError,
        FeatureSpec,
        save_npy_atomic,
        speech_windows,
    )
    from .io import MediaError, audio_span, frame_times, probe, read_audio
    from .outputs import check_file_output

    media, out = Path(args.media), Path(args.output)
    if out.suffix != ".npy":
        raise CliError(f"{out}: the output must be a .npy file")
    check_file_output(out, inputs=[media], overwrite=args.overwrite)
    try:
        audio = read_audio(media)  # raises "has no audio track" itself
        if len(audio.samples) == 0:
            raise CliError(f"{media}: the audio track holds no samples")
        if args.fps is None and probe(media)["video"]:
            times = frame_times(media)
            source = "video timestamps"
        else:
            fps = 25.0 if args.fps is None else args.fps
            times = np.arange(max(1, math.ceil(audio.duration * fps))) / fps + audio.start
            source = f"{fps:g} fps"
        if args.start or args.end is not None:  # a trim, as preprocess cuts it: frames and sound alike
            if args.end is not None and not args.end > args.start:
                raise CliError(f"a trim needs 0 <= start < end; got --start {args.start:g}, --end {args.end:g}")
            t0 = float(times[0])
            keep = (times >= t0 + args.start - 1e-6) & (True if args.end is None else times < t0 + args.end - 1e-6)
            if not keep.any():
                raise CliError(f"{media}: no frame from {args.start:g} s on (the trim's start lies past the clip's end)")
            times = times[keep]
            audio = audio_span(audio, t0 + args.start, None if args.end is None else t0 + args.end)
            source += f", {args.start:g}-{'end' if args.end is None else f'{args.end:g} s'}"
        with tqdm(total=round(audio.duration, 1), unit="s", desc=f"{args.kind} features", disable=audio.duration < 30 or None) as bar:
            spec = FeatureSpec(args.kind, model_dir=args.model_dir)
            windows = speech_windows(audio, times, spec, progress=lambda n: bar.update(round(n / MODEL_RATE, 2)))
    except (MediaError, FeatureError) as exc:
        raise CliError(str(exc)) from exc
    save_npy_atomic(out, windows)
    print(f"{out}: {windows.shape[0]} frames ({source}) x {windows.shape[1]} x {windows.shape[2]} {args.kind} features from {audio.duration:.2f} s of audio")
    return 0


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


def _interrupted() -> type[BaseException]:
    """Training stopped by a signal after writing its checkpoint (imported when an error is matched)."""
    from .model.train import TrainingInterrupted

    return TrainingInterrupted


def _user_errors() -> tuple[type[BaseException], ...]:
    """Exceptions whose message is for the user (bad input), printed without a traceback."""
    from .atomic import DiskFullError
    from .audio.features import FeatureError
    from .commands.render_video import RenderError
    from .io import MediaError
    from .lock import FolderBusyError
    from .memory import MemoryNeedError
    from .model.data import DatasetError
    from .model.run_folder import RunError
    from .outputs import OutputError
    from .preprocess.pipeline import PreprocessError

    return (DatasetError, DiskFullError, FeatureError, FolderBusyError, MediaError, MemoryNeedError, OutputError, PreprocessError, RenderError, RunError)


def _cmd_synth(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .audio.espeak import EspeakError, check_voice
    from .lock import FolderLock
    from .outputs import check_folder_output
    from .synth import SynthConfig, espeak_available, synthesize

    cfg = SynthConfig(seconds=args.seconds, size=args.size, seed=args.seed, voice=args.voice, speaker=args.speaker, words_per_minute=args.wpm, mouth=args.mouth, features=args.features, fps=args.fps)
    try:
        cfg.validate()
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    check_folder_output(args.output, "dataset", overwrite=args.overwrite)  # before the progress bar
    try:
        if cfg.voice == "espeak" or (cfg.voice == "auto" and espeak_available()):
            check_voice(cfg.speaker)
        with FolderLock(args.output, "dataset"), tqdm(total=cfg.n_frames, desc="synth frames", unit="frame") as bar:  # the lock before the bar
            out = synthesize(args.output, cfg, progress=lambda step, done, total: bar.update(done - bar.n), overwrite=args.overwrite)
    except EspeakError as exc:  # an unknown --speaker, or no espeak-ng for --voice espeak
        raise CliError(str(exc)) from exc
    print(f"{out}: synthetic talking head, {cfg.seconds:g} s at {cfg.fps:g} fps, {cfg.size}x{cfg.size}")
    return 0


def _cmd_preprocess(args: argparse.Namespace) -> int:

    from .preprocess.pipeline import PreprocessConfig, preprocess_video, step_bars

    extra = {} if args.pose_landmarks is None else {"pose_landmarks": args.pose_landmarks}
    cfg = PreprocessConfig(parser=args.parser, features=args.features, face=args.face, flow=args.flow, cut=args.cut, clothes=args.clothes, focal=args.focal, test_fraction=args.test_fraction, fps=args.fps, start=args.start, end=args.end, crop=args.crop, size=args.size or None, allow_cuts=args.allow_cuts, **extra)
    with step_bars() as bars:  # closed before an error line is printed
        report = preprocess_video(args.video, args.output, cfg, progress=bars, overwrite=args.overwrite)
    keys = ("frames", "decode", "parse_face_failures", "face_detected", "face_interpolated", "face_head_torso_cut", "face_clothes", "layers", "layers_warning", "torso", "torso_warning", "pose_reprojection_rms_px", "pose_landmark_rms_px", "plate_filled_fraction", "timings_s")
    print(json.dumps({k: report[k] for k in keys if k in report}, indent=1))
    print(f"{args.output}: dataset written (report: {args.output}/preprocess_report.json, .png)")
    return 0


def _cmd_check_preprocess(args: argparse.Namespace) -> int:
    from .preprocess.check import check_preprocess

    out = check_preprocess(args.dataset, args.truth)
    if args.json:
        print(json.dumps(out))
    else:
        for k, v in out.items():
            print(f"{k:32s} {v}")
    return 0


def _cmd_lip_signal(args: argparse.Namespace) -> int:
    from .evaluation.lip_signal import dataset_lip_signal

    try:
        signal = dataset_lip_signal(args.dataset, blocks=args.blocks, guard=args.guard)
    except _user_errors():  # not a dataset, no landmarks: main prints them
        raise
    except ValueError as exc:  # too few frames for the folds
        raise CliError(str(exc)) from exc
    doc = signal.to_dict()
    if args.json:
        print(json.dumps(doc))
        return 0
    words = {
        "loudness_corr": "opening vs voiced loudness (corr, same frame)",
        "loudness_offset_frames": "best shift, frames (> 0: mouth after sound)",
        "loudness_corr_at_offset": "corr at that shift",
        "ridge_tail_corr": "audio -> opening, fit on train, held-out corr",
        "ridge_cv_corr": f"audio -> opening, {args.blocks}-block cross-validated corr",
    }
    print(f"{args.dataset}: {doc['frames']} frames")
    for key, text in words.items():
        value = doc[key]
        print(f"{text:>48}: {value:.3f}" if isinstance(value, float) else f"{text:>48}: {value}")
    print(f"{'per block':>48}: " + " ".join(f"{c:.2f}" for c in doc["ridge_cv_blocks"]))
    if doc["ridge_cv_corr"] is not None and doc["ridge_cv_corr"] < 0.3:
        print("a cross-validated correlation this low means the clip is too short (or its mouth too little tied to its sound) for any audio encoder to learn its lip movements; AD-NeRF trains on 3-5 minutes")
    return 0


def _train_config(args: argparse.Namespace):
    """The schedule: ``--config`` keys, then ``--amp`` and ``--iters``, over the defaults (a new
    run) or over the run's stored schedule (``--resume``), so a resume changes only what is given."""
    from .model.run_folder import RunError, stored_config
    from .model.train_config import TrainConfig

    doc: object = {}
    if args.config:
        try:
            doc = json.loads(open(args.config).read())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise CliError(f"{args.config}: not a readable JSON training config ({exc})") from exc
        if not isinstance(doc, dict):
            raise CliError(f"{args.config}: a training config is a JSON object of TrainConfig fields (e.g. {{\"rays\": 2048}}); got a {type(doc).__name__}")
    doc = dict(doc)  # type: ignore[arg-type]
    if getattr(args, "amp", None):
        doc["amp"] = args.amp
    base = TrainConfig()
    if args.resume:
        if not (Path(args.output) / "run.json").exists():
            raise RunError(f"{args.output}: nothing to resume (no run.json); drop --resume to start a new run")
        base = stored_config(args.output)
    if args.iters is not None:
        if args.stage in ("head", "all"):
            doc["head_iters"] = args.iters
        if args.stage in ("torso", "all"):
            doc["torso_iters"] = args.iters if args.stage == "torso" else args.iters // 2
    scale = getattr(args, "scale", 1)
    if scale > 1 and args.resume:
        raise CliError("--scale sets a new run's schedule; a resumed run keeps its own (drop --scale)")
    try:
        cfg = TrainConfig.from_dict(doc, base)
        cfg.validate()
        cfg = cfg.scaled(scale)
        cfg.validate()
    except (TypeError, ValueError) as exc:
        raise CliError(f"invalid training config: {exc}") from exc
    return cfg


def _cmd_train(args: argparse.Namespace) -> int:
    from .model.train import train

    cfg = _train_config(args)
    root = train(args.dataset, args.output, stage=args.stage, config=cfg, device=_device(args.device), resume=args.resume)
    if os.environ.get("RANK", "0") == "0":  # under torchrun, process 0 speaks for all
        print(f"{root}: trained ({args.stage}); render with `adnerf render {root} --audio SPEECH -o out.mp4`")
    return 0


def _cmd_import_adnerf(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .lock import FolderLock
    from .preprocess.adnerf_import import import_adnerf

    with FolderLock(args.output, "dataset"), tqdm(desc="import frames", unit="frame") as bar, warnings.catch_warnings(record=True) as caught:  # the lock before the bar
        warnings.simplefilter("always")

        def tick(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        summary = import_adnerf(args.source, args.output, fps=args.fps, audio=args.audio, overwrite=args.overwrite, progress=tick)
    for w in caught:
        print(f"adnerf: warning: {w.message}", file=sys.stderr)
    print(
        f"{summary['dataset']}: {summary['frames']} frames ({summary['train']} train, {summary['test']} test), "
        f"{summary['size'][0]}x{summary['size'][1]}, DeepSpeech features {tuple(summary['features'])}, poses rescaled by {summary['scale']:.4g}; "
        f"train with `adnerf train {summary['dataset']} -o RUN`"
    )
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .commands.render_video import check_render_outputs, render_audio_video
    from .model.run_folder import load_run

    if not args.output.endswith(".mp4"):
        raise CliError(f"{args.output}: the output must be an .mp4 file")
    inputs = [args.audio, args.poses, args.features, args.background, args.source, args.still_frame, None if args.blink in ("auto", "none") else args.blink, *(a.file for a in (args.yaw, args.pitch, args.roll) if a.file is not None)]
    check_render_outputs(args.output, args.frames, inputs=inputs, overwrite=args.overwrite)  # before loading and rendering
    run = load_run(args.run, _device(args.device))
    bars: list[tqdm] = []  # opened at the first frame, so a refused input prints no bar

    def tick(done: int, total: int) -> None:
        if not bars:
            bars.append(tqdm(total=total, desc="render", unit="frame"))
        bars[0].update(done - bars[0].n)

    try:
        summary = render_audio_video(
            run,
            args.audio,
            args.output,
            poses_file=args.poses,
            from_dataset=args.from_dataset,
            yaw=args.yaw,
            pitch=args.pitch,
            roll=args.roll,
            strict_pose=args.strict_pose,
            background=args.background,
            features=args.features,
            frames_dir=args.frames,
            blink=args.blink,
            overwrite=args.overwrite,
            progress=tick,
            paste_back=args.paste_back,
            source=args.source,
            still_frame=args.still_frame,
        )
    finally:
        for bar in bars:
            bar.close()
    blinks = "" if summary["blinks"] is None else f", {summary['blinks']} blinks"
    pasted = f" ({summary['size'][0]}x{summary['size'][1]}, pasted back into the source frames)" if summary["pasted_back"] else ""
    print(f"{summary['output']}: {summary['frames']} frames{pasted}, {summary['audio_seconds']:.2f} s{blinks}, rendered at {summary['render_fps']:.2f} frames/s")
    return 0


def _cmd_stream(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .commands.render_video import check_render_outputs
    from .commands.stream_video import stream_to_video
    from .model.run_folder import load_run

    if not args.output.endswith(".mp4"):
        raise CliError(f"{args.output}: the output must be an .mp4 file")
    check_render_outputs(args.output, args.frames, inputs=[None if args.audio == "-" else args.audio, args.background], overwrite=args.overwrite)
    run = load_run(args.run, _device(args.device))
    with tqdm(desc="stream", unit="frame") as bar:
        summary = stream_to_video(
            run, args.audio, args.output, chunk_s=args.chunk_ms / 1000.0, yaw=args.yaw, pitch=args.pitch, roll=args.roll,
            blink=args.blink, background=args.background, frames_dir=args.frames, progress=lambda n: bar.update(n - bar.n),
        )  # fmt: skip
    if args.json:
        print(json.dumps(summary))
        return 0
    first = "-" if summary["first_frame_s"] is None else f"{summary['first_frame_s']:.2f} s"
    print(
        f"{summary['output']}: {summary['frames']} frames, {summary['audio_seconds']:.2f} s of speech; look-ahead {summary['lookahead_s'] * 1000:.0f} ms, "
        f"first frame after {first} of work, {summary['realtime_factor']:.2f}x real time"
    )
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluation.evaluate import evaluate_run
    from .evaluation.lpips import lpips_if_available
    from .evaluation.syncnet import load_syncnet
    from .model.data import load_dataset
    from .model.run_folder import load_run

    device = _device(args.device)
    try:
        model = lpips_if_available(args.lpips_backbone, args.lpips_linear, device)
        sync = load_syncnet(args.syncnet, device) if args.syncnet else None
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    run = load_run(args.run, device)
    ds = load_dataset(args.dataset)
    metrics, _ = evaluate_run(run, ds, args.split, landmarks=not args.no_landmarks, lpips=model, syncnet=sync)
    metrics["lpips"] = metrics.get("lpips", "no weights")
    if args.sweep:
        from .evaluation.pose_sweep import SWEEP_YAWS, pose_sweep, spread, sweep_sheet

        frames = spread(getattr(ds.meta, args.split), args.sweep)
        metrics["pose_sweep"], renders = pose_sweep(run, ds, frames)
        if args.sweep_sheet:
            sweep_sheet(args.sweep_sheet, renders, SWEEP_YAWS, [f"frame {f}" for f in frames])
    metrics.pop("syncnet_curve", None)
    metrics = {k: v for k, v in metrics.items() if not k.startswith("mouth_opening_")}  # the per-frame series: bench real --plot draws them
    if args.json:
        print(json.dumps(metrics))
    else:
        for key, value in metrics.items():
            print(f"{key:>20}: {value:.4f}" if isinstance(value, float) else f"{key:>20}: {value}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from .commands.demo import run_demo
    from .outputs import OutputError

    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: is a file, not a folder; give a folder for the demo")
    from .commands.demo import DEMO_TRAIN

    metrics = run_demo(args.output, device=_device(args.device), train_config=DEMO_TRAIN.scaled(args.scale))
    keys = ("psnr_test", "ssim_test", "psnr_mouth_test", "mouth_open_corr", "train_seconds", "render_fps", "total_seconds")
    print(json.dumps({k: metrics[k] for k in keys}, indent=1))
    return 0


def _with_formatter(add_parser):
    """Wrap a subparsers' ``add_parser`` so every subcommand's help shows defaults."""

    def add(*args, **kwargs):
        kwargs.setdefault("formatter_class", _HelpFormatter)
        return add_parser(*args, **kwargs)

    return add


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``adnerf`` command."""
    parser = argparse.ArgumentParser(prog="adnerf", description="Audio-driven neural radiance fields for talking heads.", formatter_class=_HelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser = _with_formatter(sub.add_parser)  # type: ignore[method-assign]

    bench = sub.add_parser("bench", help="benchmarks: error against run time")
    bench_sub = bench.add_subparsers(dest="bench_command", required=True)
    bench_sub.add_parser = _with_formatter(bench_sub.add_parser)  # type: ignore[method-assign]
    render = bench_sub.add_parser("render", help="quadrature error of rendering an analytic sphere vs samples per ray, and time")
    render.add_argument("--json", action="store_true", help="print one JSON line per configuration (the table goes to stderr)")
    render.add_argument("--samples", type=_positive_int_list, default=(8, 16, 32, 64, 128, 256), help="comma-separated samples per ray")
    render.add_argument("--size", type=_number(int, 1, 4096), default=128, help="image side in pixels, 1 to 4096")
    render.add_argument("--repeats", type=_number(int, 1), default=3, help="timed repeats (>= 1); the best is reported")
    render.add_argument("--device", default="cpu", help="cpu or cuda")
    render.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    render.add_argument("--sigma", type=_positive, default=10.0, help="density of the analytic sphere (> 0; 10 is surface-like)")
    render.set_defaults(func=_cmd_bench_render)
    fields = bench_sub.add_parser("fields", help="held-out PSNR against training time per field configuration (paper MLP, fast grids, skipping, fine pass)")
    fields.add_argument("--dataset", default=None, help="dataset folder (default: synthesise the built-in scene at --size)")
    fields.add_argument("--configs", default=None, help="comma-separated: paper, fast, fast-no-skip, fast-coarse-only (default: all)")
    fields.add_argument("--budget", type=_positive, default=300.0, help="seconds of training per configuration (> 0)")
    fields.add_argument("--checkpoints", type=_positive_float_list, default=(5, 10, 20, 30, 60, 120, 300), help="training times (s) to measure PSNR at")
    fields.add_argument("--size", type=_number(int, 16, 1024), default=128, help="frame size of the synthesised scene, 16 to 1024")
    fields.add_argument("--device", default="cpu", help="cpu or cuda")
    fields.add_argument("--seed", type=int, default=0)
    fields.add_argument("--plot", default=None, help="write a PNG of PSNR against training time")
    fields.add_argument("--json", action="store_true", help="JSON lines on stdout, table on stderr")
    fields.set_defaults(func=_cmd_bench_fields)
    real = bench_sub.add_parser("real", help="a real clip: preprocess, train within a budget, render its held-out tail, measure (PSNR, SSIM, LMD, lip sync, LPIPS)")
    real.add_argument("video", help="the clip (one person, static camera, with audio)")
    real.add_argument("--size", type=_number(int, 0, 2048), default=256, help="longer side in pixels the clip is resized to first, 0 to keep it")
    real.add_argument("--minutes", type=_number(float, 0.0, 10000.0, open_lo=True), default=10.0, help="training budget for both stages, minutes of training time")
    real.add_argument("--device", default="cpu", help="cpu or cuda")
    real.add_argument("--cut", choices=("jaw", "neck-row"), default="jaw", help="head / torso cut of the preprocessing (neck-row: the earlier cut, to compare)")
    real.add_argument("--clothes", choices=("grabcut", "none"), default="grabcut", help="clothes completion of the preprocessing (none: as before it existed, to compare)")
    real.add_argument("--features", choices=("logmel", "phonemes"), default="logmel", help="audio features of the dataset")
    real.add_argument("--test-fraction", type=_number(float, 0.0, 0.5, open_lo=True), default=0.15, help="fraction of the clip held out at its end, in (0, 0.5]")
    real.add_argument("--focal", type=_positive, default=None, help="focal length in pixels at --size (default: preprocessing's guess)")
    real.add_argument("--work", default="adnerf_bench_real", help="folder for the cached video, dataset and run")
    real.add_argument("--lpips-backbone", default=None, help="AlexNet weights for LPIPS (default: the torch hub cache's alexnet-owt-7be5be79.pth, if there)")
    real.add_argument("--lpips-linear", default=None, help="LPIPS linear layers (default: those the lpips package ships, if installed)")
    real.add_argument("--syncnet", default=None, metavar="CHECKPOINT", help="SyncNet checkpoint (syncnet_v2.model of the public release) for LSE-D / LSE-C; without it they read \"no weights\" (nothing is downloaded)")
    real.add_argument("--seed", type=_number(int, 0), default=0, help="training seed")
    real.add_argument("--iters", type=_head_torso_iters, default=None, help="HEAD,TORSO iterations instead of the schedule fitted to --minutes (equal schedules for comparisons)")
    real.add_argument("--drive", action="append", default=[], metavar="AUDIO", help="another speech file to drive the trained run with (repeat for more); reports how its lips follow that speech")
    real.add_argument("--sweep", type=_count, default=6, metavar="FRAMES", help="held-out frames rendered with the head turned by 0, 5, 10, 15 and 20 degrees of yaw (face geometry, sharpness, neck, torso against the un-edited render; a contact sheet); 0 skips it")
    real.add_argument("--plot", default=None, help="write a PNG of the true and rendered mouth opening over the held-out frames")
    real.add_argument("--json", action="store_true", help="one JSON line on stdout, the table on stderr")
    real.set_defaults(func=_cmd_bench_real)
    scale = bench_sub.add_parser("scale", help="a clip looped or cut to several lengths: preprocessing time per step and per frame, training speed and peak memory of each")
    scale.add_argument("video", help="the clip (one person, static camera, with audio)")
    scale.add_argument("--seconds", type=_positive_float_list, default=(10.0, 50.0, 300.0), help="comma-separated clip lengths in seconds, each made from the clip by looping it (frames and audio) or cutting it")
    scale.add_argument("--size", type=_number(int, 0, 2048), default=512, help="longer side in pixels the clip is resized to first, 0 to keep it")
    scale.add_argument("--steps", type=_number(int, 1), default=40, help="head iterations of each timed training run (the torso gets half)")
    scale.add_argument("--device", default="cpu", help="cpu or cuda (training)")
    scale.add_argument("--work", default="adnerf_bench_scale", help="folder for the clips, datasets, runs and logs")
    scale.add_argument("--json", action="store_true", help="one JSON line on stdout, the table on stderr")
    scale.set_defaults(func=_cmd_bench_scale)
    voices = bench_sub.add_parser("voices", help="train on one espeak-ng voice, drive with others: how the rendered mouth follows the viseme truth, per feature kind")
    voices.add_argument("--kinds", nargs="+", choices=("logmel", "phonemes"), default=["logmel", "phonemes"], help="feature kinds to compare (one scene and run each)")
    voices.add_argument("--seconds", type=_number(float, 5.0, 600.0), default=30.0, help="length of the training scene, 5 to 600 s")
    voices.add_argument("--drive-seconds", type=_number(float, 1.0, 120.0), default=8.0, help="length of each driving clip, 1 to 120 s")
    voices.add_argument("--size", type=_number(int, 32, 512), default=128, help="frame size in pixels, 32 to 512")
    voices.add_argument("--iters", type=_head_torso_iters, default=None, help="HEAD,TORSO iterations (default: the demo's 3600,3000)")
    voices.add_argument("--seed", type=_number(int, 0), default=0, help="seed of the scene, the training and the sentence order")
    voices.add_argument("--device", default="cpu", help="cpu or cuda")
    voices.add_argument("--work", default="adnerf_bench_voices", help="folder for the cached scenes, runs and the plot")
    voices.add_argument("--json", action="store_true", help="one JSON line on stdout, the table on stderr")
    voices.set_defaults(func=_cmd_bench_voices)
    fbench = bench_sub.add_parser("features", help="speech feature extraction speed (seconds of audio per second)")
    fbench.add_argument("--media", default=None, help="audio/video file to use (default: 60 s of synthetic voiced audio)")
    fbench.add_argument("--seconds", type=_number(float, 1.0, 3600.0), default=60.0, help="length of the synthetic audio, 1 to 3600 s")
    fbench.add_argument("--repeats", type=_number(int, 1), default=2, help="timed repeats (>= 1)")
    fbench.add_argument("--json", action="store_true", help="JSON lines on stdout, table on stderr")
    fbench.set_defaults(func=_cmd_bench_features)

    feats = sub.add_parser("features", help="per-frame speech feature windows (N, 16, D) of a video or audio file")
    feats.add_argument("media", help="video (frames timed by its timestamps) or audio file (wav, mp3, m4a, flac, ...)")
    feats.add_argument("-o", "--output", required=True, help="output .npy file")
    feats.add_argument("--kind", choices=("phonemes", "logmel", "wav2vec2"), default="phonemes", help="extractor (default: phonemes, hama's IPA log-probs)")
    feats.add_argument("--model-dir", default=None, help="local wav2vec2 / HuBERT model directory for --kind wav2vec2")
    feats.add_argument("--fps", type=_positive, default=None, help="frame rate (> 0) for audio-only input (default 25); overrides a video's timestamps")
    feats.add_argument("--start", type=_number(float, 0.0), default=0.0, help="seconds from the first frame (or the audio's start) to begin at, as preprocess --start: earlier frames and sound are left out")
    feats.add_argument("--end", type=_number(float, 0.0, open_lo=True), default=None, help="seconds from the first frame to stop at (frames and sound from then on are left out)")
    feats.add_argument("--overwrite", action="store_true", help="replace an existing output file (never an input)")
    feats.set_defaults(func=_cmd_features)

    demo = sub.add_parser("demo", help="synthesise a talking head, train, render held-out audio three ways, evaluate")
    demo.add_argument("-o", "--output", default="adnerf_demo", help="output folder (default adnerf_demo); re-running resumes")
    demo.add_argument("--device", default="cpu", help="cpu or cuda")
    demo.add_argument("--scale", type=_number(int, 1, 64), default=1, help="train the demo's schedule in K times fewer steps of K times the rays from K times the frames, learning rates times sqrt(K) (as train --scale; for GPUs: --scale 4)")
    demo.set_defaults(func=_cmd_demo)

    synth = sub.add_parser("synth", help="create a synthetic talking-head dataset with exact ground truth")
    synth.add_argument("-o", "--output", required=True, help="dataset folder to create")
    synth.add_argument("--seconds", type=_number(float, 1.0, 600.0), default=18.0, help="length of the scene, 1 to 600 s")
    synth.add_argument("--size", type=_number(int, 16, 1024), default=128, help="frame width and height in pixels, 16 to 1024")
    synth.add_argument("--fps", type=_number(float, 1.0, 120.0), default=25.0, help="frame rate, 1 to 120")
    synth.add_argument("--seed", type=_number(int, 0), default=0, help="random seed of the pose track and the speech (>= 0)")
    synth.add_argument("--voice", choices=("auto", "formant", "espeak"), default="auto", help="speech source (auto: espeak-ng when installed)")
    synth.add_argument("--speaker", default="en", help="espeak-ng voice of the speech, e.g. en, en+f3 (female), en-us+klatt (espeak-ng --voices lists them)")
    synth.add_argument("--wpm", type=_number(int, 80, 450), default=150, help="speaking rate of the espeak-ng speech, 80 to 450 words per minute")
    synth.add_argument("--mouth", choices=("auto", "visemes", "loudness"), default="auto", help="what opens the jaw: the phonemes spoken (visemes; needs espeak-ng) or the voice's loudness (auto: visemes with espeak-ng)")
    synth.add_argument("--features", choices=("logmel", "phonemes"), default="logmel", help="audio features stored with the dataset")
    synth.add_argument("--overwrite", action="store_true", help="replace an existing adnerf dataset folder (never another folder)")
    synth.set_defaults(func=_cmd_synth)

    pre = sub.add_parser("preprocess", help="turn a static-camera talking-head video into a dataset (parsing, head pose, plate)")
    pre.add_argument("video", help="video file with an audio track")
    pre.add_argument("-o", "--output", required=True, help="dataset folder to create")
    pre.add_argument("--parser", default="classical", help="face parser: classical (default, needs no weights), mediapipe (opt-in install, see docs/preprocessing.md) or bisenet:CHECKPOINT (your 19-class face-parsing BiSeNet .pth, e.g. the 79999_iter.pth AD-NeRF uses)")
    pre.add_argument("--features", choices=("logmel", "phonemes", "none"), default="logmel", help="audio features (none: silent dataset, allowed without audio)")
    pre.add_argument("--face", default="dlib", help="face box and 68 landmarks: dlib (default; HOG detector and the 68-point model of the face-recognition-models package), dlib:PREDICTOR.dat (your own 68-point model) or none")
    pre.add_argument("--flow", choices=("dis", "deepflow"), default="dis", help="dense optical flow for head tracking")
    pre.add_argument("--cut", choices=("jaw", "neck-row"), default="jaw", help="where head meets torso for the classical parser: the landmarks' jaw line, or the silhouette's narrowest row (the earlier cut, for comparisons)")
    pre.add_argument("--clothes", choices=("grabcut", "none"), default="grabcut", help="clothes the classical parser took for background (they never move): grabcut (default) adds them to the torso by colour below the chin; none leaves them")
    pre.add_argument("--focal", type=_positive, default=None, help="focal length of the camera in the video's pixels, > 0 (default 1.33 x the larger frame side); the crop and --size scale it")
    pre.add_argument("--pose-landmarks", type=_number(float, 0.0, 1000.0), default=None, help="weight of a rigid landmark (nose, eye corners) against a flow track in the head-pose bundle adjustment, 0 to 1000 (default: PreprocessConfig.pose_landmarks, 30; 0: the tracks alone, as before)")
    pre.add_argument("--test-fraction", type=_number(float, 0.0, 0.9, open_lo=True), default=0.1, help="fraction of frames at the end held out for testing, in (0, 0.9]")
    pre.add_argument("--fps", type=_number(float, 1.0, 240.0), default=None, help="frame rate of the dataset, 1 to 240: frames are placed on this constant rate by their timestamps, repeated or left out where a variable-rate file (phones) has gaps (default: the clip's nominal rate)")
    pre.add_argument("--start", type=_number(float, 0.0), default=0.0, help="seconds into the video (from its first frame) where the dataset begins; frames and audio are cut alike")
    pre.add_argument("--end", type=_positive, default=None, help="seconds into the video where the dataset ends (default: its end)")
    pre.add_argument("--crop", default="auto", help="the part of the frame the dataset shows: auto (a fixed square around the face's range over the clip, with the shoulders; a frame already within --size is used whole), none (the whole frame) or X,Y,W,H in the video's pixels")
    pre.add_argument("--size", type=_number(int, 0, 4096), default=512, help="longest side of the dataset's frames in pixels: the crop is scaled down to it, never up; 0 keeps the crop's size")
    pre.add_argument("--allow-cuts", action="store_true", help="keep a clip whose picture jumps (shot cuts, reframings); by default it is refused with the longest clean stretch named")
    pre.add_argument("--overwrite", action="store_true", help="replace an existing adnerf dataset folder (never another folder, nor one holding the video)")
    pre.set_defaults(func=_cmd_preprocess)

    imp = sub.add_parser("import-adnerf", help="convert a dataset preprocessed by the original AD-NeRF code into an adnerf dataset")
    imp.add_argument("source", help="AD-NeRF dataset folder (transforms_train.json, ori_imgs/, parsing/, bc.jpg, aud.npy, aud.wav)")
    imp.add_argument("-o", "--output", required=True, help="dataset folder to create")
    imp.add_argument("--fps", type=_positive, default=25.0, help="frame rate of the original video (> 0; AD-NeRF assumes 25)")
    imp.add_argument("--audio", default=None, help="the original audio (default SOURCE/aud.wav)")
    imp.add_argument("--overwrite", action="store_true", help="replace an existing adnerf dataset folder (never another folder, nor one holding the source)")
    imp.set_defaults(func=_cmd_import_adnerf)

    chk = sub.add_parser("check-preprocess", help="compare a preprocessed synthetic video with the scene's truth (pose, parsing, plate)")
    chk.add_argument("dataset", help="dataset written by adnerf preprocess from SYNTH/video.mp4")
    chk.add_argument("--truth", required=True, help="the synthetic scene folder (adnerf synth output)")
    chk.add_argument("--json", action="store_true", help="one JSON object on stdout")
    chk.set_defaults(func=_cmd_check_preprocess)

    lips = sub.add_parser("lip-signal", help="how much a preprocessed clip's audio predicts its mouth opening: the lip-sync ceiling of training on it")
    lips.add_argument("dataset", help="dataset written by adnerf preprocess (needs its landmarks.npy)")
    lips.add_argument("--blocks", type=int, default=6, help="contiguous cross-validation blocks")
    lips.add_argument("--guard", type=int, default=8, help="frames left out on either side of a tested block")
    lips.add_argument("--json", action="store_true", help="one JSON object on stdout")
    lips.set_defaults(func=_cmd_lip_signal)

    tr = sub.add_parser("train", help="train the head (stage 1) and torso (stage 2) fields on a dataset")
    tr.add_argument("dataset", help="dataset folder")
    tr.add_argument("-o", "--output", required=True, help="run folder")
    tr.add_argument("--stage", choices=("head", "torso", "all"), default="all", help="head (stage 1), torso (stage 2; needs a finished head stage and --resume) or all")
    tr.add_argument("--iters", type=_count, default=None, help="iterations of the stage, >= 0 (with all: head; the torso gets half); with --resume, trains the run longer")
    tr.add_argument("--amp", choices=("auto", "bf16", "off"), default=None, help="mixed precision of the fields (default auto: bfloat16 on CUDA, off on CPU)")
    tr.add_argument("--scale", type=_number(int, 1, 64), default=1, help="train the schedule (after --config and --iters) in K times fewer steps of K times the rays, drawn from K times the frames, with the learning rates times sqrt(K) (for GPUs, where a larger step costs little more; K=4 is measured in docs/benchmarks.md, K=8 leaves the torso too few steps); a new run only")
    tr.add_argument("--device", default="cpu", help="cpu or cuda")
    tr.add_argument("--config", default=None, help="JSON file of TrainConfig fields (e.g. {\"rays\": 2048, \"preset\": \"paper\"}); with --resume only head_iters, torso_iters, amp, checkpoint_every and log_every may differ from the run's")
    tr.add_argument("--resume", action="store_true", help="continue from the run's checkpoint, with its stored config, on the same dataset")
    tr.set_defaults(func=_cmd_train)

    rn = sub.add_parser("render", help="render a trained run saying new audio, as an mp4 with that audio")
    rn.add_argument("run", help="run folder")
    rn.add_argument("--audio", required=True, help="speech (any audio or video file)")
    poses = rn.add_mutually_exclusive_group()
    poses.add_argument("--poses", default=None, help=".npy of (N, 4, 4) head poses, one per output frame")
    poses.add_argument("--from", dest="from_dataset", default=None, help="take the pose track of this dataset (played back and forth)")
    edit = "; or a .npy of one angle per frame, or sway:AMPLITUDE,PERIOD (degrees, seconds: an idle motion kept inside the poses the run was taught)"
    rn.add_argument("--yaw", type=_angle, default="0", metavar="DEG|FILE.npy|sway:A,P", help="degrees added about the head's vertical axis, -180 to 180; positive turns the face towards the image's left (the person's right)" + edit)
    rn.add_argument("--pitch", type=_angle, default="0", metavar="DEG|FILE.npy|sway:A,P", help="degrees added about the horizontal axis; positive nods the face down" + edit)
    rn.add_argument("--roll", type=_angle, default="0", metavar="DEG|FILE.npy|sway:A,P", help="degrees added about the viewing axis; positive turns the head clockwise in the image" + edit)
    rn.add_argument("--strict-pose", action="store_true", help="refuse poses farther outside the range the training frames showed than the margin (5 degrees, 0.1 head widths), instead of warning")
    rn.add_argument("--features", default=None, help=".npy of precomputed feature windows (M, 16, D) for the audio, one per frame (e.g. AD-NeRF's DeepSpeech aud.npy); required for runs trained on imported DeepSpeech features")
    rn.add_argument("--background", default=None, help="replacement background image")
    rn.add_argument("--blink", default="auto", metavar="auto|none|FILE.npy", help="eye openness for runs trained with eyes (datasets with eye.npy): auto plays natural blinks (one every 2-6 s, 0.2 s long), none keeps the eyes open, a .npy gives one value per frame (1 open, 0 closed)")
    rn.add_argument("--frames", default=None, help="also write the rendered squares as PNGs (000000.png, ...) into this folder; never inside a dataset or run")
    rn.add_argument("--paste-back", action=argparse.BooleanOptionalAction, default=None, help="paste the render back into the source video's full frames, at its size (default: when the dataset was cropped from a larger video and that video is at hand; --no-paste-back writes the square)")
    rn.add_argument("--source", default=None, metavar="VIDEO", help="with paste-back: the video the dataset was made from, when it has moved since preprocessing")
    rn.add_argument("--frame", dest="still_frame", default=None, metavar="IMAGE", help="with paste-back: paste every rendered square into this full-size image instead of the source video's frames")
    rn.add_argument("--overwrite", action="store_true", help="replace an existing output .mp4 and existing frame PNGs (never an input)")
    rn.add_argument("--device", default="cpu", help="cpu or cuda")
    rn.add_argument("-o", "--output", required=True, help="output .mp4")
    rn.set_defaults(func=_cmd_render)

    st = sub.add_parser(
        "stream",
        help="render a run frame by frame as its speech arrives (a file played as a stream, or raw PCM on stdin), each frame as soon as no later audio can change it",
        description="Frames wait for about 0.3 s of speech after their time at 25 fps (the look-ahead: 140 ms of feature window, 16 ms of FFT, "
        "and AudioAttNet's 3 following frames) and equal adnerf render's frames of the same audio. Runs trained on log-mel features only.",
    )
    st.add_argument("run", help="run folder")
    st.add_argument("--audio", required=True, help="speech file, or - for raw 16 kHz mono signed 16-bit little-endian PCM on standard input (arecord -f S16_LE -r 16000 -c 1)")
    st.add_argument("--chunk-ms", type=_number(float, 1, 10000), default=40.0, help="milliseconds of audio taken at a time (default 40)")
    st.add_argument("--yaw", type=_number(float, -180, 180), default=0.0, help="degrees added about the head's vertical axis (as render --yaw)")
    st.add_argument("--pitch", type=_number(float, -180, 180), default=0.0, help="degrees added about the horizontal axis")
    st.add_argument("--roll", type=_number(float, -180, 180), default=0.0, help="degrees added about the viewing axis")
    st.add_argument("--blink", choices=("auto", "none"), default="auto", help="natural blinks or open eyes, for runs trained with eyes")
    st.add_argument("--background", default=None, help="replacement background image")
    st.add_argument("--frames", default=None, help="also write the frames as PNGs into this folder as they come")
    st.add_argument("--overwrite", action="store_true", help="replace an existing output .mp4 and frame PNGs")
    st.add_argument("--device", default="cpu", help="cpu or cuda")
    st.add_argument("--json", action="store_true", help="print the summary (frames, look-ahead, first-frame latency, real-time factor) as one JSON object")
    st.add_argument("-o", "--output", required=True, help="output .mp4")
    st.set_defaults(func=_cmd_stream)

    ev = sub.add_parser("evaluate", help="PSNR / SSIM (full frame, head, mouth), LMD, lip sync, and LPIPS and SyncNet LSE-D / LSE-C (with local weights) on held-out frames")
    ev.add_argument("run", help="run folder")
    ev.add_argument("dataset", help="dataset folder")
    ev.add_argument("--split", choices=("train", "test"), default="test")
    ev.add_argument("--device", default="cpu", help="cpu or cuda")
    ev.add_argument("--no-landmarks", action="store_true", help="skip the landmark metrics (LMD, lip-sync correlation and offset; dlib on every frame twice)")
    ev.add_argument("--lpips-backbone", default=None, help="AlexNet weights for LPIPS (default: the torch hub cache's alexnet-owt-7be5be79.pth, if there)")
    ev.add_argument("--lpips-linear", default=None, help="LPIPS linear layers (default: those the lpips package ships, if installed)")
    ev.add_argument("--syncnet", default=None, metavar="CHECKPOINT", help="SyncNet checkpoint (syncnet_v2.model of the public release) for LSE-D / LSE-C; without it they read \"no weights\" (nothing is downloaded)")
    ev.add_argument("--sweep", type=_count, default=0, metavar="FRAMES", help="also render this many frames of the split with the head turned by 0, 5, 10, 15 and 20 degrees of yaw and measure how the face, the neck and the torso hold up (pose_sweep in the output); 0: no sweep")
    ev.add_argument("--sweep-sheet", default=None, metavar="PNG", help="with --sweep: a contact sheet of the sweep's renders")
    ev.add_argument("--json", action="store_true", help="one JSON object on stdout")
    ev.set_defaults(func=_cmd_evaluate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``adnerf`` command; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: a refused argument (2, message printed) or --help (0)
        return int(exc.code or 0)
    from .allocator import tune_allocator

    tune_allocator()  # keeps freed tensor memory for reuse: fewer page faults (ADNERF_TUNE_MALLOC=0: off)
    try:
        with _sigterm_as_interrupt(), warnings.catch_warnings():
            warnings.showwarning = lambda message, *rest, **kw: print(f"adnerf: warning: {message}", file=sys.stderr)
            return int(args.func(args))
    except _user_errors() as exc:
        print(f"adnerf: error: {exc}", file=sys.stderr)
        return 2
    except CliError as exc:
        print(f"adnerf: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        from .atomic import disk_full  # a write outside atomic_path (frames of a dataset, PNGs)

        message = disk_full(exc.filename) if exc.filename else "the disk is full (no space left on the device); free some space and run the same command again"
        print(f"adnerf: error: {message}", file=sys.stderr)
        return 2
    except _interrupted() as exc:
        print(f"adnerf: {exc}", file=sys.stderr)
        return 128 + exc.signum  # 130 for SIGINT, 143 for SIGTERM, as the shell reports a signal
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (_Terminated): what was finished is kept
        print(f"adnerf: {str(exc) or 'interrupted'}", file=sys.stderr)
        return 143 if isinstance(exc, _Terminated) else 130


if __name__ == "__main__":
    sys.exit(main())
