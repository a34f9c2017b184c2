"""Face box and landmarks: the dlib backend on a real photograph, and the tracking around it
(search crops, gating, interpolation, smoothing) with a marker-finding stand-in detector."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import skimage.data

from adnerf.data import LABEL_HEAD
from adnerf.preprocess.landmarks import (
    BROWS,
    EYES,
    JAW,
    MOUTH,
    NOSE_BASE,
    Detection,
    DlibFaceDetector,
    FaceTrackConfig,
    bundled_shape_predictor,
    make_face_detector,
    track_faces,
)


@pytest.fixture(scope="module")
def dlib_detector() -> DlibFaceDetector:
    return DlibFaceDetector()


def _best(det: DlibFaceDetector, image: np.ndarray) -> Detection:
    found = det.detect(image)
    assert found, "no face detected"
    return max(found, key=lambda d: d.score)


def test_dlib_finds_the_astronauts_face_with_landmarks_in_anatomical_order(dlib_detector: DlibFaceDetector) -> None:
    img = skimage.data.astronaut()
    d = _best(dlib_detector, img)
    x0, y0, x1, y1 = d.box
    assert 150 < x0 < x1 < 300 and 50 < y0 < y1 < 200  # her face, not the flag or the suit
    lm = d.landmarks
    assert lm.shape == (68, 2) and np.isfinite(lm).all()
    brows, eyes, nose, mouth, chin = lm[BROWS, 1].mean(), lm[EYES, 1].mean(), lm[NOSE_BASE, 1], lm[MOUTH, 1].mean(), lm[8, 1]
    assert brows < eyes < nose < mouth < chin  # image y grows downwards
    assert lm[36:42, 0].mean() < lm[42:48, 0].mean()  # iBUG order: the first eye is on the image's left
    assert lm[JAW, 0][0] < lm[JAW, 0][-1]


@pytest.mark.parametrize("angle, scale, shift", [(8.0, 0.8, (30.0, -20.0)), (-12.0, 1.1, (-25.0, 10.0)), (20.0, 0.9, (0.0, 0.0))])
def test_dlib_landmarks_move_with_the_image(dlib_detector: DlibFaceDetector, angle: float, scale: float, shift: tuple[float, float]) -> None:
    """Detect on the photograph and on a similarity-warped copy: the landmarks must map onto each
    other by the same similarity (measured: median 0.6-0.7 px, max 2.6 px, eyes 35-48 px apart)."""
    img = skimage.data.astronaut()
    M = cv2.getRotationMatrix2D((256.0, 256.0), angle, scale)
    M[:, 2] += shift
    warped = cv2.warpAffine(img, M, (512, 512), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    A = M[:, :2]
    b = M[:, 2] + 0.5 - A @ np.array([0.5, 0.5])  # OpenCV maps pixel indices; ours are centres at +0.5
    before, after = _best(dlib_detector, img).landmarks, _best(dlib_detector, warped).landmarks
    err = np.linalg.norm(after - (before @ A.T + b), axis=1)
    iod = np.linalg.norm(after[36:42].mean(0) - after[42:48].mean(0))
    assert np.median(err) < 0.05 * iod and err.max() < 0.15 * iod, (np.median(err), err.max(), iod)


def test_predictor_files_are_checked(tmp_path: Path) -> None:
    junk = tmp_path / "junk.dat"
    junk.write_bytes(b"not a model")
    with pytest.raises(ValueError, match="not a dlib shape predictor"):
        DlibFaceDetector(junk)
    five = bundled_shape_predictor().with_name("shape_predictor_5_face_landmarks.dat")
    if five.is_file():
        with pytest.raises(ValueError, match="5 parts"):
            DlibFaceDetector(five)
    with pytest.raises(ValueError, match="no such shape predictor"):
        make_face_detector(f"dlib:{tmp_path / 'missing.dat'}")
    with pytest.raises(ValueError, match="unknown face backend"):
        make_face_detector("haar")
    assert make_face_detector("none") is None


class MarkerDetector:
    """Finds bright squares in whatever image it is given and reports each as a face: box = the
    square, landmarks = a fixed pattern scaled to it. It sees only the search crop, so the
    positions ``track_faces`` returns test its crop and resampling arithmetic."""

    name = "marker"
    pattern = np.random.default_rng(0).uniform(0.1, 0.9, size=(68, 2))

    def detect(self, image: np.ndarray) -> list[Detection]:
        n, lab, stats, _ = cv2.connectedComponentsWithStats((image[..., 0] > 127).astype(np.uint8))
        out = []
        for k in range(1, n):
            x, y, w, h = stats[k, :4]
            box = np.array([x, y, x + w, y + h], dtype=np.float64)
            out.append(Detection(box, box[:2] + self.pattern * np.array([w, h], dtype=np.float64), float(w * h)))
        return out


def _marker_clip(n: int = 12, size: int = 96) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    frames = np.full((n, size, size, 3), 40, np.uint8)
    labels = np.zeros((n, size, size), np.uint8)
    labels[:, 20:70, 15:65] = LABEL_HEAD
    boxes = np.zeros((n, 4))
    for i in range(n):
        x = 25 + 2 * i  # the face moves right by 2 px per frame
        boxes[i] = (x, 30, x + 16, 46)
        if i not in (3, 4, 5):  # the "detector" misses these frames
            frames[i, 30:46, x : x + 16] = 255
    frames[7, 5:40, 67:80] = 255  # a larger "face" beside the head (centre outside its box): rejected
    return frames, labels, boxes


def test_track_faces_maps_crops_back_gates_and_interpolates() -> None:
    frames, labels, truth = _marker_clip()
    track = track_faces(frames, MarkerDetector(), labels, FaceTrackConfig(smooth_sigma=0.0))
    assert track.detected.tolist() == [i not in (3, 4, 5) for i in range(12)]
    assert np.isnan(track.scores[[3, 4, 5]]).all() and np.isfinite(track.scores[track.detected]).all()
    # Crop at 1.6 x the head box, resampled 160 / 50 = 3.2 x and mapped back: within the
    # resampling's edge blur of the truth, in detected and interpolated frames alike (linear motion).
    np.testing.assert_allclose(track.boxes, truth, atol=0.35)
    expect = truth[:, None, :2] + MarkerDetector.pattern * 16.0
    np.testing.assert_allclose(track.landmarks, expect, atol=0.35)


def test_track_faces_smooths_the_rigid_landmarks_only() -> None:
    frames, labels, _ = _marker_clip()
    flicker = np.zeros((12, 68, 2))
    flicker[::2] = 1.0  # the detector's landmarks flicker by a pixel every other frame

    def wobble(lm: np.ndarray) -> float:
        """Mean |second difference| over time past the gap (the motion itself is linear: 0)."""
        return float(np.abs(np.diff(lm, 2, axis=0))[6:].mean())

    rough = track_faces(frames, _Offset(MarkerDetector(), flicker), labels, FaceTrackConfig(smooth_sigma=0.0))
    smooth = track_faces(frames, _Offset(MarkerDetector(), flicker), labels, FaceTrackConfig(smooth_sigma=1.5))
    assert wobble(rough.landmarks[:, 17:48]) > 1.5
    assert wobble(smooth.landmarks[:, 17:48]) < 0.3  # brows, nose, eyes: the flicker is gone
    np.testing.assert_allclose(smooth.landmarks[:, MOUTH], rough.landmarks[:, MOUTH])  # mouth and jaw keep every frame's motion
    np.testing.assert_allclose(smooth.landmarks[:, JAW], rough.landmarks[:, JAW])
    assert wobble(smooth.boxes) < wobble(rough.boxes) + 1e-12


class _Offset:
    """Adds a per-call offset (in full-frame pixels, via the crop scale) to another detector's landmarks."""

    name = "offset"

    def __init__(self, inner: MarkerDetector, offsets: np.ndarray) -> None:
        self.inner, self.offsets, self.calls = inner, offsets, 0

    def detect(self, image: np.ndarray) -> list[Detection]:
        found = self.inner.detect(image)
        scale = 160.0 / 50.0  # crop pixels per frame pixel for the marker clip's head box
        out = [Detection(d.box, d.landmarks + scale * self.offsets[self.calls], d.score) for d in found]
        self.calls += 1
        return out


def test_track_faces_reports_no_face_as_nan() -> None:
    frames, labels, _ = _marker_clip()
    frames[:] = 40
    track = track_faces(frames, MarkerDetector(), labels)
    assert not track.detected.any() and np.isnan(track.landmarks).all() and np.isnan(track.boxes).all()
