"""Head-pose edits for rendering: per-frame yaw / pitch / roll tracks and the range check.

``render --yaw`` (and ``--pitch``, ``--roll``) takes a number of degrees added to every frame, a
``.npy`` of one angle per frame, or ``sway:AMPLITUDE,PERIOD``: a slow idle motion (two sines of
incommensurate periods, so that it does not look mechanical) of that amplitude in degrees and
main period in seconds, kept inside the pose range the run was taught
(:class:`~adnerf.model.pose_range.PoseRange`), so that a still speaker looks alive without leaving
what the training frames showed.

The edits rotate each pose about the head centre in camera axes (:func:`adnerf.pose.perturb_pose`);
:func:`check_pose_range` then compares the edited poses with the taught range.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..model.pose_range import AXES, ROTATION_MARGIN_DEG, TRANSLATION_MARGIN, PoseRange, edit_poses  # edit_poses: re-exported

__all__ = ["AngleTrack", "PoseRangeError", "check_pose_range", "edit_poses", "keep_inside", "parse_angle", "sway"]


class PoseRangeError(ValueError):
    """Requested head poses outside the taught range, refused (``--strict-pose``)."""


@dataclass(frozen=True)
class AngleTrack:
    """An edit of one rotation axis: ``constant`` degrees, a per-frame ``file``, or a ``sway``.

    Attributes:
        spec: What the user wrote (for messages).
        constant: Degrees added to every frame (when neither ``file`` nor ``sway``).
        file: A ``.npy`` of one angle per frame, degrees.
        sway: ``(amplitude degrees, period seconds)`` of an idle motion kept inside the taught range.
    """

    spec: str
    constant: float = 0.0
    file: Path | None = None
    sway: tuple[float, float] | None = None

    def angles(self, n: int, fps: float, phase: float = 0.0) -> np.ndarray:
        """The track's ``(n,)`` degrees at ``fps`` (``phase``: radians, so that axes swaying together
        do not move in step).

        Raises:
            ValueError: A file that is not ``n`` finite angles.
        """
        if self.sway is not None:
            return sway(n, fps, *self.sway, phase=phase)
        if self.file is not None:
            try:
                a = np.load(self.file)
            except (OSError, ValueError) as exc:
                raise ValueError(f"{self.file}: not a readable .npy of angles ({exc})") from exc
            a = np.asarray(a, dtype=np.float64)
            if a.shape != (n,) or not np.isfinite(a).all():
                raise ValueError(f"{self.file}: needs {n} finite angles in degrees, one per frame; got shape {a.shape}")
            return a
        return np.full(n, float(self.constant))


def parse_angle(text: str | float) -> AngleTrack:
    """``"12.5"`` (degrees, -180..180), ``"PATH.npy"`` or ``"sway:AMPLITUDE,PERIOD"`` (degrees > 0
    and at most 30; seconds > 0).

    Raises:
        ValueError: Anything else, with what is accepted.
    """
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        text = repr(float(text))
    s = str(text).strip()
    if s.startswith("sway:"):
        try:
            amp, period = (float(v) for v in s[5:].split(","))
        except ValueError:
            raise ValueError(f"{s!r}: write sway:AMPLITUDE,PERIOD, degrees and seconds (e.g. sway:2,6)") from None
        if not (math.isfinite(amp) and 0 < amp <= 30 and math.isfinite(period) and period > 0):
            raise ValueError(f"{s!r}: the amplitude must lie in (0, 30] degrees and the period be > 0 seconds")
        return AngleTrack(s, sway=(amp, period))
    if s.endswith(".npy"):
        return AngleTrack(s, file=Path(s))
    try:
        value = float(s)
    except ValueError:
        raise ValueError(f"{s!r}: give degrees (e.g. 10), a .npy of one angle per frame, or sway:AMPLITUDE,PERIOD") from None
    if not (math.isfinite(value) and -180 <= value <= 180):
        raise ValueError(f"{s!r}: degrees must be a finite number in [-180, 180]")
    return AngleTrack(s, constant=value)


def sway(n: int, fps: float, amplitude: float, period: float, *, phase: float = 0.0) -> np.ndarray:
    """An idle head motion ``(n,)`` degrees: ``amplitude (0.7 sin(w t + phase) + 0.3 sin(2.71 w t +
    2 phase))`` with ``w = 2 pi / period``, within ``+-amplitude``, 0 at ``t = 0`` for ``phase = 0``."""
    t = np.arange(n) / fps
    w = 2.0 * math.pi / period
    return amplitude * (0.7 * np.sin(w * t + phase) + 0.3 * np.sin(2.71 * w * t + 2.0 * phase))


def keep_inside(poses: np.ndarray, angles: np.ndarray, axes: list[int], taught: PoseRange, iterations: int = 6) -> np.ndarray:
    """``angles (N, 3)`` with the columns ``axes`` reduced, frame by frame, until the edited pose's
    angle on that axis lies inside the taught range (an edit of one axis moves the others' angles
    slightly, so this iterates; a yaw edit is exactly additive)."""
    a = np.array(angles, dtype=np.float64)
    for _ in range(iterations):
        got = taught.angles(edit_poses(poses, a))
        lo, hi = taught.rotation[:, 0], taught.rotation[:, 1]
        over = np.minimum(0.0, hi - got) + np.maximum(0.0, lo - got)  # how far to move back inside
        done = True
        for k in axes:
            if np.any(over[:, k] != 0):
                done = False
                a[:, k] += over[:, k]
        if done:
            break
    return a


def check_pose_range(taught: PoseRange | None, poses: np.ndarray, *, strict: bool, margin_deg: float = ROTATION_MARGIN_DEG, margin_translation: float = TRANSLATION_MARGIN) -> str | None:
    """Compare the poses to render ``(N, 4, 4)`` with the taught range: a warning (returned and
    issued) when some lie outside by more than the margins, :class:`PoseRangeError` with
    ``strict``; ``None`` when all lie inside or the run's range is unknown."""
    if taught is None:
        return None
    problem = taught.check(poses, margin_deg=margin_deg, margin_translation=margin_translation)
    if problem is None:
        return None
    if strict:
        raise PoseRangeError(f"{problem} (--strict-pose refuses; drop it to render anyway, or keep the edits within the range)")
    warnings.warn(problem, stacklevel=2)
    return problem


def angle_tracks(tracks: dict[str, AngleTrack], poses: np.ndarray, fps: float, taught: PoseRange | None) -> np.ndarray:
    """The per-frame edits ``(N, 3)`` degrees (yaw, pitch, roll) of ``tracks`` (keyed by axis name)
    for ``poses (N, 4, 4)``; sways are kept inside ``taught`` (which a sway needs).

    Raises:
        ValueError: A sway without a taught range, or a file of the wrong length.
    """
    n = len(poses)
    angles = np.zeros((n, 3))
    swaying = []
    for k, name in enumerate(AXES):
        track = tracks.get(name)
        if track is None:
            continue
        angles[:, k] = track.angles(n, fps, phase=1.3 * k)
        if track.sway is not None:
            swaying.append(k)
    if swaying:
        if taught is None:
            raise ValueError("a sway stays inside the pose range the run was taught, and this run's is unknown (its dataset is gone); give angles instead")
        angles = keep_inside(poses, angles, swaying, taught)
    return angles
