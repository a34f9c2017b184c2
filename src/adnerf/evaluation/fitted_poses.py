"""The head poses a run is judged under: the tracked ones, or the ones fitted to the frames.

The protocol judges a render of a held-out frame against that frame, so the frame's head pose is
an input measured from the footage, as its audio is. The tracker's poses carry an error of about a
degree that drifts slowly (``docs/decisions.md``, *The head poses are fitted to the pixels*);
``"fitted"`` ends the tracking as training ends it for the training frames: each frame's pose is
the tracked one moved by a correction that aligns the trained head to the frame's rigid part
(:func:`~adnerf.model.pose_refine.fit_frames`: the inside of the head label, without its
outline or the mouth box, which the mouth metrics read). Training frames of the run's own dataset take the correction training learnt for them.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from ..formats.dataset import TalkingHeadDataset
from ..model.pose_refine import corrected_matrices, fit_frames
from ..model.render_clip import frame_setup, frame_signals
from ..model.run_folder import Run

__all__ = ["POSE_CHOICES", "judged_poses"]

POSE_CHOICES = ("fitted", "tracked")
"""What :func:`judged_poses` gives: poses fitted to the frames, or the tracked ones as they are."""


def judged_poses(run: Run, ds: TalkingHeadDataset, frames: Sequence[int], poses: str = "fitted", *, progress: bool = False) -> np.ndarray:
    """The head poses ``(len(frames), 4, 4)`` under which ``run`` renders frames ``frames`` of
    ``ds`` to be judged against them.

    Args:
        run: A loaded run.
        ds: The dataset (the run's own, or another of its camera).
        frames: Frame indices, in the order the codes of their audio are made (a split's).
        poses: ``"tracked"``: the dataset's poses; ``"fitted"``: each moved by a correction, the one
            training learnt for it (training frames of the run's dataset), else one fitted now. A
            synthetic scene's poses (a dataset loaded with its ``truth``) are exact: there is
            nothing to fit, and they are given as they are.
        progress: Show the fit's progress bar.

    Raises:
        ValueError: ``poses`` is not one of :data:`POSE_CHOICES`.
    """
    if poses not in POSE_CHOICES:
        raise ValueError(f"poses must be one of {POSE_CHOICES}; got {poses!r}")
    frames = np.asarray(frames, dtype=np.int64)
    tracked = np.asarray(ds.poses[frames], dtype=np.float64)
    if poses == "tracked" or not len(frames) or ds.truth is not None:
        return tracked
    learnt = run.learnt_corrections(ds.root, ds.meta.n_frames)
    delta = np.zeros((len(frames), 6), dtype=np.float64) if learnt is None else learnt[frames].copy()
    todo = np.flatnonzero(~delta.any(axis=1))  # a frame training drew has a non-zero correction
    if len(todo):
        model = run.model
        camera, plate = frame_setup(run, ds.background.astype(np.float32) / 255.0)
        dev = plate.device
        with torch.no_grad():  # the codes the render makes: over the frames in their order
            codes = model.frame_codes(torch.as_tensor(ds.features[frames], device=dev))[torch.as_tensor(todo, device=dev)]
        picked = frames[todo]
        eye = ds.eye[picked] if ds.eye is not None and model.reads_eye else None
        delta[todo] = fit_frames(
            model, camera, plate, ds, picked, tracked[todo], codes, eye=eye, signals=frame_signals(run, ds, picked), seed=run.train_config.seed, amp=run.train_config.amp, progress=progress,
        )  # fmt: skip
    return corrected_matrices(tracked, delta)
