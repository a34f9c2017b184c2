"""LPIPS (Zhang et al., CVPR 2018, version 0.1, AlexNet) from weights the user already has.

adnerf downloads nothing. LPIPS needs two sets of weights:

- the AlexNet backbone, in torchvision's layout (``features.0.weight`` ...): a path, or
  torchvision's own download if it is in the torch hub cache
  (``<torch.hub.get_dir()>/checkpoints/alexnet-owt-7be5be79.pth``);
- the five 1x1 linear layers (``lin0.model.1.weight`` ... ``lin4.model.1.weight``): a path, or the
  ``weights/v0.1/alex.pth`` file that the ``lpips`` package ships, if that package is installed
  (it is read as a file; the package itself is not imported).

:func:`find_lpips` returns ``None`` when either is missing, and the benchmark then says "no
weights". The distance: both images scaled to ``[-1, 1]`` and normalised by LPIPS's fixed shift and
scale, AlexNet's five ReLU outputs unit-normalised along channels (with LPIPS's ``1e-10`` in the
norm, to match the reference numbers), squared differences weighted by the linear layers, averaged
over space and summed over the layers.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch
from torch import Tensor, nn

__all__ = ["LPIPS", "AlexFeatures", "find_lpips", "load_lpips", "lpips_if_available"]

CHANNELS = (64, 192, 384, 256, 256)
BACKBONE_FILE = "alexnet-owt-7be5be79.pth"


class AlexFeatures(nn.Module):
    """AlexNet's convolutional part with torchvision's parameter names; returns its five ReLU outputs."""

    def __init__(self) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(),
        )  # fmt: skip

    def forward(self, x: Tensor) -> list[Tensor]:
        outs, taps = [], {1, 4, 7, 9, 11}  # the ReLUs
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in taps:
                outs.append(x)
        return outs


class LPIPS(nn.Module):
    """The LPIPS distance with an AlexNet backbone.

    Args:
        backbone: The feature extractor.
        linear: Five 1x1 weights, shapes ``(1, C_k, 1, 1)``.
    """

    shift = (-0.030, -0.088, -0.188)
    scale = (0.458, 0.448, 0.450)

    def __init__(self, backbone: AlexFeatures, linear: list[Tensor]) -> None:
        super().__init__()
        self.backbone = backbone.eval()
        for k, (w, c) in enumerate(zip(linear, CHANNELS)):
            if tuple(w.shape) != (1, c, 1, 1):
                raise ValueError(f"LPIPS linear layer {k} must have shape (1, {c}, 1, 1); got {tuple(w.shape)}")
            self.register_buffer(f"lin{k}", w.detach().clone().float())

    @torch.no_grad()
    def forward(self, a: Tensor, b: Tensor) -> Tensor:
        """Distances ``(N,)`` between images ``(N, 3, H, W)`` in ``[0, 1]`` (RGB)."""
        shift = torch.tensor(self.shift, device=a.device).view(1, 3, 1, 1)
        scale = torch.tensor(self.scale, device=a.device).view(1, 3, 1, 1)
        fa = self.backbone(((2 * a.float() - 1) - shift) / scale)
        fb = self.backbone(((2 * b.float() - 1) - shift) / scale)
        total = torch.zeros(a.shape[0], device=a.device)
        for k, (x, y) in enumerate(zip(fa, fb)):
            x = x / (x.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            y = y / (y.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + (getattr(self, f"lin{k}") * (x - y).pow(2)).sum(1).mean((1, 2))
        return total


def load_lpips(backbone_path: str | Path, linear_path: str | Path, device: str | torch.device = "cpu") -> LPIPS:
    """LPIPS from an AlexNet checkpoint (torchvision layout; other keys such as the classifier are
    ignored) and the linear layers' file (lpips layout).

    Raises:
        ValueError: A file is unreadable or lacks the expected weights.
    """
    try:
        state = torch.load(backbone_path, map_location="cpu", weights_only=True)
        lin = torch.load(linear_path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch.load raises many types on a bad file
        raise ValueError(f"LPIPS weights could not be read ({type(exc).__name__}: {exc})") from exc
    backbone = AlexFeatures()
    wanted = backbone.state_dict().keys()
    missing = [k for k in wanted if k not in state]
    if missing:
        raise ValueError(f"{backbone_path}: not an AlexNet checkpoint in torchvision's layout (missing {missing[:2]})")
    backbone.load_state_dict({k: state[k] for k in wanted})
    try:
        linear = [lin[f"lin{k}.model.1.weight"] for k in range(5)]
    except KeyError as exc:
        raise ValueError(f"{linear_path}: not LPIPS linear layers (no {exc.args[0]})") from exc
    return LPIPS(backbone, linear).to(device)


def find_lpips(backbone: str | Path | None = None, linear: str | Path | None = None) -> tuple[Path, Path] | None:
    """The LPIPS weight files to use: the given paths, else the torch hub cache's AlexNet and the
    installed ``lpips`` package's linear layers; ``None`` when either is not on this machine."""
    if backbone is None:
        cached = Path(torch.hub.get_dir()) / "checkpoints" / BACKBONE_FILE
        backbone = cached if cached.is_file() else None
    if linear is None:
        spec = importlib.util.find_spec("lpips")
        if spec is not None and spec.submodule_search_locations:
            shipped = Path(list(spec.submodule_search_locations)[0]) / "weights" / "v0.1" / "alex.pth"
            linear = shipped if shipped.is_file() else None
    if backbone is None or linear is None or not Path(backbone).is_file() or not Path(linear).is_file():
        return None
    return Path(backbone), Path(linear)


def lpips_if_available(backbone: str | Path | None = None, linear: str | Path | None = None, device: str | torch.device = "cpu") -> LPIPS | None:
    """:func:`load_lpips` of the weights :func:`find_lpips` finds, or ``None`` when they are not
    on this machine (the caller reports "no weights").

    Raises:
        ValueError: Weights were found but cannot be loaded.
    """
    found = find_lpips(backbone, linear)
    return None if found is None else load_lpips(*found, device=device)
