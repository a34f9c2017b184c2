"""Point tracks on the near-rigid part of the head, from dense optical flow.

The paper tracks the head with dense flow and bundle adjustment. Here: dense flow between
consecutive frames (OpenCV DIS, fast, or DeepFlow from ``cv2.optflow``, accurate) carries corner
points (Shi-Tomasi) chosen inside the *rigid region* of the head -- the head label, eroded away
from its silhouette, above the mouth (the top ``rigid_fraction`` of the head box: forehead, hair
line, eyes, nose bridge, ears; not the mouth or jaw). A point is followed while the forward and
backward flows agree (round trip below ``max_fb_error`` pixels) and it stays in the region; new
points are seeded whenever too few remain. Every track becomes one 3D point of the bundle
adjustment.

Pixel coordinates follow the project convention: a pixel's centre is at ``(u + 0.5, v + 0.5)``,
so the corner found at integer array position ``(x, y)`` is at ``(x + 0.5, y + 0.5)``.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Callable, Iterator

import cv2
import numpy as np

from ..formats.dataset import LABEL_HEAD
from ..threads import in_threads

__all__ = ["FLOWS", "TrackConfig", "Tracks", "dense_flow", "rigid_region", "rigid_regions", "track_points", "extend_tracks"]

FLOWS = ("dis", "deepflow")


def dense_flow(method: str) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """A function ``flow(gray0, gray1) -> (H, W, 2) float32`` with ``gray1[p + flow[p]] ~ gray0[p]``.

    Args:
        method: ``"dis"`` (OpenCV DIS, medium preset) or ``"deepflow"`` (``cv2.optflow``).
    """
    if method == "dis":
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        return lambda a, b: dis.calc(a, b, None)
    if method == "deepflow":
        if not hasattr(cv2, "optflow"):
            raise ValueError("--flow deepflow needs cv2.optflow (pip install opencv-contrib-python-headless)")
        deep = cv2.optflow.createOptFlow_DeepFlow()
        return lambda a, b: deep.calc(a, b, None)
    raise ValueError(f"unknown flow method {method!r}; choose one of {', '.join(FLOWS)}")


def rigid_region(labels: np.ndarray, rigid_fraction: float = 0.62, edge_margin: float = 0.1, limit: float | None = None) -> np.ndarray:
    """The near-rigid part of the head in one frame: head label, eroded, above the mouth.

    Args:
        labels: ``(H, W)`` uint8 parsing.
        rigid_fraction: Fraction of the head's height, from its top, that is kept.
        edge_margin: Band along the head's silhouette that is removed, as a fraction of the head's
            width (flow near an occluding edge mixes head and background motion; measured on the
            synthetic scene, points within 10 % of the width of the edge drift 3x more).
        limit: A pixel row (``v``, centre convention) the region never reaches below, e.g. the
            nose base from face landmarks: long hair hanging past the chin lengthens the head
            label, and its ``rigid_fraction`` would then reach the mouth. ``None``: no limit.

    Returns:
        ``(H, W)`` bool.
    """
    head = labels == LABEL_HEAD
    rows = np.flatnonzero(head.any(1))
    if len(rows) == 0:
        return head
    cols = np.flatnonzero(head.any(0))
    erode = int(round(edge_margin * (cols[-1] - cols[0] + 1)))
    cut = rows[0] + rigid_fraction * (rows[-1] - rows[0] + 1)
    if limit is not None and np.isfinite(limit):
        cut = min(cut, limit - 0.5)  # rows whose centre lies above the limit
    stop = max(0, int(np.ceil(cut)))
    if erode > 0 and stop > rows[0]:
        # Erode only the box the kept rows can reach: a pixel's erosion reads the pixels within
        # `erode` of it, so the box grows by that much (clipped to the frame, where OpenCV's
        # erosion treats the outside as set, as it does for the whole frame).
        h, w = head.shape
        y0, y1 = max(0, rows[0] - erode), min(h, stop + erode)
        x0, x1 = max(0, cols[0] - erode), min(w, cols[-1] + 1 + erode)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode + 1, 2 * erode + 1))
        head[y0:stop, x0:x1] = (cv2.erode(head[y0:y1, x0:x1].astype(np.uint8), kernel) > 0)[: stop - y0]
    head[stop:] = False
    return head


@dataclass
class TrackConfig:
    """Settings of :func:`track_points`.

    Attributes:
        flow: ``"dis"`` or ``"deepflow"``.
        n_points: Points kept alive at a time.
        reseed_below: Seed new points when fewer than this fraction of ``n_points`` are alive.
        max_fb_error: Forward-backward round-trip error (pixels) that ends a track.
        max_length: Frames after which a track ends (limits the drift a chain of flows gathers).
        min_length: Tracks shorter than this are dropped (they constrain nothing).
        rigid_fraction, edge_margin: See :func:`rigid_region`.
        min_distance: Minimum spacing of seeds, as a fraction of the head's width.
        anchor_window: Window (pixels) of the Lucas-Kanade refinement that re-anchors every
            tracked point to its appearance in the seed frame (removes the drift of chained flow);
            0 disables it.
        max_anchor_shift: A refinement that moves a point further than this (pixels) from the
            flow's position ends the track instead.
        flow_margin: The dense flow of a frame pair is computed on the box of the two frames'
            rigid regions (where every point it carries lies), grown on each side by this
            fraction of the box's larger side and 16 pixels; ``None``: on the whole frames.
    """

    flow: str = "dis"
    n_points: int = 120
    reseed_below: float = 0.7
    max_fb_error: float = 0.5
    max_length: int = 60
    min_length: int = 5
    rigid_fraction: float = 0.62
    edge_margin: float = 0.1
    min_distance: float = 0.05
    anchor_window: int = 15
    max_anchor_shift: float = 2.0
    flow_margin: float | None = 0.15


@dataclass
class Tracks:
    """Point observations over a clip.

    Attributes:
        uv: ``(N, P, 2)`` float64 pixel positions (centre convention), NaN where track ``p`` is not
            observed in frame ``n``.
        seed_frame: ``(P,)`` frame where each track starts.
    """

    uv: np.ndarray
    seed_frame: np.ndarray

    @property
    def observed(self) -> np.ndarray:
        """``(N, P)`` bool."""
        return np.isfinite(self.uv[..., 0])

    @property
    def lengths(self) -> np.ndarray:
        """``(P,)`` frames per track."""
        return self.observed.sum(0)


def rigid_regions(labels: np.ndarray, config: TrackConfig = TrackConfig(), limits: np.ndarray | None = None) -> np.ndarray:
    """:func:`rigid_region` of every frame, ``(N, H, W)`` bool, made once for the passes that
    read them (:func:`track_points` and each :func:`extend_tracks`).

    Args:
        labels: ``(N, H, W)`` uint8 parsing.
        config: The region's settings (``rigid_fraction``, ``edge_margin``).
        limits: ``(N,)`` rows each frame's region stays above, or ``None``.
    """
    out = np.empty(labels.shape, dtype=bool)
    for i, region in enumerate(in_threads(lambda i: rigid_region(labels[i], config.rigid_fraction, config.edge_margin, _limit(limits, i)), range(len(labels)))):
        out[i] = region
    return out


def _flow_box(region: np.ndarray, margin: float | None) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)``: the box of ``region`` grown by ``margin`` (see
    :attr:`TrackConfig.flow_margin`), within the frame; the whole frame for ``None`` or an
    empty region."""
    h, w = region.shape
    rows, cols = np.flatnonzero(region.any(1)), np.flatnonzero(region.any(0))
    if margin is None or len(rows) == 0:
        return 0, 0, w, h
    grow = 16 + int(np.ceil(margin * max(rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1)))
    return max(0, cols[0] - grow), max(0, rows[0] - grow), min(w, cols[-1] + 1 + grow), min(h, rows[-1] + 1 + grow)


