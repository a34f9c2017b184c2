"""The talking-head model: audio encoders, head and torso fields, and how a frame is put together.

A frame is composed as in AD-NeRF: the head field (canonical space, warped by the head pose,
conditioned on the audio code) is rendered over the background plate; the torso field (camera
space, conditioned on the audio code and the head pose) is rendered over that result::

    head_on_plate = head.rgb + (1 - head.opacity) * plate
    frame         = torso.rgb + (1 - torso.opacity) * head_on_plate

Rays are sampled only inside the head box (moved with the head pose) and the torso box; rays that
miss a box get that layer's opacity 0 without evaluating anything.
"""

from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass
from typing import Callable, Literal

import torch
from torch import Tensor, nn

from .audio import AudioAttNet, AudioNet
from .cameras import Camera
from .compositor import Composite
from .data import SceneMeta
from .fields import POSE_CODE_DIM, FieldConfig, check_config_keys, HeadField, TorsoField, fast_config, paper_config
from .occupancy import OccupancyGrid
from .pose import HeadPose
from .rays import RayBundle
from .renderer import RenderOutput, VolumeRenderer
from .samplers import AABBBounds, Bounds, PosedAABBBounds

__all__ = [
    "FrameRender",
    "ModelConfig",
    "TalkingHead",
    "layer_bounds",
    "layer_occupancy",
    "mixed_precision",
    "model_config",
    "render_frame",
    "render_chunk",
    "render_part",
    "update_occupancy",
]

Part = Literal["head", "torso"]
AMP_MODES = ("auto", "bf16", "off")


def mixed_precision(device: torch.device | str, mode: str = "auto") -> contextlib.AbstractContextManager:
    """The autocast context for field evaluation.

    ``"auto"``: bfloat16 autocast on CUDA, nothing on CPU (where bfloat16 matrix products are
    rarely faster); ``"bf16"``: bfloat16 autocast on any device; ``"off"``: full precision.
    Geometry stays float64 (autocast never touches float64 tensors) and the renderer hands the
    field's half-precision outputs to the compositor in float32 (see
    :func:`~adnerf.renderer.evaluate_field`), so transmittance is never accumulated in bfloat16.
    """
    if mode not in AMP_MODES:
        raise ValueError(f"amp must be one of {AMP_MODES}; got {mode!r}")
    device_type = torch.device(device).type
    if mode == "off" or (mode == "auto" and device_type != "cuda"):
        return contextlib.nullcontext()
    return torch.autocast(device_type=device_type, dtype=torch.bfloat16)


@dataclass
class ModelConfig:
    """Architecture and sampling of a :class:`TalkingHead`.

    Attributes:
        feature_dim: Audio feature width ``D``.
        head: Coarse head field.
        head_fine: Fine head field.
        torso: Coarse torso field (``cond_dim = audio_dim + 9``).
        torso_fine: Fine torso field.
        head_aabb: Head box, canonical space.
        torso_aabb: Torso box, camera space.
        audio_dim: Audio code width (paper: 64).
        att_len: Frames the audio attention looks at (paper: 8).
        att_centre_logit: Initial extra score of the frame itself in AudioAttNet (0: the
            paper's near-uniform start; see :class:`~adnerf.audio.AudioAttNet`). Measured on the
            demo scene's held-out head rays: with 0, switching the filter on at 60% of training
            dropped the PSNR from 32.3 to 29.5 dB for good; with 4 it rose to 34.1 dB.
        head_samples: ``(coarse, fine)`` samples per ray for the head.
        torso_samples: ``(coarse, fine)`` samples per ray for the torso.
        occupancy_resolution: Cells per axis of each layer's occupancy grid (head: canonical
            space, torso: camera space); 0 turns empty-space skipping off.
        occupancy_threshold: Density (1 / scene unit) below which a cell is empty. At the
            default 0.01 a skipped sample of length 0.15 would have had opacity < 0.0015.
    """

    feature_dim: int
    head: FieldConfig
    head_fine: FieldConfig
    torso: FieldConfig
    torso_fine: FieldConfig
    head_aabb: tuple[tuple[float, float, float], tuple[float, float, float]]
    torso_aabb: tuple[tuple[float, float, float], tuple[float, float, float]]
    audio_dim: int = 64
    att_len: int = 8
    att_centre_logit: float = 4.0
    head_samples: tuple[int, int] = (16, 16)
    torso_samples: tuple[int, int] = (16, 16)
    occupancy_resolution: int = 32
    occupancy_threshold: float = 0.01

    def to_dict(self) -> dict:
        """JSON-serialisable form."""
        d = asdict(self)
        for key in ("head", "head_fine", "torso", "torso_fine"):
            d[key] = getattr(self, key).to_dict()
        return d

    @staticmethod
    def from_dict(d: dict) -> "ModelConfig":
        """Inverse of :meth:`to_dict` (unknown keys are an error)."""
        check_config_keys(d, ModelConfig, "model config")
        d = dict(d)
        for key in ("head", "head_fine", "torso", "torso_fine"):
            d[key] = FieldConfig.from_dict(d[key])
        for key in ("head_aabb", "torso_aabb"):
            d[key] = tuple(tuple(v) for v in d[key])
        for key in ("head_samples", "torso_samples"):
            if key in d:
                d[key] = tuple(d[key])
        return ModelConfig(**d)


