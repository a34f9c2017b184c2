"""BiSeNet face parsing (CelebAMask-HQ, 19 classes) from a user-supplied checkpoint.

The network is the ResNet-18 BiSeNet of the widely used ``face-parsing.PyTorch`` project, which
AD-NeRF's preprocessing runs (its ``79999_iter.pth``). Module names match that checkpoint's
``state_dict`` keys, so such a file loads as it is; adnerf never downloads it.

Classes (CelebAMask-HQ order) and what they become here:

====  ==========================================================================  ==========
0     background                                                                  background
1-13  skin, brows, eyes, glasses, ears, earring, nose, mouth, lips                head
14    neck                                                                        torso
15    necklace                                                                    torso
16    cloth                                                                       torso
17    hair                                                                        head
18    hat                                                                         head
====  ==========================================================================  ==========

Frames are resized to ``size`` x ``size`` (512, as the network was trained), normalised with the
ImageNet mean and std, and the argmax of the main output is resized back with nearest neighbours.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..formats.dataset import LABEL_HEAD, LABEL_TORSO

__all__ = ["BiSeNet", "BiSeNetParser", "CELEBAMASK_TO_LABEL", "N_CLASSES", "load_bisenet"]

N_CLASSES = 19
#: Our label (0 background, 1 head, 2 torso) of each CelebAMask-HQ class.
CELEBAMASK_TO_LABEL = np.array([0] + [LABEL_HEAD] * 13 + [LABEL_TORSO] * 3 + [LABEL_HEAD] * 2, dtype=np.uint8)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class ConvBNReLU(nn.Module):
    """Convolution without bias, batch norm, ReLU."""

    def __init__(self, cin: int, cout: int, kernel: int = 3, stride: int = 1) -> None:
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, kernel, stride, kernel // 2, bias=False)
        self.bn = nn.BatchNorm2d(cout)

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.bn(self.conv(x)))


class BasicBlock(nn.Module):
    """ResNet basic block (two 3x3 convolutions and a shortcut)."""

    def __init__(self, cin: int, cout: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout)) if stride != 1 or cin != cout else None

    def forward(self, x: Tensor) -> Tensor:
        y = self.bn2(self.conv2(F.relu(self.bn1(self.conv1(x)))))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


class ResNet18(nn.Module):
    """ResNet-18 trunk returning the features at strides 8, 16 and 32 (128, 256, 512 channels)."""

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        widths = (64, 128, 256, 512)
        for i, cout in enumerate(widths):
            cin = widths[max(i - 1, 0)]
            stride = 1 if i == 0 else 2
            setattr(self, f"layer{i + 1}", nn.Sequential(BasicBlock(cin, cout, stride), BasicBlock(cout, cout, 1)))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        x = self.maxpool(F.relu(self.bn1(self.conv1(x))))
        f8 = self.layer2(self.layer1(x))
        f16 = self.layer3(f8)
        return f8, f16, self.layer4(f16)


class AttentionRefinement(nn.Module):
    """Features re-weighted per channel by their global average (sigmoid gate)."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.conv = ConvBNReLU(cin, cout)
        self.conv_atten = nn.Conv2d(cout, cout, 1, bias=False)
        self.bn_atten = nn.BatchNorm2d(cout)

    def forward(self, x: Tensor) -> Tensor:
        feat = self.conv(x)
        gate = torch.sigmoid(self.bn_atten(self.conv_atten(F.adaptive_avg_pool2d(feat, 1))))
        return feat * gate


class ContextPath(nn.Module):
    """ResNet-18 with attention refinement at strides 16 and 32 and a global context term."""

    def __init__(self) -> None:
        super().__init__()
        self.resnet = ResNet18()
        self.arm16 = AttentionRefinement(256, 128)
        self.arm32 = AttentionRefinement(512, 128)
        self.conv_head32 = ConvBNReLU(128, 128)
        self.conv_head16 = ConvBNReLU(128, 128)
        self.conv_avg = ConvBNReLU(512, 128, kernel=1)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        f8, f16, f32 = self.resnet(x)
        context = self.conv_avg(F.adaptive_avg_pool2d(f32, 1))
        up32 = self.conv_head32(F.interpolate(self.arm32(f32) + context, size=f16.shape[2:], mode="nearest"))
        up16 = self.conv_head16(F.interpolate(self.arm16(f16) + up32, size=f8.shape[2:], mode="nearest"))
        return f8, up16, up32


