"""Face parsing of a static-camera video into background / head / torso, behind one interface.

A parser maps the whole clip ``(N, H, W, 3)`` uint8 RGB to label maps ``(N, H, W)`` uint8 with
0 background, 1 head (face, hair, ears) and 2 torso (neck, shoulders, clothes) -- the labels of
:mod:`adnerf.data`. Parsers see the whole clip, not one frame, because the camera is static and
the background is the same in every frame: the default parser exploits exactly that.

Backends (:func:`make_parser`): ``"classical"`` (default, no weights), a temporal background model
plus GrabCut per frame, then the head/torso split at the neck (see :class:`ClassicalParser`).
Learned backends (BiSeNet with a user-supplied CelebAMask-HQ checkpoint, mediapipe's bundled
models) plug in behind the same :class:`Parser` protocol.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol

import cv2
import numpy as np
from scipy.ndimage import uniform_filter1d

from ..data import LABEL_HEAD, LABEL_TORSO

__all__ = ["Parser", "ClassicalParser", "make_parser", "split_head_torso", "person_hull", "PARSERS"]

Progress = Callable[[int, int], None]


class Parser(Protocol):
    """What every parsing backend provides."""

    name: str

    def parse(self, frames: np.ndarray, progress: Progress | None = None) -> np.ndarray:
        """Label maps ``(N, H, W)`` uint8 in {0, 1, 2} for RGB frames ``(N, H, W, 3)`` uint8."""
        ...


def _lab(frames: np.ndarray) -> np.ndarray:
    """CIE Lab of uint8 RGB frames as float32 ``(..., H, W, 3)`` (OpenCV's 8-bit scaling)."""
    flat = frames.reshape(-1, frames.shape[-2], 3)
    return cv2.cvtColor(flat, cv2.COLOR_RGB2LAB).reshape(frames.shape).astype(np.float32)


def person_hull(moving: np.ndarray, margin: int) -> np.ndarray:
    """Where the person can be: each column filled from its first moving pixel down to the bottom.

    A talking-head video shows the person from the top of the head to the bottom edge of the
    frame, so everything below a pixel that ever moved is person in some frame or other.

    Args:
        moving: ``(H, W)`` bool, pixels that changed in some frame.
        margin: Dilation in pixels added around the result.

    Returns:
        ``(H, W)`` bool.
    """
    h, w = moving.shape
    first = np.where(moving.any(0), moving.argmax(0), h)
    hull = np.arange(h)[:, None] >= first[None, :]
    if margin > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
        hull = cv2.dilate(hull.astype(np.uint8), kernel) > 0
    return hull


def _largest_component(mask: np.ndarray) -> np.ndarray:
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=4)
    if n <= 1:
        return np.zeros_like(mask, dtype=bool)
    keep = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return lab == keep


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """Fill the background pockets that do not reach the image border."""
    from scipy.ndimage import binary_fill_holes

    return binary_fill_holes(mask)