def model_config(meta: SceneMeta, preset: Literal["fast", "paper"] = "fast", audio_dim: int = 64) -> ModelConfig:
    """The model for a dataset.

    ``"fast"``: tri-plane grids with small MLPs (the default; what trains on a CPU in minutes).
    ``"paper"``: AD-NeRF's 8x256 positional-encoding MLPs with 64 + 128 samples per ray.
    """
    torso_cond = audio_dim + POSE_CODE_DIM
    if preset == "paper":
        return ModelConfig(
            feature_dim=meta.feature_dim,
            head=paper_config(audio_dim),
            head_fine=paper_config(audio_dim),
            torso=paper_config(torso_cond),
            torso_fine=paper_config(torso_cond),
            head_aabb=meta.head_aabb,
            torso_aabb=meta.torso_aabb,
            audio_dim=audio_dim,
            head_samples=(64, 128),
            torso_samples=(64, 128),
        )
    if preset != "fast":
        raise ValueError(f"unknown model preset {preset!r}; choose fast or paper")
    head = fast_config(audio_dim, *meta.head_aabb)
    head_coarse = FieldConfig.from_dict({**head.to_dict(), "grid_max_resolution": 64, "width": 32})
    head_fine = FieldConfig.from_dict({**head.to_dict(), "grid_max_resolution": 256, "grid_levels": 4})
    torso = fast_config(torso_cond, *meta.torso_aabb)
    torso_coarse = FieldConfig.from_dict({**torso.to_dict(), "grid_max_resolution": 64, "width": 32})
    # A 128 rather than 256 finest torso grid: held-out torso 24.1 -> 24.8 dB after 4500 iterations
    # on the demo scene at the same speed (512: 23.1 dB at 2500 iterations, 40% slower).
    torso_fine = FieldConfig.from_dict({**torso.to_dict(), "grid_max_resolution": 128})
    return ModelConfig(
        feature_dim=meta.feature_dim,
        head=head_coarse,
        head_fine=head_fine,
        torso=torso_coarse,
        torso_fine=torso_fine,
        head_aabb=meta.head_aabb,
        torso_aabb=meta.torso_aabb,
        audio_dim=audio_dim,
    )


