"""Face box and 68 facial landmarks per frame, from a detector that works offline.

Step 2 of preprocessing. The default backend, ``"dlib"``, is dlib's HOG + linear SVM frontal face
detector (built into dlib, no model file) and dlib's 68-point shape predictor (an ensemble of
regression trees, Kazemi and Sullivan 2014) whose model file the ``face-recognition-models``
package ships; both come from pip (``dlib-bin``, ``face-recognition-models``) and nothing is
downloaded at run time. ``"dlib:PATH"`` loads another 68-point shape predictor ``.dat``. The
bundled 68-point model was trained on the iBUG 300-W data set, whose licence excludes commercial
use; train or bring your own model for that.

Landmarks follow the iBUG 300-W layout: jaw 0-16, brows 17-26, nose 27-35 (33 is the nose base),
eyes 36-47, mouth 48-67 (inner lips 60-67). Pixel coordinates use the project convention: a
pixel's centre is at ``(u + 0.5, v + 0.5)``; a box ``(x0, y0, x1, y1)`` spans ``x0 <= u < x1``.

:func:`track_faces` runs a detector over a clip. The parsing of the clip says where the head is
and how large: each frame is searched in a square crop around the head label, resampled so that
the head is ``target_width`` pixels wide (HOG's window is 80 pixels, and a 96-pixel video shows a
30-pixel face), and a detection counts only when its box centre lies inside the head label's box
(a face on a poster or a screen behind the speaker does not). Frames without a detection take
values interpolated linearly in time from the nearest detected frames (held at the ends of the
clip) and are counted. The box and the rigid landmarks (brows, nose, eyes) are smoothed over
time; the jaw and the mouth are not, since they move with speech at up to the frame rate.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Protocol

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from .headpose import head_boxes

__all__ = [
    "Detection",
    "FaceDetector",
    "DlibFaceDetector",
    "FaceTrackConfig",
    "FaceTrack",
    "track_faces",
    "mouth_centres",
    "eye_aspect_ratio",
    "eye_centres_px",
    "eye_openness",
    "make_face_detector",
    "bundled_shape_predictor",
    "JAW",
    "BROWS",
    "NOSE",
    "NOSE_BASE",
    "POSE_LANDMARKS",
    "pose_landmarks",
    "EYES",
    "MOUTH",
    "INNER_LIPS",
    "N_LANDMARKS",
]

N_LANDMARKS = 68
JAW, BROWS, NOSE, EYES, MOUTH, INNER_LIPS = slice(0, 17), slice(17, 27), slice(27, 36), slice(36, 48), slice(48, 68), slice(60, 68)
NOSE_BASE = 33
# Landmarks that move with the skull, not with the expression: the nose (27-35) and the eyes'
# corners (36, 39, 42, 45). They join the head-pose bundle adjustment (PreprocessConfig.pose_landmarks).
POSE_LANDMARKS = (27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 39, 42, 45)


def pose_landmarks(landmarks: np.ndarray, detected: np.ndarray) -> np.ndarray:
    """``(N, 13, 2)``: the :data:`POSE_LANDMARKS` of the frames where the detector found the face,
    NaN in the frames :func:`track_faces` filled in (a guess between neighbours is no measurement).

    Args:
        landmarks: ``(N, 68, 2)`` landmarks (pixel centres at ``+0.5``).
        detected: ``(N,)`` bool, whether the detector found the face in each frame.
    """
    if landmarks.shape[1:] != (N_LANDMARKS, 2) or detected.shape != landmarks.shape[:1]:
        raise ValueError(f"pose_landmarks: landmarks {landmarks.shape} and detected {detected.shape} do not match")
    return np.where(detected[:, None, None], landmarks[:, list(POSE_LANDMARKS)], np.nan)


_RIGID = np.r_[17:48]  # brows, nose, eyes: smoothed over time


@dataclass
class Detection:
    """One face found in one image.

    Attributes:
        box: ``(4,)`` float64 ``(x0, y0, x1, y1)`` in pixels (centre convention, end exclusive).
        landmarks: ``(68, 2)`` float64 pixel positions ``(u, v)``.
        score: Detector confidence (backend-specific scale; larger is surer).
    """

    box: np.ndarray
    landmarks: np.ndarray
    score: float

    def mapped(self, scale: float, offset: tuple[float, float]) -> "Detection":
        """The detection in the coordinates of an image of which this one is a crop at ``offset``
        (pixels of the larger image) resampled by ``scale`` (crop pixels per image pixel)."""
        off = np.asarray(offset, dtype=np.float64)
        return Detection(self.box / scale + np.tile(off, 2), self.landmarks / scale + off, self.score)


class FaceDetector(Protocol):
    """What every face backend provides."""

    name: str

    def detect(self, image: np.ndarray) -> list[Detection]:
        """All faces in an ``(H, W, 3)`` uint8 RGB image, any order."""
        ...


def bundled_shape_predictor() -> Path:
    """The 68-point shape predictor file of the ``face-recognition-models`` package.

    Raises:
        FileNotFoundError: The package is not installed (``pip install face-recognition-models``).
    """
    spec = importlib.util.find_spec("face_recognition_models")  # found, not imported: its __init__ needs pkg_resources
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("the 68-point landmark model comes with the face-recognition-models package: pip install face-recognition-models (or give --face dlib:PATH)")
    path = Path(list(spec.submodule_search_locations)[0]) / "models" / "shape_predictor_68_face_landmarks.dat"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing from the installed face-recognition-models package")
    return path


class DlibFaceDetector:
    """dlib's HOG face detector and a 68-point shape predictor.

    Args:
        predictor: A dlib shape predictor ``.dat`` with 68 parts; ``None`` takes the bundled one
            (:func:`bundled_shape_predictor`).
        threshold: Detection threshold added to the SVM's own (dlib's ``adjust_threshold``);
            lower finds more faces and more false ones.

    Raises:
        ImportError: dlib is not installed.
        FileNotFoundError: No predictor file.
        ValueError: The predictor does not have 68 parts.
    """

    def __init__(self, predictor: str | Path | None = None, threshold: float = 0.0) -> None:
        try:
            import dlib
        except ImportError as exc:  # pragma: no cover - dlib-bin is a dependency
            raise ImportError("the dlib face backend needs dlib: pip install dlib-bin") from exc
        path = Path(predictor) if predictor is not None else bundled_shape_predictor()
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such shape predictor file")
        self._detector = dlib.get_frontal_face_detector()
        try:
            self._predictor = dlib.shape_predictor(str(path))
        except RuntimeError as exc:
            raise ValueError(f"{path}: not a dlib shape predictor ({exc})") from exc
        parts = self._predictor(np.zeros((16, 16, 3), np.uint8), dlib.rectangle(0, 0, 15, 15)).num_parts
        if parts != N_LANDMARKS:
            raise ValueError(f"{path}: a shape predictor with {parts} parts; the 68-point (iBUG 300-W) layout is needed")
        self.threshold = threshold
        self.name = "dlib" if predictor is None else f"dlib:{path}"

    def detect(self, image: np.ndarray) -> list[Detection]:
        image = np.ascontiguousarray(image)
        rects, scores, _ = self._detector.run(image, 0, self.threshold)
        out = []
        for r, s in zip(rects, scores):
            shape = self._predictor(image, r)
            # dlib works in pixel indices (centre of pixel i at i); ours puts it at i + 0.5.
            lm = np.array([[p.x, p.y] for p in shape.parts()], dtype=np.float64) + 0.5
            box = np.array([r.left(), r.top(), r.right() + 1, r.bottom() + 1], dtype=np.float64)
            out.append(Detection(box, lm, float(s)))
        return out


def make_face_detector(spec: str) -> FaceDetector | None:
    """The face backend named by ``spec``: ``"dlib"``, ``"dlib:PATH"`` or ``"none"`` (``None``).

    Raises:
        ValueError: Unknown backend, or a predictor file that is missing or not a 68-point model.
    """
    if spec == "none":
        return None
    if spec == "dlib":
        try:
            return DlibFaceDetector()
        except FileNotFoundError as exc:
            raise ValueError(str(exc)) from exc
    if spec.startswith("dlib:"):
        try:
            return DlibFaceDetector(spec.split(":", 1)[1])
        except FileNotFoundError as exc:
            raise ValueError(f"--face {spec}: {exc}") from exc
    raise ValueError(f"unknown face backend {spec!r}; choose dlib, dlib:PREDICTOR.dat or none")


@dataclass
class FaceTrackConfig:
    """Settings of :func:`track_faces`.

    Attributes:
        target_width: Width in pixels that the head label's box is resampled to before detection.
        crop_scale: Side of the square search crop as a multiple of the head box's larger side.
        smooth_sigma: Gaussian smoothing over time (frames) of the box and the rigid landmarks;
            0 disables it.
    """

    target_width: int = 160
    crop_scale: float = 1.6
    smooth_sigma: float = 1.0


@dataclass
class FaceTrack:
    """Face boxes and landmarks over a clip.

    Attributes:
        boxes: ``(N, 4)`` float64 ``(x0, y0, x1, y1)``; interpolated where not detected.
        landmarks: ``(N, 68, 2)`` float64 pixel positions; interpolated where not detected.
        detected: ``(N,)`` bool, frames with an accepted detection.
        scores: ``(N,)`` float64 detector scores, NaN where not detected.
    """

    boxes: np.ndarray
    landmarks: np.ndarray
    detected: np.ndarray
    scores: np.ndarray


def mouth_centres(landmarks: np.ndarray) -> np.ndarray:
    """``(..., 2)`` centre of the inner lips of ``(..., 68, 2)`` landmarks (pixels)."""
    return landmarks[..., INNER_LIPS, :].mean(-2)


def eye_centres_px(landmarks: np.ndarray) -> np.ndarray:
    """``(..., 2, 2)`` centres of both eyes (36-41, the image-left eye, then 42-47) of ``(..., 68, 2)`` landmarks."""
    return np.stack([landmarks[..., 36:42, :].mean(-2), landmarks[..., 42:48, :].mean(-2)], axis=-2)


def eye_aspect_ratio(landmarks: np.ndarray) -> np.ndarray:
    """The eye aspect ratio (Soukupova and Cech, 2016) of ``(..., 68, 2)`` landmarks, both eyes'
    mean: ``(|p2 - p6| + |p3 - p5|) / (2 |p1 - p4|)`` over each eye's six points (36-41, 42-47);
    about 0.3 for an open eye, under 0.1 for a closed one. Shape ``(...)``."""
    ratios = []
    for first in (36, 42):
        p = landmarks[..., first : first + 6, :]
        vertical = np.linalg.norm(p[..., 1, :] - p[..., 5, :], axis=-1) + np.linalg.norm(p[..., 2, :] - p[..., 4, :], axis=-1)
        ratios.append(vertical / (2.0 * np.linalg.norm(p[..., 0, :] - p[..., 3, :], axis=-1)))
    return 0.5 * (ratios[0] + ratios[1])


EYE_CLOSED_RATIO = 0.4  # a closed eye's aspect ratio as a fraction of the clip's usual (open) one


def eye_openness(landmarks: np.ndarray) -> np.ndarray:
    """Per-frame eye openness ``(N,)`` float32 from ``(N, 68, 2)`` landmarks, normalised per clip.

    The eye aspect ratio (:func:`eye_aspect_ratio`; the landmarks are already smoothed over time
    by :func:`track_faces`) mapped so that the clip's median (eyes are open most of the time) is 1
    and :data:`EYE_CLOSED_RATIO` of it is 0, clipped to ``[0, 1.25]``. Frames without finite
    landmarks take the median (open).
    """
    ear = eye_aspect_ratio(np.asarray(landmarks, dtype=np.float64))
    ok = np.isfinite(ear)
    if not ok.any():
        return np.ones(len(ear), np.float32)
    usual = float(np.median(ear[ok]))
    closed = EYE_CLOSED_RATIO * usual
    out = np.where(ok, (ear - closed) / max(usual - closed, 1e-9), 1.0)
    return np.clip(out, 0.0, 1.25).astype(np.float32)


def _search_window(head: np.ndarray, h: int, w: int, config: FaceTrackConfig) -> tuple[int, int, int, float]:
    """Crop origin ``(x0, y0)``, side and scale for a frame whose head label box is ``head``
    (``(4,)``, NaN when there is no head label: the whole frame, at most 640 pixels wide)."""
    if not np.isfinite(head).all():
        side = max(h, w)
        return 0, 0, side, min(1.0, 640.0 / side)
    hx0, hy0, hx1, hy1 = head
    side = int(np.ceil(config.crop_scale * max(hx1 - hx0, hy1 - hy0)))
    x0 = int(np.floor(0.5 * (hx0 + hx1) - 0.5 * side))
    y0 = int(np.floor(0.5 * (hy0 + hy1) - 0.5 * side))
    return x0, y0, side, config.target_width / (hx1 - hx0)


def _crop(frame: np.ndarray, x0: int, y0: int, side: int, scale: float) -> tuple[np.ndarray, float]:
    """The square ``side`` x ``side`` crop at ``(x0, y0)`` (edge pixels repeated outside the frame),
    resampled to ``round(side * scale)`` pixels; returns it and the exact scale used."""
    h, w = frame.shape[:2]
    pad = (max(0, -y0), max(0, y0 + side - h), max(0, -x0), max(0, x0 + side - w))
    crop = frame[max(0, y0) : y0 + side, max(0, x0) : x0 + side]
    if any(pad):
        crop = cv2.copyMakeBorder(crop, *pad, cv2.BORDER_REPLICATE)
    n = max(1, int(round(side * scale)))
    if n != side:
        crop = cv2.resize(crop, (n, n), interpolation=cv2.INTER_AREA if n < side else cv2.INTER_LINEAR)
    return crop, n / side


def _fill(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Linear interpolation over time (axis 0) from the ``known`` frames; constant past the ends."""
    t = np.arange(len(values))
    flat = values.reshape(len(values), -1)
    out = np.empty_like(flat)
    for k in range(flat.shape[1]):
        out[:, k] = np.interp(t, t[known], flat[known, k])
    return out.reshape(values.shape)