def split_head_torso(person: np.ndarray, min_rows: int = 4) -> tuple[np.ndarray, int | None]:
    """Split a person silhouette into head and torso at the neck.

    The silhouette's width per row rises over the head, falls to the neck and rises again at the
    shoulders. The neck is the narrowest stretch between the widest head row and the shoulders;
    the cut is the first row below the head's widest row whose width is within 12 % of that
    narrowest width (the chin's tip below the cut is a small sliver).

    Args:
        person: ``(H, W)`` bool silhouette of one frame.
        min_rows: Silhouettes with fewer rows than this are left unsplit.

    Returns:
        ``(labels (H, W) uint8, cut row or None when no head shape was found)``. Without a head
        shape every person pixel is torso.
    """
    h, _ = person.shape
    labels = np.zeros(person.shape, np.uint8)
    rows = np.flatnonzero(person.any(1))
    if len(rows) < min_rows:
        labels[person] = LABEL_TORSO
        return labels, None
    width = person.sum(1).astype(np.float64)
    width[rows[0] : rows[-1] + 1] = uniform_filter1d(width[rows[0] : rows[-1] + 1], 3, mode="nearest")
    top = rows[0]
    span = rows[-1] - top + 1
    # The head's widest row lies in the upper part of the silhouette; search down from it.
    upper = slice(top, top + max(2, int(0.6 * span)))
    peak = top + int(np.argmax(width[upper]))
    below = np.arange(peak + 1, rows[-1] + 1)
    if len(below) < 2:
        labels[person] = LABEL_HEAD
        return labels, None
    # Shoulders: the first row below the peak that is wider than the head again (or the bottom).
    wider = below[width[below] > 1.05 * width[peak]]
    end = int(wider[0]) if len(wider) else int(rows[-1]) + 1
    neck_rows = np.arange(peak + 1, end)
    if len(neck_rows) == 0 or width[neck_rows].min() > 0.8 * width[peak]:
        # No narrowing below the head: the frame cuts the person at the chin or the head fills it.
        labels[person] = LABEL_HEAD
        return labels, None
    narrow = width[neck_rows].min()
    cut = int(neck_rows[np.argmax(width[neck_rows] <= 1.12 * narrow)])
    yy = np.arange(h)[:, None]
    labels[person & (yy < cut)] = LABEL_HEAD
    labels[person & (yy >= cut)] = LABEL_TORSO
    return labels, cut


