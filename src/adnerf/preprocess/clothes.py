"""Clothes that never move: completing the torso layer below the face.

A parser that finds the person by motion (:class:`~adnerf.preprocess.parsing.ClassicalParser`)
takes a jacket that never moves for the wall behind it: on the shared sample clip only 73% of the
frame's bottom edge under her face was labelled person. The torso layer then misses the clothes and
the background plate keeps them, so the torso field never learns them and the person cannot be put
on another background.

:func:`complete_torso` adds them back with the 68 landmarks, in the band of rows from
:data:`BAND_ABOVE_CHIN` face widths above the chin down to the bottom edge:

1. **Samples.** The clothes: where a frame shows shoulders (its bottom edge lies at least
   :data:`~adnerf.preprocess.parsing.SHOULDERS_BELOW_CHIN` face widths below the chin), a strip
   along the bottom edge :data:`STRIP_HALF_WIDTH` face widths either side of the chin; in a
   head-and-shoulders framing the body fills it (shoulders are 2.5-3 face widths wide). The wall:
   the pixels beside the head above the chin's row that the parse calls background.
2. **Where GrabCut starts.** Four k-means colour centres of each sample set (Lab) label the rest:
   a pixel below the chin nearer the clothes' colours starts as probably person, one nearer the
   wall's as probably background; a wall sample that looks like the clothes (a shoulder risen above
   the chin's row) is only probably background. The parsed person and the strip are sure person.
3. **The cut.** GrabCut (:func:`.parsing.grabcut_clip`: colour models fitted on a few frames, then
   frozen) cuts every frame.

Only pixels below the chin's row that the cut calls person and that join the parsed person or the
strip are added, as torso (beside the face below the chin the jaw cut makes everything torso;
under the face the neck is torso already). The head layer and every pixel above the chin's row
are never changed, so clothes risen above it stay background.
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

from ..formats.dataset import LABEL_TORSO
from .parsing import CHIN_TIP, SHOULDERS_BELOW_CHIN, _fill_holes, face_widths, grabcut_clip

__all__ = ["complete_torso", "clothes_seeds", "STRIP", "STRIP_HALF_WIDTH", "BAND_ABOVE_CHIN"]

STRIP_HALF_WIDTH = 0.9  # face widths either side of the chin seeded as person along the bottom edge
BAND_ABOVE_CHIN = 0.5  # face widths above the chin where the band (and its background seeds) begins
FIT_FRAMES = 8  # frames the colour samples and GrabCut's models are taken from
STRIP = 255  # the bottom strip's value in clothes_seeds' output (sure person, and the clothes' colour sample)


def clothes_seeds(labels: np.ndarray, chin: np.ndarray, width: float, top: int) -> np.ndarray:
    """GrabCut seeds of one frame's band (:mod:`module docstring <adnerf.preprocess.clothes>`).

    Args:
        labels: ``(H, W)`` uint8 parsing of the frame.
        chin: ``(2,)`` pixel position ``(u, v)`` of the chin tip (landmark 8; centres at ``+0.5``).
        width: The face width in pixels (landmarks 0 to 16).
        top: First row of the band.

    Returns:
        ``(H - top, W)`` uint8: OpenCV's GrabCut classes ``GC_FGD`` on the person, ``GC_BGD`` on
        the background beside the head above the chin's row and ``GC_PR_BGD`` elsewhere, and
        :data:`STRIP` on the strip along the bottom edge (when the frame shows shoulders).
    """
    h, w = labels.shape
    rows = np.arange(top, h)[:, None] + 0.5
    cols = np.arange(w)[None, :] + 0.5
    person = labels[top:] > 0
    seeds = np.full(person.shape, cv2.GC_PR_BGD, np.uint8)
    seeds[(rows < chin[1]) & ~person] = cv2.GC_BGD
    seeds[person] = cv2.GC_FGD
    if h - chin[1] >= SHOULDERS_BELOW_CHIN * width:
        strip = max(2, round(0.04 * width))
        seeds[(rows >= h - strip) & (np.abs(cols - chin[0]) <= STRIP_HALF_WIDTH * width)] = STRIP
    return seeds


def _centres(lab: np.ndarray, k: int = 4) -> np.ndarray:
    """``(k, 3)`` k-means centres of ``(P, 3)`` float32 colours (fewer when there are fewer)."""
    k = min(k, len(lab))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.5)
    _, _, centres = cv2.kmeans(np.ascontiguousarray(lab, np.float32), k, None, crit, 2, cv2.KMEANS_PP_CENTERS)
    return centres


def _nearer_clothes(lab: np.ndarray, clothes: np.ndarray, wall: np.ndarray) -> np.ndarray:
    """Whether each colour ``(..., 3)`` lies nearer the clothes' centres than the wall's."""

    channels = [np.ascontiguousarray(lab[..., j]) for j in range(3)]

    def nearest(centres: np.ndarray) -> np.ndarray:  # the Euclidean distance, a centre at a time (no (..., k, 3) temporary)
        best = None
        for centre in centres.astype(lab.dtype):
            d = (channels[0] - centre[0]) ** 2
            d += (channels[1] - centre[1]) ** 2
            d += (channels[2] - centre[2]) ** 2
            best = d if best is None else np.minimum(best, d, out=best)
        return np.sqrt(best)

    return nearest(clothes) < nearest(wall)


class _Band:
    """The rows from ``top`` down of frames ``valid`` of a clip, a frame at a time (what
    :func:`~.parsing.grabcut_clip` reads), without copying the clip's bands."""

    def __init__(self, frames: np.ndarray, valid: np.ndarray, top: int) -> None:
        self.frames, self.valid, self.top = frames, valid, top
        self.shape = (len(valid), frames.shape[1] - top, *frames.shape[2:])

    def __len__(self) -> int:
        return len(self.valid)

    def __getitem__(self, k: int) -> np.ndarray:
        return np.ascontiguousarray(self.frames[self.valid[k], self.top :])


