"""Render a trained talking head saying new audio: poses, pose edits, backgrounds, mp4 output.

The audio (any file PyAV reads: another speaker, another language) gives the number of frames,
``floor(duration * fps)`` at the run's frame rate, and one feature window per frame, aligned by
time exactly as in training. Head poses come from a ``.npy`` file of ``(N, 4, 4)`` transforms,
from a dataset's pose track (played forwards and backwards to cover the audio), or by default from
the training dataset. Yaw, pitch and roll (degrees) rotate every pose about the head centre.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..audio.features import (
    FEATURE_KINDS,
    MODEL_RATE,
    FeatureSpec,
    load_npy_windows,
    speech_windows,
)
from ..io import AudioTrack, MediaError, read_audio, read_image, read_rgb, write_video
from ..model.blinks import count_blinks, eye_track
from ..model.render_clip import RenderedClip, RenderError, checked_poses, dataset_track, pingpong_index, render_frames  # re-exported: the command's refusals and its loop
from ..model.run_folder import Run
from ..lock import writes_folder
from ..formats.dataset import DatasetFolder
from ..formats.outputs import check_file_output, check_frames_folder
from ..formats.run_folder import RunFolder
from ..preprocess.framing import Framing
from .paste_back import PasteBackError, paste_back_frames, source_frames_of_dataset, write_pasted
from .pose_edits import AngleTrack, angle_tracks, check_pose_range, edit_poses, parse_angle

__all__ = ["RenderError", "RenderedClip", "check_render_outputs", "check_speech", "load_background", "pingpong", "render_frames", "render_audio_video"]



def check_speech(audio: AudioTrack, where: str, *, level: float = 0.01, min_fraction: float = 0.05) -> None:
    """Raise :class:`RenderError` unless some of ``audio`` is louder than silence.

    Audio counts as containing sound when at least ``min_fraction`` of its 20 ms blocks have an
    RMS above ``level`` (-40 dBFS).
    """
    x = np.asarray(audio.samples, dtype=np.float64)
    block = max(1, int(0.02 * audio.sample_rate))
    n = len(x) // block
    if n == 0:
        raise RenderError(f"{where}: the audio is shorter than 20 ms")
    rms = np.sqrt((x[: n * block].reshape(n, block) ** 2).mean(axis=1))
    if (rms > level).mean() < min_fraction:
        raise RenderError(f"{where}: the audio has no speech (it is silent or nearly silent: {100 * (rms > level).mean():.1f}% of it above -40 dBFS)")


def load_background(path: str | Path, height: int, width: int) -> np.ndarray:
    """An RGB image as a background ``(height, width, 3)`` float in [0, 1] (:func:`adnerf.io.read_image`).

    Raises:
        RenderError: A missing or unreadable image.
    """
    try:
        return read_image(path, height, width)
    except MediaError as exc:
        raise RenderError(str(exc)) from exc


@dataclass
class PastePlan:
    """Where a render's squares go back (:mod:`adnerf.commands.paste_back`).

    Attributes:
        framing: The dataset's framing (a crop, scaled).
        video: The source video whose frames the squares are pasted into (``None`` with ``still``).
        still: One full-size uint8 image ``(H, W, 3)`` to paste every square into instead.
        plate: The background behind the render, ``(h, w, 3)`` float in [0, 1], when a full-size
            ``--background`` replaces the whole frame (its crop, scaled); ``None``: as usual.
    """

    framing: Framing
    video: Path | None
    still: np.ndarray | None = None
    plate: np.ndarray | None = None


def _read_rgb(path: str | Path, what: str) -> np.ndarray:
    try:
        return read_rgb(path)
    except MediaError as exc:
        raise RenderError(f"{exc} ({what})") from exc


def plan_paste_back(meta: dict, paste_back: bool | None, *, source: str | Path | None = None, still_frame: str | Path | None = None, background: str | Path | None = None) -> PastePlan | None:
    """Decide, before any rendering, whether and into what the render is pasted back.

    Args:
        meta: The run's dataset metadata (its ``framing``, when preprocessing cropped the frames).
        paste_back: ``True`` asks for it, ``False`` refuses it, ``None`` (the default of ``render``)
            pastes back when the dataset was cropped and its source frames are at hand (else the
            square is written, with a warning).
        source: The source video, when it has moved since preprocessing.
        still_frame: A full-size image to paste every square into, instead of the source frames.
        background: ``--background``: an image of the source's size replaces the whole frame;
            any other size covers the square only.

    Raises:
        RenderError: Paste-back asked for and impossible: the dataset was not cropped, the source
            video is missing, or an image is not the source's size.
    """
    framing = Framing.from_dict(meta["framing"]) if meta.get("framing") else None
    asked = paste_back is True or source is not None or still_frame is not None
    if paste_back is False:
        if asked and (source is not None or still_frame is not None):
            raise RenderError("--source and --frame paste the render back into full frames: they cannot go with --no-paste-back")
        return None
    if framing is None or not framing.cropped:
        if asked:
            raise RenderError("this run's dataset was not cropped from a larger video (its metadata holds no framing): its renders already have the video's size")
        return None
    W, H = framing.source_size
    still = None
    if still_frame is not None:
        still = _read_rgb(still_frame, "--frame")
        if (still.shape[1], still.shape[0]) != (W, H):
            raise RenderError(f"{still_frame}: a --frame image must have the source video's size, {W}x{H}; got {still.shape[1]}x{still.shape[0]}")
    plate = None
    if background is not None:
        full = _read_rgb(background, "--background")
        if (full.shape[1], full.shape[0]) == (W, H):
            still = full if still is None else still
            plate = framing.transform(full).astype(np.float32) / 255.0
    video = None
    if still is None:
        video = Path(source) if source is not None else (Path(framing.video) if framing.video else None)
        if video is None or not video.is_file():
            where = "the dataset does not record its source video" if video is None else f"{video}: no such file"
            if paste_back is None:
                warnings.warn(f"the render is not pasted back into the full frames ({where}): writing the {framing.size[0]}x{framing.size[1]} square; --source VIDEO gives the video")
                return None
            raise RenderError(f"--paste-back: {where}; give the video the dataset was made from with --source VIDEO, or a still frame with --frame IMAGE")
    return PastePlan(framing, video, still, plate)


def pingpong(poses: np.ndarray, n: int) -> np.ndarray:
    """``n`` poses taken from ``poses`` forwards, then backwards, and so on (no jump at the ends;
    :func:`~adnerf.model.render_clip.pingpong_index`)."""
    return poses[pingpong_index(np.arange(n), len(poses))]


def load_poses(path: str | Path, n: int) -> np.ndarray:
    """A ``.npy`` file of ``(n, 4, 4)`` poses; anything else is a :class:`RenderError`."""
    p = Path(path)
    try:
        poses = np.load(p)
    except (OSError, ValueError) as exc:
        raise RenderError(f"{p}: not a readable .npy file of poses ({exc})") from exc
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise RenderError(f"{p}: poses must have shape (N, 4, 4); got {poses.shape}")
    if len(poses) != n:
        raise RenderError(f"{p}: has {len(poses)} poses but the audio gives {n} frames at this fps; give one pose per frame")
    return checked_poses(poses.astype(np.float64), str(p))


def frame_name(i: int) -> str:
    """The name of frame ``i``'s image written by ``--frames``: ``000000.png``, ..."""
    return f"{i:06d}.png"


