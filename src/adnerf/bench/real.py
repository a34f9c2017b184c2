"""``adnerf bench real VIDEO``: how good adnerf is on a real person, within a training budget.

Steps, each timed (the times go into the result):

1. **video**: the clip resized to ``size`` pixels (its longer side; audio kept), cached in the
   work folder.
2. **preprocess**: ``adnerf preprocess`` of that video (cached: a dataset already there with the
   same settings is reused); the last ``test_fraction`` of the clip is held out.
3. **train**: both stages within ``minutes`` of training time: the iteration counts are fitted to
   the budget from the measured speed of a short probe (55% of the budget for the head, 45% for
   the torso, the demo's proportions).
4. **evaluate**: the held-out tail rendered with its own audio and its poses fitted to its frames
   (:func:`~adnerf.evaluation.fitted_poses.judged_poses`; the fit's seconds are the step's), and measured
   (:func:`adnerf.evaluation.evaluate.evaluate_run` with landmarks: PSNR / SSIM on the full frame, the head
   label and the mouth crop; LMD; mouth-opening correlation and audio-visual offset; LPIPS where
   weights are on this machine).
5. **sheet**: a contact sheet of true and rendered held-out frames with their mouths enlarged.
6. **drive** (with ``drive``): other speech (another speaker, another language) drives the run
   over the held-out poses (written as ``driven_<audio name>.mp4`` in the work folder). No true frames exist for it, so the rendered inner-lip opening (dlib
   landmarks) is compared with the driving audio's own speech activity (the voiced band's
   loudness, :func:`adnerf.audio.features.voiced_loudness`): their correlation and the shift that
   maximises it (> 0: the mouth is late). The clip's own audio gets the same measure as the
   reference: over every frame with preprocessing's landmarks, and over the held-out frames for
   the true frames and for the render.

The result is one dict (``--json`` prints it as one line) and, in the run's folder, ``bench_real.png``
(and ``bench_real_sweep.png``), so that runs of other seeds or variants on the clip keep their own. Besides the
metrics it holds the cost of the run: the seconds of each step above, the training seconds per
step of each stage, the bytes a frame of the clip holds in memory while training (its uint8
frame and labels) and the process's peak resident memory.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Mapping

import cv2
import numpy as np

from ..formats.dataset import DatasetFolder
from ..formats.run_folder import RunFolder
from ..memory import peak_rss_bytes

__all__ = ["bench_real", "drive_with_speech", "plot_mouth_opening", "resized_video"]

if TYPE_CHECKING:
    from ..model.train_config import TrainConfig

HEAD_SHARE = 0.55  # of the training budget; the rest is the torso's (the demo's 3600 : 3000)


def resized_video(video: str | Path, size: int | None, folder: Path) -> tuple[Path, dict]:
    """The clip with its longer side ``size`` pixels (even sizes; ``None``: the clip itself),
    written once into ``folder`` and reused; returns its path and ``{width, height, clip_frames,
    fps, source_size}``."""
    from ..io import frame_times, probe, read_video, write_video

    src = Path(video)
    meta = probe(src)  # no decoding: a cached copy is reused without reading the clip's frames
    w, h = int(meta["width"]), int(meta["height"])
    info = {"clip_frames": int(len(frame_times(src))), "fps": float(meta["fps"]), "source_size": [w, h]}
    if size is None or max(h, w) == size:
        return src, {**info, "width": w, "height": h}
    scale = size / max(h, w)
    nw, nh = 2 * round(w * scale / 2), 2 * round(h * scale / 2)
    out = folder / f"{src.stem}_{nw}x{nh}.mp4"
    if not out.exists():
        video_data = read_video(src)
        frames = np.stack([cv2.resize(f, (nw, nh), interpolation=cv2.INTER_AREA) for f in video_data.frames])
        # write_video plays sample 0 with frame 0: align the track to it
        audio = None if video_data.audio is None else video_data.audio.starting_at(float(video_data.timestamps[0]))
        write_video(out, frames, video_data.fps, audio)
    return out, {**info, "width": nw, "height": nh}


def _probe_seconds(dataset: Path, folder: Path, device: str, tcfg: "TrainConfig", steps: int = 30) -> tuple[float, float]:
    """Training seconds per head iteration, and per training frame of a pose refit pass (0 when
    ``tcfg`` asks for none), from a throwaway run of ``steps`` iterations under ``tcfg`` (removed
    afterwards; it lies in the benchmark's own work folder). Measured before empty-space skipping
    starts, so both err slow and the fitted schedule ends inside the budget."""
    from ..model.train import pose_refit_seconds, train

    probe = folder / "probe_run"
    shutil.rmtree(probe, ignore_errors=True)
    cfg = replace(tcfg, head_iters=10 * steps, checkpoint_every=steps, log_every=steps, pose_refit=0)
    try:
        train(dataset, probe, config=cfg, device=device, progress=False, max_steps=steps)
        per_iteration = RunFolder(probe).elapsed()["head"] / steps
        per_frame = pose_refit_seconds(probe, dataset, device=device) if tcfg.pose_refit else 0.0
    finally:
        shutil.rmtree(probe, ignore_errors=True)
    return per_iteration, per_frame


def schedule_config(config: Mapping[str, object] | None, seed: int) -> tuple["TrainConfig", str]:
    """The training config of a benchmark run: ``config``'s :class:`TrainConfig` fields over the
    defaults, with ``seed``; and the run folder's suffix that tells such a run from the default's
    (empty without ``config``). The iteration counts are the benchmark's (``iterations`` or the
    fitted schedule), so ``config`` may not give them.

    Raises:
        ValueError: ``config`` gives the iteration counts or the seed, or is not a valid config.
    """
    from ..model.train import TrainConfig

    given = dict(config or {})
    owned = sorted(k for k in ("head_iters", "torso_iters", "seed") if k in given)
    if owned:
        raise ValueError(f"the training config may not set {', '.join(owned)}: the benchmark's --iters (or the schedule fitted to --minutes) and --seed do")
    try:
        tcfg = TrainConfig.from_dict({**given, "seed": seed})
        tcfg.validate()
    except (TypeError, ValueError) as exc:
        raise ValueError(f"invalid training config: {exc}") from exc
    tag = "_cfg" + hashlib.sha1(json.dumps(given, sort_keys=True).encode()).hexdigest()[:8] if given else ""
    return tcfg, tag


def fitted_schedule(base: "TrainConfig", minutes: float, per_iteration: float, refit_pass: float = 0.0) -> tuple["TrainConfig", str]:
    """``base`` with the iteration counts that fill ``minutes`` of training: the time left after
    ``base.pose_refit`` passes of ``refit_pass`` seconds each, at ``per_iteration`` seconds an
    iteration, split :data:`HEAD_SHARE` to the head; and how they were fitted, in words.

    Raises:
        ValueError: The refit passes leave fewer than 100 iterations.
    """
    refits = base.pose_refit * refit_pass
    total = (minutes * 60.0 - refits) / per_iteration
    if refits and total < 100:
        raise ValueError(f"{minutes:g} min leaves {max(total, 0):.0f} iterations after the {base.pose_refit} pose refit passes (~{refits / 60:.1f} min); give more minutes or fewer passes")
    tcfg = replace(base, head_iters=max(1, round(HEAD_SHARE * total)), torso_iters=max(1, round((1 - HEAD_SHARE) * total)))
    return tcfg, f"{per_iteration * 1e3:.0f} ms each" + (f", {base.pose_refit} pose refit passes ~{refits:.0f} s" if refits else "") + f", fitted to {minutes:g} min"


def _sheet(path: Path, ds, frames: list[int], rendered: np.ndarray, count: int = 5) -> Path:
    """True and rendered held-out frames, with their mouth crops enlarged beside them."""
    from ..evaluation.sheets import contact_sheet
    from ..evaluation.evaluate import mouth_boxes

    picks = np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int)
    boxes = mouth_boxes(ds, [frames[k] for k in picks])
    h, w = ds.meta.height, ds.meta.width
    rows = []
    for k, (x0, y0, x1, y1) in zip(picks, boxes):
        true, render = ds.frames[frames[k]], rendered[k]
        zoom = [cv2.resize(img[y0:y1, x0:x1], (w, h), interpolation=cv2.INTER_NEAREST) for img in (true, render)]
        rows.append(np.stack([true, render, *zoom]))
    return contact_sheet(path, rows, ["true (held out)", "render", "true mouth", "rendered mouth"], [f"frame {frames[k]}" for k in picks])


def _sweep(run, ds, sheet: Path, count: int, log: Callable[[str], None]) -> dict:  # noqa: ANN001
    """The pose sweep of ``count`` held-out frames spread over the tail, with its contact sheet."""
    from ..evaluation.pose_sweep import SWEEP_YAWS, pose_sweep, spread, sweep_sheet

    t0 = time.perf_counter()
    frames = spread(ds.meta.test, count)
    log(f"turning the head of {len(frames)} held-out frames by {', '.join(f'{y:g}' for y in SWEEP_YAWS)} degrees")
    rows, renders = pose_sweep(run, ds, frames)
    shown = np.linspace(0, len(frames) - 1, min(3, len(frames))).round().astype(int)
    h, w = ds.meta.height, ds.meta.width
    zoom = (w // 4, 3 * h // 8, 3 * w // 4, 7 * h // 8) if h >= 64 else None  # in a head-and-shoulders framing: the mouth, the chin, the neck and the collar
    sweep_sheet(sheet, renders[shown], SWEEP_YAWS, [f"frame {frames[k]}" for k in shown], zoom=zoom)
    return {"frames": frames, "rows": rows, "sheet": str(sheet), "seconds": time.perf_counter() - t0}


def drive_with_speech(run, ds, audio_path: str | Path, video: str | Path | None = None, syncnet=None) -> dict:
    """Render ``run`` driven by the speech in ``audio_path`` over the dataset's held-out poses
    (played forwards and backwards) and measure how the rendered lips follow that speech.

    Args:
        run: A loaded run.
        ds: Its dataset (poses, plate).
        audio_path: The driving speech.
        video: Where to write the rendered clip with that speech (an mp4), or ``None``.
        syncnet: A :class:`~adnerf.evaluation.syncnet.SyncNet` to score the driven clip against the driving
            speech (LSE-D / LSE-C need no truth, so they judge speech the person never said), or
            ``None``.

    Returns:
        ``audio``, ``seconds``, ``frames``, ``landmarks_found``, ``video`` and
        :func:`~adnerf.bench.voices.mouth_follow`'s figures of the lip opening against the speech
        activity (``None`` when landmarks are found in fewer than half of
        the frames); with ``syncnet`` (and 25 frames per second) also its scores.
    """
    from ..audio.features import voiced_loudness
    from ..commands.render_video import audio_frames, pingpong, render_frames
    from ..model.render_clip import frame_signals
    from ..evaluation.landmark_metrics import mouth_opening
    from ..evaluation.syncnet import SYNCNET_FPS, face_crops, sync_scores
    from ..io import AudioTrack, read_audio, write_video
    from ..formats.dataset import LABEL_HEAD
    from ..preprocess.landmarks import DlibFaceDetector, track_faces
    from .voices import mouth_follow

    audio = read_audio(audio_path, sample_rate=16000)
    fps = ds.meta.fps
    windows = audio_frames(audio, fps, run.meta["feature_kind"], str(audio_path))
    n = len(windows)
    played = pingpong(np.asarray(ds.meta.test), n)  # the held-out frames' poses and torso motion
    clip = render_frames(run, windows, ds.poses[played], ds.background.astype(np.float32) / 255.0, signals=frame_signals(run, ds, played))
    if video is not None:
        write_video(video, clip.frames, fps, AudioTrack(audio.samples, audio.sample_rate, 0.0))
    labels = np.where(clip.head_opacity > 0.5, LABEL_HEAD, 0).astype(np.uint8)
    track = track_faces(clip.frames, DlibFaceDetector(), labels)
    row = {"audio": str(audio_path), "seconds": round(audio.duration, 2), "frames": n, "landmarks_found": int(track.detected.sum()), "video": None if video is None else str(video)}
    if track.detected.sum() < 0.5 * n:
        return {**row, "corr": None, "offset": None, "corr_at_offset": None}
    if syncnet is not None and abs(fps - SYNCNET_FPS) < 1e-6:
        row.update(sync_scores(syncnet, face_crops(clip.frames, track.boxes), audio.samples).as_dict())
    activity = voiced_loudness(audio.samples, audio.sample_rate, np.arange(n) / fps)
    return {**row, **mouth_follow(mouth_opening(track.landmarks), activity)}


def bench_real(
    video: str | Path,
    *,
    size: int | None = 256,
    minutes: float = 10.0,
    device: str = "cpu",
    cut: str = "jaw",
    clothes: str = "grabcut",
    features: str = "auto",
    test_fraction: float = 0.15,
    focal: float | None = None,
    work: str | Path = "adnerf_bench_real",
    lpips_backbone: str | Path | None = None,
    lpips_linear: str | Path | None = None,
    syncnet: str | Path | None = None,
    seed: int = 0,
    iterations: tuple[int, int] | None = None,
    config: Mapping[str, object] | None = None,
    drive: tuple[str | Path, ...] = (),
    sweep: int = 6,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict:
    """Preprocess a real clip, train within a budget, render its held-out tail and measure it.

    Args:
        video: The clip (one person, static camera, with audio).
        size: Longer side in pixels the clip is resized to first (``None``: as it is).
        minutes: Training budget (both stages), minutes of training time.
        device: ``"cpu"`` or ``"cuda"``.
        cut: Head / torso cut of the preprocessing (``"jaw"``, or ``"neck-row"`` to compare).
        clothes: Clothes completion of the preprocessing (``"grabcut"``, or ``"none"`` to compare).
        features: Audio features of the dataset (``"auto"``, ``"logmel"``, ``"phonemes"`` or
            ``"logmel+phonemes"``: :class:`~adnerf.preprocess.pipeline.PreprocessConfig`); the row's
            ``feature_kind`` is the kind the dataset got.
        test_fraction: Fraction of the clip, at its end, held out.
        focal: Focal length in pixels at ``size`` (default: preprocessing's guess).
        work: Folder for the cached video, dataset and run (``<stem>_<size>_<cut>/`` inside;
            ``_<features>`` appended for features other than ``"auto"``, ``_noclothes`` without
            the clothes completion).
        lpips_backbone: AlexNet weights for LPIPS (default: the torch hub cache's, if there).
        lpips_linear: LPIPS linear layers (default: the installed ``lpips`` package's, if any).
        syncnet: SyncNet checkpoint for LSE-D / LSE-C (:mod:`adnerf.evaluation.syncnet`; none: "no weights").
        seed: Training seed.
        iterations: ``(head, torso)`` iterations instead of the schedule fitted to ``minutes``
            (the probe's speed depends on the machine's load; comparisons want equal schedules).
        config: :class:`~adnerf.model.train.TrainConfig` fields other than the iteration counts
            and the seed, over the defaults (a variant to compare; its run folder's name carries a
            hash of them, so it never continues another variant's run). The fitted schedule
            counts a pose refit's passes (``pose_refit``) in the budget.
        drive: Other speech files to drive the trained run with (step 6).
        sweep: Held-out frames rendered with the head turned by each of
            :data:`~adnerf.evaluation.pose_sweep.SWEEP_YAWS` (:func:`~adnerf.evaluation.pose_sweep.pose_sweep`),
            with a contact sheet; 0 skips it.
        progress: Progress bars.
        log: Where step messages go.

    Returns:
        The metrics, the settings, the iteration counts and the seconds of each step.
    """
    from ..evaluation.evaluate import evaluate_run
    from ..evaluation.lip_signal import dataset_lip_signal
    from ..evaluation.lpips import lpips_if_available
    from ..evaluation.syncnet import load_syncnet
    from ..formats.dataset import frame_bytes, load_dataset, read_meta
    from ..model.train import load_run, train
    from ..preprocess.pipeline import PreprocessConfig, preprocess_video, step_bars

    sync = load_syncnet(syncnet, device) if syncnet is not None else None  # a bad file fails before hours of work
    if not minutes > 0 or not math.isfinite(minutes):
        raise ValueError(f"the training budget must be a positive number of minutes; got {minutes}")
    base, tag = schedule_config(config, seed)  # a bad config fails before hours of work
    for path in drive:  # before hours of work
        if not Path(path).is_file():
            raise ValueError(f"{path}: no such audio file to drive the run with")
    seconds: dict[str, float] = {}
    folder = Path(work) / (f"{Path(video).stem}_{size or 'native'}_{cut}" + ("" if features == "auto" else f"_{features}") + ("" if clothes == "grabcut" else "_noclothes"))
    folder.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    clip, info = resized_video(video, size, folder)
    seconds["video"] = time.perf_counter() - t0

    data = folder / "data"
    pcfg = PreprocessConfig(cut=cut, clothes=clothes, features=features, test_fraction=test_fraction, focal=focal)
    run_dir = folder / ((f"run_{iterations[0]}+{iterations[1]}it_seed{seed}" if iterations else f"run_{minutes:g}min_seed{seed}") + tag)
    t0 = time.perf_counter()
    report_path = DatasetFolder(data).report
    if not (report_path.exists() and {**asdict(PreprocessConfig()), **json.loads(report_path.read_text())["config"]} == asdict(pcfg)):  # settings added since take their defaults
        if RunFolder(run_dir).is_run():  # it would go on training on a dataset it was not started on
            raise ValueError(f"{run_dir} was trained on the dataset of other preprocessing settings; remove it (or choose another --work) to train afresh")
        log(f"preprocessing {clip} into {data}")
        with step_bars() as bars:
            preprocess_video(clip, data, pcfg, progress=bars if progress else None, overwrite=data.exists())
    seconds["preprocess"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if RunFolder(run_dir).is_run():
        log(f"continuing the run in {run_dir}")
        train(data, run_dir, device=device, resume=True, progress=progress)
    else:
        if iterations is not None:
            tcfg = replace(base, head_iters=iterations[0], torso_iters=iterations[1])
            how = "given"
        else:
            per_iteration, refit_per_frame = _probe_seconds(data, folder, device, base)
            tcfg, how = fitted_schedule(base, minutes, per_iteration, refit_per_frame * len(read_meta(data).train))
        log(f"training {tcfg.head_iters} head + {tcfg.torso_iters} torso iterations ({how}) into {run_dir}")
        train(data, run_dir, config=tcfg, device=device, progress=progress)
    seconds["train_wall"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    run, ds = load_run(run_dir, device), load_dataset(data, truth=False)
    model = lpips_if_available(lpips_backbone, lpips_linear, device)
    metrics, rendered = evaluate_run(run, ds, "test", landmarks=True, lpips=model, syncnet=sync)
    seconds["evaluate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    sheet = _sheet(run_dir / "bench_real.png", ds, list(ds.meta.test), rendered.frames)
    seconds["sheet"] = time.perf_counter() - t0

    swept = _sweep(run, ds, run_dir / "bench_real_sweep.png", sweep, log) if sweep else None
    if swept is not None:
        seconds["sweep"] = swept.pop("seconds")

    driven: list[dict] = []
    if drive:
        from ..audio.features import voiced_loudness
        from ..evaluation.landmark_metrics import mouth_opening
        from .voices import mouth_follow

        t0 = time.perf_counter()
        every, test = np.arange(ds.meta.n_frames), list(ds.meta.test)
        activity = voiced_loudness(ds.audio.samples, ds.audio.sample_rate, every / ds.meta.fps - ds.audio.start)
        landmarks = DatasetFolder(data).landmarks  # preprocessing's, every frame: the longest reference
        if landmarks.exists():
            whole = {"audio": "the clip's own audio, every frame", "seconds": round(len(every) / ds.meta.fps, 2), "frames": len(every)}
            driven.append({**whole, "lips": "true frames (preprocessing's landmarks)", **mouth_follow(mouth_opening(np.load(landmarks)), activity)})
        if "mouth_opening_true_px" in metrics:
            own = {"audio": "the clip's own held-out audio", "seconds": round(len(test) / ds.meta.fps, 2), "frames": len(test)}
            driven.append({**own, "lips": "true frames", **mouth_follow(np.asarray(metrics["mouth_opening_true_px"]), activity[test])})
            driven.append({**own, "lips": "render", **mouth_follow(np.asarray(metrics["mouth_opening_render_px"]), activity[test])})
        for path in drive:
            log(f"driving the run with {path}")
            driven.append({**drive_with_speech(run, ds, path, folder / f"driven_{Path(path).stem}.mp4", sync), "lips": "render"})
        seconds["drive"] = time.perf_counter() - t0

    try:  # the clip's own ceiling: how much its audio predicts its mouth (before any training)
        lips = dataset_lip_signal(data).to_dict()
    except ValueError as exc:  # no landmarks, or too few frames for the folds
        lips = {"unavailable": str(exc)}
    elapsed = run.elapsed
    report = json.loads(report_path.read_text())
    peak = peak_rss_bytes()  # this process's, the training included
    return {
        "video": str(video),
        **info,
        "size": size,
        "cut": cut,
        "clothes": clothes,
        "features": features,
        "feature_kind": ds.meta.feature_kind,
        "held_out_frames": len(ds.meta.test),
        "train_frames": len(ds.meta.train),
        "budget_minutes": minutes,
        "config": dict(config or {}),
        "head_iters": run.train_config.head_iters,
        "torso_iters": run.train_config.torso_iters,
        "train_seconds": elapsed["head"] + elapsed["torso"],
        "seconds_per_step": {stage: round(elapsed[stage] / max(iters, 1), 4) for stage, iters in (("head", run.train_config.head_iters), ("torso", run.train_config.torso_iters))},
        "data_bytes_per_frame": frame_bytes(ds.meta),
        "peak_rss_gib": None if peak is None else round(peak / 2**30, 2),
        "device": device,
        "layers": report.get("layers"),
        "lip_signal": lips,
        **metrics,
        "lpips": metrics.get("lpips", "no weights"),
        "syncnet": metrics["syncnet"],
        "driven": driven,
        "pose_range": run.pose_range.to_dict()["rotation_deg"] if run.pose_range is not None else None,
        "pose_sweep": swept,
        "seconds": {k: round(v, 1) for k, v in seconds.items()},
        "sheet": str(sheet),
        "dataset": str(data),
        "run": str(run_dir),
    }


def plot_mouth_opening(row: dict, path: str | Path) -> Path:
    """The true and rendered inner-lip opening over the held-out frames, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3))
    if "mouth_opening_true_px" in row:
        ax.plot(row["mouth_opening_true_px"], label="true", color="black")
        ax.plot(row["mouth_opening_render_px"], label=f"render (corr {row['mouth_open_corr']:.2f}, offset {row['av_offset_frames']} frames, slope {row['mouth_open_slope']:.2f})", color="tab:red")
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no landmarks found in enough frames", ha="center", transform=ax.transAxes)
    ax.set_xlabel("held-out frame")
    ax.set_ylabel("inner-lip opening (px)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
