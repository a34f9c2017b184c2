"""Clothes that never move: the torso layer completed below the face (adnerf.preprocess.clothes)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage

from adnerf.formats.dataset import LABEL_HEAD, LABEL_TORSO
from adnerf.preprocess.clothes import complete_torso
from adnerf.preprocess.landmarks import DlibFaceDetector

SKIN = (205, 160, 140)


def _dark_suit_clip(n: int = 3, size: int = 160, suit: tuple = (45, 48, 62), corner: tuple = (50, 46, 44), seed: int = 0) -> tuple[np.ndarray, ...]:
    """A head on a neck above a dark suit, on a wall that darkens to ``corner`` at the bottom edges
    (the dark-edged background), with the parse a motion-based parser gives: head and neck only.

    Returns:
        ``(frames (N, S, S, 3) uint8, parse (N, S, S), truth (N, S, S), landmarks (N, 68, 2))``; only
        landmarks 0, 16 (the face's width) and 8 (the chin) are placed, the rest sit at the face's
        centre.
    """
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    wall, dark = np.array([178.0, 168.0, 150.0]), np.array(corner, float)
    r = np.clip((np.hypot((xx - size / 2) / (size / 2), (yy - 0.2 * size) / (0.8 * size)) - 0.3) / 0.9, 0.0, 1.0)[..., None]
    background = wall * (1 - r) + dark * r
    frames, parse, truth, landmarks = [], [], [], []
    for i in range(n):
        cx, cy, width = size / 2 + i, 0.38 * size, 0.375 * size  # the head moves a pixel a frame
        head = ((xx - cx) / (0.5 * width)) ** 2 + ((yy - cy) / (0.62 * width)) ** 2 <= 1
        chin = cy + 0.62 * width
        neck = (np.abs(xx - cx) <= 0.25 * width) & (yy > cy) & (yy <= chin + 0.5 * width) & ~head
        body = (yy >= chin + 0.3 * width + 0.25 * np.abs(xx - cx)) & ~head & ~neck  # shoulders falling outwards
        img = background.copy()
        img[body] = suit
        img[neck | head] = SKIN
        frames.append(np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8))
        p = np.zeros((size, size), np.uint8)
        p[head], p[neck] = LABEL_HEAD, LABEL_TORSO
        parse.append(p)
        truth.append(np.where(body, LABEL_TORSO, p).astype(np.uint8))
        lm = np.tile([cx, cy], (68, 1))
        lm[0], lm[16], lm[8] = (cx - width / 2, cy), (cx + width / 2, cy), (cx, chin)
        landmarks.append(lm)
    return np.stack(frames), np.stack(parse), np.stack(truth), np.stack(landmarks)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_dark_suit_on_a_dark_edged_background_joins_the_torso() -> None:
    frames, parse, truth, lm = _dark_suit_clip()
    out, report = complete_torso(frames, parse, lm)
    torso = truth == LABEL_TORSO
    assert _iou(parse == LABEL_TORSO, torso) < 0.2  # the neck alone: what the motion parse had
    assert _iou(out == LABEL_TORSO, torso) > 0.97  # measured 1.0
    assert ((out > 0) & (truth == 0)).sum() <= 0.01 * (truth == 0).sum()  # the dark corners stay wall
    assert report["frames"] == 3 and report["frames_changed"] == 3 and report["added_fraction"] > 0.1
    # Only background pixels below the chin's row change, and only to torso.
    changed = out != parse
    rows = np.arange(frames.shape[1])[None, :, None] + 0.5
    assert not (changed & (rows <= lm[:, 8, 1][:, None, None])).any()
    assert (parse[changed] == 0).all() and (out[changed] == LABEL_TORSO).all()
    # The same clip completes the same way whatever OpenCV's random state was before.
    cv2.setRNGSeed(12345)
    cv2.kmeans(np.random.default_rng(1).random((50, 3), np.float32), 3, None, (cv2.TERM_CRITERIA_MAX_ITER, 5, 0), 1, cv2.KMEANS_RANDOM_CENTERS)
    assert np.array_equal(complete_torso(frames, parse, lm)[0], out)


def test_a_suit_like_the_wall_is_not_invented_and_close_crops_are_left_alone() -> None:
    # A frame whose bottom edge is barely below the chin shows no shoulders: nothing to seed, no cut.
    frames, parse, _, lm = _dark_suit_clip(n=2)
    crop = frames[:, : int(lm[0, 8, 1]) + 5]
    out, report = complete_torso(crop, parse[:, : crop.shape[1]], lm)
    assert np.array_equal(out, parse[:, : crop.shape[1]]) and report["frames"] == 0
    # A frame without landmarks is left as parsed; the others are completed.
    lm_missing = lm.copy()
    lm_missing[1] = np.nan
    out, report = complete_torso(frames, parse, lm_missing)
    assert np.array_equal(out[1], parse[1]) and not np.array_equal(out[0], parse[0]) and report["frames"] == 1
    with pytest.raises(ValueError, match="do not match"):
        complete_torso(frames[:1], parse, lm)


@pytest.fixture(scope="module")
def astronaut() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The astronaut photograph (her orange suit, a flag, a helmet beside her), its 68 landmarks
    from the bundled dlib model and the parse a motion-based parser gives of it: her head (an
    ellipse over hair and face) and her neck, the suit left as background."""
    img = skimage.data.astronaut()
    found = DlibFaceDetector().detect(img)
    assert found, "no face detected"
    lm = max(found, key=lambda d: d.score).landmarks
    width = float(np.linalg.norm(lm[16] - lm[0]))
    cx, top = float(lm[:, 0].mean()), float(lm[19:25, 1].min()) - 0.5 * width
    parse = np.zeros(img.shape[:2], np.uint8)
    cv2.ellipse(parse, (int(cx), int((top + lm[8, 1]) / 2)), (int(0.62 * width), int((lm[8, 1] - top) / 2)), 0, 0, 360, LABEL_HEAD, -1)
    neck = np.zeros(img.shape[:2], bool)
    neck[int(lm[8, 1]) - 5 : int(lm[8, 1] + 0.35 * width), int(lm[5, 0]) : int(lm[11, 0])] = True
    parse[neck & (parse == 0)] = LABEL_TORSO
    return img, parse, lm


def test_astronauts_suit_joins_the_torso_and_her_helmet_does_not(astronaut: tuple) -> None:
    """A real photograph: her suit rises above her chin at the shoulders, where the wall samples
    would teach the background its orange; below the chin it is torso, the black helmet held
    beside her (not clothes) stays background."""
    img, parse, lm = astronaut
    out, _ = complete_torso(img[None], parse[None], lm[None])
    torso = out[0] == LABEL_TORSO
    assert 170 < lm[8, 1] < 190 and 200 < lm[8, 0] < 240  # her chin, where the boxes below assume it
    for y0, y1, x0, x1 in ((260, 300, 80, 160), (300, 360, 250, 300), (440, 500, 150, 250)):  # the suit: shoulder, chest, waist
        assert torso[y0:y1, x0:x1].mean() > 0.9, (y0, x0)
    assert torso[400:460, 380:460].mean() < 0.1  # the helmet
    assert np.array_equal(out[0][: int(lm[8, 1])], parse[: int(lm[8, 1])])  # above the chin: as parsed


def test_completing_a_clip_holds_about_two_label_arrays_not_a_seed_mask_per_frame() -> None:
    """The seeds and anchors of each frame are made when its turn comes, and GrabCut reads the
    frames' bands without a copy of the clip's: what numpy allocates grows with the clip by under
    2.5 bytes a label (the result and the cut's band take about 1.6). Holding a seed mask and an
    anchor per frame for the whole clip and a copy of its bands grew it by about 5."""
    import tracemalloc

    peaks, sizes = [], []
    for n in (16, 64):
        frames, parse, truth, lm = _dark_suit_clip(n=n, size=96)
        tracemalloc.start()
        try:
            out, report = complete_torso(frames, parse, lm)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert report["frames_changed"] == n and _iou(out == LABEL_TORSO, truth == LABEL_TORSO) > 0.9
        peaks.append(peak)
        sizes.append(parse.nbytes)
    per_label = (peaks[1] - peaks[0]) / (sizes[1] - sizes[0])
    assert 1.0 <= per_label < 2.5, per_label
