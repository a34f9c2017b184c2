"""Face box and landmarks: the dlib backend on a real photograph, and the tracking around it
(search crops, gating, interpolation, smoothing) with a marker-finding stand-in detector."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import skimage.data

from adnerf.formats.dataset import LABEL_HEAD, LABEL_TORSO
from adnerf.preprocess.landmarks import (
    BROWS,
    EYES,
    JAW,
    MOUTH,
    NOSE_BASE,
    POSE_LANDMARKS,
    Detection,
    DlibFaceDetector,
    FaceTrackConfig,
    bundled_shape_predictor,
    make_face_detector,
    pose_landmarks,
    track_faces,
)
from adnerf.preprocess.parsing import (
    JAW_MARGIN,
    layer_check,
    split_at_landmarks,
    split_head_torso,
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


def test_jaw_split_puts_mouth_chin_hair_and_ears_in_the_head(dlib_detector: DlibFaceDetector) -> None:
    """The astronaut's face on a body (head, a neck as wide as the jaw, shoulders): cut along the
    jaw line of her landmarks, every lip landmark and the chin are head, the neck below the jaw
    and the shoulders torso, the hair above and beside the face head. Her neck is as wide as her
    jaw, so the silhouette has no narrowing under the chin (a close crop), where the neck-row cut
    gives up and makes everything head."""
    img = skimage.data.astronaut()
    lm = _best(dlib_detector, img).landmarks
    h, w = img.shape[:2]
    face_w = float(np.linalg.norm(lm[16] - lm[0]))
    cx, top = float(lm[:, 0].mean()), float(lm[19:25, 1].min()) - 0.5 * face_w  # hair above the brows
    person = np.zeros((h, w), np.uint8)
    cv2.ellipse(person, (int(cx), int((top + lm[8, 1]) / 2)), (int(0.62 * face_w), int((lm[8, 1] - top) / 2)), 0, 0, 360, 1, -1)
    person[int(lm[5, 1]) : int(lm[8, 1] + 0.6 * face_w), int(lm[4, 0]) : int(lm[12, 0])] = 1  # neck
    person[int(lm[8, 1] + 0.5 * face_w) :, int(cx - 1.5 * face_w) : int(cx + 1.5 * face_w)] = 1  # shoulders
    person[int(lm[2, 1]) : int(lm[7, 1]), int(lm[0, 0]) - 8 : int(lm[4, 0])] = 1  # hair hanging beside the left cheek
    person = person.astype(bool)
    labels = split_at_landmarks(np.where(person, LABEL_HEAD, 0)[None].astype(np.uint8), lm[None])[0]
    check = layer_check(labels[None], lm[None])
    assert check["lip_in_head"] == 1.0 and check["chin_lip_midpoint_in_head"] == 1.0 and check["chin_in_head"] == 1.0
    assert set(np.unique(labels[person])) == {LABEL_HEAD, LABEL_TORSO} and not labels[~person].any()
    below_jaw = int(lm[8, 1] + (JAW_MARGIN + 0.05) * face_w)
    assert (labels[below_jaw:][person[below_jaw:]] == LABEL_TORSO).all()  # neck and shoulders
    assert (labels[: int(lm[19:25, 1].min())][person[: int(lm[19:25, 1].min())]] == LABEL_HEAD).all()  # hair
    side = int(lm[0, 0]) - 3  # beside the face, level with the eyes: hair / ear
    assert person[int(lm[36, 1]), side] and labels[int(lm[36, 1]), side] == LABEL_HEAD
    # Hair beside the lower cheek: outside the jaw contour, inside the landmarks' columns, above the
    # chin. The cut follows the contour only under the lower jaw (4-12), so this is head.
    u, v = int(lm[3, 0]) + 1, int(lm[5, 1])  # her jaw runs straight down to landmark 3, then curves in
    assert lm[0, 0] < u + 0.5 < lm[4, 0] and person[v, u]
    assert labels[v, u] == LABEL_HEAD
    # The margin: the jaw's own pixels just below the landmark line are head.
    assert labels[int(lm[8, 1]) + 1, int(lm[8, 0])] == LABEL_HEAD
    # The neck-row cut finds no narrowing and makes the whole person head: an empty torso layer.
    row_labels, row = split_head_torso(person)
    assert row is None and not (row_labels == LABEL_TORSO).any()


def test_layer_check_counts_landmarks_in_the_head() -> None:
    """Known answer: a head label above row 50 holds exactly the landmarks above it."""
    labels = np.zeros((1, 100, 100), np.uint8)
    labels[0, :50] = LABEL_HEAD
    labels[0, 50:] = LABEL_TORSO
    lm = np.full((1, 68, 2), 20.5)
    lm[0, 48:58, 1] = 60.5  # half of the 20 lip points below the cut
    lm[0, 8] = (20.5, 90.5)  # chin tip far below: the chin-lip midpoint (20.5, 40.5)... lower lip 57 is at 60.5
    check = layer_check(labels, lm)
    assert check["lip_in_head"] == 0.5 and check["lip_in_head_worst"] == 0.5
    assert check["chin_lip_midpoint_in_head"] == 0.0 and check["chin_lip_midpoint_worst_frame"] == 0  # (90.5 + 60.5) / 2 = 75.5
    assert check["chin_in_head"] == 0.8  # landmarks 6, 7, 9, 10 at row 20.5, 8 at 90.5


def test_pose_landmarks_are_the_nose_and_eye_corners_of_detected_frames_only() -> None:
    """The pose's adjustment gets the nose (27-35) and the eyes' corners, measured: frames the
    tracker filled in between detections are NaN, not a guess weighted as a measurement."""
    lm = np.arange(3 * 68 * 2, dtype=np.float64).reshape(3, 68, 2)
    out = pose_landmarks(lm, np.array([True, False, True]))
    assert POSE_LANDMARKS == tuple(range(27, 36)) + (36, 39, 42, 45)
    np.testing.assert_array_equal(out[[0, 2]], lm[[0, 2]][:, list(POSE_LANDMARKS)])
    assert np.isnan(out[1]).all()
    with pytest.raises(ValueError, match="do not match"):
        pose_landmarks(lm, np.array([True, False]))
