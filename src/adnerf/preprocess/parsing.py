"""Face parsing of a static-camera video into background / head / torso, behind one interface.

A parser maps the whole clip ``(N, H, W, 3)`` uint8 RGB to label maps ``(N, H, W)`` uint8 with
0 background, 1 head (face, hair, ears) and 2 torso (neck, shoulders, clothes) -- the labels of
:mod:`adnerf.formats.dataset`. Parsers see the whole clip, not one frame, because the camera is static and
the background is the same in every frame: the default parser exploits exactly that.

Backends (:func:`adnerf.preprocess.parsers.make_parser`): ``"classical"`` (default, no weights), a temporal background model
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

from ..formats.dataset import LABEL_HEAD, LABEL_TORSO
from ..threads import in_threads

__all__ = ["Parser", "ClassicalParser", "split_head_torso", "split_at_jaw", "split_at_landmarks", "layer_check", "torso_check", "person_hull", "grabcut_clip", "face_widths", "JAW_MARGIN", "SHOULDERS_BELOW_CHIN", "SHOULDER_HALF_WIDTH"]

Progress = Callable[[int, int], None]


class Parser(Protocol):
    """What every parsing backend provides.

    Attributes:
        name: The backend's name (as ``--parser`` takes it).
        cuts_at_jaw: Whether its head / torso boundary follows the jaw (a learned parser, a face
            mesh); otherwise ``adnerf preprocess`` re-splits along the 68 landmarks' jaw line.
        finds_clothes: Whether it labels clothes that never move as person (it segments by
            appearance); otherwise ``adnerf preprocess`` adds them below the chin
            (:mod:`adnerf.preprocess.clothes`).
    """

    name: str
    cuts_at_jaw: bool
    finds_clothes: bool

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


def split_at_jaw(person: np.ndarray, face_points: np.ndarray, margin: float = 0.0, neck_span: tuple[float, float] | None = None) -> np.ndarray:
    """Head and torso labels of a silhouette cut along the jaw line of a face.

    Args:
        person: ``(H, W)`` bool silhouette.
        face_points: ``(P, 2)`` pixel positions ``(u, v)`` of points covering the face (pixel
            centres at ``+0.5``): 68 iBUG landmarks, or a face mesh.
        margin: Pixels the cut is moved down from the points' lower edge (the jaw's underside
            and its shadow belong to the head).
        neck_span: ``(u_min, u_max)``: the columns under the lower jaw, where the neck is; the cut
            follows the points' lower edge only there, and beside them lies at the chin's row (so
            hair hanging beside the cheeks stays head). ``None``: all the points' columns.

    Raises:
        ValueError: Fewer than 3 finite points.

    Returns:
        ``(H, W)`` uint8 labels (all torso when the face lies outside the frame): in the columns
        of the points' convex hull (within ``neck_span``), head where the person is on or above
        the hull's lower edge (the jaw line) plus ``margin`` and torso below (the neck); beside
        them, head down to the chin's row plus ``margin`` where it joins the head above (hair,
        ears), torso below and wherever it does not (shoulders raised beside the neck; see
        :func:`_unjoined_beside`).
    """
    h, w = person.shape
    points = face_points[np.isfinite(face_points).all(1)]
    if len(points) < 3:
        raise ValueError(f"split_at_jaw needs at least 3 finite face points; got {len(points)}")
    hull = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(np.clip(np.floor(points), -(2**20), 2**20).astype(np.int32)), 1)
    cols = np.flatnonzero(hull.any(0))
    labels = np.zeros((h, w), np.uint8)
    if len(cols) == 0:  # the face lies outside the frame
        labels[person] = LABEL_TORSO
        return labels
    chin = float(h - 1 - np.argmax(hull[::-1].any(1)))
    cut = np.full(w, chin)  # beside the face: the chin's row
    if neck_span is not None:
        cols = cols[(cols + 0.5 >= neck_span[0]) & (cols + 0.5 <= neck_span[1])]
    cut[cols] = h - 1 - np.argmax(hull[::-1, cols] > 0, axis=0)  # under the face: its lower edge
    head = person & (np.arange(h)[:, None] <= cut[None, :] + margin)
    head &= ~_unjoined_beside(head, cols, int(np.argmax(hull.any(1))), chin)
    labels[head] = LABEL_HEAD
    labels[person & ~head] = LABEL_TORSO
    return labels


def _unjoined_beside(head: np.ndarray, neck_cols: np.ndarray, top: int, chin: float) -> np.ndarray:
    """Pixels of ``head`` beside the neck's columns, below the face's middle row and down to the
    chin, that do not join the head above that row: clothes, not hair or ears.

    Shoulders of a speaker filmed from a little above rise beside the neck to the chin's height;
    hair and ears there hang from the head above. Below the row halfway between the face's top
    ``top`` and the chin (about the nose's tip, which shoulders do not reach) and beside the
    neck columns ``neck_cols``, a connected piece of ``head`` (8-neighbours, within that band)
    stays head only when it touches the head on the band's top row.
    """
    h, w = head.shape
    mid = int((top + chin) // 2)
    band = np.zeros_like(head)
    band[mid:, :] = head[mid:, :]
    band[:, neck_cols] = False
    if not band.any():
        return band
    count, pieces = cv2.connectedComponents(band.astype(np.uint8), connectivity=8)
    joined = np.unique(pieces[mid][band[mid]])  # pieces on the band's top row, under the head above it
    return band & ~np.isin(pieces, joined[joined > 0])


# iBUG 68-point layout: jaw 0-16 (chin tip 8), lips 48-67 (lower lip's middle 57). The neck lies
# under the lower jaw, landmarks 4-12.
JAW, CHIN, LIPS, CHIN_TIP, LOWER_LIP, NECK_SPAN = slice(0, 17), slice(6, 11), slice(48, 68), 8, 57, slice(4, 13)
JAW_MARGIN = 0.04  # the cut's margin below the jaw line, as a fraction of the face width (landmarks 0 to 16)


def face_widths(landmarks: np.ndarray) -> np.ndarray:
    """``(N,)`` face widths in pixels: the distance between landmarks 0 and 16 (NaN without a face)."""
    return np.linalg.norm(landmarks[:, 16] - landmarks[:, 0], axis=-1)


def split_at_landmarks(labels: np.ndarray, landmarks: np.ndarray, margin: float = JAW_MARGIN) -> np.ndarray:
    """Re-split every frame's person (head + torso) along the jaw line of its 68 landmarks.

    Args:
        labels: ``(N, H, W)`` uint8 parsing; only ``labels > 0`` (the person) is used.
        landmarks: ``(N, 68, 2)`` iBUG landmarks (pixel centres at ``+0.5``).
        margin: Margin below the jaw as a fraction of the face width.

    Returns:
        ``(N, H, W)`` uint8 labels (:func:`split_at_jaw` per frame, the cut following the jaw
        between landmarks 4 and 12 and at the chin's row beside them).
    """
    out = np.empty_like(labels)
    widths = face_widths(landmarks)
    for i in range(len(labels)):
        lm = landmarks[i]
        width = float(widths[i])
        span = (float(lm[NECK_SPAN, 0].min()), float(lm[NECK_SPAN, 0].max()))
        out[i] = split_at_jaw(labels[i] > 0, lm, margin * width if np.isfinite(width) else 0.0, neck_span=span)
    return out


def layer_check(labels: np.ndarray, landmarks: np.ndarray) -> dict:
    """Whether the audio-driven face is in the head layer: fractions of landmarks inside it.

    Args:
        labels: ``(N, H, W)`` uint8 parsing.
        landmarks: ``(N, 68, 2)`` landmarks (pixel centres at ``+0.5``).

    Returns:
        ``lip_in_head`` (lip landmarks 48-67 in the head label, over all frames),
        ``lip_in_head_worst`` (the lowest fraction of one frame), ``chin_in_head`` (jaw landmarks
        6-10), ``chin_lip_midpoint_in_head`` (frames whose point halfway between the chin tip 8 and
        the lower lip 57 is head) and ``chin_lip_midpoint_worst_frame`` (index of a frame where
        that point is not head, else ``None``).
    """
    n, h, w = labels.shape

    def inside(points: np.ndarray) -> np.ndarray:  # (N, P, 2) -> (N, P) bool
        uv = np.floor(points).astype(np.int64)
        ok = np.isfinite(points).all(-1) & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
        u, v = np.clip(uv[..., 0], 0, w - 1), np.clip(uv[..., 1], 0, h - 1)
        return ok & (labels[np.arange(n)[:, None], v, u] == LABEL_HEAD)

    lips = inside(landmarks[:, LIPS])
    mid = inside(0.5 * (landmarks[:, CHIN_TIP : CHIN_TIP + 1] + landmarks[:, LOWER_LIP : LOWER_LIP + 1]))[:, 0]
    misses = np.flatnonzero(~mid)
    return {
        "lip_in_head": float(lips.mean()),
        "lip_in_head_worst": float(lips.mean(1).min()),
        "chin_in_head": float(inside(landmarks[:, CHIN]).mean()),
        "chin_lip_midpoint_in_head": float(mid.mean()),
        "chin_lip_midpoint_worst_frame": int(misses[0]) if len(misses) else None,
    }


SHOULDER_HALF_WIDTH = 1.0  # face widths each side of the chin that shoulders cover at least
# A frame shows shoulders when its bottom edge lies at least this many face widths below the chin
# (the shared sample clip's lies 0.29-0.42 below hers and shows her jacket across it).
SHOULDERS_BELOW_CHIN = 0.25


def torso_check(labels: np.ndarray, landmarks: np.ndarray, below_chin: float = SHOULDERS_BELOW_CHIN) -> dict:
    """Whether the clothes are in the person: how much of the frame's bottom row under the face is
    labelled person.

    In a head-and-shoulders (or closer) framing the body fills the bottom edge at least
    :data:`SHOULDER_HALF_WIDTH` face widths (landmarks 0 to 16) either side of the chin (landmark
    8): shoulders are about 2.5-3 face widths wide. Where less of that span (clipped to the
    image) is head or torso, clothes were taken for background, as the classical parser does
    with a jacket that never moves (it finds the person by motion).

    Args:
        labels: ``(N, H, W)`` uint8 parsing.
        landmarks: ``(N, 68, 2)`` landmarks (pixel centres at ``+0.5``); frames without a face
            (NaN) are left out.
        below_chin: Frames whose bottom row is closer than this many face widths below the chin
            (the face reaches the edge: no shoulders to see) are left out.

    Returns:
        ``person_at_bottom`` (the median over frames of the labelled fraction of that span),
        ``person_at_bottom_worst`` (the lowest) and ``frames`` (how many were measured; the two
        are ``None`` when none was).
    """
    n, h, w = labels.shape
    widths = face_widths(landmarks)
    fractions = []
    for i in range(n):
        lm = landmarks[i]
        if not np.isfinite(lm).all():
            continue
        width = float(widths[i])
        chin_x, chin_y = float(lm[CHIN_TIP, 0]), float(lm[CHIN_TIP, 1])
        if not width > 0 or h - chin_y < below_chin * width:
            continue
        a = int(np.clip(np.floor(chin_x - SHOULDER_HALF_WIDTH * width), 0, w))
        b = int(np.clip(np.ceil(chin_x + SHOULDER_HALF_WIDTH * width), 0, w))
        if b <= a:
            continue
        fractions.append(float((labels[i, h - 1, a:b] > 0).mean()))
    if not fractions:
        return {"person_at_bottom": None, "person_at_bottom_worst": None, "frames": 0}
    return {"person_at_bottom": float(np.median(fractions)), "person_at_bottom_worst": float(min(fractions)), "frames": len(fractions)}


@dataclass
class ClassicalParser:
    """Parsing without learned weights, for a static camera.

    1. **Motion**: the per-pixel temporal median of the clip is a first background; pixels that
       differ from it by more than ``motion_threshold`` (Lab units) in some frames moved, and the
       columns below the first moving pixel form the *person hull* (:func:`person_hull`).
    2. **GrabCut, pass 1**: colour models of person and background are fitted on a few frames with
       the hull as "probably person" and everything else as background (when the hull covers
       nearly the whole frame, as in a close crop: the moving pixels as "probably person" and the
       still ones as "probably background"), then up to ``plate_frames`` frames spread over the
       clip are cut with the models frozen.
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
        plate_frames: Frames (spread over the clip) that pass 1 cuts and the plate is the median
            of, so that a long clip costs one cut a frame, not two.
        min_outside: Fraction of the frame the hull must leave outside to seed the background
            (else pass 1 is seeded by motion alone).
    """

    motion_threshold: float = 20.0
    plate_low: float = 6.0
    plate_high: float = 25.0
    hull_margin: int = 4
    max_stat_frames: int = 80
    plate_frames: int = 300
    min_outside: float = 0.02
    name: str = "classical"
    cuts_at_jaw: bool = False  # cuts at the neck's row; the pipeline re-splits with landmarks
    finds_clothes: bool = False  # finds the person by motion; the pipeline completes the torso

    def parse(self, frames: np.ndarray, progress: Progress | None = None) -> np.ndarray:
        # GrabCut's k-means draws from OpenCV's per-thread global RNG: reset it, so a clip parses
        # the same whatever ran before in the process (seed 0 is OpenCV's fresh state, 0xffffffff).
        cv2.setRNGSeed(0)
        n, h, w, _ = frames.shape
        stat = np.linspace(0, n - 1, min(n, self.max_stat_frames)).round().astype(int)
        moving = self.moving_pixels(frames[stat])
        hull = person_hull(moving, self.hull_margin)
        # Pass 1 cuts the frames the plate is the median of: at most plate_frames of them, spread
        # over the clip (and the statistics' frames, which both passes fit their models on).
        sub = np.union1d(stat, np.linspace(0, n - 1, min(n, self.plate_frames)).round().astype(int))
        total = len(sub) + n
        first = self._first_seeds(hull, moving)
        sub_frames = frames[sub] if len(sub) < n else frames  # one copy of the sampled frames, for the cuts and the plate
        first_pass = grabcut_clip(sub_frames, lambda i: first, np.searchsorted(sub, stat), progress, 0, total)
        plate, seen = self._plate(sub_frames, first_pass)
        del sub_frames
        plate_lab = _lab(plate[None])[0]
        in_sub = np.full(n, -1)
        in_sub[sub] = np.arange(len(sub))

        def seeds(i: int) -> np.ndarray:  # made when its frame is cut, not held for the clip
            d = np.linalg.norm(_lab(frames[i][None])[0] - plate_lab, axis=-1)
            # Which probable class a pixel starts in does not change a cut with frozen models
            # (GrabCut scores both by the colour models); outside pass 1 the hull stands in.
            prior = first_pass[in_sub[i]] if in_sub[i] >= 0 else hull
            m = np.where(prior, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
            m[seen & (d > self.plate_high)] = cv2.GC_FGD
            m[seen & (d < self.plate_low) & ~hull] = cv2.GC_BGD
            m[seen & (d < self.plate_low) & hull] = cv2.GC_PR_BGD
            m[~hull] = np.where(m[~hull] == cv2.GC_FGD, cv2.GC_PR_FGD, cv2.GC_BGD)
            return m

        person = grabcut_clip(frames, seeds, stat, progress, len(sub), total)
        labels = np.empty((n, h, w), np.uint8)
        for i, label in enumerate(in_threads(lambda i: split_head_torso(_fill_holes(_largest_component(person[i])))[0], range(n))):
            labels[i] = label
        return labels

    def moving_pixels(self, frames: np.ndarray) -> np.ndarray:
        """``(H, W)`` bool: the pixels that differ from the frames' per-pixel median by more than
        ``motion_threshold`` (Lab) in more than 2% of ``frames`` ``(N, H, W, 3)`` uint8 RGB,
        cleared of specks by a 3x3 opening."""
        lab = _lab(frames)
        diff = np.linalg.norm(lab - np.median(lab, axis=0), axis=-1)
        moving = (diff > self.motion_threshold).mean(0) > 0.02
        return cv2.morphologyEx(moving.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0

    def _first_seeds(self, hull: np.ndarray, moving: np.ndarray) -> np.ndarray:
        """Pass 1's GrabCut seeds ``(H, W)`` uint8: the hull probably person and the rest
        background; when the hull leaves less than ``min_outside`` of the frame (a close crop whose
        hair sweeps the top edge across nearly every column), the pixels that moved probably
        person and the rest probably background, so the colour models decide (else no pixel
        would seed the background and the whole frame would be person)."""
        if (~hull).mean() >= self.min_outside:
            return self._hull_seeds(hull)
        return np.where(moving, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)

    def _hull_seeds(self, hull: np.ndarray) -> np.ndarray:
        m = np.full(hull.shape, cv2.GC_BGD, np.uint8)
        m[hull] = cv2.GC_PR_FGD
        edge = cv2.dilate(hull.astype(np.uint8), np.ones((2 * self.hull_margin + 1,) * 2, np.uint8)) > 0
        m[edge & ~hull] = cv2.GC_PR_BGD
        return m

    @staticmethod
    def _plate(frames: np.ndarray, person: np.ndarray, margin: int = 2) -> tuple[np.ndarray, np.ndarray]:
        from .plate import median_plate

        plate, count = median_plate(frames, person, margin=margin)
        return plate, count > 0


def grabcut_clip(frames: np.ndarray, seeds: Callable[[int], np.ndarray], stat: np.ndarray, progress: Progress | None = None, done: int = 0, total: int | None = None) -> np.ndarray:
    """GrabCut every frame of a clip with colour models fitted once and then frozen.

    The two colour models (5-component GMMs) are fitted on up to four of the ``stat`` frames side
    by side (3 iterations), then every frame is cut with them frozen (one graph cut each), so the
    frames of a clip are cut alike and fast.

    Args:
        frames: ``(N, H, W, 3)`` uint8 RGB (or any sequence of such frames with a ``shape``).
        seeds: Frame index -> its seed mask ``(H, W)`` uint8 of OpenCV's GrabCut classes
            (``GC_BGD``, ``GC_FGD``, ``GC_PR_BGD``, ``GC_PR_FGD``); called once a frame (in worker
            threads, :func:`adnerf.threads.in_threads`), so a clip's seeds need not be held.
        stat: Indices of the frames the fit may draw from.
        progress: Called with ``(done + i + 1, total)`` after frame ``i``.
        done: Offset of the progress count.
        total: The progress total (``N`` when ``None``).

    Returns:
        ``(N, H, W)`` bool, True where the cut says foreground. When the fit frames' seeds lack
        either class, no cut is made and the seeds' foreground is returned.
    """
    total = len(frames) if total is None else total
    bgd = np.zeros((1, 65), np.float64)
    fgd = np.zeros((1, 65), np.float64)
    fit = stat[np.linspace(0, len(stat) - 1, min(4, len(stat))).round().astype(int)]
    strip = np.concatenate([cv2.cvtColor(frames[i], cv2.COLOR_RGB2BGR) for i in fit], 1)
    strip_mask = np.concatenate([seeds(i) for i in fit], 1)
    if not _has_both(strip_mask):
        return np.stack([np.isin(seeds(i), (cv2.GC_FGD, cv2.GC_PR_FGD)) for i in range(len(frames))])
    cv2.grabCut(strip, strip_mask, None, bgd, fgd, 3, cv2.GC_INIT_WITH_MASK)

    def cut(i: int) -> np.ndarray:  # the models are frozen: each frame's cut is its own, in any order
        m = seeds(i).copy()
        if _has_both(m):
            cv2.grabCut(cv2.cvtColor(frames[i], cv2.COLOR_RGB2BGR), m, None, bgd.copy(), fgd.copy(), 1, cv2.GC_EVAL_FREEZE_MODEL)
        return np.isin(m, (cv2.GC_FGD, cv2.GC_PR_FGD))

    out = np.empty((len(frames),) + frames.shape[1:3], bool)
    for i, mask in enumerate(in_threads(cut, range(len(frames)))):
        out[i] = mask
        if progress is not None:
            progress(done + i + 1, total)
    return out


def _has_both(mask: np.ndarray) -> bool:
    fg = np.isin(mask, (cv2.GC_FGD, cv2.GC_PR_FGD)).any()
    bg = np.isin(mask, (cv2.GC_BGD, cv2.GC_PR_BGD)).any()
    return bool(fg and bg)