def frame_names(n: int) -> list[str]:
    """The names of ``n`` frame images written by ``--frames``."""
    return [frame_name(i) for i in range(n)]


def check_render_outputs(out: str | Path, frames_dir: str | Path | None, *, inputs: list, overwrite: bool = False) -> None:
    """Refuse outputs a render must not write, before any rendering (see :mod:`adnerf.formats.outputs`):
    an ``out`` that is an input or an existing file without ``overwrite``, and a ``frames_dir``
    inside a dataset or run or already holding frame images (``NNNNNN.png``) without ``overwrite``.
    """
    check_file_output(out, inputs=inputs, overwrite=overwrite)
    if frames_dir is not None:
        check_frames_folder(frames_dir, overwrite=overwrite)


def audio_frames(audio: AudioTrack, fps: float, feature_kind: str, where: str) -> np.ndarray:
    """Feature windows ``(N, 16, D)`` of ``audio``, one per frame of ``fps`` (after checking it holds speech)."""
    check_speech(audio, where)
    n = int(math.floor(audio.duration * fps))
    if n < 1:
        raise RenderError(f"{where}: the audio is shorter than one frame at {fps} fps")
    times = audio.start + np.arange(n) / fps
    return speech_windows(audio, times, FeatureSpec(kind=feature_kind))