def track_faces(
    frames: np.ndarray,
    detector: FaceDetector,
    labels: np.ndarray | None = None,
    config: FaceTrackConfig = FaceTrackConfig(),
    progress: Callable[[int, int], None] | None = None,
) -> FaceTrack:
    """Detect, gate, fill and smooth the face of a clip (see the module docstring).

    Args:
        frames: ``(N, H, W, 3)`` uint8 RGB.
        detector: A :class:`FaceDetector`.
        labels: ``(N, H, W)`` uint8 parsing; ``None`` searches whole frames and accepts the
            best-scoring face anywhere.
        config: :class:`FaceTrackConfig`.
        progress: Called as ``progress(done, total)``.

    Returns:
        A :class:`FaceTrack`; when no frame has a face, ``detected`` is all False and the boxes and
        landmarks are NaN.
    """
    n, h, w = frames.shape[:3]
    boxes = np.full((n, 4), np.nan)
    lms = np.full((n, N_LANDMARKS, 2), np.nan)
    scores = np.full(n, np.nan)
    heads = head_boxes(labels) if labels is not None else np.full((n, 4), np.nan)
    for i in range(n):
        head = heads[i]
        x0, y0, side, scale = _search_window(head, h, w, config)
        crop, s = _crop(frames[i], x0, y0, side, scale)
        best = None
        for det in detector.detect(crop):
            d = det.mapped(s, (x0, y0))
            cx, cy = 0.5 * (d.box[0] + d.box[2]), 0.5 * (d.box[1] + d.box[3])
            if np.isfinite(head).all() and not (head[0] <= cx < head[2] and head[1] <= cy < head[3]):
                continue  # a face elsewhere than on the speaker's head
            if best is None or d.score > best.score:
                best = d
        if best is not None:
            boxes[i], lms[i], scores[i] = best.box, best.landmarks, best.score
        if progress is not None:
            progress(i + 1, n)
    detected = np.isfinite(scores)
    if detected.any():
        boxes, lms = _fill(boxes, detected), _fill(lms, detected)
        if config.smooth_sigma > 0 and n > 1:
            boxes = gaussian_filter1d(boxes, config.smooth_sigma, axis=0, mode="nearest")
            lms[:, _RIGID] = gaussian_filter1d(lms[:, _RIGID], config.smooth_sigma, axis=0, mode="nearest")
    return FaceTrack(boxes, lms, detected, scores)
