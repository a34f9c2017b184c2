"""What one frame's radiance layers are conditioned on.

A :class:`FrameCondition` carries a frame's signals: its audio code, its head pose, and any further
named signal (``extra``). A layer lists the signals it reads (:attr:`RadianceLayer.conditions
<adnerf.model.layers.RadianceLayer.conditions>`), and :meth:`FrameCondition.vector` concatenates them in
that order into the one conditioning vector its fields take. The head pose enters as its 9-d
continuous code (:meth:`~adnerf.pose.HeadPose.code`), the eye openness as its code
(:func:`eye_code`), every other signal as it is.

Every signal but the audio code is a registered :class:`Signal` (its name, its width in a field's
input, how a frame's value becomes that input, and for a new one where training finds each
frame's value and what a rendered frame gets without one): ``pose``, ``eye`` and ``mouth`` are
registered here. Adding a condition is one :func:`register_signal` and naming it in the model
(``model_config(meta, signals=(name,))``, stored as ``ModelConfig.head_signals``): the trainer
hands each frame its value from the dataset (the signal's ``track``), rendering its ``rest``
value; a frame carries it in ``extra``. The renderer and the compositor are not touched.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from ..fields import POSE_CODE_DIM
from ..pose import HeadPose

__all__ = [
    "EYE_FREQUENCIES", "FrameCondition", "MOUTH_FREQUENCIES", "SIGNALS", "SIGNAL_WIDTHS", "Signal", "eye_code", "mouth_code", "register_signal", "signal_width",
    "torso_rays_map",
]  # fmt: skip

EYE_FREQUENCIES = 4
MOUTH_FREQUENCIES = 3


def _as_is(value: Tensor) -> Tensor:
    return value


@dataclass(frozen=True)
class Signal:
    """A condition a layer may read, besides the audio code.

    Attributes:
        name: The name layers list it by (and a frame's ``extra`` key).
        width: Its width in a field's input.
        encode: A frame's value ``(..., k)`` -> the field's input ``(..., width)``.
        track: For a signal training reads from the dataset: the dataset
            (:class:`~adnerf.formats.dataset.TalkingHeadDataset`) -> every frame's value
            ``(N, k)``, or ``None`` where the dataset has none. ``pose``, ``eye`` and ``mouth``
            have their own sources and leave it unset.
        rest: The value ``(k,)`` of a frame rendered without one of its own (new audio); empty:
            such a frame must be given one.
    """

    name: str
    width: int
    encode: Callable[[Tensor], Tensor] = _as_is
    track: Callable[[Any], np.ndarray | None] | None = None
    rest: tuple[float, ...] = ()


SIGNALS: dict[str, Signal] = {}


def register_signal(signal: Signal) -> Signal:
    """Make ``signal`` known to layers and frames (a name registered again is replaced).

    Raises:
        ValueError: The name ``audio`` (the audio code is the model's own), or a width below 1.
    """
    if signal.name == "audio" or signal.width < 1:
        raise ValueError(f"a signal needs a name other than 'audio' and a width >= 1; got {signal.name!r}, {signal.width}")
    SIGNALS[signal.name] = signal
    return signal


class _Widths(Mapping[str, int]):
    """The registered signals' widths by name, read from :data:`SIGNALS` as it is now."""

    def __getitem__(self, name: str) -> int:
        return SIGNALS[name].width

    def __iter__(self) -> Iterator[str]:
        return iter(SIGNALS)

    def __len__(self) -> int:
        return len(SIGNALS)


# Widths of the signals other than the audio code (whose width is the model's ``audio_dim``).
SIGNAL_WIDTHS: Mapping[str, int] = _Widths()


def eye_code(openness: Tensor) -> Tensor:
    """The code ``(..., 2 * EYE_FREQUENCIES)`` a field reads for eye openness ``(..., 1)``
    (1 open, 0 closed).

    With ``c = 1 - openness`` the closure and ``k = 1 .. EYE_FREQUENCIES``: ``sin(k pi c / 2)``
    and ``1 - cos(k pi c / 2)``. All entries are 0 for open eyes, so the open eyes of most frames
    leave a field's input as it is and the weights that read the code learn the blinks alone; and
    each degree of closure moves the input in its own direction, which a small MLP needs to draw
    a lid that moves (a single number only scales one direction: on the demo scene the head then
    rendered half-closed eyes open, and closed ones only half closed).
    """
    c = 1.0 - openness
    k = torch.arange(1, EYE_FREQUENCIES + 1, dtype=openness.dtype, device=openness.device)
    angle = (0.5 * math.pi) * c * k
    return torch.cat([torch.sin(angle), 1.0 - torch.cos(angle)], dim=-1)


def mouth_code(mouth: Tensor) -> Tensor:
    """The code ``(..., 4 * MOUTH_FREQUENCIES)`` a field reads for the mouth ``(..., 2)``: its
    opening and width in standard deviations of the training frames about their mean
    (:func:`adnerf.model.mouth_target.mouth_targets`).

    Per value ``v`` and ``k = 1 .. MOUTH_FREQUENCIES``: ``sin(k pi v / 8)`` and ``1 - cos(k pi v / 8)``:
    all 0 for the mean mouth, the lowest frequency monotonic over ``+-4`` standard deviations, and
    each degree of opening a direction of its own (as :func:`eye_code` does for the lids).
    """
    k = torch.arange(1, MOUTH_FREQUENCIES + 1, dtype=mouth.dtype, device=mouth.device)
    angle = (math.pi / 8.0) * mouth[..., :, None] * k  # (..., 2, K)
    return torch.cat([torch.sin(angle), 1.0 - torch.cos(angle)], dim=-1).flatten(-2)


def torso_rays_map(maps: np.ndarray, intrinsics: Sequence[float]) -> np.ndarray:
    """The maps ``(N, 9)`` (row-major ``3 x 3``) of camera-ray directions that draw a reference
    picture moved by pixel affine maps ``(N, 2, 3)`` (``x' = A x + b``, reference pixels to the
    frame's: a dataset's ``torso.npy``) through a pinhole of ``intrinsics`` ``(fx, fy, cx, cy)``.

    The frame's pixel ``u`` shows the reference's pixel ``A^-1 (u - b)``; in normalised image
    coordinates ``n = F^-1 (u - c)`` (``F = diag(fx, fy)``) that is ``M n + m`` with
    ``M = F^-1 A^-1 F`` and ``m = F^-1 (A^-1 (c - b) - c)``, so a direction ``d = (n, 1) z`` goes
    to ``H d`` with ``H = [[M, m], [0, 0, 1]]`` (its depth ``z`` kept). The identity map gives the
    identity.
    """
    maps = np.asarray(maps, dtype=np.float64)
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    F, c = np.diag([fx, fy]), np.array([cx, cy])
    inv = np.linalg.inv(maps[:, :, :2])  # (N, 2, 2)
    H = np.zeros((len(maps), 3, 3))
    H[:, :2, :2] = np.linalg.inv(F) @ inv @ F
    H[:, :2, 2] = (inv @ (c - maps[:, :, 2])[..., None])[..., 0] - c
    H[:, :2, 2] /= np.array([fx, fy])
    H[:, 2, 2] = 1.0
    return H.reshape(len(maps), 9)


def _torso_track(ds: Any) -> np.ndarray | None:
    return None if ds.torso is None else torso_rays_map(ds.torso, ds.meta.intrinsics)


register_signal(Signal("pose", POSE_CODE_DIM))  # the head pose's continuous code (HeadPose.code)
register_signal(Signal("eye", 2 * EYE_FREQUENCIES, eye_code))  # eye openness (a dataset's eye track)
register_signal(Signal("mouth", 2 * 2 * MOUTH_FREQUENCIES, mouth_code))  # the mouth's opening and width, standardised
# The torso's motion in the image (a layer's warp, not a field input): its rays' map, identity at rest.
register_signal(Signal("torso_motion", 9, track=_torso_track, rest=(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)))


@dataclass
class FrameCondition:
    """The signals of one frame, or of each ray of a batch drawn from several frames.

    Attributes:
        audio: Audio code ``(audio_dim,)``; per ray ``(R, audio_dim)``.
        pose: The frame's head pose, one ``R (3, 3)``, ``t (3,)`` (canonical to camera); per ray
            ``R (R, 3, 3)``, ``t (R, 3)``.
        extra: Further named signals, each ``(width,)`` (``"eye"``: the openness, ``(1,)``;
            ``"mouth"``: the standardised opening and width, ``(2,)``; ``"pose"``: the 9-d code
            of the pose the layers read, where it differs from ``pose``, which moves the rays: a
            render that turns the head alone); per ray ``(R, width)``.
    """

    audio: Tensor
    pose: HeadPose
    extra: Mapping[str, Tensor] = field(default_factory=dict)

    @property
    def per_ray(self) -> bool:
        """Whether the signals are one per ray (:meth:`of_rays`) rather than one frame's."""
        return self.pose.R.dim() > 2

    @staticmethod
    def of_rays(frames: Sequence["FrameCondition"], index: Tensor) -> "FrameCondition":
        """Per-ray signals for a batch of rays of several frames: ray ``i`` gets the signals of
        ``frames[index[i]]``.

        Args:
            frames: One-frame conditions with the same signals.
            index: ``(R,)`` integer indices into ``frames``, on the signals' device.

        Raises:
            ValueError: No frames, a condition that is already per ray, or frames that carry
                different signals.
        """
        if not frames:
            raise ValueError("per-ray conditions need at least one frame's condition")
        keys = set(frames[0].extra)
        for c in frames:
            if c.per_ray:
                raise ValueError("of_rays takes one-frame conditions; got a per-ray one")
            if set(c.extra) != keys:
                raise ValueError(f"the frames carry different signals: {sorted(keys)} and {sorted(c.extra)}")

        def pick(values: list[Tensor]) -> Tensor:
            # index_select: its backward sums each frame's rays in a fixed order (indexing's adds
            # them atomically across CPU threads: gradients that differ run to run).
            return torch.stack(values).index_select(0, index)

        pose = HeadPose(pick([c.pose.R for c in frames]), pick([c.pose.t for c in frames]))
        return FrameCondition(pick([c.audio for c in frames]), pose, {k: pick([c.extra[k] for c in frames]) for k in sorted(keys)})

    def signal(self, name: str) -> Tensor:
        """One signal by name, as a field reads it: ``"audio"``; ``"pose"`` (its 9-d code, or the
        code in ``extra`` where the pose read differs from the pose that moves the head); a
        registered signal in ``extra`` through its :attr:`Signal.encode` (``"eye"``:
        :func:`eye_code`, ``"mouth"``: :func:`mouth_code`); any other key of ``extra`` as it is.

        Raises:
            KeyError: No such signal in this frame.
        """
        if name == "audio":
            return self.audio
        if name == "pose" and "pose" not in self.extra:
            return self.pose.code()
        if name in self.extra:
            return SIGNALS[name].encode(self.extra[name]) if name in SIGNALS else self.extra[name]
        raise KeyError(f"this frame has no {name!r} signal (it has audio, pose{''.join(', ' + k for k in self.extra)})")

    def vector(self, names: Sequence[str], dtype: torch.dtype) -> Tensor | None:
        """The named signals concatenated in order, as ``dtype`` (``None`` for no names)."""
        if not names:
            return None
        return torch.cat([self.signal(n).to(dtype) for n in names], dim=-1)


def signal_width(name: str, audio_dim: int) -> int:
    """The width of a signal in a model whose audio code has ``audio_dim`` entries
    (:data:`SIGNAL_WIDTHS` for the others).

    Raises:
        KeyError: An unknown signal.
    """
    if name == "audio":
        return audio_dim
    if name not in SIGNALS:
        raise KeyError(f"unknown condition signal {name!r}; known: audio, {', '.join(SIGNALS)} (register_signal adds one)")
    return SIGNALS[name].width
