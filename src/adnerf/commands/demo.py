"""``adnerf demo``: the whole product on the built-in synthetic scene.

Steps: synthesise a scene (``DIR/data``), train both stages (``DIR/run``), evaluate the held-out
frames, and render the held-out audio three ways: with the original poses, with a yaw of
+15 degrees, and over a replaced background. Writes ``DIR/demo.mp4`` (ground truth and the three
renders side by side, with the held-out audio), ``DIR/contact_sheet.png`` and ``DIR/metrics.json``.
Re-running with the same folder reuses the scene and resumes the training; a folder holding
another scene than the demo's is refused (:func:`check_reused_scene`).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable

import numpy as np

from ..evaluation.evaluate import evaluate_run
from ..evaluation.sheets import contact_sheet  # re-exported: the demo's sheet
from ..io import write_video
from ..formats.dataset import DatasetError, DatasetFolder, SceneMeta, load_dataset, tail_split
from ..formats.outputs import OutputError
from ..formats.run_folder import RunFolder
from ..model.train import TrainConfig, load_run, train
from ..subnormals import flush_subnormals
from ..synth import SynthConfig, synthesize
from ..model.render_clip import render_frames
from .options import add_device, checked_device, number

__all__ = ["DEMO_SYNTH", "DEMO_TRAIN", "DEMO_TRAIN_GPU", "check_reused_scene", "demo_schedule", "contact_sheet", "register", "run", "run_demo"]

# 30 s rather than the synthesiser's 18 s: the audio encoder learns the jaw from the training
# frames' speech alone, and more of it generalises better (docs/decisions.md). The last 10%
# (3 s, 75 frames) is held out.
DEMO_SYNTH = SynthConfig(seconds=30.0, test_fraction=0.1)
DEMO_TRAIN = TrainConfig(head_iters=3000, torso_iters=2000, rays=512, torso_samples=8, head_grid=128)
"""The demo's schedule on a CPU: steps of 512 rays (on two cores a step of 1024 rays costs 1.7
times as much), 3000 head and 2000 torso steps, the torso drawn with 8 + 8 samples a ray and the
head's finest plane at 128 cells, the 128 px scene's width (``docs/decisions.md``, *The demo in
five minutes on two cores*)."""
DEMO_TRAIN_GPU = TrainConfig()
"""The schedule a GPU's ``--scale`` multiplies (1024-ray steps; measured with ``--scale 4`` on an H200)."""
DEMO_YAW = 15.0


def demo_schedule(device: str, scale: int = 1) -> TrainConfig:
    """The demo's schedule on ``device`` (``"cpu"`` or ``"cuda"``) in ``scale`` times fewer, larger steps (:meth:`TrainConfig.scaled`)."""
    return (DEMO_TRAIN if device == "cpu" else DEMO_TRAIN_GPU).scaled(scale)


def new_background(height: int, width: int) -> np.ndarray:
    """The replacement background: ``skimage.data.coffee()`` resized, float [0, 1]."""
    import cv2
    from skimage import data

    img = data.coffee().astype(np.float32) / 255.0
    h, w = img.shape[:2]
    x0 = (w - h) // 2
    return cv2.resize(img[:, x0 : x0 + h], (width, height), interpolation=cv2.INTER_AREA)


def check_reused_scene(meta: SceneMeta, config: SynthConfig, where: Path, has_eye: bool = True) -> None:
    """Raise :class:`~adnerf.formats.dataset.DatasetError` if the scene in ``where`` is not the one ``config``
    makes (length, size, frame rate, held-out frames, what drives the jaw, whether it blinks:
    ``has_eye``, the dataset has ``eye.npy``), e.g. one left by an older demo: its figures would be
    reported under this demo's settings."""
    from ..synth import espeak_available

    n = config.n_frames
    _, test = tail_split(n, config.test_fraction)
    mouth = config.mouth if config.mouth != "auto" else ("visemes" if config.voice != "formant" and espeak_available() else "loudness")
    found_mouth = "visemes" if "mouth=visemes" in meta.source else "loudness"  # scenes before visemes say nothing
    blinks = has_eye and "blinks=off" not in meta.source
    found = (meta.n_frames, meta.width, meta.height, meta.fps, list(meta.test), found_mouth, blinks)
    wanted = (n, config.size, config.size, config.fps, test, mouth, config.blinks)
    if found != wanted:
        said = {True: "blinking", False: "not blinking"}
        raise DatasetError(
            f"{where} holds another scene ({meta.source}; {meta.n_frames} frames, {len(meta.test)} held out, {found_mouth} jaw, {said[blinks]}) than this demo "
            f"makes ({config.seconds:g} s at {config.fps:g} fps, {config.size} px, {len(test)} held out, {mouth} jaw, {said[config.blinks]}); "
            "choose another output folder or delete that one"
        )


