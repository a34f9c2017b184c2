"""The audio networks of AD-NeRF: per-frame feature windows to a 64-d audio code.

* :class:`AudioNet` encodes one window ``(16, D)`` of speech features (D = 29 DeepSpeech logits
  in the paper; 191 phoneme log-probabilities or 80 log-mel bands here) with four strided
  ``Conv1d`` (LeakyReLU 0.02) that shrink time 16 -> 8 -> 4 -> 2 -> 1, then two ``Linear`` layers,
  to a code of ``code_dim`` (64).
* :class:`AudioAttNet` smooths codes over time: a ``Conv1d`` stack scores each of 8 neighbouring
  frames' codes, a ``Linear`` + softmax turns the scores into weights that sum to 1, and the
  output is the weighted sum of the codes. AD-NeRF switches it on late in training.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["AudioAttNet", "AudioNet"]


class AudioNet(nn.Module):
    """Feature window ``(..., 16, in_dim)`` -> audio code ``(..., code_dim)``.

    Args:
        in_dim: Feature width ``D`` of the extractor.
        code_dim: Output code width (paper: 64).
        window: Features per window (16; must be a power of two >= 16 to reach length 1).
    """

    def __init__(self, in_dim: int, code_dim: int = 64, window: int = 16) -> None:
        super().__init__()
        if window != 16:
            raise ValueError("AudioNet's four stride-2 convolutions need a window of 16 features")
        self.in_dim, self.code_dim, self.window = in_dim, code_dim, window
        channels = [in_dim, 32, 32, 64, 64]
        self.convs = nn.ModuleList(nn.Conv1d(a, b, kernel_size=3, stride=2, padding=1) for a, b in zip(channels[:-1], channels[1:]))
        self.fc1 = nn.Linear(64, 64)
        self.fc2 = nn.Linear(64, code_dim)

    def forward(self, windows: Tensor) -> Tensor:
        """Encode windows ``(..., 16, in_dim)`` to codes ``(..., code_dim)``."""
        if windows.shape[-2:] != (self.window, self.in_dim):
            raise ValueError(f"AudioNet expects windows (..., {self.window}, {self.in_dim}); got {tuple(windows.shape)}")
        batch = windows.shape[:-2]
        h = windows.reshape(-1, self.window, self.in_dim).transpose(1, 2)  # (B, D, 16)
        for conv in self.convs:
            h = F.leaky_relu(conv(h), 0.02)
        h = F.leaky_relu(self.fc1(h[..., 0]), 0.02)
        return self.fc2(h).reshape(*batch, self.code_dim)


class AudioAttNet(nn.Module):
    """Temporal filter over neighbouring audio codes ``(..., seq_len, code_dim)`` -> ``(..., code_dim)``.

    Args:
        code_dim: Code width.
        seq_len: Number of neighbouring frames (paper: 8); the frame itself is at position
            ``seq_len // 2``.
        centre_logit: Added to the initial score of the frame itself. 0 is the paper's
            initialisation, whose weights start near uniform: switched on mid-training, it
            replaces the code the field has learned to read by an 8-frame average. A positive
            value starts the filter close to the identity (4: about 0.86 on the frame itself)
            and lets it learn how much to smooth.
    """

    def __init__(self, code_dim: int = 64, seq_len: int = 8, centre_logit: float = 0.0) -> None:
        super().__init__()
        self.code_dim, self.seq_len = code_dim, seq_len
        channels = [code_dim, 16, 8, 4, 2, 1]
        self.convs = nn.ModuleList(nn.Conv1d(a, b, kernel_size=3, stride=1, padding=1) for a, b in zip(channels[:-1], channels[1:]))
        self.score = nn.Linear(seq_len, seq_len)
        with torch.no_grad():
            self.score.bias[seq_len // 2] += centre_logit

    def weights(self, codes: Tensor) -> Tensor:
        """Attention weights ``(..., seq_len)`` (non-negative, summing to 1)."""
        if codes.shape[-2:] != (self.seq_len, self.code_dim):
            raise ValueError(f"AudioAttNet expects codes (..., {self.seq_len}, {self.code_dim}); got {tuple(codes.shape)}")
        batch = codes.shape[:-2]
        h = codes.reshape(-1, self.seq_len, self.code_dim).transpose(1, 2)  # (B, C, L)
        for conv in self.convs:
            h = F.leaky_relu(conv(h), 0.02)
        return torch.softmax(self.score(h[:, 0]), dim=-1).reshape(*batch, self.seq_len)

    def forward(self, codes: Tensor) -> Tensor:
        """The attention-weighted sum of the codes, ``(..., code_dim)``."""
        return (self.weights(codes)[..., None] * codes).sum(dim=-2)