def complete_torso(frames: np.ndarray, labels: np.ndarray, landmarks: np.ndarray, progress: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, dict]:
    """Add the clothes a motion-based parse took for background to the torso layer.

    Args:
        frames: ``(N, H, W, 3)`` uint8 RGB.
        labels: ``(N, H, W)`` uint8 parsing (0 background, 1 head, 2 torso), already split at the
            jaw or the neck.
        landmarks: ``(N, 68, 2)`` iBUG landmarks (pixel centres at ``+0.5``); frames with NaN are
            left as they are.
        progress: Called with ``(frames done, frames)``.

    Returns:
        ``(labels (N, H, W) uint8, report)``: the completed parsing (a new array; head pixels and
        every pixel above the chin's row unchanged) and ``frames`` (frames cut), ``frames_changed``
        and ``added_fraction`` (the mean fraction of a frame's pixels added as torso). With no
        frame that shows shoulders, or no background beside the head, nothing is cut and the
        labels come back unchanged.
    """
    n, h, w = labels.shape
    if frames.shape[:3] != labels.shape or landmarks.shape[:2] != (n, 68):
        raise ValueError(f"complete_torso: frames {frames.shape}, labels {labels.shape} and landmarks {landmarks.shape} do not match")
    cv2.setRNGSeed(0)  # the k-means of the colour centres and of GrabCut: the same clip completes the same way
    out = labels.copy()
    width = face_widths(landmarks)
    valid = np.flatnonzero(np.isfinite(landmarks).all((1, 2)) & (width > 0))
    chin = landmarks[:, CHIN_TIP]
    shoulders = valid[h - chin[valid, 1] >= SHOULDERS_BELOW_CHIN * width[valid]]
    report = {"frames": 0, "frames_changed": 0, "added_fraction": 0.0}
    top = int(np.clip(np.floor(np.min(chin[valid, 1] - BAND_ABOVE_CHIN * width[valid], initial=h)), 0, h - 1))

    def raw_seeds(k: int) -> np.ndarray:  # frame valid[k]'s seeds, made when needed: a clip's would be a byte a pixel
        i = valid[k]
        return clothes_seeds(labels[i], chin[i], float(width[i]), top)

    fit = np.searchsorted(valid, shoulders[np.linspace(0, len(shoulders) - 1, min(FIT_FRAMES, len(shoulders))).round().astype(int)]) if len(shoulders) else []
    fit_seeds = {k: raw_seeds(k) for k in fit}
    if len(fit) == 0 or not all((fit_seeds[k] == cv2.GC_BGD).any() for k in fit):
        if progress is not None:
            progress(1, 1)
        return out, report
    # The colours of the clothes (the bottom strip) and of the wall beside the head decide where
    # GrabCut starts: a pixel below the chin nearer the clothes starts as probably person, and a
    # background seed that looks like the clothes (a shoulder risen above the chin) is not sure.
    def lab(i: int) -> np.ndarray:  # one frame's band in Lab, float32 (a frame at a time: the clip's would be 12 bytes a pixel)
        return cv2.cvtColor(np.ascontiguousarray(frames[i, top:]), cv2.COLOR_RGB2LAB).astype(np.float32)

    fit_lab = {k: lab(valid[k]) for k in fit}
    clothes = _centres(np.concatenate([fit_lab[k][fit_seeds[k] == STRIP] for k in fit]))
    wall = _centres(np.concatenate([fit_lab[k][fit_seeds[k] == cv2.GC_BGD] for k in fit]))
    rows = np.arange(h)[:, None] + 0.5

    def seeds(k: int) -> np.ndarray:  # GrabCut's seeds of frame valid[k] (called from worker threads)
        i, m = valid[k], raw_seeds(k)
        like = _nearer_clothes(fit_lab[k] if k in fit_lab else lab(i), clothes, wall)
        m[(m == cv2.GC_BGD) & like] = cv2.GC_PR_BGD
        m[(m == cv2.GC_PR_BGD) & like & (rows[top:] > chin[i, 1])] = cv2.GC_PR_FGD
        m[m == STRIP] = cv2.GC_FGD
        return m

    person = grabcut_clip(_Band(frames, valid, top), seeds, fit, progress)
    added = []
    for k, i in enumerate(valid):
        anchor = labels[i] > 0  # what the added pixels must join: the parsed person or the strip
        anchor[top:] |= raw_seeds(k) == STRIP
        cut = np.zeros((h, w), bool)
        cut[top:] = person[k]
        below = rows > chin[i, 1]
        grown = (cut & below) | anchor
        _, comp = cv2.connectedComponents(grown.astype(np.uint8), connectivity=4)
        joined = np.isin(comp, np.unique(comp[anchor])) & (comp > 0)
        new = _fill_holes(joined) & (labels[i] == 0) & below
        out[i][new] = LABEL_TORSO
        added.append(float(new.mean()))
    report.update(frames=len(valid), frames_changed=int(sum(a > 0 for a in added)), added_fraction=float(np.mean(added)))
    return out, report