@dataclass
class ClassicalParser:
    """Parsing without learned weights, for a static camera.

    1. **Motion**: the per-pixel temporal median of the clip is a first background; pixels that
       differ from it by more than ``motion_threshold`` (Lab units) in some frames moved, and the
       columns below the first moving pixel form the *person hull* (:func:`person_hull`).
    2. **GrabCut, pass 1**: colour models of person and background are fitted on a few frames with
       the hull as "probably person" and everything else as background, then every frame is cut
       with the models frozen.
    3. **Plate and pass 2**: a background plate is the per-pixel median of the frames where the
       pixel was background; where the plate is known, a frame's difference from it gives sure
       person (> ``plate_high``) and background (< ``plate_low``; only "probably" inside the hull)
       seeds, and GrabCut cuts each frame again.
    4. **Head / torso**: the largest silhouette component is split at the neck
       (:func:`split_head_torso`).

    Attributes:
        motion_threshold: Lab distance from the median that counts as motion.
        plate_low: Lab distance from the plate below which a pixel is surely background.
        plate_high: Lab distance from the plate above which a pixel is surely person.
        hull_margin: Pixels of margin around the person hull.
        max_stat_frames: Frames used for the temporal statistics.
    """

    motion_threshold: float = 20.0
    plate_low: float = 6.0
    plate_high: float = 25.0
    hull_margin: int = 4
    max_stat_frames: int = 80
    name: str = "classical"

    def parse(self, frames: np.ndarray, progress: Progress | None = None) -> np.ndarray:
        n, h, w, _ = frames.shape
        stat = np.linspace(0, n - 1, min(n, self.max_stat_frames)).round().astype(int)
        lab = _lab(frames[stat])
        median = np.median(lab, axis=0)
        diff = np.linalg.norm(lab - median, axis=-1)
        moving = (diff > self.motion_threshold).mean(0) > 0.02
        moving = cv2.morphologyEx(moving.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0
        hull = person_hull(moving, self.hull_margin)
        total = 2 * n
        person = self._cut_all(frames, [self._hull_seeds(hull)] * n, stat, progress, 0, total)
        plate, seen = self._plate(frames, person)
        plate_lab = _lab(plate[None])[0]
        seeds = []
        for i in range(n):
            d = np.linalg.norm(_lab(frames[i][None])[0] - plate_lab, axis=-1)
            m = np.where(person[i], cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
            m[seen & (d > self.plate_high)] = cv2.GC_FGD
            m[seen & (d < self.plate_low) & ~hull] = cv2.GC_BGD
            m[seen & (d < self.plate_low) & hull] = cv2.GC_PR_BGD
            m[~hull] = np.where(m[~hull] == cv2.GC_FGD, cv2.GC_PR_FGD, cv2.GC_BGD)
            seeds.append(m)
        person = self._cut_all(frames, seeds, stat, progress, n, total)
        labels = np.empty((n, h, w), np.uint8)
        for i in range(n):
            sil = _fill_holes(_largest_component(person[i]))
            labels[i], _ = split_head_torso(sil)
        return labels

    def _hull_seeds(self, hull: np.ndarray) -> np.ndarray:
        m = np.full(hull.shape, cv2.GC_BGD, np.uint8)
        m[hull] = cv2.GC_PR_FGD
        edge = cv2.dilate(hull.astype(np.uint8), np.ones((2 * self.hull_margin + 1,) * 2, np.uint8)) > 0
        m[edge & ~hull] = cv2.GC_PR_BGD
        return m

    @staticmethod
    def _cut_all(frames: np.ndarray, seeds: list[np.ndarray], stat: np.ndarray, progress: Progress | None, done: int, total: int) -> np.ndarray:
        """GrabCut every frame with colour models fitted on a few frames and then frozen."""
        bgd = np.zeros((1, 65), np.float64)
        fgd = np.zeros((1, 65), np.float64)
        fit = stat[np.linspace(0, len(stat) - 1, min(4, len(stat))).round().astype(int)]
        strip = np.concatenate([cv2.cvtColor(frames[i], cv2.COLOR_RGB2BGR) for i in fit], 1)
        strip_mask = np.concatenate([seeds[i] for i in fit], 1).copy()
        if not _has_both(strip_mask):
            return np.isin(np.stack(seeds), (cv2.GC_FGD, cv2.GC_PR_FGD))
        cv2.grabCut(strip, strip_mask, None, bgd, fgd, 3, cv2.GC_INIT_WITH_MASK)
        out = np.empty((len(frames),) + frames.shape[1:3], bool)
        for i, frame in enumerate(frames):
            m = seeds[i].copy()
            if _has_both(m):
                cv2.grabCut(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR), m, None, bgd, fgd, 1, cv2.GC_EVAL_FREEZE_MODEL)
            out[i] = np.isin(m, (cv2.GC_FGD, cv2.GC_PR_FGD))
            if progress is not None:
                progress(done + i + 1, total)
        return out

    @staticmethod
    def _plate(frames: np.ndarray, person: np.ndarray, margin: int = 2) -> tuple[np.ndarray, np.ndarray]:
        from .plate import median_plate

        plate, count = median_plate(frames, person, margin=margin)
        return plate, count > 0


def _has_both(mask: np.ndarray) -> bool:
    fg = np.isin(mask, (cv2.GC_FGD, cv2.GC_PR_FGD)).any()
    bg = np.isin(mask, (cv2.GC_BGD, cv2.GC_PR_BGD)).any()
    return bool(fg and bg)


PARSERS = ("classical", "mediapipe", "bisenet:CHECKPOINT")


def make_parser(spec: str) -> Parser:
    """A parser by name: ``"classical"`` (no weights), ``"mediapipe"`` (mediapipe 0.10.21's bundled
    models, an opt-in install, see :mod:`adnerf.preprocess.mediapipe_parser`) or ``"bisenet:PATH"``
    (a user's 19-class face-parsing checkpoint, see :mod:`adnerf.preprocess.bisenet`; on CUDA when
    available).

    Raises:
        ValueError: Unknown name, a checkpoint that cannot be loaded, or mediapipe missing.
    """
    if spec == "classical":
        return ClassicalParser()
    if spec == "mediapipe":
        from .mediapipe_parser import MediapipeParser, import_mediapipe

        try:
            import_mediapipe()
        except ImportError as exc:
            raise ValueError(str(exc)) from exc
        return MediapipeParser()
    if spec.startswith("bisenet:"):
        import torch

        from .bisenet import BiSeNetParser

        return BiSeNetParser(spec.split(":", 1)[1], device="cuda" if torch.cuda.is_available() else "cpu")
    raise ValueError(f"unknown parser {spec!r}; available: {', '.join(PARSERS)}")
