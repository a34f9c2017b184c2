"""What one frame's radiance layers are conditioned on.

A :class:`FrameCondition` carries a frame's signals: its audio code, its head pose, and any further
named signal (``extra``). A layer lists the signals it reads (:attr:`RadianceLayer.conditions
<adnerf.layers.RadianceLayer.conditions>`), and :meth:`FrameCondition.vector` concatenates them in
that order into the one conditioning vector its fields take. The head pose enters as its 9-d
continuous code (:meth:`~adnerf.pose.HeadPose.code`); every other signal as it is.

Adding a condition is adding a signal here (or passing it in ``extra``) and naming it in the layers
that read it; the renderer, the compositor and the training loop are not touched.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import torch
from torch import Tensor

from .fields import POSE_CODE_DIM
from .pose import HeadPose

__all__ = ["FrameCondition", "SIGNAL_WIDTHS", "signal_width"]

# Widths of the signals other than the audio code (whose width is the model's ``audio_dim``).
SIGNAL_WIDTHS = {
    "pose": POSE_CODE_DIM,  # the head pose's continuous code
    "eye": 1,  # eye openness: 1 open as usual, 0 closed (a dataset's eye.npy)
}



@dataclass
class FrameCondition:
    """The signals of one frame.

    Attributes:
        audio: Audio code ``(audio_dim,)``.
        pose: The frame's head pose, one ``R (3, 3)``, ``t (3,)`` (canonical to camera).
        extra: Further named signals, each ``(width,)``.
    """

    audio: Tensor
    pose: HeadPose
    extra: Mapping[str, Tensor] = field(default_factory=dict)

    def signal(self, name: str) -> Tensor:
        """One signal by name: ``"audio"``, ``"pose"`` (its 9-d code) or a key of ``extra``.

        Raises:
            KeyError: No such signal in this frame.
        """
        if name == "audio":
            return self.audio
        if name == "pose":
            return self.pose.code()
        if name in self.extra:
            return self.extra[name]
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
    if name not in SIGNAL_WIDTHS:
        raise KeyError(f"unknown condition signal {name!r}; known: audio, {', '.join(SIGNAL_WIDTHS)}")
    return SIGNAL_WIDTHS[name]