DEMO_BLINK_GAP = (0.5, 1.0)  # blinks commanded on the held-out frames: 3-5 in their 3 s


def blinks_on_command(run, ds, test: list[int], plate: np.ndarray, seed: int = 1) -> dict:  # noqa: ANN001
    """Blink the held-out frames on command and read the eyes back.

    The held-out poses and audio are rendered with a commanded eye-openness track (natural blinks,
    closer together: :data:`DEMO_BLINK_GAP`); :class:`~adnerf.evaluation.readers.EyeReader` reads the eye
    openness off the renders and off the scene rendered exactly with the same command.

    Returns:
        ``blink_corr`` (the reading of the renders against the command, Pearson), ``blink_corr_gt``
        (the same of the exact frames: the ceiling the reader allows), ``blinks_commanded``, and a
        contact-sheet row (``strip``, ``strip_label``): the eyes enlarged, truth closed, then the
        render at openness 1, 0.5 and 0.
    """
    import cv2

    from ..evaluation.landmark_metrics import pearson
    from ..evaluation.readers import EyeReader, exact_frame
    from ..model.blinks import blink_track, count_blinks
    from ..synth import HeadModel, TorsoModel

    fps = ds.meta.fps
    command = blink_track(np.arange(len(test)) / fps, seed, gap=DEMO_BLINK_GAP).astype(np.float32)
    poses = ds.poses[test]
    reader = EyeReader(ds, poses)
    # Only the eyes are read: the renders cover the box around every frame's eye box, placed in
    # otherwise empty frames (the reader crops each frame's own box, inside it).
    x0, y0 = reader.boxes[:, :2].min(axis=0)
    x1, y1 = reader.boxes[:, 2:].max(axis=0)
    rendered = np.zeros((len(test), ds.meta.height, ds.meta.width, 3), np.uint8)
    rendered[:, y0:y1, x0:x1] = render_frames(run, ds.features[test], poses, plate, eye=command, box=(int(x0), int(y0), int(x1), int(y1))).frames
    head, torso = HeadModel(ds.meta.width), TorsoModel(ds.meta.width)
    scene_plate = ds.background.astype(np.float64) / 255.0
    index = np.arange(len(test))
    exact = [exact_frame(head, torso, p, scene_plate, opening=j, eye=e, box=reader.box(i)) for i, p, j, e in zip(index, poses, ds.truth.jaw[test], command)]
    # The strip: one held-out frame, its eyes enlarged (a square around both eyes, nearest-neighbour).
    k = int(np.argmin(command))
    x0, y0, x1, y1 = reader.boxes[k]
    side = max(x1 - x0, y1 - y0) + 6
    cx, cy = (x0 + x1) // 2, (y0 + y1) // 2
    a, b = max(0, cx - side // 2), max(0, cy - side // 2)
    H, W = ds.meta.height, ds.meta.width

    def zoom(img: np.ndarray) -> np.ndarray:
        return cv2.resize(img[b : b + side, a : a + side], (W, H), interpolation=cv2.INTER_NEAREST)

    at = [render_frames(run, ds.features[test[k] : test[k] + 1], poses[k : k + 1], plate, eye=np.array([e], np.float32)).frames[0] for e in (1.0, 0.5, 0.0)]
    truth_closed = exact_frame(head, torso, poses[k], scene_plate, opening=float(ds.truth.jaw[test[k]]), eye=0.0)
    return {
        "blink_corr": pearson(reader.read(rendered, index), command),
        "blink_corr_gt": pearson(reader.read_crops(exact, index), command),
        "blinks_commanded": count_blinks(command),
        "strip": np.stack([zoom(truth_closed)] + [zoom(f) for f in at]),
        "strip_label": f"eyes, frame {test[k]}: truth closed | render open, half, closed",
    }


def run_demo(
    out_dir: str | Path = "adnerf_demo",
    *,
    device: str = "cpu",
    synth_config: SynthConfig = DEMO_SYNTH,
    train_config: TrainConfig | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict:
    """Run the demo (``train_config``: :func:`demo_schedule` of the device when ``None``); returns
    the metrics written to ``DIR/metrics.json``."""
    train_config = demo_schedule(device) if train_config is None else train_config
    flush_subnormals()  # before the first torch work starts the worker threads (adnerf.subnormals)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data_dir, run_dir = out / "data", out / "run"
    t0 = time.perf_counter()
    if not DatasetFolder(data_dir).is_dataset():
        log(f"synthesising the scene into {data_dir}")
        synthesize(data_dir, synth_config)
    synth_seconds = time.perf_counter() - t0
    ds = load_dataset(data_dir)
    check_reused_scene(ds.meta, synth_config, data_dir, has_eye=ds.eye is not None)
    t1 = time.perf_counter()
    train(data_dir, run_dir, config=train_config, device=device, resume=RunFolder(run_dir).is_run(), progress=progress)
    train_seconds = time.perf_counter() - t1
    run = load_run(run_dir, device)
    log("evaluating the held-out frames")
    # The new background's panel: the evaluated frames composited over it (no second render); the
    # turned head's panel: over the evaluated frames' torso, which reads the un-turned pose.
    # The synthetic scene's poses are exact: nothing to fit, and the turned panel's torso is the one
    # rendered under the same poses.
    metrics, plain = evaluate_run(run, ds, "test", backgrounds=[new_background(ds.meta.height, ds.meta.width)], keep=("torso",), poses="tracked")
    test = list(ds.meta.test)
    windows, poses = ds.features[test], ds.poses[test]
    plate = ds.background.astype(np.float32) / 255.0
    turned = render_frames(run, windows, poses, plate, yaw=DEMO_YAW, given=plain.kept)
    replaced = plain.over[0]
    gt = ds.frames[test]
    panels = np.concatenate([gt, plain.frames, turned.frames, replaced], axis=2)
    write_video(out / "demo.mp4", panels, ds.meta.fps, ds.audio_of(test[0], test[-1] + 1))
    blinks = blinks_on_command(run, ds, test, plate) if run.model.reads_eye and ds.truth is not None else None
    picks = np.linspace(0, len(test) - 1, 5).round().astype(int)
    rows = [np.stack([gt[k], plain.frames[k], turned.frames[k], replaced[k]]) for k in picks]
    labels = [f"frame {test[k]}" for k in picks]
    if blinks is not None:
        rows.append(blinks.pop("strip"))
        labels.append(blinks.pop("strip_label"))
    contact_sheet(out / "contact_sheet.png", rows, ["ground truth", "render (test audio)", f"yaw +{DEMO_YAW:g} deg", "new background"], labels)
    result = {
        "psnr_test": metrics["psnr"],
        "ssim_test": metrics["ssim"],
        "psnr_mouth_test": metrics["psnr_mouth"],
        "ssim_mouth_test": metrics["ssim_mouth"],
        "mouth_open_corr": metrics.get("mouth_open_corr"),
        "mouth_open_corr_gt": metrics.get("mouth_open_corr_gt"),
        **(blinks or {}),
        "test_frames": metrics["frames"],
        "train_seconds": train_seconds,
        "synth_seconds": synth_seconds,
        "render_fps": metrics["render_fps"],
        "total_seconds": time.perf_counter() - t0,
        "device": device,
        "size": ds.meta.width,
        "synth": asdict(synth_config),
        "train": asdict(train_config),
    }
    (out / "metrics.json").write_text(json.dumps(result, indent=1))
    log(f"wrote {out / 'demo.mp4'}, {out / 'contact_sheet.png'} and {out / 'metrics.json'}")
    return result


def register(sub: argparse._SubParsersAction) -> None:
    """``adnerf demo``."""
    p = sub.add_parser("demo", help="synthesise a talking head, train, render held-out audio three ways, evaluate")
    p.add_argument("-o", "--output", default="adnerf_demo", help="output folder (default adnerf_demo); re-running resumes")
    add_device(p)
    p.add_argument("--scale", type=number(int, 1, 64), default=1, help="train the demo's schedule in K times fewer steps of K times the rays from K times the frames, learning rates times sqrt(K) (as train --scale; for GPUs: --scale 4)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: is a file, not a folder; give a folder for the demo")
    device = checked_device(args.device)
    metrics = run_demo(args.output, device=device, train_config=demo_schedule(device, args.scale))
    keys = ("psnr_test", "ssim_test", "psnr_mouth_test", "mouth_open_corr", "train_seconds", "render_fps", "total_seconds")
    print(json.dumps({k: metrics[k] for k in keys}, indent=1))
    return 0