class TalkingHead(nn.Module):
    """Audio encoders plus coarse/fine head and torso fields.

    Args:
        config: The architecture.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.audio_net = AudioNet(config.feature_dim, config.audio_dim)
        self.att_net = AudioAttNet(config.audio_dim, config.att_len, config.att_centre_logit)
        self.head = HeadField(config.head)
        self.head_fine = HeadField(config.head_fine)
        self.torso = TorsoField(config.torso, config.audio_dim)
        self.torso_fine = TorsoField(config.torso_fine, config.audio_dim)
        # Per-feature standardisation of the audio windows, fitted on the training frames.
        self.register_buffer("feature_mean", torch.zeros(config.feature_dim))
        self.register_buffer("feature_std", torch.ones(config.feature_dim))
        # Empty-space skipping: until its first update a grid is "all occupied" and not used.
        self.head_occupancy: OccupancyGrid | None = None
        self.torso_occupancy: OccupancyGrid | None = None
        if config.occupancy_resolution > 0:
            res, thr = config.occupancy_resolution, config.occupancy_threshold
            self.head_occupancy = OccupancyGrid(*config.head_aabb, resolution=res, threshold=thr)
            self.torso_occupancy = OccupancyGrid(*config.torso_aabb, resolution=res, threshold=thr)

    def fit_feature_scale(self, windows: Tensor) -> None:
        """Set the standardisation from training windows ``(N, 16, D)`` (a zero std is left at 1)."""
        flat = windows.reshape(-1, windows.shape[-1]).to(self.feature_mean)
        self.feature_mean.copy_(flat.mean(dim=0))
        std = flat.std(dim=0)
        self.feature_std.copy_(torch.where(std > 0, std, torch.ones_like(std)))

    def audio_codes(self, windows: Tensor) -> Tensor:
        """Per-frame codes ``(N, audio_dim)`` from feature windows ``(N, 16, D)``."""
        x = (windows.to(self.feature_mean) - self.feature_mean) / self.feature_std
        return self.audio_net(x)

    def neighbours(self, index: int, n: int, device: torch.device | str | None = None) -> Tensor:
        """The ``att_len`` frame indices around ``index`` that AudioAttNet filters, clamped to ``[0, n)``.

        ``index`` itself is at position ``att_len // 2``, where AudioAttNet puts its centre.
        """
        half = self.config.att_len // 2
        return torch.arange(index - half, index - half + self.config.att_len, device=device).clamp(0, n - 1)

    def smoothed_code(self, codes: Tensor, index: int) -> Tensor:
        """AudioAttNet over the ``att_len`` codes around frame ``index`` (clamped at the ends)."""
        return self.att_net(codes[self.neighbours(index, codes.shape[0], codes.device)])

    def frame_code(self, windows: Tensor, index: int, smooth: bool) -> Tensor:
        """The audio code ``(audio_dim,)`` of frame ``index`` from all windows ``(N, 16, D)``.

        With ``smooth``, only the ``att_len`` neighbouring windows are encoded and filtered.
        """
        if not smooth:
            return self.audio_codes(windows[index : index + 1])[0]
        return self.att_net(self.audio_codes(windows[self.neighbours(index, windows.shape[0], windows.device)]))

    def all_codes(self, windows: Tensor, smooth: bool, batch: int = 512) -> Tensor:
        """Codes ``(N, audio_dim)`` of every frame (smoothed with AudioAttNet when ``smooth``)."""
        raw = torch.cat([self.audio_codes(windows[i : i + batch]) for i in range(0, windows.shape[0], batch)])
        if not smooth:
            return raw
        return torch.stack([self.smoothed_code(raw, i) for i in range(raw.shape[0])])


def _box(aabb: tuple[tuple[float, ...], tuple[float, ...]], like: Tensor) -> tuple[Tensor, Tensor]:
    return torch.tensor(aabb[0], dtype=like.dtype, device=like.device), torch.tensor(aabb[1], dtype=like.dtype, device=like.device)


def head_bounds(config: ModelConfig, pose: HeadPose) -> PosedAABBBounds:
    """Per-ray bounds of the head box moved by ``pose``."""
    lo, hi = _box(config.head_aabb, pose.R)
    return PosedAABBBounds(lo, hi, pose.R, pose.t)


def torso_bounds(config: ModelConfig, like: Tensor) -> AABBBounds:
    """Per-ray bounds of the torso box (camera space)."""
    lo, hi = _box(config.torso_aabb, like)
    return AABBBounds(lo, hi)


def layer_bounds(model: TalkingHead, part: Part, pose: HeadPose) -> Bounds:
    """The sampling bounds of a layer: the head box moved by ``pose``, or the torso box."""
    if part == "head":
        return head_bounds(model.config, pose)
    if part == "torso":
        return torso_bounds(model.config, pose.t)
    raise ValueError(f"part must be head or torso; got {part!r}")


def _layer_fields(model: TalkingHead, part: Part) -> tuple[nn.Module, nn.Module]:
    """The coarse and fine fields of a layer."""
    if part == "head":
        return model.head, model.head_fine
    if part == "torso":
        return model.torso, model.torso_fine
    raise ValueError(f"part must be head or torso; got {part!r}")


def _layer_grid(model: TalkingHead, part: Part) -> OccupancyGrid | None:
    """The occupancy grid of a layer (``None`` when the model has none)."""
    return model.head_occupancy if part == "head" else model.torso_occupancy


def layer_occupancy(model: TalkingHead, part: Part, pose: HeadPose) -> Callable[[Tensor], Tensor] | None:
    """The empty-space predicate of a layer on camera-space points ``(..., 3) -> bool (...)``.

    ``None`` (evaluate every sample) when the model has no grids or the layer's grid has not been
    estimated yet. The head's grid lives in canonical space, so points are moved by ``pose``
    first; the torso's lives in camera space.
    """
    grid = _layer_grid(model, part)
    if grid is None or not grid.estimated:
        return None
    if part == "head":
        return lambda points: grid.is_occupied(pose.to_canonical(points.to(pose.R)))
    return grid.is_occupied


@torch.no_grad()
def update_occupancy(
    model: TalkingHead,
    part: Part,
    pose: HeadPose,
    code: Tensor,
    *,
    decay: float = 0.7,
    dilation: int = 1,
    generator: torch.Generator | None = None,
) -> float:
    """Re-estimate a layer's occupancy grid from its coarse and fine fields under one frame's condition.

    Each cell keeps ``max(decay * old, density)``, the density being the larger of the two
    fields' at a random point of the cell, so over many frames the grid holds the union of what
    the conditions (mouth shapes, poses) occupy; the occupied region is then grown by
    ``dilation`` cells, a margin for how the field changes until the next update.

    Args:
        model: The model (it must have grids).
        part: ``"head"`` (canonical points, conditioned on ``code``) or ``"torso"`` (camera
            points, conditioned on ``code`` and ``pose``).
        pose: The frame's head pose.
        code: The frame's audio code ``(audio_dim,)``.
        decay: Weight of the previous estimate, in ``[0, 1]``.
        dilation: Cells of margin.
        generator: Random generator of the points in the cells.

    Returns:
        The occupied fraction of the cells (after dilation).
    """
    grid = _layer_grid(model, part)
    if grid is None:
        raise ValueError("this model has no occupancy grids (occupancy_resolution = 0)")
    coarse, fine = _layer_fields(model, part)
    # The head's grid is canonical: its fields are evaluated with the identity pose there.
    at = HeadPose.identity(dtype=pose.R.dtype, device=pose.R.device) if part == "head" else pose

    def density(points: Tensor) -> Tensor:
        dirs = torch.zeros_like(points)
        dirs[:, 2] = 1.0  # density does not depend on the view direction; paper fields want one
        return torch.maximum(coarse(points, dirs, pose=at, audio=code).density, fine(points, dirs, pose=at, audio=code).density)

    grid.update(density, decay=decay, generator=generator)
    grid.dilate(dilation)
    return grid.occupied.float().mean().item()


def _layer_renderer(model: TalkingHead, part: Part, pose: HeadPose) -> tuple[VolumeRenderer, nn.Module, nn.Module]:
    """The renderer (bounds and sample counts) and the coarse and fine fields of a layer."""
    samples = model.config.head_samples if part == "head" else model.config.torso_samples
    return VolumeRenderer(layer_bounds(model, part, pose), *samples), *_layer_fields(model, part)


def render_part(
    model: TalkingHead,
    part: Part,
    rays: RayBundle,
    pose: HeadPose,
    code: Tensor,
    *,
    background: Tensor | None = None,
    jitter: bool = False,
    generator: torch.Generator | None = None,
) -> RenderOutput:
    """Render the head or the torso layer along rays ``(R,)`` for one frame.

    Args:
        model: The model.
        part: ``"head"`` (canonical space, warped by ``pose``) or ``"torso"`` (camera space,
            ``pose`` as input).
        rays: Camera-space rays ``(R,)``.
        pose: The frame's head pose.
        code: The frame's audio code ``(audio_dim,)``.
        background: Colour behind the layer ``(R, 3)``; ``None`` gives premultiplied colour.
        jitter: Random samples (training).
        generator: Random generator for the samples.
    """
    renderer, coarse, fine = _layer_renderer(model, part, pose)
    occupancy = layer_occupancy(model, part, pose)
    return renderer.render_rays(
        rays, coarse, fine, background=background, occupancy=occupancy, jitter=jitter, generator=generator, pose=pose, audio=code
    )


@dataclass
class FrameRender:
    """One rendered frame.

    Attributes:
        rgb: Final colour ``(H, W, 3)`` in ``[0, 1]``.
        head_opacity: Head opacity ``(H, W)``.
        torso_opacity: Torso opacity ``(H, W)``.
        head_on_plate: The head rendered over the plate ``(H, W, 3)`` (the torso's background).
        head_depth: Head depth along the unit pixel ray ``(H, W)`` (far bound where opacity 0).
    """

    rgb: Tensor
    head_opacity: Tensor
    torso_opacity: Tensor
    head_on_plate: Tensor
    head_depth: Tensor


def render_chunk(device: torch.device | str) -> int:
    """Rays per batch for whole-frame renders: 1024 on the CPU (what every CPU figure was measured
    with); 262144 on a GPU, a whole 450x450 frame per layer in one batch. Measured on an H100 at
    450x450, head and torso (``docs/bench/gpu.json``): 0.8 frames/s with 1024, 19-22 with 65536,
    32 with 262144, at 1.7 GB."""
    return 1024 if torch.device(device).type == "cpu" else 262144


def _render_hits(model: TalkingHead, part: Part, rays: RayBundle, pose: HeadPose, code: Tensor, chunk: int | None) -> tuple[Tensor, Composite | None]:
    """Render a layer along only the rays ``(R,)`` that cross its box; returns their mask and composite."""
    renderer, coarse, fine = _layer_renderer(model, part, pose)
    near, far = renderer.coarse_sampler.bounds(rays)
    hit = far > near
    if not bool(hit.any()):
        return hit, None
    occupancy = layer_occupancy(model, part, pose)
    chunk = chunk or render_chunk(rays.origins.device)
    return hit, renderer.render_chunked(rays[hit], coarse, fine, chunk=chunk, occupancy=occupancy, pose=pose, audio=code).final


@torch.no_grad()
def render_head_on_plate(
    model: TalkingHead,
    rays: RayBundle,
    pose: HeadPose,
    code: Tensor,
    plate: Tensor,
    *,
    chunk: int | None = None,
    amp: str = "auto",
) -> Tensor:
    """The head layer over the plate along some rays (no gradients): ``head + (1 - a_head) plate``.

    The same values as :func:`render_frame`'s ``head_on_plate`` at those pixels, for callers that
    need only part of a frame (stage 2 needs the head only where torso rays are drawn).

    Args:
        model: The trained model.
        rays: Camera rays ``(R,)``.
        pose: The frame's head pose.
        code: The frame's audio code ``(audio_dim,)``.
        plate: Plate colours of those pixels ``(R, 3)`` in ``[0, 1]``.
        chunk: Rays per batch (default :func:`render_chunk` of the device).
        amp: Mixed precision of the fields (see :func:`mixed_precision`).

    Returns:
        ``(R, 3)`` float32 colours.
    """
    out = plate.to(torch.float32).clone()
    with mixed_precision(out.device, amp):
        hit, comp = _render_hits(model, "head", rays, pose, code, chunk)
    if comp is not None:
        out[hit] = comp.rgb.to(out) + (1 - comp.opacity.to(out))[:, None] * out[hit]
    return out


@torch.no_grad()
def render_frame(
    model: TalkingHead,
    camera: Camera,
    pose: HeadPose,
    code: Tensor,
    plate: Tensor,
    *,
    torso: bool = True,
    chunk: int | None = None,
    amp: str = "auto",
) -> FrameRender:
    """Render a full frame (no gradients).

    Args:
        model: The trained model.
        camera: The static camera.
        pose: The frame's head pose (single ``R (3, 3)``, ``t (3,)``).
        code: The frame's audio code ``(audio_dim,)``.
        plate: Background ``(H, W, 3)`` in ``[0, 1]``.
        torso: Also render the torso layer (off: the head-only stage-1 picture).
        chunk: Rays per batch (default :func:`render_chunk` of the device).
        amp: Mixed precision of the fields (see :func:`mixed_precision`; default: bfloat16 on CUDA).
    """
    H, W = camera.height, camera.width
    rays = camera.rays().flatten()
    plate_flat = plate.reshape(-1, 3).to(torch.float32)
    n = H * W
    dev = plate_flat.device
    head_rgb = torch.zeros(n, 3, device=dev)
    head_opacity = torch.zeros(n, device=dev)
    head_depth = torch.zeros(n, device=dev, dtype=torch.float64)

    with mixed_precision(dev, amp):
        hit, comp = _render_hits(model, "head", rays, pose, code, chunk)
    if comp is not None:
        head_rgb[hit] = comp.rgb.to(head_rgb)
        head_opacity[hit] = comp.opacity.to(head_opacity)
        head_depth[hit] = comp.depth.to(head_depth)
    head_on_plate = head_rgb + (1 - head_opacity)[:, None] * plate_flat
    torso_rgb = torch.zeros(n, 3, device=dev)
    torso_opacity = torch.zeros(n, device=dev)
    if torso:
        with mixed_precision(dev, amp):
            hit, comp = _render_hits(model, "torso", rays, pose, code, chunk)
        if comp is not None:
            torso_rgb[hit] = comp.rgb.to(torso_rgb)
            torso_opacity[hit] = comp.opacity.to(torso_opacity)
    rgb = torso_rgb + (1 - torso_opacity)[:, None] * head_on_plate
    return FrameRender(
        rgb=rgb.reshape(H, W, 3).clamp(0, 1),
        head_opacity=head_opacity.reshape(H, W),
        torso_opacity=torso_opacity.reshape(H, W),
        head_on_plate=head_on_plate.reshape(H, W, 3),
        head_depth=head_depth.reshape(H, W),
    )
