"""Metrics from face landmarks found in rendered and true frames: LMD and a lip-sync measure.

Both need no downloaded weights: the landmarks come from the same dlib detector preprocessing uses
(:mod:`adnerf.preprocess.landmarks`), run on the render and on the true frame.

- **LMD** (landmark distance, as the talking-head papers report it): the mean Euclidean distance
  between corresponding landmarks of the render and of the true frame, over the mouth landmarks
  (48-67) and over all 68; in pixels and as a fraction of the true face's width (landmarks 0 to
  16), so clips of other sizes compare.
- **Mouth shape and the still mouth**: the mouth LMD mixes where the mouth is (the head's pose)
  with what shape it has (the speech). ``lmd_mouth_shape_px`` is the mouth LMD with each frame's
  rendered mouth moved onto the true mouth's centre; ``lmd_mouth_still_px`` is the same figure for
  the best mouth that never moves: the mean true mouth shape of the evaluated frames, held in
  every frame. A render whose shape LMD is below it moves its mouth with the speech better than
  any still mouth could. One above it may still follow the speech, since this reference knows
  the evaluated frames' mean shape, which a render has to find from their audio.
- **Mouth opening**: the mean distance between the inner lips (61-67, 62-66, 63-65). Its
  correlation between render and truth over the held-out frames measures whether the mouth
  follows the audio; the **audio-visual offset** is the shift of the render (in frames) that
  maximises that correlation: 0 when the render is in sync, ``+k`` when it moves ``k`` frames
  late.
- **Mouth-opening amplitude**: how wide the rendered mouth opens against the truth, as the slope of
  the rendered opening regressed on the true one (least squares, with an intercept) and as the
  ratio of their standard deviations. 1 for both when the render opens as wide as the truth; a
  mouth that follows the speech at half the amplitude scores 0.5 with any correlation. The slope
  is the correlation times the ratio, so a render that opens wide out of step scores a low slope.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..ridge import pearson  # re-exported: landmark metrics' correlations are Pearson's

__all__ = ["LandmarkMetrics", "amplitude", "av_offset", "landmark_metrics", "lmd", "lmd_shape", "mouth_opening", "pearson", "still_lmd"]

MOUTH = slice(48, 68)
INNER_PAIRS = ((61, 67), (62, 66), (63, 65))  # upper and lower inner lip, left to right


def mouth_opening(landmarks: np.ndarray) -> np.ndarray:
    """Inner-lip opening ``(N,)`` in pixels of landmarks ``(N, 68, 2)``."""
    upper = landmarks[:, [a for a, _ in INNER_PAIRS]]
    lower = landmarks[:, [b for _, b in INNER_PAIRS]]
    return np.linalg.norm(upper - lower, axis=-1).mean(axis=1)


def lmd(pred: np.ndarray, true: np.ndarray, points: slice = slice(None)) -> float:
    """Mean distance in pixels between landmarks ``(N, 68, 2)`` of two clips over ``points``."""
    return float(np.linalg.norm(pred[:, points] - true[:, points], axis=-1).mean())


def lmd_shape(pred: np.ndarray, true: np.ndarray, points: slice = MOUTH) -> float:
    """:func:`lmd` over ``points`` with each frame's predicted points moved onto the centroid of
    the true ones: the error of the shape alone, in pixels."""
    p, t = pred[:, points], true[:, points]
    return float(np.linalg.norm((p - p.mean(axis=1, keepdims=True)) - (t - t.mean(axis=1, keepdims=True)), axis=-1).mean())


def still_lmd(true: np.ndarray, points: slice = MOUTH) -> float:
    """:func:`lmd_shape` of a shape that never moves: the mean centred shape of ``true`` over its
    frames, against every frame (the best a still mouth could score on these frames)."""
    t = true[:, points] - true[:, points].mean(axis=1, keepdims=True)
    return float(np.linalg.norm(t - t.mean(axis=0), axis=-1).mean())


def amplitude(rendered: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    """``(slope, std ratio)`` of a rendered series against the true one: the least-squares slope
    of ``rendered`` regressed on ``true`` (with an intercept) and ``std(rendered) / std(true)``;
    NaN for both when ``true`` is constant."""
    r, t = np.asarray(rendered, float), np.asarray(true, float)
    if r.shape != t.shape or r.ndim != 1:
        raise ValueError(f"amplitude needs two series of one length; got {r.shape} and {t.shape}")
    spread = t.std()
    if spread == 0:
        return float("nan"), float("nan")
    slope = float(np.mean((r - r.mean()) * (t - t.mean())) / spread**2)
    return slope, float(r.std() / spread)


def av_offset(rendered: np.ndarray, true: np.ndarray, max_shift: int = 5) -> tuple[int, float]:
    """The shift ``k`` in ``[-max_shift, max_shift]`` maximising the correlation of
    ``rendered[t + k]`` with ``true[t]`` (``k > 0``: the render is late), and that correlation.

    Shifts that leave fewer than 8 overlapping frames are not tried.
    """
    n = len(true)
    best = (0, pearson(rendered, true))
    for k in range(-max_shift, max_shift + 1):
        if n - abs(k) < 8 or k == 0:
            continue
        r, t = (rendered[k:], true[: n - k]) if k > 0 else (rendered[: n + k], true[-k:])
        c = pearson(r, t)
        if np.isfinite(c) and (not np.isfinite(best[1]) or c > best[1]):
            best = (k, c)
    return best


@dataclass
class LandmarkMetrics:
    """Landmark metrics of a rendered clip against the true frames.

    Attributes:
        lmd_mouth_px: LMD over the mouth landmarks (48-67), pixels.
        lmd_all_px: LMD over all 68 landmarks, pixels.
        lmd_mouth: ``lmd_mouth_px`` over the true face width.
        lmd_all: ``lmd_all_px`` over the true face width.
        lmd_mouth_shape_px: LMD over the mouth landmarks with each rendered mouth moved onto the
            true mouth's centre (the shape's error alone), pixels.
        lmd_mouth_still_px: The same for the mean true mouth shape of the frames held still in
            every frame: the best a mouth that never moves could score.
        mouth_open_corr: Correlation of the rendered and true mouth openings.
        av_offset_frames: Shift of the render that maximises that correlation (0: in sync).
        av_offset_corr: The correlation at that shift.
        mouth_open_slope: Slope of the rendered mouth opening regressed on the true one
            (:func:`amplitude`; 1: as wide as the truth).
        mouth_open_std_ratio: Standard deviation of the rendered opening over the true one's.
        face_width_px: Median true face width.
    """

    lmd_mouth_px: float
    lmd_all_px: float
    lmd_mouth: float
    lmd_all: float
    lmd_mouth_shape_px: float
    lmd_mouth_still_px: float
    mouth_open_corr: float
    av_offset_frames: int
    av_offset_corr: float
    mouth_open_slope: float
    mouth_open_std_ratio: float
    face_width_px: float

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def landmark_metrics(pred: np.ndarray, true: np.ndarray, max_shift: int = 5) -> LandmarkMetrics:
    """Compare the landmarks ``(N, 68, 2)`` found in rendered frames with those of the true ones."""
    if pred.shape != true.shape or pred.ndim != 3 or pred.shape[1:] != (68, 2):
        raise ValueError(f"landmarks must both be (N, 68, 2); got {pred.shape} and {true.shape}")
    width = float(np.median(np.linalg.norm(true[:, 16] - true[:, 0], axis=-1)))
    mouth_px, all_px = lmd(pred, true, MOUTH), lmd(pred, true)
    opening_pred, opening_true = mouth_opening(pred), mouth_opening(true)
    shift, corr = av_offset(opening_pred, opening_true, max_shift)
    slope, ratio = amplitude(opening_pred, opening_true)
    return LandmarkMetrics(mouth_px, all_px, mouth_px / width, all_px / width, lmd_shape(pred, true), still_lmd(true), pearson(opening_pred, opening_true), shift, corr, slope, ratio, width)