class FeatureFusion(nn.Module):
    """Concatenation, a 1x1 convolution, and a squeeze-excitation residual."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.convblk = ConvBNReLU(cin, cout, kernel=1)
        self.conv1 = nn.Conv2d(cout, cout // 4, 1, bias=False)
        self.conv2 = nn.Conv2d(cout // 4, cout, 1, bias=False)

    def forward(self, spatial: Tensor, context: Tensor) -> Tensor:
        feat = self.convblk(torch.cat([spatial, context], dim=1))
        gate = torch.sigmoid(self.conv2(F.relu(self.conv1(F.adaptive_avg_pool2d(feat, 1)))))
        return feat + feat * gate


class Head(nn.Module):
    """3x3 ConvBNReLU then a 1x1 class projection."""

    def __init__(self, cin: int, mid: int, n_classes: int) -> None:
        super().__init__()
        self.conv = ConvBNReLU(cin, mid)
        self.conv_out = nn.Conv2d(mid, n_classes, 1, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv_out(self.conv(x))


class BiSeNet(nn.Module):
    """BiSeNet with the stride-8 ResNet features as its spatial path.

    ``forward`` returns the main class logits ``(B, n_classes, H, W)`` at the input size (the two
    auxiliary heads of training are kept so that checkpoints load, and are not evaluated).
    """

    def __init__(self, n_classes: int = N_CLASSES) -> None:
        super().__init__()
        self.cp = ContextPath()
        self.ffm = FeatureFusion(256, 256)
        self.conv_out = Head(256, 256, n_classes)
        self.conv_out16 = Head(128, 64, n_classes)
        self.conv_out32 = Head(128, 64, n_classes)

    def forward(self, x: Tensor) -> Tensor:
        f8, up16, _ = self.cp(x)
        logits = self.conv_out(self.ffm(f8, up16))
        return F.interpolate(logits, size=x.shape[2:], mode="bilinear", align_corners=True)


def load_bisenet(path: str | Path, device: str | torch.device = "cpu") -> BiSeNet:
    """Load a 19-class BiSeNet checkpoint (a ``state_dict``, possibly under ``"state_dict"`` or with
    ``module.`` prefixes from ``DataParallel``).

    Raises:
        ValueError: Missing file, or keys or shapes that are not this network's (named).
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: no BiSeNet checkpoint there (give a face-parsing.PyTorch 19-class file, e.g. 79999_iter.pth)")
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for foreign files
        raise ValueError(f"{p}: not a readable PyTorch checkpoint ({exc})") from exc
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise ValueError(f"{p}: expected a state_dict; got {type(state).__name__}")
    state = {k.removeprefix("module."): v for k, v in state.items()}
    net = BiSeNet(N_CLASSES)
    own = net.state_dict()
    missing = sorted(k for k in set(own) - set(state) if not k.endswith("num_batches_tracked"))
    unexpected = sorted(set(state) - set(own))
    wrong = sorted(k for k in set(own) & set(state) if tuple(own[k].shape) != tuple(state[k].shape))
    if missing or unexpected or wrong:
        raise ValueError(
            f"{p}: not a 19-class face-parsing BiSeNet checkpoint: {len(missing)} missing keys {missing[:3]}, "
            f"{len(unexpected)} unexpected {unexpected[:3]}, {len(wrong)} of another shape {wrong[:3]}"
        )
    net.load_state_dict(state, strict=False)  # only batch-norm step counters may be absent (checked above)
    return net.to(device).eval()


class BiSeNetParser:
    """The :class:`~adnerf.preprocess.parsing.Parser` backend running :class:`BiSeNet`.

    Args:
        checkpoint: Path of the user's checkpoint.
        device: ``"cpu"`` or ``"cuda"``.
        size: Square input side the frames are resized to (512: the training size).
        batch: Frames per forward pass.
    """

    def __init__(self, checkpoint: str | Path, device: str | torch.device = "cpu", size: int = 512, batch: int = 4) -> None:
        if size < 32 or batch < 1:
            raise ValueError("BiSeNet input size must be >= 32 and batch >= 1")
        self.name = f"bisenet:{checkpoint}"
        self.cuts_at_jaw = True  # its skin / neck classes meet at the jaw
        self.finds_clothes = True  # it has a cloth class
        self.net = load_bisenet(checkpoint, device)
        self.device, self.size, self.batch = torch.device(device), size, batch

    def classes(self, frames: np.ndarray) -> np.ndarray:
        """CelebAMask-HQ classes ``(N, size, size)`` int64 of RGB uint8 frames ``(N, H, W, 3)``."""
        x = torch.as_tensor(np.stack([cv2.resize(f, (self.size, self.size), interpolation=cv2.INTER_LINEAR) for f in frames]))
        x = x.to(self.device).permute(0, 3, 1, 2).float() / 255.0
        mean = torch.tensor(IMAGENET_MEAN, device=self.device).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD, device=self.device).view(1, 3, 1, 1)
        with torch.inference_mode():
            return self.net((x - mean) / std).argmax(1).cpu().numpy()

    def parse(self, frames: np.ndarray, progress: Callable[[int, int], None] | None = None) -> np.ndarray:
        """Label maps ``(N, H, W)`` uint8 in {0, 1, 2} of RGB frames ``(N, H, W, 3)`` uint8."""
        n, h, w, _ = frames.shape
        out = np.empty((n, h, w), np.uint8)
        for start in range(0, n, self.batch):
            cls = self.classes(frames[start : start + self.batch])
            for k, c in enumerate(cls):
                out[start + k] = cv2.resize(CELEBAMASK_TO_LABEL[c], (w, h), interpolation=cv2.INTER_NEAREST)
            if progress is not None:
                progress(min(start + self.batch, n), n)
        return out