def _pair_flows(gray: list[np.ndarray], regions: np.ndarray, config: TrackConfig) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Forward and backward dense flow of each consecutive frame pair on the box of its rigid
    regions (:func:`_flow_box`), with the box's corner ``(x0, y0)``, computed on threads in order."""
    local = threading.local()

    def pair(i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # a flow object per thread: they keep state
        if not hasattr(local, "flow"):
            local.flow = dense_flow(config.flow)
        x0, y0, x1, y1 = _flow_box(regions[i] | regions[i + 1], config.flow_margin)
        a, b = np.ascontiguousarray(gray[i][y0:y1, x0:x1]), np.ascontiguousarray(gray[i + 1][y0:y1, x0:x1])
        return local.flow(a, b), local.flow(b, a), np.array([x0, y0], np.float64)

    return in_threads(pair, range(len(gray) - 1))


def _sample(flow: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear sample of a flow field at centre-convention points ``(n, 2)``."""
    map_xy = (pts - 0.5).astype(np.float32).reshape(-1, 1, 2)
    out = cv2.remap(flow, map_xy[..., 0], map_xy[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, 2).astype(np.float64)


def _inside(region: np.ndarray, pts: np.ndarray) -> np.ndarray:
    h, w = region.shape
    x = np.floor(pts[:, 0]).astype(int)
    y = np.floor(pts[:, 1]).astype(int)
    ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    ok[ok] = region[y[ok], x[ok]]
    return ok


def _limit(limits: np.ndarray | None, i: int) -> float | None:
    return None if limits is None else float(limits[i])


def track_points(
    frames: np.ndarray,
    labels: np.ndarray,
    config: TrackConfig = TrackConfig(),
    progress: Callable[[int, int], None] | None = None,
    limits: np.ndarray | None = None,
    regions: np.ndarray | None = None,
) -> Tracks:
    """Track points on the head's rigid region through a clip.

    Args:
        frames: ``(N, H, W, 3)`` uint8 RGB.
        labels: ``(N, H, W)`` uint8 parsing.
        config: Tracking settings.
        progress: Called as ``progress(done, total)`` per frame pair.
        limits: ``(N,)`` rows the rigid region stays above per frame (see :func:`rigid_region`).
        regions: ``(N, H, W)`` bool rigid regions already made by :func:`rigid_regions` with
            these labels, settings and limits; ``None``: made here.

    Returns:
        :class:`Tracks` with tracks shorter than ``config.min_length`` removed.
    """
    dense_flow(config.flow)  # an unknown method fails here, before any work
    n = len(frames)
    gray = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]
    if regions is None:
        regions = rigid_regions(labels, config, limits)
    paths: list[list[tuple[int, float, float]]] = []
    alive: list[int] = []

    def seed(i: int) -> None:
        region = regions[i]
        cols = np.flatnonzero(region.any(0))
        if len(cols) == 0:
            return
        want = config.n_points - len(alive)
        mask = region.astype(np.uint8) * 255
        spacing = max(2.0, config.min_distance * (cols[-1] - cols[0] + 1))
        for p in alive:  # keep new seeds away from live tracks
            _, x, y = paths[p][-1]
            cv2.circle(mask, (int(x), int(y)), int(spacing), 0, -1)
        corners = cv2.goodFeaturesToTrack(gray[i], maxCorners=want, qualityLevel=0.01, minDistance=spacing, mask=mask)
        if corners is None:
            return
        for x, y in corners.reshape(-1, 2) + 0.5:
            alive.append(len(paths))
            paths.append([(i, float(x), float(y))])

    flows = _pair_flows(gray, regions, config)  # computed ahead, side by side, while the tracks follow
    seed(0)
    for i in range(n - 1):
        fwd, bwd, o = next(flows)
        if alive:
            pts = np.array([paths[p][-1][1:] for p in alive])
            nxt = pts + _sample(fwd, pts - o)
            back = nxt + _sample(bwd, nxt - o)
            ok = np.linalg.norm(back - pts, axis=1) < config.max_fb_error
            ok &= _inside(regions[i + 1], nxt)
            ok &= np.array([len(paths[p]) < config.max_length for p in alive])
            if config.anchor_window > 0:
                nxt, ok = _anchor(gray, paths, alive, nxt, ok, i + 1, config)
            keep = []
            for p, good, q in zip(alive, ok, nxt):
                if good:
                    paths[p].append((i + 1, float(q[0]), float(q[1])))
                    keep.append(p)
            alive[:] = keep
        if len(alive) < config.reseed_below * config.n_points:
            seed(i + 1)
        if progress is not None:
            progress(i + 1, n - 1)
    paths = [p for p in paths if len(p) >= config.min_length]
    uv = np.full((n, len(paths), 2), np.nan)
    for j, path in enumerate(paths):
        for i, x, y in path:
            uv[i, j] = (x, y)
    return Tracks(uv=uv, seed_frame=np.array([p[0][0] for p in paths], dtype=int))


def _lucas_kanade(prev: np.ndarray, nxt: np.ndarray, p0: np.ndarray, guess: np.ndarray, win: tuple[int, int], criteria: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade (two levels) of ``p0`` in ``prev`` to ``nxt``, started at ``guess``.

    OpenCV builds the pyramids and derivatives of both whole images at every call, which costs far
    more than following a few dozen points; the call runs on the part of both images that holds
    the points and ``guess`` with a margin of several windows (starting at an even pixel, so the
    coarse level averages the same pixels). The answer is the whole frames' up to rounding (the
    points' coordinates are smaller numbers; about 1e-3 px).

    Args:
        prev, nxt: ``(H, W)`` uint8 grey images.
        p0, guess: ``(k, 2)`` float32 OpenCV pixel coordinates (centre of pixel ``(x, y)`` at ``(x, y)``).
        win: Window size.
        criteria: OpenCV's termination criteria.

    Returns:
        ``(positions (k, 1, 2) float32, status (k, 1) uint8)`` as :func:`cv2.calcOpticalFlowPyrLK`.
    """
    p0, guess = p0.reshape(-1, 2), guess.reshape(-1, 2)
    pts = np.concatenate([p0, guess])
    h, w = prev.shape
    margin = 3 * max(win) + 8
    x0 = max(0, int(np.floor(pts[:, 0].min())) - margin) & ~1
    y0 = max(0, int(np.floor(pts[:, 1].min())) - margin) & ~1
    x1 = min(w, int(np.ceil(pts[:, 0].max())) + margin + 1)
    y1 = min(h, int(np.ceil(pts[:, 1].max())) + margin + 1)
    o = np.array([x0, y0], np.float32)
    got, status, _ = cv2.calcOpticalFlowPyrLK(
        np.ascontiguousarray(prev[y0:y1, x0:x1]), np.ascontiguousarray(nxt[y0:y1, x0:x1]), (p0 - o).reshape(-1, 1, 2), (guess - o).reshape(-1, 1, 2),
        winSize=win, maxLevel=1, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, criteria=criteria,
    )  # fmt: skip
    return got + o, status


def _anchor(gray: list[np.ndarray], paths: list, alive: list[int], nxt: np.ndarray, ok: np.ndarray, frame: int, config: TrackConfig) -> tuple[np.ndarray, np.ndarray]:
    """Refine flow-carried points by Lucas-Kanade from each track's seed frame (drift removal)."""
    nxt, ok = nxt.copy(), ok.copy()
    seeds = np.array([paths[p][0][0] for p in alive])
    for s in np.unique(seeds[ok]):
        sel = np.flatnonzero(ok & (seeds == s))
        if s == frame:
            continue
        p0 = np.array([paths[alive[k]][0][1:] for k in sel], np.float32) - 0.5
        guess = (nxt[sel] - 0.5).astype(np.float32)
        win = (config.anchor_window, config.anchor_window)
        got, status = _lucas_kanade(gray[s], gray[frame], p0, guess, win, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))
        got = got.reshape(-1, 2).astype(np.float64) + 0.5
        good = (status.reshape(-1) == 1) & (np.linalg.norm(got - nxt[sel], axis=1) < config.max_anchor_shift)
        nxt[sel[good]] = got[good]
        ok[sel[~good]] = False
    return nxt, ok


def extend_tracks(
    frames: np.ndarray,
    labels: np.ndarray,
    tracks: Tracks,
    predict: Callable[[int, np.ndarray], np.ndarray],
    config: TrackConfig = TrackConfig(),
    reach: int = 100,
    limits: np.ndarray | None = None,
    regions: np.ndarray | None = None,
) -> Tracks:
    """Re-observe every track in the frames around it, matched directly against its seed frame.

    Chained tracks hand the head over from one set of points to the next, and each hand-over adds
    the (spatially smooth, hence pose-like) flow error of the frames it spans. Once a first pose
    estimate exists, every track's point can be predicted in every frame; Lucas-Kanade from the
    seed frame's appearance, started at that prediction, then measures it there with no chain in
    between. A measurement is kept when it lies in the rigid region, within ``max_anchor_shift``
    pixels of the prediction, and matches back to the seed within ``max_fb_error``.

    Args:
        frames: ``(N, H, W, 3)`` uint8 RGB.
        labels: ``(N, H, W)`` uint8 parsing.
        tracks: Tracks to extend (their observations are kept).
        predict: ``predict(frame, track_indices) -> (k, 2)`` predicted pixel positions.
        config: Window, thresholds and region settings.
        reach: Frames before and after the seed frame that are searched.
        limits: ``(N,)`` rows the rigid region stays above per frame (see :func:`rigid_region`).
        regions: ``(N, H, W)`` bool rigid regions already made by :func:`rigid_regions` with
            these labels, settings and limits; ``None``: made here.

    Returns:
        New :class:`Tracks` with the added observations.
    """
    gray = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]
    if regions is None:
        regions = rigid_regions(labels, config, limits)
    uv = tracks.uv.copy()
    n = len(frames)
    win = (config.anchor_window or 15,) * 2
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    def observe(i: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """Frame ``i``'s new observations: (track indices, positions) per seed frame."""
        region = regions[i]
        near = np.flatnonzero((np.abs(tracks.seed_frame - i) <= reach) & ~np.isfinite(uv[i, :, 0]))
        if len(near) == 0:
            return []
        guess = predict(i, near)
        inside = _inside(region, guess)
        found = []
        for s in np.unique(tracks.seed_frame[near[inside]]):
            sel = near[inside][tracks.seed_frame[near[inside]] == s]
            g = guess[np.searchsorted(near, sel)]
            p0 = (tracks.uv[s, sel] - 0.5).astype(np.float32).reshape(-1, 1, 2)
            got, st = _lucas_kanade(gray[s], gray[i], p0, (g - 0.5).astype(np.float32), win, criteria)
            back, st2 = _lucas_kanade(gray[i], gray[s], got, p0, win, criteria)
            got = got.reshape(-1, 2).astype(np.float64) + 0.5
            ok = (st.reshape(-1) == 1) & (st2.reshape(-1) == 1)
            ok &= np.linalg.norm(back.reshape(-1, 2) + 0.5 - tracks.uv[s, sel], axis=1) < config.max_fb_error
            ok &= np.linalg.norm(got - g, axis=1) < config.max_anchor_shift
            ok &= _inside(region, got)
            found.append((sel[ok], got[ok]))
        return found

    # each frame reads the seed frames' positions (tracks.uv) and writes only its own row of uv
    for i, found in enumerate(in_threads(observe, range(n))):
        for sel, got in found:
            uv[i, sel] = got
    return Tracks(uv=uv, seed_frame=tracks.seed_frame.copy())
