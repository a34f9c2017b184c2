"""Reading the synthetic scene's hidden state (jaw opening, eye openness) off rendered frames.

Analysis by synthesis: for each distinct head pose, the scene is rendered exactly
(:func:`adnerf.synth.render_frame`, ray casting) at a grid of values of the quantity; a frame's
value is the grid value whose crop (the mouth, or both eyes) is nearest to the frame's in squared
error, refined by a parabola through the nearest three. On the scene's own frames a reader returns
the truth to within the grid's refinement, so what it reports on a render measures the render,
not the reader. :class:`JawReader` serves ``bench voices``; :class:`EyeReader` the demo's
``blink_corr``.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = ["EyeReader", "JawReader", "exact_frame", "eye_boxes"]


def exact_frame(head, torso, pose: np.ndarray, plate: np.ndarray, opening: float = 0.0, eye: float = 1.0, box: "tuple[int, int, int, int] | None" = None) -> np.ndarray:  # noqa: ANN001
    """The synthetic scene rendered exactly at a pose, jaw opening and eye openness, uint8: the
    whole frame, or only its pixels in ``box`` ``(x0, y0, x1, y1)`` (end exclusive)."""
    from ..synth import render_frame

    return _to_u8(render_frame(head, torso, pose, opening, plate, eye, box=box)[0])


def _to_u8(rgb: np.ndarray) -> np.ndarray:
    return np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)


def eye_boxes(meta, poses: np.ndarray, margin: float = 1.5) -> np.ndarray:  # noqa: ANN001
    """Pixel boxes ``(P, 4)`` ``(x0, y0, x1, y1)`` (end exclusive) around both eyes of the
    synthetic head under poses ``(P, 4, 4)``: the projected eye centres, widened by ``margin``
    times the lids' semi-axes (at the eyes' depth), clipped to the image."""
    import torch

    from ..pose import HeadPose
    from ..synth import EYE_AXES, eye_centres

    fx, fy = meta.intrinsics[:2]
    camera = meta.camera()
    centres = torch.as_tensor(eye_centres())
    out = []
    for pose in poses:
        cam = HeadPose.from_matrix(torch.as_tensor(pose, dtype=torch.float64)).from_canonical(centres)
        uv, z = camera.project(cam).numpy(), cam[:, 2].numpy()
        u, v = uv[:, 0], uv[:, 1]
        ru, rv = margin * EYE_AXES[0] * fx / z.mean(), margin * EYE_AXES[1] * fy / z.mean()
        x0, x1 = int(np.floor(u.min() - ru)), int(np.ceil(u.max() + ru))
        y0, y1 = int(np.floor(v.min() - rv)), int(np.ceil(v.max() + rv))
        out.append((max(x0, 0), max(y0, 0), min(max(x1, x0 + 2), meta.width), min(max(y1, y0 + 2), meta.height)))
    return np.array(out)


class _TemplateReader:
    """Nearest template (plus a parabola) among exact renders at a grid of values, per pose.

    ``render(p)`` is the exact render of pose ``p`` at every value, cropped to ``boxes[p]`` (only
    those pixels are ray cast), ``(steps, h, w, 3)`` uint8."""

    def __init__(self, values: np.ndarray, boxes: np.ndarray, render: Callable[[int], np.ndarray]) -> None:
        self.values, self.boxes = values, boxes
        self.templates = [render(p).astype(np.float32) for p in range(len(boxes))]  # per pose (steps, h, w, 3): the boxes differ in size

    def box(self, p: int) -> tuple[int, int, int, int]:
        """Pose ``p``'s box ``(x0, y0, x1, y1)`` (end exclusive)."""
        x0, y0, x1, y1 = (int(v) for v in self.boxes[p])
        return x0, y0, x1, y1

    def read(self, frames: np.ndarray, pose_index: np.ndarray) -> np.ndarray:
        """Values ``(N,)`` of frames ``(N, H, W, 3)`` uint8 rendered with poses ``pose_index``."""
        crops = []
        for frame, p in zip(frames, pose_index):
            x0, y0, x1, y1 = self.box(p)
            crops.append(frame[y0:y1, x0:x1])
        return self.read_crops(crops, pose_index)

    def read_crops(self, crops: "list[np.ndarray] | np.ndarray", pose_index: np.ndarray) -> np.ndarray:
        """Values ``(N,)`` of the crops ``(h, w, 3)`` uint8 of frames rendered with poses
        ``pose_index``, each cropped to its pose's box (:meth:`box`)."""
        out = np.empty(len(crops))
        step = self.values[1] - self.values[0]
        for i, (crop, p) in enumerate(zip(crops, pose_index)):
            if crop.shape != self.templates[p].shape[1:]:
                raise ValueError(f"crop {i} is {crop.shape}; pose {p}'s box is {self.templates[p].shape[1:]}")
            err = ((self.templates[p] - crop.astype(np.float32)) ** 2).mean(axis=(1, 2, 3))
            k = int(np.argmin(err))
            shift = 0.0
            if 0 < k < len(err) - 1:
                curve = err[k - 1] - 2 * err[k] + err[k + 1]
                shift = 0.5 * (err[k - 1] - err[k + 1]) / curve if curve > 0 else 0.0
            out[i] = float(np.clip(self.values[k] + shift * step, self.values[0], self.values[-1]))
        return out


class JawReader(_TemplateReader):
    """Reads the jaw opening off frames of the synthetic scene (mouth crops; eyes open).

    Args:
        ds: The synthetic dataset (camera, background, mouth point).
        poses: ``(P, 4, 4)`` distinct head poses the frames are rendered with.
        steps: Openings in the grid.
    """

    def __init__(self, ds, poses: np.ndarray, steps: int = 21) -> None:  # noqa: ANN001
        import torch

        from ..pose import HeadPose
        from ..synth import HeadModel, TorsoModel
        from .evaluate import mouth_boxes_at

        head, torso = HeadModel(ds.meta.width), TorsoModel(ds.meta.width)
        plate = ds.background.astype(np.float64) / 255.0
        boxes = mouth_boxes_at(ds.meta, HeadPose.from_matrix(torch.as_tensor(poses, dtype=torch.float64)))
        values = np.linspace(0.0, 1.0, steps)
        super().__init__(values, boxes, lambda p: np.stack([exact_frame(head, torso, poses[p], plate, opening=v, box=self.box(p)) for v in values]))


class EyeReader(_TemplateReader):
    """Reads the eye openness off frames of the synthetic scene (both eyes' crop; jaw closed,
    which does not reach the eyes).

    Args:
        ds: The synthetic dataset (camera, background).
        poses: ``(P, 4, 4)`` distinct head poses the frames are rendered with.
        steps: Openness values in the grid.
    """

    def __init__(self, ds, poses: np.ndarray, steps: int = 11) -> None:  # noqa: ANN001
        from ..synth import HeadModel, TorsoModel, render_eye_openings

        head, torso = HeadModel(ds.meta.width), TorsoModel(ds.meta.width)
        plate = ds.background.astype(np.float64) / 255.0
        values = np.linspace(0.0, 1.0, steps)
        # The lids are painted on the head: one ray cast a pose serves every openness.
        super().__init__(values, eye_boxes(ds.meta, poses), lambda p: _to_u8(render_eye_openings(head, torso, poses[p], 0.0, plate, values, box=self.box(p))))