@writes_folder("frames_dir", "frames folder")  # one writer per --frames folder
def render_audio_video(
    run: Run,
    audio_path: str | Path,
    out: str | Path,
    *,
    poses_file: str | Path | None = None,
    from_dataset: str | Path | None = None,
    yaw: float | str | AngleTrack = 0.0,
    pitch: float | str | AngleTrack = 0.0,
    roll: float | str | AngleTrack = 0.0,
    strict_pose: bool = False,
    background: str | Path | None = None,
    features: str | Path | None = None,
    frames_dir: str | Path | None = None,
    blink: str | Path = "auto",
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    paste_back: bool | None = None,
    source: str | Path | None = None,
    still_frame: str | Path | None = None,
) -> dict:
    """Render the run saying the audio of ``audio_path`` and write an mp4 with that audio.

    A run whose dataset was cropped from a larger video is pasted back into the source's full
    frames by default (:func:`plan_paste_back`; ``paste_back`` ``False`` writes the square,
    ``source`` names a moved video, ``still_frame`` a full-size image to paste into).

    ``yaw``, ``pitch`` and ``roll`` are each degrees, a ``.npy`` of one angle per frame or
    ``sway:AMPLITUDE,PERIOD`` (:func:`~adnerf.commands.pose_edits.parse_angle`). The poses to render
    are compared with the range the run was taught (:attr:`Run.pose_range
    <adnerf.model.run_folder.Run.pose_range>`): beyond it by more than the margins a warning says
    how far, and ``strict_pose`` refuses before rendering (:class:`RenderError`).

    A run whose head reads the eye openness blinks as ``blink`` says
    (:func:`adnerf.model.blinks.eye_track`: ``"auto"`` natural blinks, ``"none"`` eyes open, or an
    ``.npy`` of one value per frame); other runs cannot blink and refuse a file.

    The audio's feature windows are computed with the run's extractor, or read from ``features``
    (an ``.npy`` of ``(M, 16, D)`` windows, one per frame at the run's fps; needed for runs whose
    features cannot be computed here, such as DeepSpeech features imported from AD-NeRF). Then
    the clip has ``min(M, frames of audio)`` frames.

    ``out`` (and ``frames_dir``) are checked before any work: an input or an existing file is
    never replaced without ``overwrite`` (:func:`check_render_outputs`). A ``features`` file with
    fewer windows than the audio has frames shortens the clip (and its audio), with a warning.

    Returns:
        A summary: frames, seconds of audio, render wall time and frames per second, output path.
    """

    if poses_file is not None and from_dataset is not None:
        raise RenderError("give either a pose file or a dataset to take poses from, not both")
    try:
        tracks = {name: v if isinstance(v, AngleTrack) else parse_angle(v) for name, v in (("yaw", yaw), ("pitch", pitch), ("roll", roll))}
    except ValueError as exc:
        raise RenderError(str(exc)) from exc
    blink_file = None if str(blink) in ("auto", "none") else blink
    track_files = [t.file for t in tracks.values() if t.file is not None]
    check_render_outputs(out, frames_dir, inputs=[audio_path, poses_file, features, background, blink_file, source, still_frame, *track_files], overwrite=overwrite)
    plan = plan_paste_back(run.meta, paste_back, source=source, still_frame=still_frame, background=background)
    if blink_file is not None and not run.model.reads_eye:
        raise RenderError(f"--blink {blink}: this run's head has no eye condition (it was trained on a dataset without eye openness), so it cannot blink on command")
    try:
        audio = read_audio(audio_path, sample_rate=MODEL_RATE)
    except MediaError as exc:
        raise RenderError(str(exc)) from exc
    meta = run.meta
    windows, audio = _feature_windows(meta, audio, audio_path, features)
    n = len(windows)
    poses, signals = (load_poses(poses_file, n), {}) if poses_file is not None else _dataset_poses(run, from_dataset, n)
    if plan is not None and plan.plate is not None:
        plate = plan.plate
    else:
        plate = load_background(background if background is not None else RunFolder(run.root).background, meta["height"], meta["width"])
    try:
        eye = eye_track(blink, n, meta["fps"]) if run.model.reads_eye else None
        angles = angle_tracks(tracks, poses, meta["fps"], run.pose_range)
        pose_warning = check_pose_range(run.pose_range, edit_poses(poses, angles), strict=strict_pose)
    except ValueError as exc:  # a bad blink or track file, a sway without a range, PoseRangeError
        raise RenderError(str(exc)) from exc
    source_index = None
    if plan is not None and plan.still is None:
        try:  # before rendering: a wrong video fails fast
            source_index = source_frames_of_dataset(plan.framing, plan.video, int(meta["n_frames"]), float(meta["fps"]))
        except PasteBackError as exc:
            raise RenderError(str(exc)) from exc
        source_index = source_index[pingpong(np.arange(len(source_index)), n)]
    clip = render_frames(run, windows, poses, plate, yaw=angles[:, 0], pitch=angles[:, 1], roll=angles[:, 2], eye=eye, progress=progress, signals=signals)
    track = AudioTrack(audio.samples, audio.sample_rate, 0.0)
    if plan is None:
        write_video(out, clip.frames, meta["fps"], track)
    else:
        write_pasted(out, paste_back_frames(clip.frames, plan.framing, video=plan.video, source_index=source_index, still=plan.still), meta["fps"], track)
    if frames_dir is not None:
        _write_frames(Path(frames_dir), clip.frames)
    size = list(plan.framing.source_size) if plan is not None else [int(meta["width"]), int(meta["height"])]
    return {"output": str(out), "frames": n, "size": size, "pasted_back": plan is not None, "audio_seconds": audio.duration, "render_seconds": clip.seconds, "render_fps": n / max(clip.seconds, 1e-9), "blinks": None if eye is None else count_blinks(eye), "pose_warning": pose_warning}


