"""What the audio code is asked to tell about the mouth: the lip landmarks' opening and width.

Stage 1 learns the audio encoders from the photometric loss alone in AD-NeRF. That gradient
reaches a frame's audio code only through the few rays of a step that land in its mouth, and an L2
loss on an uncertain mouth pulls every frame toward the mean mouth: on a real minute of footage the
rendered mouth opened a third as wide as the truth even on training frames. The landmarks that
preprocessing finds in every frame say directly how open the mouth is, so training also asks a
linear read-out of the audio code (:class:`MouthProbe`) to predict them
(:attr:`~adnerf.model.train_config.TrainConfig.lip_weight`): the code must carry the opening,
and the field learns to draw what the code carries.

The targets are scale-free and standardised on the training frames: per frame, the inner-lip
opening (the mean distance of the pairs 61-67, 62-66, 63-65 of the iBUG 68-point layout) and the
mouth width (corners 48-54), each over the distance of the outer eye corners (36-45), so that a
head nearer the camera does not look more open; then each minus its training mean, over its
training standard deviation.

The target is used only where the clip's audio predicts the opening on training frames it was
not fitted on (:func:`opening_signal`, at least
:attr:`~adnerf.model.train_config.TrainConfig.lip_min_signal`): from a short clip, whose audio
tells little about its mouth, the read-out would teach the code to name each training frame's
opening, and held-out speech would then call up openings at random.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from ..ridge import blocked_cv_corr

__all__ = ["MOUTH_TARGETS", "MouthProbe", "mouth_targets", "opening_signal"]

MOUTH_TARGETS = ("opening", "width")
"""The columns of :func:`mouth_targets`."""


def mouth_targets(landmarks: np.ndarray, train: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """The standardised mouth opening and width of every frame.

    Args:
        landmarks: ``(N, 68, 2)`` face landmarks in pixels (iBUG layout).
        train: The training frames, on which the standardisation is fitted.

    Returns:
        ``(targets (N, 2) float32, valid (N,) bool)``: the columns of :data:`MOUTH_TARGETS`;
        ``valid`` is false (and the row 0) where a landmark is not finite or the eye corners
        coincide.

    Raises:
        ValueError: ``landmarks`` is not ``(N, 68, 2)``, or fewer than two training frames have a
            valid target or a column does not vary over them (its spread under a millionth of its mean: nothing to standardise).
    """
    lm = np.asarray(landmarks, dtype=np.float64)
    if lm.ndim != 3 or lm.shape[1:] != (68, 2):
        raise ValueError(f"landmarks must be (N, 68, 2); got {lm.shape}")

    def dist(a: int, b: int) -> np.ndarray:
        return np.linalg.norm(lm[:, a] - lm[:, b], axis=-1)

    eyes = dist(36, 45)
    with np.errstate(invalid="ignore"):  # non-finite landmarks give NaN distances, masked below
        valid = np.isfinite(lm).all(axis=(1, 2)) & (eyes > 0)
    scale = np.where(valid, eyes, 1.0)
    raw = np.stack([(dist(61, 67) + dist(62, 66) + dist(63, 65)) / 3.0, dist(48, 54)], axis=1) / scale[:, None]
    raw = np.where(valid[:, None], raw, 0.0)
    fit = np.asarray(train, dtype=np.int64)
    fit = fit[valid[fit]]
    if len(fit) < 2:
        raise ValueError(f"{len(fit)} training frame(s) with finite landmarks: too few to standardise the mouth targets")
    mean, std = raw[fit].mean(axis=0), raw[fit].std(axis=0)
    varies = std > 1e-6 * np.abs(mean)  # a constant column's std is rounding, not 0
    if not varies.all():
        flat = [name for name, v in zip(MOUTH_TARGETS, varies) if not v]
        raise ValueError(f"the mouth {' and '.join(flat)} does not vary over the training frames: nothing for the audio code to predict")
    targets = np.where(valid[:, None], (raw - mean) / std, 0.0)
    return targets.astype(np.float32), valid


def opening_signal(windows: np.ndarray, targets: np.ndarray, valid: np.ndarray, train: Sequence[int]) -> float:
    """How well the audio predicts the mouth opening on the training frames: the mean over six
    contiguous blocks of the training frames (in clip order, 8 frames left out on either side) of
    the correlation of the standardised opening with a ridge map from the feature windows fitted
    on the frames outside the block (:func:`adnerf.ridge.blocked_cv_corr`; ``adnerf lip-signal``
    measures the same on the whole clip). ``nan`` when the frames are too few for the blocks.

    Args:
        windows: ``(N, 16, D)`` feature windows.
        targets: ``(N, 2)`` :func:`mouth_targets`.
        valid: ``(N,)`` bool, the frames with a target.
        train: The training frames.
    """
    frames = np.asarray(train, dtype=np.int64)
    frames = frames[valid[frames]]
    try:
        blocks = blocked_cv_corr(np.asarray(windows)[frames], targets[frames, 0])
    except ValueError:  # too few frames for the folds
        return float("nan")
    scored = [b for b in blocks if np.isfinite(b)]
    return float(np.mean(scored)) if scored else float("nan")


class MouthProbe(nn.Module):
    """A linear read-out of the audio code: ``(..., audio_dim)`` -> ``(..., 2)``, the
    :data:`MOUTH_TARGETS` (training only; rendering never reads it).

    Args:
        audio_dim: The audio code's width.
    """

    def __init__(self, audio_dim: int) -> None:
        super().__init__()
        self.linear = nn.Linear(audio_dim, len(MOUTH_TARGETS))

    def forward(self, codes: Tensor) -> Tensor:
        return self.linear(codes)

    def loss(self, codes: Tensor, targets: Tensor) -> Tensor:
        """The mean squared error of the read-out of ``codes (F, audio_dim)`` against ``targets (F, 2)``."""
        return torch.nn.functional.mse_loss(self(codes).float(), targets.float())
