"""Render a run's frames: one per audio feature window, under given (or edited) head poses.

The one rendering loop of the product, below both the ``render`` command
(:mod:`adnerf.commands.render_video`) and the evaluation (:mod:`adnerf.evaluation.evaluate`):
each frame's pose (rotated by per-frame yaw, pitch and roll about the head centre), its audio
code, its eye openness, what the torso reads under an edit
(:func:`~adnerf.model.pose_range.torso_reads`), and the further signals the model reads per frame
(the torso's motion: :func:`frame_signals` of the frames whose poses are played).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np
import torch

from ..cameras import Camera
from ..compositor import Layer
from ..pose import HeadPose
from ..formats.dataset import DatasetError, DatasetFolder, DatasetTracks, TalkingHeadDataset, check_poses, read_tracks
from ..formats.run_folder import scene_meta
from .conditions import SIGNALS
from .pose_range import edit_poses, torso_reads
from .run_folder import Run
from .talking_head import FrameRender, render_frame

__all__ = ["RenderError", "RenderedClip", "checked_poses", "dataset_track", "frame_setup", "frame_signals", "pingpong_index", "render_frames", "render_layers", "render_one"]


class RenderError(ValueError):
    """Inputs to rendering that cannot be used (silent audio, wrong pose count, bad image)."""


def checked_poses(poses: np.ndarray, where: str) -> np.ndarray:
    """``poses`` after the dataset loader's rigidity checks (:func:`adnerf.formats.dataset.check_poses`)."""
    try:
        check_poses(poses, where)
    except DatasetError as exc:
        raise RenderError(str(exc)) from exc
    return poses


@dataclass
class RenderedClip:
    """Rendered frames with what they were rendered from.

    Attributes:
        frames: ``(N, H, W, 3)`` uint8.
        head_opacity: ``(N, H, W)`` float32.
        torso_opacity: ``(N, H, W)`` float32.
        seconds: Wall time of the rendering.
        over: The same frames over each of the further backgrounds asked for, ``(N, H, W, 3)``
            uint8 each (the layers composited once more, not rendered again).
        kept: The layers asked to be kept, by name: each frame's layer and depth
            (:meth:`~adnerf.model.talking_head.FrameRender.layer`), to be handed to another render
            of the same frames whose edit the layer does not read (``render_frames(given=...)``).
    """

    frames: np.ndarray
    head_opacity: np.ndarray
    torso_opacity: np.ndarray
    seconds: float
    over: list[np.ndarray] = field(default_factory=list)
    kept: dict[str, list[tuple[Layer, torch.Tensor]]] = field(default_factory=dict)


def pingpong_index(j: int | np.ndarray, m: int) -> np.ndarray:
    """The track frame shown at output frame(s) ``j`` of a track of ``m`` frames played forwards,
    then backwards, and so on (no jump at the ends): how ``render`` plays the training poses."""
    if m == 1:
        return np.zeros_like(np.asarray(j))
    period = 2 * (m - 1)
    k = np.asarray(j) % period
    return np.where(k < m, k, period - k)


def frame_setup(run: Run, plate: np.ndarray) -> tuple[Camera, torch.Tensor]:
    """The run's camera and a background ``(H, W, 3)`` float in [0, 1] as a tensor on its device.

    Raises:
        RenderError: A background of another size than the run's frames.
    """
    meta = run.meta
    if plate.shape != (meta["height"], meta["width"], 3):
        raise RenderError(f"background must be ({meta['height']}, {meta['width']}, 3); got {plate.shape}")
    dev = next(run.model.parameters()).device
    camera = scene_meta(meta).camera(device=dev)
    return camera, torch.as_tensor(plate, dtype=torch.float32, device=dev)


def frame_signals(run: Run, ds: "TalkingHeadDataset | DatasetTracks", frames: Sequence[int] | np.ndarray) -> dict[str, np.ndarray]:
    """The values ``(len(frames), k)`` of the run's
    :attr:`~adnerf.model.talking_head.ModelConfig.frame_signals` on dataset frames (a loaded
    dataset, or its tracks alone: :func:`~adnerf.formats.dataset.read_tracks`), read as training
    reads them (each signal's ``track``): what a render of those frames' poses gives each frame
    (the torso's motion with the pose of the frame it moved in). A signal the dataset has no
    track of is left out (its ``rest`` value)."""
    out = {}
    for name in run.model.config.frame_signals:
        track = SIGNALS[name].track
        values = None if track is None else track(ds)
        if values is not None:
            out[name] = np.asarray(values, dtype=np.float64).reshape(ds.meta.n_frames, -1)[np.asarray(frames, dtype=np.int64)]
    return out