def _feature_windows(meta: dict, audio: AudioTrack, audio_path: str | Path, features: str | Path | None) -> tuple[np.ndarray, AudioTrack]:
    """The audio's feature windows ``(n, 16, D)`` (computed with the run's extractor, or read from
    ``features``) and the audio they cover (cut short when ``features`` holds fewer windows)."""
    if features is None:
        if meta["feature_kind"] == "none":
            raise RenderError("this run was trained on a silent dataset (--features none); it has no audio pathway to drive")
        if meta["feature_kind"] not in FEATURE_KINDS:
            raise RenderError(
                f"this run was trained on {meta['feature_kind']!r} features, which adnerf cannot compute; "
                "give the windows of the new audio with --features FILE.npy (for AD-NeRF's DeepSpeech: the aud.npy its extractor writes)"
            )
        return audio_frames(audio, meta["fps"], meta["feature_kind"], str(audio_path)), audio
    try:
        windows = load_npy_windows(features)
    except MediaError as exc:
        raise RenderError(str(exc)) from exc
    if windows.shape[2] != meta["feature_dim"] or not np.isfinite(windows).all():
        raise RenderError(f"{features}: this run needs finite windows of shape (M, 16, {meta['feature_dim']}); got {windows.shape}")
    wanted = max(1, int(math.floor(audio.duration * meta["fps"])))
    if len(windows) < wanted:
        warnings.warn(
            f"{features}: {len(windows)} feature windows but the audio gives {wanted} frames at {meta['fps']:g} fps; "
            f"the video stops after {len(windows) / meta['fps']:.2f} s of the {audio.duration:.2f} s of audio"
        )
        audio = AudioTrack(audio.samples[: int(round(len(windows) / meta["fps"] * audio.sample_rate))], audio.sample_rate, audio.start)
    return windows[:wanted], audio


def _dataset_poses(run: Run, from_dataset: str | Path | None, n: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """``n`` poses of a dataset's track played back and forth: ``from_dataset``'s, or the run's own
    dataset's; and the run's further signals on the same frames (the torso's motion in each)."""
    folder = Path(from_dataset) if from_dataset is not None else run.dataset
    track = DatasetFolder(folder).poses
    if not track.exists():
        hint = "" if from_dataset is not None else " (the run's training dataset has moved or gone: take poses from a dataset with --from DATASET, or give them with --poses FILE.npy)"
        raise RenderError(f"{track.parent}: no {track.name} to take poses from{hint}")
    poses, signals = dataset_track(run, folder)
    index = pingpong(np.arange(len(poses)), n)
    return poses[index], {name: values[index] for name, values in signals.items()}


def _write_frames(folder: Path, frames: np.ndarray) -> None:
    """``--frames``: the rendered squares as PNGs ``000000.png, ...``."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, f in zip(frame_names(len(frames)), frames):
        if not cv2.imwrite(str(folder / name), cv2.cvtColor(f, cv2.COLOR_RGB2BGR)):
            raise RenderError(f"{folder / name}: could not write the frame")
