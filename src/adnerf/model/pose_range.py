"""The head poses a run was taught: the range its training frames covered, and edits outside it.

A radiance field renders the head poses it was trained on; far outside them a turned head smears
and its features double, and the torso, which reads the pose as an input, extrapolates. A
:class:`PoseRange` records what the training frames showed, relative to their mean rotation
``M`` (the chordal mean): each pose's rotation ``R_i M^T`` as yaw, pitch and roll in camera axes
(:func:`adnerf.pose.euler_angles`, the axes of ``render --yaw/--pitch/--roll``), and its
translation ``t_i`` (camera space, scene units). Rendering asks :meth:`PoseRange.excess` how far a
requested pose lies outside, per axis, and warns (or refuses, ``--strict-pose``) beyond
:data:`ROTATION_MARGIN_DEG` / :data:`TRANSLATION_MARGIN`.

The range is stored in ``run.json`` (``"pose_range"``) when training starts; a run written before
that gets it from its dataset's poses and training split when the dataset is still there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..pose import euler_angles, euler_rotation, mean_rotation, perturb_pose

__all__ = ["AXES", "PoseRange", "ROTATION_MARGIN_DEG", "TORSO_POSES", "TRANSLATION_MARGIN", "relative_angles", "torso_reads"]

AXES = ("yaw", "pitch", "roll")
"""The rotation axes, in the order of :func:`adnerf.pose.euler_angles`."""

ROTATION_MARGIN_DEG = 5.0
"""Degrees a pose may leave the taught rotation range before rendering warns: up to about there a
turned face is still a rigid turn of itself (``docs/decisions.md``, *The taught pose range, its
5-degree margin, and the torso under an edit*)."""

TRANSLATION_MARGIN = 0.1
"""Head widths (the head box's extent along x) a pose's translation may leave the taught range."""


def relative_angles(R: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Yaw, pitch and roll in degrees ``(N, 3)`` of rotations ``R (N, 3, 3)`` relative to
    ``reference (3, 3)``: the Euler angles of ``R_i reference^T`` (camera axes)."""
    rel = np.asarray(R, dtype=np.float64) @ np.asarray(reference, dtype=np.float64).T
    return np.degrees(euler_angles(torch.from_numpy(np.ascontiguousarray(rel))).numpy())


@dataclass(frozen=True)
class PoseRange:
    """The head poses of a run's training frames.

    Attributes:
        reference: ``(3, 3)`` the training rotations' mean, which the angles are relative to.
        rotation: ``(3, 2)`` degrees, min and max of yaw, pitch and roll (:data:`AXES`).
        rotation_quantiles: ``(3, 3)`` degrees, the 5th, 50th and 95th percentile per axis.
        translation: ``(3, 2)`` scene units, min and max of ``t`` per camera axis.
        head_width: The head box's extent along x, scene units (the unit of the translation margin).
        histogram: Per axis, counts of the training frames in 1-degree bins starting at
            ``floor(min)`` (a simple density of the poses seen).
        frames: How many training frames the range is made of.
    """

    reference: np.ndarray
    rotation: np.ndarray
    rotation_quantiles: np.ndarray
    translation: np.ndarray
    head_width: float
    histogram: tuple[tuple[int, ...], ...]
    frames: int

    @staticmethod
    def from_poses(poses: np.ndarray, head_width: float) -> "PoseRange":
        """The range of training poses ``(N, 4, 4)`` (canonical to camera).

        Raises:
            ValueError: No poses, or poses not ``(N, 4, 4)`` and finite.
        """
        p = np.asarray(poses, dtype=np.float64)
        if p.ndim != 3 or p.shape[1:] != (4, 4) or not len(p) or not np.isfinite(p).all():
            raise ValueError(f"a pose range needs finite poses (N >= 1, 4, 4); got shape {p.shape}")
        if not (math.isfinite(head_width) and head_width > 0):
            raise ValueError(f"head_width must be a positive length; got {head_width}")
        reference = mean_rotation(p[:, :3, :3])
        angles = relative_angles(p[:, :3, :3], reference)
        t = p[:, :3, 3]
        hist = []
        for a in angles.T:
            lo = math.floor(a.min())
            hist.append(tuple(int(c) for c in np.bincount(np.floor(a - lo).astype(np.int64))))
        return PoseRange(
            reference=reference,
            rotation=np.stack([angles.min(0), angles.max(0)], axis=1),
            rotation_quantiles=np.percentile(angles, [5, 50, 95], axis=0).T,
            translation=np.stack([t.min(0), t.max(0)], axis=1),
            head_width=float(head_width),
            histogram=tuple(hist),
            frames=len(p),
        )

    def angles(self, poses: np.ndarray) -> np.ndarray:
        """Yaw, pitch and roll in degrees ``(N, 3)`` of poses ``(N, 4, 4)`` relative to :attr:`reference`."""
        return relative_angles(np.asarray(poses, dtype=np.float64)[:, :3, :3], self.reference)

    def excess(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """How far poses ``(N, 4, 4)`` lie outside the range: ``(degrees (N, 3), head widths (N, 3))``,
        per rotation axis and translation axis, 0 inside."""
        p = np.asarray(poses, dtype=np.float64)
        a = self.angles(p)
        rot = np.maximum(0.0, np.maximum(self.rotation[:, 0] - a, a - self.rotation[:, 1]))
        t = p[:, :3, 3]
        trans = np.maximum(0.0, np.maximum(self.translation[:, 0] - t, t - self.translation[:, 1])) / self.head_width
        return rot, trans

    def clamp(self, poses: np.ndarray) -> np.ndarray:
        """Poses ``(N, 4, 4)`` moved into the range: yaw, pitch and roll (about :attr:`reference`)
        and the translation clipped per axis to what the training frames showed. Poses inside it
        are returned as they are (to rounding)."""
        p = np.array(poses, dtype=np.float64)
        a = np.clip(self.angles(p), self.rotation[:, 0], self.rotation[:, 1])
        r = torch.from_numpy(np.radians(a))
        p[:, :3, :3] = euler_rotation(r[:, 0], r[:, 1], r[:, 2], like=r).numpy() @ self.reference
        p[:, :3, 3] = np.clip(p[:, :3, 3], self.translation[:, 0], self.translation[:, 1])
        return p

    def density(self, poses: np.ndarray, within_deg: float = 1.0) -> np.ndarray:
        """How often the training frames came near each pose ``(N, 4, 4)``: per axis the share of
        training frames within ``within_deg`` of the pose's angle, read from :attr:`histogram`
        (1-degree bins; a bin counts when its span meets the interval), and the smallest of the
        three shares, ``(N,)`` (an upper bound of the share near the pose on all axes at once)."""
        a = self.angles(poses)
        share = np.ones(len(a))
        for axis, counts in enumerate(self.histogram):
            lo = math.floor(self.rotation[axis, 0])
            c = np.asarray(counts, dtype=np.float64)
            edges = lo + np.arange(len(c))
            for i, v in enumerate(a[:, axis]):
                near = (edges + 1 > v - within_deg) & (edges < v + within_deg)
                share[i] = min(share[i], c[near].sum() / self.frames)
        return share

    def describe(self) -> str:
        """The range in one phrase: ``yaw -4.9..3.8, pitch ..., roll ... degrees``."""
        return ", ".join(f"{name} {lo:+.1f}..{hi:+.1f}" for name, (lo, hi) in zip(AXES, self.rotation)) + " degrees"

    def check(self, poses: np.ndarray, *, margin_deg: float = ROTATION_MARGIN_DEG, margin_translation: float = TRANSLATION_MARGIN) -> str | None:
        """``None`` when every pose lies within the range plus the margins, else one line that says
        how far the farthest goes and what the training frames covered."""
        rot, trans = self.excess(poses)
        worst_rot = rot.max(0)
        worst_t = trans.max(0)
        parts = []
        a = self.angles(poses)
        for k, name in enumerate(AXES):
            if worst_rot[k] > margin_deg:
                i = int(rot[:, k].argmax())
                parts.append(f"{name} {a[i, k]:+.1f} degrees (taught {self.rotation[k, 0]:+.1f}..{self.rotation[k, 1]:+.1f}, {rot[i, k]:.1f} past it)")
        for k, name in enumerate("xyz"):
            if worst_t[k] > margin_translation:
                parts.append(f"translation {name} {worst_t[k]:.2f} head widths past the taught range")
        if not parts:
            return None
        n_out = int(((rot > margin_deg).any(1) | (trans > margin_translation).any(1)).sum())
        return (
            f"{n_out} of {len(rot)} requested head poses lie outside what the training frames showed by more than "
            f"{margin_deg:g} degrees / {margin_translation:g} head widths: {'; '.join(parts)}. The face may smear and the torso "
            "disagree with the head there"
        )

    def to_dict(self) -> dict:
        """JSON-serialisable form (``run.json``'s ``"pose_range"``)."""
        return {
            "reference": self.reference.tolist(),
            "rotation_deg": {name: [round(float(lo), 4), round(float(hi), 4)] for name, (lo, hi) in zip(AXES, self.rotation)},
            "rotation_quantiles_deg": {name: [round(float(q), 4) for q in qs] for name, qs in zip(AXES, self.rotation_quantiles)},
            "translation": [[float(lo), float(hi)] for lo, hi in self.translation],
            "head_width": self.head_width,
            "histogram_1deg": {name: list(h) for name, h in zip(AXES, self.histogram)},
            "frames": self.frames,
        }

    @staticmethod
    def from_dict(d: dict) -> "PoseRange":
        """Inverse of :meth:`to_dict`.

        Raises:
            ValueError: A missing key or a value of the wrong shape.
        """
        try:
            out = PoseRange(
                reference=np.asarray(d["reference"], dtype=np.float64).reshape(3, 3),
                rotation=np.asarray([d["rotation_deg"][a] for a in AXES], dtype=np.float64).reshape(3, 2),
                rotation_quantiles=np.asarray([d["rotation_quantiles_deg"][a] for a in AXES], dtype=np.float64).reshape(3, 3),
                translation=np.asarray(d["translation"], dtype=np.float64).reshape(3, 2),
                head_width=float(d["head_width"]),
                histogram=tuple(tuple(int(c) for c in d["histogram_1deg"][a]) for a in AXES),
                frames=int(d["frames"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"not a stored pose range ({type(exc).__name__}: {exc})") from exc
        return out


TORSO_POSES = ("track", "clamped", "edited")
"""What the torso reads when the head is turned by an edit (:func:`torso_reads`)."""


def torso_reads(mode: str, track: np.ndarray, edited: np.ndarray, taught: PoseRange | None) -> np.ndarray | None:
    """The poses ``(N, 4, 4)`` the torso reads as its pose signal when rendering ``edited`` poses
    made from the pose track ``track`` (``None``: the edited ones themselves).

    ``"track"``: the track's own poses (an edit turns the head alone, the shoulders keep the
    track's motion; without an edit, the frames render exactly as before); ``"clamped"``: the
    edited poses clamped to the range; ``"edited"``: the edited poses (the torso extrapolates
    outside the range). Without a known range, ``"clamped"`` reads the edited poses.

    Raises:
        ValueError: An unknown mode.
    """
    if mode not in TORSO_POSES:
        raise ValueError(f"the torso's pose is one of {TORSO_POSES}; got {mode!r}")
    if mode == "edited" or (mode == "clamped" and taught is None):
        return None
    if mode == "track":
        return track
    return edited if taught is None else taught.clamp(edited)


def edit_poses(poses: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Poses ``(N, 4, 4)`` rotated about the head centre by per-frame yaw, pitch and roll
    ``angles (N, 3)`` in degrees (:func:`adnerf.pose.perturb_pose`); float64."""
    p = torch.as_tensor(np.asarray(poses, dtype=np.float64))
    a = torch.as_tensor(np.radians(np.asarray(angles, dtype=np.float64)))
    R, t = perturb_pose(p[:, :3, :3], p[:, :3, 3], yaw=a[:, 0], pitch=a[:, 1], roll=a[:, 2])
    out = np.tile(np.eye(4), (len(poses), 1, 1))
    out[:, :3, :3], out[:, :3, 3] = R.numpy(), t.numpy()
    return out