def dataset_track(run: Run, folder: str | Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A dataset's pose track ``(M, 4, 4)`` and the run's frame signals on its frames
    (:func:`frame_signals`; ``{}`` for a run that reads none, whose render needs only the poses):
    what a render over that track plays (``adnerf render``, a stream), frame by frame. On the
    run's own dataset the poses are those training aligned (:meth:`Run.dataset_poses`).

    Raises:
        RenderError: Poses that are not rigid motions, or a dataset whose tracks do not read.
    """
    poses_file = DatasetFolder(Path(folder)).poses
    if not run.model.config.frame_signals:
        poses, signals = np.load(poses_file), {}
    else:
        try:
            tracks = read_tracks(folder)
        except DatasetError as exc:
            raise RenderError(str(exc)) from exc
        poses, signals = tracks.poses, frame_signals(run, tracks, np.arange(len(tracks.poses)))
    poses = checked_poses(poses, str(poses_file))
    if run.learnt_corrections(folder, len(poses)) is not None:
        poses = run.dataset_poses(poses, np.arange(len(poses)))
    return poses, signals


def _checked_signals(run: Run, signals: Mapping[str, np.ndarray] | None, n: int) -> dict[str, np.ndarray]:
    """``signals`` checked against the run's frame signals: known names, ``(n, width)`` finite values."""
    known = run.model.config.frame_signals
    out = {}
    for name, values in (signals or {}).items():
        if name not in known:
            raise RenderError(f"the run reads no {name!r} signal; it reads {', '.join(known) or 'none'}")
        values = np.asarray(values, dtype=np.float64)
        if values.shape != (n, SIGNALS[name].width) or not np.isfinite(values).all():
            raise RenderError(f"the {name} signal must be ({n}, {SIGNALS[name].width}) finite values, one row per frame; got shape {values.shape}")
        out[name] = values
    return out


def render_layers(
    run: Run,
    camera: Camera,
    plate: torch.Tensor,
    pose: np.ndarray,
    code: torch.Tensor,
    *,
    eye: float | None = None,
    read_pose: np.ndarray | None = None,
    box: tuple[int, int, int, int] | None = None,
    given: Mapping[str, tuple[Layer, torch.Tensor]] | None = None,
    signals: Mapping[str, np.ndarray] | None = None,
) -> FrameRender:
    """One frame as :class:`~adnerf.model.talking_head.FrameRender` (its layers, opacities and
    depths; the pixels of ``box`` only when given; ``signals``: the frame's values of the model's
    :attr:`~adnerf.model.talking_head.ModelConfig.frame_signals`): what :func:`render_one` and
    :func:`render_frames` render every frame with."""
    dev = plate.device
    as_pose = lambda m: HeadPose.from_matrix(torch.as_tensor(m, dtype=torch.float64, device=dev))  # noqa: E731
    return render_frame(
        run.model, camera, as_pose(pose), code, plate, eye=eye, layers=run.trained_layers, amp=run.train_config.amp, read_pose=None if read_pose is None else as_pose(read_pose), box=box, given=given,
        signals=signals,
    )  # fmt: skip


def _u8(rgb: torch.Tensor) -> np.ndarray:
    return np.round(rgb.cpu().numpy() * 255.0).astype(np.uint8)


def render_one(
    run: Run, camera: Camera, plate: torch.Tensor, pose: np.ndarray, code: torch.Tensor, *, eye: float | None = None, read_pose: np.ndarray | None = None,
    signals: Mapping[str, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """One frame: its head pose ``(4, 4)``, audio code ``(audio_dim,)`` and eye openness (``None``:
    open), the torso reading ``read_pose`` when given (an edit), and the frame's further signals
    (:func:`render_layers`).

    Returns:
        ``(rgb (H, W, 3) uint8, head opacity (H, W), torso opacity (H, W))``.
    """
    out = render_layers(run, camera, plate, pose, code, eye=eye, read_pose=read_pose, signals=signals)
    return _u8(out.rgb), out.head_opacity.cpu().numpy(), out.torso_opacity.cpu().numpy()


def render_frames(
    run: Run,
    windows: np.ndarray,
    poses: np.ndarray,
    plate: np.ndarray,
    *,
    yaw: float | np.ndarray = 0.0,
    pitch: float | np.ndarray = 0.0,
    roll: float | np.ndarray = 0.0,
    eye: np.ndarray | None = None,
    torso_pose: str = "track",
    progress: Callable[[int, int], None] | None = None,
    backgrounds: Sequence[np.ndarray] = (),
    box: tuple[int, int, int, int] | None = None,
    keep: Sequence[str] = (),
    given: Mapping[str, Sequence[tuple[Layer, torch.Tensor]]] | None = None,
    signals: Mapping[str, np.ndarray] | None = None,
) -> RenderedClip:
    """Render one frame per feature window.

    Args:
        run: A loaded run.
        windows: Audio feature windows ``(N, 16, D)``.
        poses: Head poses ``(N, 4, 4)``.
        plate: Background ``(H, W, 3)`` float in [0, 1].
        yaw: Added rotation about the head's vertical axis through its centre, degrees (one
            number, or ``(N,)`` per frame); positive turns the face towards the image's left (the
            person's right).
        pitch: About the horizontal axis, degrees (a number or ``(N,)``); positive nods the face down.
        roll: About the viewing axis, degrees (a number or ``(N,)``); positive turns the head
            clockwise in the image.
        eye: Eye openness per frame ``(N,)`` (1 open, 0 closed) for runs whose head reads it;
            ``None``: open.
        torso_pose: What the torso reads under an edit (:func:`~adnerf.model.pose_range.torso_reads`):
            ``"track"`` the un-edited poses.
        progress: Called as ``progress(done, total)``.
        backgrounds: Further backgrounds ``(H, W, 3)`` float in [0, 1]: each frame is also
            composited over each (:attr:`RenderedClip.over`), at no further field evaluation.
        box: ``(x0, y0, x1, y1)`` (end exclusive): render only these pixels of every frame; the
            clip's images are the box's ``(h, w)``.
        keep: Names of layers whose per-frame pictures the clip keeps (:attr:`RenderedClip.kept`).
        given: Layers already drawn for these frames, by name, one per frame (another clip's
            :attr:`RenderedClip.kept`): composited instead of rendered. Only for a layer that
            reads nothing the two renders differ in: the torso of a head turned with
            ``torso_pose="track"`` is the un-edited torso.
        signals: Per-frame values ``(N, k)`` of the model's
            :attr:`~adnerf.model.talking_head.ModelConfig.frame_signals` by name (the torso's
            motion, ``torso_motion``: :func:`frame_signals` of a dataset's frames); one left out
            gets the signal's ``rest`` value.
    """
    model = run.model
    dev = next(model.parameters()).device
    if len(poses) != len(windows):
        raise RenderError(f"{len(poses)} poses for {len(windows)} audio frames")
    given = dict(given or {})
    for name, layers in given.items():
        if len(layers) != len(windows):
            raise RenderError(f"{len(layers)} given {name} layers for {len(windows)} frames")
    drawn = run.trained_layers or tuple(model.layers)
    for name in (*keep, *given):
        if name not in drawn:
            raise RenderError(f"the run draws no {name!r} layer to keep or be given; it draws {', '.join(drawn)}")
    if given and torso_pose != "track":
        raise RenderError(f"given layers are composited as they were drawn; with torso_pose={torso_pose!r} the torso reads the edited pose")
    if eye is not None and (np.shape(eye) != (len(windows),) or not np.isfinite(eye).all()):
        raise RenderError(f"eye openness must be {len(windows)} finite values, one per frame; got shape {np.shape(eye)}")
    signals = _checked_signals(run, signals, len(windows))
    try:
        angles = np.stack([np.broadcast_to(np.asarray(a, dtype=np.float64), (len(windows),)) for a in (yaw, pitch, roll)], axis=1)
    except ValueError:
        raise RenderError(f"yaw, pitch and roll must be numbers or one angle per frame ({len(windows)}); got shapes {[np.shape(a) for a in (yaw, pitch, roll)]}") from None
    if not np.isfinite(angles).all():
        raise RenderError("yaw, pitch and roll must be finite degrees")
    track = checked_poses(np.asarray(poses, dtype=np.float64), "poses")
    poses = edit_poses(track, angles)
    reads = torso_reads(torso_pose, track, poses, run.pose_range)
    camera, plate_t = frame_setup(run, plate)
    others = [frame_setup(run, b)[1] for b in backgrounds]
    if box is not None:
        others = [b[box[1] : box[3], box[0] : box[2]] for b in others]
    t0 = time.perf_counter()
    with torch.no_grad():
        codes = model.frame_codes(torch.as_tensor(windows, device=dev))
    n = len(windows)
    H, W = (camera.height, camera.width) if box is None else (box[3] - box[1], box[2] - box[0])
    frames = np.empty((n, H, W, 3), dtype=np.uint8)
    head_op = np.empty((n, H, W), dtype=np.float32)
    torso_op = np.empty((n, H, W), dtype=np.float32)
    over = [np.empty((n, H, W, 3), dtype=np.uint8) for _ in others]
    kept: dict[str, list[tuple[Layer, torch.Tensor]]] = {name: [] for name in keep}
    for i in range(n):
        read = None if reads is None or not angles[i].any() else reads[i]  # an un-edited frame reads its own pose
        mine = {name: layers[i] for name, layers in given.items()}
        out = render_layers(
            run, camera, plate_t, poses[i], codes[i], eye=None if eye is None else float(eye[i]), read_pose=read, box=box, given=mine or None,
            signals={name: values[i] for name, values in signals.items()},
        )  # fmt: skip
        frames[i], head_op[i], torso_op[i] = _u8(out.rgb), out.head_opacity.cpu().numpy(), out.torso_opacity.cpu().numpy()
        for k, background in enumerate(others):
            over[k][i] = _u8(out.over(background))
        for name in keep:
            kept[name].append(out.layer(name))
        if progress is not None:
            progress(i + 1, n)
    return RenderedClip(frames, head_op, torso_op, time.perf_counter() - t0, over, kept)
