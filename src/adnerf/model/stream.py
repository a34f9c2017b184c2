"""Streaming: render a run saying speech that arrives in pieces, each frame as soon as it is final.

A :class:`Streamer` takes 16 kHz mono samples as they come (a microphone, a text-to-speech
engine) and hands back the frames that no later audio can change. A frame waits for

- its feature window: 16 log-mel features centred on its time, the last 140 ms after it, each
  feature half an FFT (16 ms) wide (:class:`~adnerf.audio.features.StreamingWindows`);
- AudioAttNet's neighbours, when the run smooths its audio codes: the windows of the
  ``att_len - att_len // 2 - 1`` frames after it (3 of the paper's 8); none in the causal mode
  (``causal=True``: the smoothing reads no later frame, its window clamped at the frame itself).

:attr:`Streamer.lookahead_s` is the sum: about 0.3 s at 25 fps (0.18 s causal). The frames equal those of
:func:`~adnerf.model.render_clip.render_frames` for the same audio, poses and edits (the offline
``adnerf render``): the same features, codes, poses, blinks and renderer, computed piece by piece
(the features to float rounding, about 1e-6, when a piece holds a single feature).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from ..audio.features import MODEL_RATE, StreamingWindows
from ..formats.dataset import DatasetFolder
from ..formats.run_folder import RunFolder
from ..io import read_audio, read_image
from .blinks import blink_track
from .pose_range import edit_poses, torso_reads
from .render_clip import RenderError, checked_poses, dataset_track, frame_setup, pingpong_index, render_one  # pingpong_index: re-exported
from .run_folder import Run

__all__ = ["Streamer", "pingpong_index", "stream_file_chunks"]


class Streamer:
    """Render a run frame by frame as its speech arrives (see the module docstring).

    Args:
        run: A loaded run trained on log-mel features.
        poses: Head poses ``(M, 4, 4)`` played forwards and backwards (default: the run's training
            dataset's track, as ``adnerf render`` plays it, each frame with the torso's motion
            of the track's frame where the run follows it; given poses: the reference torso).
        plate: Background ``(H, W, 3)`` float in [0, 1] (default: the run's plate).
        yaw: Degrees added about the head's vertical axis (as ``render --yaw``).
        pitch: Degrees added about the horizontal axis.
        roll: Degrees added about the viewing axis.
        blink: ``"auto"`` (natural blinks) or ``"none"``, for runs whose head reads the eye.
        start: Time of the first sample, seconds (a file's audio start; 0 for a live stream).
        causal: The low-latency mode: AudioAttNet reads no frame after the one it smooths (its
            window is clamped there, as the offline render clamps it at a clip's last frame), so
            a frame waits for its feature window only; the frames then differ from the offline
            render's wherever the following frames would have changed the smoothing.

    Raises:
        RenderError: A run whose features cannot be computed as the audio arrives, no pose track,
            or bad edits.
    """

    def __init__(
        self,
        run: Run,
        *,
        poses: np.ndarray | None = None,
        plate: np.ndarray | None = None,
        yaw: float = 0.0,
        pitch: float = 0.0,
        roll: float = 0.0,
        blink: str = "auto",
        start: float = 0.0,
        causal: bool = False,
    ) -> None:
        meta = run.meta
        if meta["feature_kind"] != "logmel":
            raise RenderError(
                f"this run reads {meta['feature_kind']!r} features; streaming computes log-mel features as the audio arrives "
                "(the phoneme and wav2vec2 extractors read seconds of context on either side): render it with adnerf render, "
                "or train the run to stream on a dataset preprocessed with --features logmel"
            )
        if blink not in ("auto", "none"):
            raise RenderError(f"a stream blinks 'auto' or 'none'; got {blink!r}")
        angles = np.array([yaw, pitch, roll], dtype=np.float64)
        if not np.isfinite(angles).all() or np.abs(angles).max() > 180:
            raise RenderError("yaw, pitch and roll must be finite degrees within -180..180")
        self.signals: dict[str, np.ndarray] = {}  # per track frame: the torso's motion in it
        if poses is None:
            track = DatasetFolder(run.dataset).poses
            if not track.exists():
                raise RenderError(f"{track}: no pose track to play (the run's training dataset has moved or gone): give poses")
            poses, self.signals = dataset_track(run, run.dataset)
        self.run, self.fps = run, float(meta["fps"])
        self.track = checked_poses(np.asarray(poses, dtype=np.float64), "poses")
        self.angles = angles
        self.blink = blink if run.model.reads_eye else None
        if plate is None:
            plate = read_image(RunFolder(run.root).background, meta["height"], meta["width"])
        self.camera, self.plate = frame_setup(run, plate)
        self.windows = StreamingWindows(self.fps, start=start, n_mels=int(meta["feature_dim"]))
        model = run.model
        self.causal = causal
        self._after = (model.config.att_len - model.config.att_len // 2 - 1) if model.smooths_audio and not causal else 0
        self._before = model.config.att_len // 2 if model.smooths_audio else 0
        self._held = np.zeros((0, 16, int(meta["feature_dim"])), np.float32)  # windows of the frames not yet rendered, and their neighbours
        self._held_from = 0  # frame index of _held[0]
        self._n_windows = 0
        self.frames_out = 0
        self.first_frame_s: float | None = None  # wall seconds from the first push to the first frame
        self._t0: float | None = None

    @property
    def lookahead_s(self) -> float:
        """Seconds of speech past a frame's time that it waits for before it is rendered."""
        return self.windows.lookahead_s + self._after / self.fps

    def push(self, samples: np.ndarray) -> list[np.ndarray]:
        """Add 16 kHz mono float samples; the frames now final, uint8 ``(H, W, 3)``, in order."""
        if self._t0 is None:
            self._t0 = time.perf_counter()
        return self._take(self.windows.push(samples), finished=False)

    def finish(self) -> list[np.ndarray]:
        """End of the speech: the frames that waited for audio that will not come."""
        return self._take(self.windows.finish(), finished=True)

    def _take(self, new: np.ndarray, finished: bool) -> list[np.ndarray]:
        if len(new):
            self._held = np.concatenate([self._held, new])
            self._n_windows += len(new)
        last = self._n_windows if finished else self._n_windows - self._after  # frames whose neighbours are all here
        out = []
        while self.frames_out < last:
            out.append(self._render(self.frames_out, finished))
            self.frames_out += 1
            if self.first_frame_s is None and self._t0 is not None:
                self.first_frame_s = time.perf_counter() - self._t0
        drop = max(0, self.frames_out - self._before - self._held_from)  # windows no frame to come reads
        self._held, self._held_from = self._held[drop:], self._held_from + drop
        return out

    def _render(self, i: int, finished: bool) -> np.ndarray:
        model = self.run.model
        lo = max(0, i - self._before)
        hi = i + 1 if self.causal else self._n_windows if finished else i + self._after + 1
        local = torch.as_tensor(self._held[lo - self._held_from : hi - self._held_from], device=self.plate.device)
        with torch.no_grad():
            code = model.frame_codes(local, [i - lo])[0]  # neighbours clamped at the clip's ends as offline
        k = int(pingpong_index(i, len(self.track)))
        track = self.track[k][None]
        pose = edit_poses(track, self.angles[None])[0]
        reads = torso_reads("track", track, pose[None], self.run.pose_range)
        read = None if reads is None or not self.angles.any() else reads[0]
        eye = None if self.blink is None else 1.0 if self.blink == "none" else float(blink_track(np.array([i / self.fps]))[0])
        signals = {name: values[k] for name, values in self.signals.items()}
        rgb, _, _ = render_one(self.run, self.camera, self.plate, pose, code, eye=eye, read_pose=read, signals=signals)
        return rgb


def stream_file_chunks(path: str | Path, chunk_s: float) -> tuple[float, list[np.ndarray]]:
    """A file's audio at 16 kHz as pieces of ``chunk_s`` seconds, and its start time (tests and
    ``adnerf stream --audio FILE``: a recording played as if it were arriving)."""
    audio = read_audio(path, sample_rate=MODEL_RATE)
    step = max(1, int(round(chunk_s * MODEL_RATE)))
    return audio.start, [audio.samples[k : k + step] for k in range(0, len(audio.samples), step)]
