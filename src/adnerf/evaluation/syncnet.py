"""SyncNet's lip-sync scores LSE-D and LSE-C, from a checkpoint the user already has.

The talking-head papers (Wav2Lip, and the NeRF heads after it) score lip sync with SyncNet
(Chung and Zisserman, ACCV 2016 workshops) in the evaluation protocol of its public release
(``syncnet_v2.model``): a face crop per frame, five frames at a time, against 0.2 s of MFCCs, and
the mean embedding distance at every audio-visual shift of up to 15 frames. adnerf downloads
nothing: :func:`load_syncnet` reads the file a user gives, and without one the scores are
reported as "no weights".

The protocol, as :func:`sync_scores` computes it:

- **Video**: 25 frames per second; each frame's face is cropped square-ish around a smoothed face
  box (:func:`face_crops`: half-size ``s``, from ``s`` above the box centre to ``1.8 s`` below it,
  ``1.4 s`` to either side, the frame padded with grey 110 where the crop leaves it), resized to
  224 x 224 and fed in BGR order with values 0..255. A window is 5 frames: ``(3, 5, 224, 224)``.
- **Audio**: 16 kHz mono on the int16 scale; 13 MFCCs per 10 ms (``python_speech_features``'
  defaults, the reference's own feature code), so a frame spans 4 MFCC columns and a window of 5
  frames spans 20: ``(1, 13, 20)``.
- **Scores**: with video embeddings ``v_i`` and audio embeddings ``a_j`` of the windows starting
  at frames ``i, j = 0 .. n - 6`` (the reference stops one window short; so do we), the distance
  curve is ``D(d) = mean_i |v_i - a_{i+d}|`` for shifts ``d = -15 .. 15``, audio embeddings
  outside the clip counting as zero vectors. **LSE-D** is the curve's minimum, **LSE-C** its
  median minus its minimum (confidence: how clearly one shift stands out), and the **offset** is
  ``-d*`` at the minimum, the reference's sign: positive when the lips move after the sound.

Where adnerf differs from the reference pipeline: the face box comes from dlib (the evaluation's
detector) rather than S3FD, and the crops are taken from frames in memory rather than from an
re-encoded video. The scores are therefore comparable in kind to published LSE figures, not
identical to the digit.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor, nn

__all__ = ["SyncNet", "SyncScores", "load_syncnet", "face_crops", "mfcc_16k", "distance_curve", "sync_scores", "CROP_SIZE", "MAX_SHIFT", "SYNCNET_FPS"]

CROP_SIZE = 224
WINDOW = 5  # video frames per window
MFCC_PER_FRAME = 4  # 10 ms MFCC hops per 40 ms frame
MAX_SHIFT = 15  # frames, either way
SYNCNET_FPS = 25.0
SAMPLE_RATE = 16000
CROP_SCALE = 0.4
PAD_VALUE = 110
_PREFIXES = ("module.", "__S__.")


def _conv_block(conv: nn.Module, norm: nn.Module, pool: nn.Module | None = None) -> list[nn.Module]:
    return [conv, norm, nn.ReLU()] + ([pool] if pool is not None else [])


class SyncNet(nn.Module):
    """The audio and lip encoders of the released SyncNet, with its parameter names.

    ``netcnnaud`` + ``netfcaud`` embed MFCC windows ``(N, 1, 13, 20)`` and ``netcnnlip`` +
    ``netfclip`` embed face windows ``(N, 3, 5, 224, 224)``, both to ``(N, embedding)``.

    Args:
        embedding: Width of the embeddings (1024 in the released model).
    """

    def __init__(self, embedding: int = 1024) -> None:
        super().__init__()
        c2, b2, p2 = nn.Conv2d, nn.BatchNorm2d, nn.MaxPool2d
        self.netcnnaud = nn.Sequential(
            *_conv_block(c2(1, 64, 3, padding=1), b2(64), p2(1, 1)),
            *_conv_block(c2(64, 192, 3, padding=1), b2(192), p2(3, (1, 2))),
            *_conv_block(c2(192, 384, 3, padding=1), b2(384)),
            *_conv_block(c2(384, 256, 3, padding=1), b2(256)),
            *_conv_block(c2(256, 256, 3, padding=1), b2(256), p2(3, 2)),
            *_conv_block(c2(256, 512, (5, 4)), b2(512)),
        )
        c3, b3, p3 = nn.Conv3d, nn.BatchNorm3d, nn.MaxPool3d
        self.netcnnlip = nn.Sequential(
            *_conv_block(c3(3, 96, (5, 7, 7), stride=(1, 2, 2)), b3(96), p3((1, 3, 3), (1, 2, 2))),
            *_conv_block(c3(96, 256, (1, 5, 5), stride=(1, 2, 2), padding=(0, 1, 1)), b3(256), p3((1, 3, 3), (1, 2, 2), padding=(0, 1, 1))),
            *_conv_block(c3(256, 256, (1, 3, 3), padding=(0, 1, 1)), b3(256)),
            *_conv_block(c3(256, 256, (1, 3, 3), padding=(0, 1, 1)), b3(256)),
            *_conv_block(c3(256, 256, (1, 3, 3), padding=(0, 1, 1)), b3(256), p3((1, 3, 3), (1, 2, 2))),
            *_conv_block(c3(256, 512, (1, 6, 6)), b3(512)),
        )
        self.netfcaud = nn.Sequential(nn.Linear(512, 512), nn.BatchNorm1d(512), nn.ReLU(), nn.Linear(512, embedding))
        self.netfclip = nn.Sequential(nn.Linear(512, 512), nn.BatchNorm1d(512), nn.ReLU(), nn.Linear(512, embedding))

    def forward_aud(self, x: Tensor) -> Tensor:
        """Embeddings ``(N, E)`` of MFCC windows ``(N, 1, 13, 20)``."""
        return self.netfcaud(self.netcnnaud(x).flatten(1))

    def forward_lip(self, x: Tensor) -> Tensor:
        """Embeddings ``(N, E)`` of face windows ``(N, 3, 5, 224, 224)`` (BGR, 0..255)."""
        return self.netfclip(self.netcnnlip(x).flatten(1))


def load_syncnet(path: str | Path, device: str | torch.device = "cpu") -> SyncNet:
    """The released SyncNet from its state dict (``syncnet_v2.model``; keys may carry a
    ``module.`` or ``__S__.`` prefix, or sit under ``"state_dict"``), in eval mode.

    Raises:
        ValueError: The file is unreadable or is not a SyncNet of this layout.
    """
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch.load raises many types on a bad file
        raise ValueError(f"{path}: SyncNet weights could not be read ({type(exc).__name__}: {exc})") from exc
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise ValueError(f"{path}: not a SyncNet state dict (a {type(state).__name__})")
    clean = {}
    for key, value in state.items():
        for prefix in _PREFIXES:
            key = key[len(prefix) :] if key.startswith(prefix) else key
        clean[key] = value
    width = clean.get("netfcaud.3.weight")
    model = SyncNet(int(width.shape[0]) if isinstance(width, Tensor) else 1024)
    wanted = model.state_dict()
    missing = [k for k in wanted if k not in clean]
    if missing:
        raise ValueError(f"{path}: not a SyncNet checkpoint of the released layout (missing {missing[:2]})")
    wrong = [k for k in wanted if tuple(clean[k].shape) != tuple(wanted[k].shape)]
    if wrong:
        raise ValueError(f"{path}: SyncNet weight {wrong[0]} has shape {tuple(clean[wrong[0]].shape)}, expected {tuple(wanted[wrong[0]].shape)}")
    model.load_state_dict({k: clean[k] for k in wanted})
    return model.eval().to(device)


def face_crops(frames: np.ndarray, boxes: np.ndarray, smooth: int = 13) -> np.ndarray:
    """SyncNet's face crops of RGB frames, in BGR as the network reads them.

    Args:
        frames: ``(N, H, W, 3)`` uint8 RGB.
        boxes: ``(N, 4)`` face boxes ``(x0, y0, x1, y1)`` in pixels.
        smooth: Median-filter length (frames, odd) for the box centre and size, as the reference
            smooths its tracks; shortened to the clip's length.

    Returns:
        ``(N, 224, 224, 3)`` uint8 BGR.
    """
    from scipy.signal import medfilt

    n = len(frames)
    if boxes.shape != (n, 4) or not np.isfinite(boxes).all():
        raise ValueError(f"face_crops needs {n} finite boxes (x0, y0, x1, y1); got shape {boxes.shape}")
    half = np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]) / 2
    cy, cx = (boxes[:, 1] + boxes[:, 3]) / 2, (boxes[:, 0] + boxes[:, 2]) / 2
    k = min(smooth, n if n % 2 else n - 1)
    if k >= 3:
        half, cy, cx = (medfilt(v, k) for v in (half, cy, cx))
    out = np.empty((n, CROP_SIZE, CROP_SIZE, 3), np.uint8)
    for i in range(n):
        s = float(half[i])
        if not s > 0:
            raise ValueError(f"face box {i} has no size")
        pad = int(s * (1 + 2 * CROP_SCALE))
        bgr = cv2.cvtColor(frames[i], cv2.COLOR_RGB2BGR)
        padded = cv2.copyMakeBorder(bgr, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=(PAD_VALUE,) * 3)
        my, mx = cy[i] + pad, cx[i] + pad
        face = padded[int(my - s) : int(my + s * (1 + 2 * CROP_SCALE)), int(mx - s * (1 + CROP_SCALE)) : int(mx + s * (1 + CROP_SCALE))]
        out[i] = cv2.resize(face, (CROP_SIZE, CROP_SIZE))
    return out


def mfcc_16k(samples: np.ndarray) -> np.ndarray:
    """13 MFCCs per 10 ms of 16 kHz mono audio in ``[-1, 1]``, on the int16 scale the reference
    reads its wav files in: ``(13, T)`` float32 (``python_speech_features.mfcc`` defaults)."""
    from python_speech_features import mfcc

    pcm = np.round(np.clip(np.asarray(samples, np.float64), -1.0, 1.0) * 32767.0)
    return np.asarray(mfcc(pcm, SAMPLE_RATE), np.float32).T


def distance_curve(video: Tensor, audio: Tensor, max_shift: int = MAX_SHIFT) -> Tensor:
    """``D(d) = mean_i |video_i - audio_{i+d}|`` for ``d = -max_shift .. max_shift``.

    Args:
        video: ``(n, E)`` embeddings of the video windows.
        audio: ``(n, E)`` embeddings of the audio windows; outside ``0 .. n - 1`` they count as
            zero vectors (the reference pads so).
        max_shift: Largest shift in frames.

    Returns:
        ``(2 max_shift + 1,)`` mean distances, index ``d + max_shift``.
    """
    n = len(video)
    padded = torch.nn.functional.pad(audio, (0, 0, max_shift, max_shift))
    shifts = torch.arange(2 * max_shift + 1, device=video.device)
    idx = torch.arange(n, device=video.device)[:, None] + shifts[None, :]  # (n, 2s+1) rows of padded
    d = torch.nn.functional.pairwise_distance(video[:, None, :].expand(-1, len(shifts), -1), padded[idx])
    return d.mean(0)


@dataclass(frozen=True)
class SyncScores:
    """SyncNet's lip-sync scores of one clip.

    Attributes:
        lse_d: Mean embedding distance at the best shift (lower is better).
        lse_c: Median minus minimum of the distance curve (higher is better).
        offset_frames: The best shift with the reference's sign (positive: lips after sound).
        curve: The distance curve, shifts ``-15 .. 15`` of audio against video.
        windows: How many 5-frame windows were scored.
    """

    lse_d: float
    lse_c: float
    offset_frames: int
    curve: tuple[float, ...]
    windows: int

    def as_dict(self) -> dict:
        """The scores as JSON-ready numbers (the curve rounded to 4 digits)."""
        return {"lse_d": self.lse_d, "lse_c": self.lse_c, "syncnet_offset_frames": self.offset_frames, "syncnet_windows": self.windows, "syncnet_curve": [round(c, 4) for c in self.curve]}


@torch.no_grad()
def sync_scores(model: nn.Module, crops: np.ndarray, samples: np.ndarray, *, max_shift: int = MAX_SHIFT, batch: int = 20) -> SyncScores:
    """LSE-D, LSE-C and the offset of face crops against their audio.

    Args:
        model: A :class:`SyncNet` (or anything with ``forward_lip`` / ``forward_aud``) in eval mode.
        crops: ``(n, 224, 224, 3)`` uint8 BGR crops (:func:`face_crops`), 25 frames per second.
        samples: 16 kHz mono audio in ``[-1, 1]`` whose sample 0 plays with crop 0.
        max_shift: Largest shift, frames.
        batch: Windows per forward pass.

    Raises:
        ValueError: Fewer than 6 frames with audio under them.
    """
    cc = torch.from_numpy(mfcc_16k(samples))
    n = min(len(crops), len(samples) // (SAMPLE_RATE // int(SYNCNET_FPS)))
    last = n - WINDOW  # window starts 0 .. last - 1, as the reference scores them
    if last < 1:
        raise ValueError(f"SyncNet needs at least {WINDOW + 1} frames with audio; got {n}")
    param = next(model.parameters())
    video = torch.from_numpy(np.ascontiguousarray(crops[:n].transpose(3, 0, 1, 2))).float()  # (3, n, H, W)
    lip, aud = [], []
    for a in range(0, last, batch):
        starts = range(a, min(last, a + batch))
        lip.append(model.forward_lip(torch.stack([video[:, s : s + WINDOW] for s in starts]).to(param)))
        aud.append(model.forward_aud(torch.stack([cc[None, :, MFCC_PER_FRAME * s : MFCC_PER_FRAME * (s + WINDOW)] for s in starts]).to(param)))
    curve = distance_curve(torch.cat(lip).double(), torch.cat(aud).double(), max_shift)
    best = int(torch.argmin(curve))
    low = float(curve[best])
    return SyncScores(lse_d=low, lse_c=float(torch.median(curve)) - low, offset_frames=max_shift - best, curve=tuple(float(c) for c in curve), windows=last)
