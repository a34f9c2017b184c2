"""The talking-head model: audio encoders and a stack of radiance layers over a plate.

AD-NeRF's model is two :class:`~adnerf.model.layers.RadianceLayer` s:

- ``head``: canonical space (camera rays are moved into the head's frame by the frame's pose),
  conditioned on the audio code;
- ``torso``: camera space, conditioned on the audio code and the head pose.

A frame is the layers composited front to back over the background plate
(:func:`~adnerf.compositor.composite_layers`). New models draw the head in front, as RAD-NeRF
and ER-NeRF do (:attr:`ModelConfig.head_in_front`)::

    frame = head.rgb + (1 - head.opacity) * (torso.rgb + (1 - torso.opacity) * plate)

AD-NeRF, and runs made before the option, draw the torso in front::

    frame = torso.rgb + (1 - torso.opacity) * (head.rgb + (1 - head.opacity) * plate)

With the torso in front, the torso must be transparent over the head, including the chin, which
moves with the speech: on a real clip the torso learnt a half-opaque dark band along the jaw (the
average of the chin's moving edge and the shadow under it), drawn over the chin as a seam.

Each layer samples only inside its box; rays that miss it get its opacity 0 without evaluating
anything. Adding a layer is adding it to :attr:`TalkingHead.layers` (in its place in the stack);
nothing here switches on layer names.
"""

from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass, replace
from typing import Literal, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from ..audio.nets import AudioAttNet, AudioNet
from ..cameras import Camera
from ..compositor import Layer, composite_layers
from ..fields import (
    POSE_CODE_DIM,
    FieldConfig,
    RadianceField,
    check_config_keys,
    fast_config,
    paper_config,
)
from ..pose import HeadPose
from ..rays import RayBundle
from .conditions import SIGNALS, FrameCondition, signal_width
from ..formats.dataset import SceneMeta
from .layers import RadianceLayer
from .mouth_target import MouthProbe

__all__ = [
    "FrameRender",
    "ModelConfig",
    "TalkingHead",
    "migrate_state_dict",
    "mixed_precision",
    "model_config",
    "render_frame",
    "render_chunk",
    "render_layers",
    "render_on_plate",
]

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


@dataclass(frozen=True)
class LayerConfig:
    """One radiance layer of a :class:`TalkingHead` (:attr:`ModelConfig.layers`).

    Attributes:
        name: The layer's name (``"head"``, ``"torso"``): the key of its weights, of its opacity in
            a :class:`FrameRender` and of the stage that trains it.
        space: ``"canonical"`` (the head's frame, moved by the head pose) or ``"camera"``.
        aabb: The layer's box ``(min xyz, max xyz)`` in its space.
        samples: ``(coarse, fine)`` samples per ray.
        coarse: The coarse field.
        fine: The fine field.
        conditions: The signals it reads, in order (registered names of
            :mod:`adnerf.model.conditions`); their widths sum to the fields' ``cond_dim``.
        warp: A registered signal whose value moves the layer's rays before its space
            (``"torso_motion"``: the torso's measured motion in the image), or ``None``.
    """

    name: str
    space: str
    aabb: tuple[tuple[float, float, float], tuple[float, float, float]]
    samples: tuple[int, int]
    coarse: FieldConfig
    fine: FieldConfig
    conditions: tuple[str, ...]
    warp: str | None = None


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
            paper's near-uniform start; see :class:`~adnerf.audio.AudioAttNet`): a start that
            favours the frame itself, so switching the filter on mid-training does not blur the
            codes (``docs/decisions.md``).
        head_samples: ``(coarse, fine)`` samples per ray for the head.
        torso_samples: ``(coarse, fine)`` samples per ray for the torso.
        occupancy_resolution: Cells per axis of each layer's occupancy grid (head: canonical
            space, torso: camera space); 0 turns empty-space skipping off.
        occupancy_threshold: Density (1 / scene unit) below which a cell is empty. At the
            default 0.01 a skipped sample of length 0.15 would have had opacity < 0.0015.
        eye_dim: The width of the eye openness's code (:func:`~adnerf.model.conditions.eye_code`) when
            the head reads it (datasets with ``eye.npy``; blinks on command); 0: it does not
            (AD-NeRF, and runs made before blinks).
        head_in_front: Draw the head over the torso (RAD-NeRF's and ER-NeRF's order); ``False``:
            the torso over the head (AD-NeRF's order, and that of runs whose stored configuration
            predates the option, which :meth:`from_dict` reads as ``False``).
        mouth_dim: The width of the mouth's code (:func:`~adnerf.model.conditions.mouth_code`) when
            the head reads the mouth's opening and width besides the audio code: training gives it
            each frame's landmarks, rendering what the model's read-out of the audio code predicts
            (:meth:`TalkingHead.mouth_from_codes`); 0: it does not (AD-NeRF, and runs made before).
        head_signals: Further registered signals the head reads, after the audio code, the eye
            and the mouth (:func:`~adnerf.model.conditions.register_signal`; training reads each
            frame's value from the dataset through the signal's ``track``, rendering uses its
            ``rest`` value unless given one). The signals must be registered where the model is
            built or loaded.
        torso_motion: The torso layer follows the torso's measured motion in the image (datasets
            with ``torso.npy``; the ``torso_motion`` signal, :func:`~adnerf.model.conditions.torso_rays_map`):
            its field learns the reference torso and each frame's rays are moved to it; rendering
            new audio gives each frame the motion of the pose track's frame, or none. ``False``:
            the torso's place is what its field makes of the head pose and the audio code
            (AD-NeRF, and runs made before the option).
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
    eye_dim: int = 0
    head_in_front: bool = True
    mouth_dim: int = 0
    head_signals: tuple[str, ...] = ()
    torso_motion: bool = False

    @property
    def layers(self) -> list[LayerConfig]:
        """The layers back to front (the order they are drawn over the plate): the torso (camera
        space; audio and head pose) then the head (canonical space; audio, and the eye and mouth
        when their widths are set), or the other way round without ``head_in_front``. The
        stored form (:meth:`to_dict`) stays the fields' flat one, which every run written so far
        has."""
        head = LayerConfig("head", "canonical", self.head_aabb, self.head_samples, self.head, self.head_fine, self.head_conditions)
        warp = "torso_motion" if self.torso_motion else None
        torso = LayerConfig("torso", "camera", self.torso_aabb, self.torso_samples, self.torso, self.torso_fine, ("audio", "pose"), warp)
        return [torso, head] if self.head_in_front else [head, torso]

    @property
    def head_conditions(self) -> tuple[str, ...]:
        """What the head layer reads: the audio code, the eye openness when ``eye_dim``, the
        mouth when ``mouth_dim``, then ``head_signals``."""
        return ("audio",) + (("eye",) if self.eye_dim else ()) + (("mouth",) if self.mouth_dim else ()) + tuple(self.head_signals)

    @property
    def frame_signals(self) -> tuple[str, ...]:
        """The registered signals a frame is given from the dataset's tracks in training (their
        ``rest`` value, or a given one, in rendering): ``head_signals``, then the layers' warps."""
        return tuple(self.head_signals) + tuple(layer.warp for layer in self.layers if layer.warp is not None)

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
        d.setdefault("head_in_front", False)  # stored before the option: trained with the torso in front
        for key in ("head", "head_fine", "torso", "torso_fine"):
            d[key] = FieldConfig.from_dict(d[key])
        for key in ("head_aabb", "torso_aabb"):
            d[key] = tuple(tuple(v) for v in d[key])
        for key in ("head_samples", "torso_samples", "head_signals"):
            if key in d:
                d[key] = tuple(d[key])
        return ModelConfig(**d)


MOUTH_PLANES_BOX = ((-0.5, -0.4, -0.5), (0.5, 0.6, 0.5))
"""The box of the head's conditioned residual planes (``head_planes``) about the canonical mouth
point, scene units ``(min, max)``: the lips and, below them (+y), the chin that drops with the jaw."""
MOUTH_PLANES_RESOLUTION = 128
"""Cells a side of those planes: about the head's finest planes' cell (256 over its ~2-unit box)."""


def model_config(
    meta: SceneMeta,
    preset: Literal["fast", "paper"] = "fast",
    audio_dim: int = 64,
    eye: bool = False,
    mouth: bool = False,
    signals: Sequence[str] = (),
    head_samples: int = 0,
    torso_samples: int = 0,
    head_grid: int = 0,
    torso_motion: bool = False,
    head_width: int = 0,
    head_gate: int = 0,
    head_planes: int = 0,
) -> ModelConfig:
    """The model for a dataset.

    ``"fast"``: tri-plane grids with small MLPs (the default; what trains on a CPU in minutes).
    ``"paper"``: AD-NeRF's 8x256 positional-encoding MLPs with 64 + 128 samples per ray.
    ``eye``: the head also reads the eye openness (for a dataset with ``eye.npy``).
    ``mouth``: the head also reads the mouth's opening and width (:attr:`ModelConfig.mouth_dim`).
    ``signals``: further registered signals the head reads (:attr:`ModelConfig.head_signals`).
    ``head_samples``, ``torso_samples``: samples per ray of each pass of the layer (0: the preset's).
    ``head_grid``: the finest plane resolution of the head's fine field (``"fast"``; 0: 256).
    ``head_width``: the width of the head's fine field's MLP (``"fast"``; 0: 64).
    ``head_gate``: the width of both head fields' gated condition (:attr:`FieldConfig.cond_gate
    <adnerf.fields.FieldConfig.cond_gate>`; 0: none).
    ``head_planes``: residual plane sets of the head's fine field's conditioned features around
    the mouth (:attr:`FieldConfig.cond_planes <adnerf.fields.FieldConfig.cond_planes>`, over
    :data:`MOUTH_PLANES_BOX` about ``meta.mouth`` at :data:`MOUTH_PLANES_RESOLUTION` cells a side;
    ``"fast"``; 0: none).
    ``torso_motion``: the torso layer follows the dataset's torso motion (:attr:`ModelConfig.torso_motion`).
    """
    config = replace(_preset_config(meta, preset, audio_dim, eye, mouth, signals), torso_motion=torso_motion)
    fine: dict[str, object] = {}  # what the schedule changes of the head's fine field
    if head_grid:
        if config.head_fine.encoding != "triplane":
            raise ValueError(f"head_grid sets a tri-plane's resolution; the {preset!r} preset's head has none")
        if head_grid < config.head_fine.grid_base_resolution:
            raise ValueError(f"head_grid must be at least the planes' base resolution {config.head_fine.grid_base_resolution}; got {head_grid}")
        fine["grid_max_resolution"] = head_grid
    if head_width:
        if preset != "fast":
            raise ValueError(f"head_width sets the fast preset's head MLP; the {preset!r} preset's is AD-NeRF's 256")
        fine["width"] = head_width
    if head_gate:
        fine["cond_gate"] = head_gate
        config = replace(config, head=replace(config.head, cond_gate=head_gate))
    if head_planes:
        if config.head_fine.encoding != "triplane":
            raise ValueError(f"head_planes sets residual planes of a tri-plane field; the {preset!r} preset's head has none")
        lo, hi = MOUTH_PLANES_BOX
        fine["cond_planes"] = head_planes
        fine["cond_planes_min"] = tuple(float(m + d) for m, d in zip(meta.mouth, lo))
        fine["cond_planes_max"] = tuple(float(m + d) for m, d in zip(meta.mouth, hi))
        fine["cond_planes_resolution"] = MOUTH_PLANES_RESOLUTION
    if fine:
        config = replace(config, head_fine=FieldConfig.from_dict({**config.head_fine.to_dict(), **fine}))
    if head_samples:
        config = replace(config, head_samples=(head_samples, head_samples))
    if torso_samples:
        config = replace(config, torso_samples=(torso_samples, torso_samples))
    return config


def _preset_config(meta: SceneMeta, preset: str, audio_dim: int, eye: bool, mouth: bool, signals: Sequence[str]) -> ModelConfig:
    eye_dim = signal_width("eye", 0) if eye else 0
    mouth_dim = signal_width("mouth", 0) if mouth else 0
    head_cond = audio_dim + eye_dim + mouth_dim + sum(signal_width(name, audio_dim) for name in signals)
    torso_cond = audio_dim + POSE_CODE_DIM
    if preset == "paper":
        return ModelConfig(
            feature_dim=meta.feature_dim,
            head=paper_config(head_cond),
            head_fine=paper_config(head_cond),
            torso=paper_config(torso_cond),
            torso_fine=paper_config(torso_cond),
            head_aabb=meta.head_aabb,
            torso_aabb=meta.torso_aabb,
            audio_dim=audio_dim,
            head_samples=(64, 128),
            torso_samples=(64, 128),
            eye_dim=eye_dim,
            mouth_dim=mouth_dim,
            head_signals=tuple(signals),
        )
    if preset != "fast":
        raise ValueError(f"unknown model preset {preset!r}; choose fast or paper")
    head = fast_config(head_cond, *meta.head_aabb)
    head_coarse = FieldConfig.from_dict({**head.to_dict(), "grid_max_resolution": 64, "width": 32})
    head_fine = FieldConfig.from_dict({**head.to_dict(), "grid_max_resolution": 256, "grid_levels": 4})
    torso = fast_config(torso_cond, *meta.torso_aabb)
    torso_coarse = FieldConfig.from_dict({**torso.to_dict(), "grid_max_resolution": 64, "width": 32})
    # The torso's finest grid is coarser than the head's (128, not 256): it learns a smooth body
    # faster (docs/decisions.md).
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
        eye_dim=eye_dim,
        mouth_dim=mouth_dim,
        head_signals=tuple(signals),
    )


def _layer(config: ModelConfig, layer: LayerConfig) -> RadianceLayer:
    """A layer of coarse and fine radiance fields, checked against the width of its conditions."""
    width = sum(signal_width(c, config.audio_dim) for c in layer.conditions)
    for which, field_config in (("coarse", layer.coarse), ("fine", layer.fine)):
        if field_config.cond_dim != width:
            raise ValueError(f"the {layer.name} layer's {which} field takes {field_config.cond_dim} condition values; its conditions {layer.conditions} are {width} wide")
    return RadianceLayer(
        layer.name, RadianceField(layer.coarse), RadianceField(layer.fine), layer.aabb, layer.samples, space=layer.space, conditions=layer.conditions,
        warp=layer.warp, occupancy_resolution=config.occupancy_resolution, occupancy_threshold=config.occupancy_threshold,
    )  # fmt: skip


class TalkingHead(nn.Module):
    """Audio encoders plus a stack of radiance layers (AD-NeRF's head and torso).

    Attributes:
        layers: The layers back to front (drawn in this order over the plate): ``"torso"``
            (camera space; audio and head pose) then ``"head"`` (canonical space; audio, and eye
            openness with ``eye_dim``), or the other way round without ``head_in_front``. Another
            layer is one more entry, in its place in the stack.

    Args:
        config: The architecture.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.audio_net = AudioNet(config.feature_dim, config.audio_dim)
        self.att_net = AudioAttNet(config.audio_dim, config.att_len, config.att_centre_logit)
        # The fields' initial weights are drawn head first (the order every seed was trained
        # with), whatever the drawing order; the module dict keeps the drawing order.
        made = {layer.name: _layer(config, layer) for layer in sorted(config.layers, key=lambda layer: layer.name != "head")}
        self.layers = nn.ModuleDict({layer.name: made[layer.name] for layer in config.layers})
        # Per-feature standardisation of the audio windows, fitted on the training frames.
        self.register_buffer("feature_mean", torch.zeros(config.feature_dim))
        self.register_buffer("feature_std", torch.ones(config.feature_dim))
        # Whether AudioAttNet filters the codes (frame_codes): part of the model, saved with it.
        self.register_buffer("audio_smoothing", torch.zeros((), dtype=torch.bool))
        # A head that reads the mouth gets it, when rendering, from this read-out of the audio code.
        self.mouth_probe = MouthProbe(config.audio_dim) if config.mouth_dim else None

    @property
    def reads_eye(self) -> bool:
        """Whether a layer reads the eye openness (the model can blink on command)."""
        return any("eye" in layer.conditions for layer in self.layers.values())

    @property
    def reads_mouth(self) -> bool:
        """Whether a layer reads the mouth's opening and width besides the audio code."""
        return any("mouth" in layer.conditions for layer in self.layers.values())

    def mouth_from_codes(self, codes: Tensor) -> Tensor:
        """The mouth ``(..., 2)`` (standardised opening and width) the model's read-out predicts
        from audio codes ``(..., audio_dim)``: what a head that reads the mouth is given when
        rendering new audio.

        Raises:
            ValueError: The model does not read the mouth.
        """
        if self.mouth_probe is None:
            raise ValueError("this model's head does not read the mouth (mouth_dim 0)")
        return self.mouth_probe(codes)

    def condition(
        self, code: Tensor, pose: HeadPose, eye: float | Tensor | None = None, mouth: Tensor | None = None, read_pose: HeadPose | None = None,
        signals: Mapping[str, Tensor | np.ndarray | float] | None = None,
    ) -> FrameCondition:  # fmt: skip
        """A frame's condition from its audio code ``(audio_dim,)``, head pose, eye openness (a
        number or ``(1,)``; ``None``: open, 1) and mouth (``(2,)``; ``None``: the read-out of the
        code, :meth:`mouth_from_codes`). A signal the model does not read is left out.
        ``read_pose``: the pose the layers read as their pose signal (the torso's), where it
        differs from ``pose`` (which moves the head's rays); ``None``: ``pose``. ``signals``: the
        frame's values of :attr:`ModelConfig.frame_signals` by name (the head's signals and the
        layers' warps; one left out: the signal's ``rest`` value).

        Raises:
            ValueError: A head signal with no value given and no ``rest`` value.
        """
        extra = {} if read_pose is None else {"pose": read_pose.code().to(code.dtype)}
        if self.reads_eye:
            extra["eye"] = torch.as_tensor(1.0 if eye is None else eye, dtype=code.dtype, device=code.device).reshape(1)
        if self.reads_mouth:
            extra["mouth"] = (self.mouth_from_codes(code) if mouth is None else torch.as_tensor(mouth, device=code.device)).to(code.dtype).reshape(2)
        for name in self.config.frame_signals:
            value = None if signals is None else signals.get(name)
            if value is None:
                if not SIGNALS[name].rest:
                    raise ValueError(f"the model reads the {name!r} signal, which has no rest value: give each frame's value")
                value = SIGNALS[name].rest
            dtype = code.dtype if name in self.config.head_signals else torch.float64  # a layer's warp is geometry
            extra[name] = torch.as_tensor(value, device=code.device).to(dtype).reshape(-1)
        return FrameCondition(code, pose, extra)

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

    def neighbours(self, frames: Tensor, n: int) -> Tensor:
        """The ``att_len`` frame indices ``(F, att_len)`` around each of ``frames (F,)`` that
        AudioAttNet filters, clamped to ``[0, n)``; each frame itself is at position
        ``att_len // 2``, where AudioAttNet puts its centre."""
        half = self.config.att_len // 2
        return (frames[:, None] + torch.arange(-half, self.config.att_len - half, device=frames.device)).clamp(0, n - 1)

    @property
    def smooths_audio(self) -> bool:
        """Whether AudioAttNet filters the audio codes (training switches it on at ``att_start``;
        saved with the weights)."""
        return bool(self.audio_smoothing)

    def set_audio_smoothing(self, on: bool) -> None:
        """Switch AudioAttNet's filtering of the audio codes on or off."""
        self.audio_smoothing.fill_(bool(on))

    def frame_codes(self, windows: Tensor, frames: Tensor | Sequence[int] | None = None, batch: int = 512) -> Tensor:
        """The audio codes ``(F, audio_dim)`` of ``frames`` (default: every frame) of a clip.

        The one way a frame's code is made, for training (a frame a step) and rendering (every
        frame): AudioNet encodes the frame's feature window, and once the model smooths
        (:attr:`smooths_audio`) AudioAttNet filters the codes of its ``att_len`` neighbours
        (:meth:`neighbours`; clamped at the clip's ends). Only the windows needed are encoded,
        each once, ``batch`` at a time.

        Args:
            windows: The clip's feature windows ``(N, 16, D)``, one per frame.
            frames: Frame indices ``(F,)`` in ``[0, N)``.
            batch: Windows per AudioNet call.
        """
        n = windows.shape[0]
        frames = torch.arange(n, device=windows.device) if frames is None else torch.as_tensor(frames, device=windows.device).reshape(-1)
        rows = self.neighbours(frames, n) if self.smooths_audio else frames[:, None]  # (F, L)
        need, where = torch.unique(rows, return_inverse=True)
        raw = torch.cat([self.audio_codes(windows[need[i : i + batch]]) for i in range(0, need.numel(), batch)])
        codes = raw[where]  # (F, L, audio_dim)
        return self.att_net(codes) if self.smooths_audio else codes[:, 0]


def migrate_state_dict(state: dict) -> dict:
    """A model state dict of the earlier layout (``head.field.*``, ``head_fine.field.*``, ...,
    ``head_occupancy.*``) in the layers' layout (``layers.head.coarse.*``, ``layers.head.fine.*``,
    ..., ``layers.head.occupancy.*``); a state dict of the current layout comes back unchanged."""
    renames = []
    for layer in ("head", "torso"):
        renames += [(f"{layer}.field.", f"layers.{layer}.coarse."), (f"{layer}_fine.field.", f"layers.{layer}.fine."), (f"{layer}_occupancy.", f"layers.{layer}.occupancy.")]
    out = {}
    for key, value in state.items():
        for old, new in renames:
            if key.startswith(old):
                key = new + key[len(old) :]
                break
        out[key] = value
    return out


def _over(layers: Layer, background: Tensor) -> Tensor:
    """Premultiplied ``layers`` ``(H, W, 3)`` / ``(H, W)`` over an opaque background, clamped to [0, 1]."""
    return composite_layers([layers], background.to(layers.rgb)).rgb.clamp(0, 1)


@dataclass
class FrameRender:
    """One rendered frame.

    Attributes:
        rgb: Final colour ``(H, W, 3)`` in ``[0, 1]``: :meth:`over` the plate it was rendered on.
        opacity: Each rendered layer's opacity ``(H, W)``, by name (0 where a ray misses it).
        depth: Each rendered layer's depth along the unit pixel ray ``(H, W)``, float64 (0 where
            the ray misses it; the end of its last interval where its opacity is 0).
        layers: The rendered layers composited front to back without a background: premultiplied
            colour ``(H, W, 3)`` and opacity ``(H, W)``.
        colour: Each rendered layer's premultiplied colour ``(H, W, 3)``, by name.
    """

    rgb: Tensor
    opacity: dict[str, Tensor]
    depth: dict[str, Tensor]
    layers: Layer
    colour: dict[str, Tensor]

    def layer(self, name: str) -> tuple[Layer, Tensor]:
        """The layer ``name`` alone, and its depth: what :func:`render_frame` takes as ``given``."""
        return Layer(self.colour[name], self.opacity[name]), self.depth[name]

    def over(self, background: Tensor) -> Tensor:
        """The frame over a background ``(H, W, 3)`` in ``[0, 1]`` (the same arithmetic as
        :attr:`rgb` over its plate: a new background costs no field evaluation)."""
        return _over(self.layers, background)

    @property
    def head_opacity(self) -> Tensor:
        """The head layer's opacity ``(H, W)``."""
        return self.opacity["head"]

    @property
    def torso_opacity(self) -> Tensor:
        """The torso layer's opacity ``(H, W)`` (zeros when it was not rendered)."""
        return self.opacity.get("torso", torch.zeros_like(self.opacity["head"]))


def render_chunk(device: torch.device | str) -> int:
    """Rays per batch for whole-frame renders: 1024 on the CPU (what every CPU figure was measured
    with); 262144 on a GPU, a whole 450x450 frame per layer in one batch. Measured on an H100 at
    450x450, head and torso (``docs/bench/gpu.json``): 0.8 frames/s with 1024, 19-22 with 65536,
    32 with 262144, at 1.7 GB."""
    return 1024 if torch.device(device).type == "cpu" else 262144


def _stack(model: TalkingHead, names: Sequence[str] | None) -> list[RadianceLayer]:
    """The model's layers named in ``names`` (all when ``None``), back to front."""
    if names is None:
        return list(model.layers.values())
    unknown = [n for n in names if n not in model.layers]
    if unknown:
        raise ValueError(f"the model has no layer {unknown[0]!r}; it has {', '.join(model.layers)}")
    return [layer for name, layer in model.layers.items() if name in names]


def _render_layers(
    model: TalkingHead, rays: RayBundle, cond: FrameCondition, names: Sequence[str] | None, chunk: int | None, amp: str, n: int, dev: torch.device, given: Mapping[str, tuple[Layer, Tensor]] | None = None
) -> dict[str, tuple[Layer, Tensor]]:
    """Each layer's premultiplied colour and opacity (a :class:`~adnerf.compositor.Layer`) and
    depth along ``n`` rays, by name, back to front; a layer in ``given`` is taken from there."""
    chunk = chunk or render_chunk(dev)
    out = {}
    for layer in _stack(model, names):
        if given is not None and layer.name in given:
            out[layer.name] = given[layer.name]
            continue
        rgb = torch.zeros(n, 3, device=dev)
        opacity = torch.zeros(n, device=dev)
        depth = torch.zeros(n, device=dev, dtype=torch.float64)
        with mixed_precision(dev, amp):
            hit, comp = layer.render_hits(rays, cond, chunk)
        if comp is not None:
            rgb[hit] = comp.rgb.to(rgb)
            opacity[hit] = comp.opacity.to(opacity)
            depth[hit] = comp.depth.to(depth)
        out[layer.name] = (Layer(rgb, opacity), depth)
    return out


@torch.no_grad()
def render_layers(
    model: TalkingHead,
    rays: RayBundle,
    cond: FrameCondition,
    *,
    layers: Sequence[str] | None = None,
    chunk: int | None = None,
    amp: str = "auto",
) -> dict[str, Layer]:
    """Some of the model's layers, each alone, along some rays (no gradients).

    Args:
        model: The model.
        rays: Camera rays ``(R,)``.
        cond: The frame's condition.
        layers: Names of the layers to draw (all when ``None``).
        chunk: Rays per batch (default :func:`render_chunk` of the device).
        amp: Mixed precision of the fields (see :func:`mixed_precision`).

    Returns:
        Each layer's premultiplied colour ``(R, 3)`` and opacity ``(R,)`` (float32) by name, in
        the model's order (back to front); stage 2 composites the frozen head with the torso
        it trains.
    """
    drawn = _render_layers(model, rays, cond, layers, chunk, amp, len(rays), rays.origins.device)
    return {name: layer for name, (layer, _) in drawn.items()}


@torch.no_grad()
def render_on_plate(
    model: TalkingHead,
    rays: RayBundle,
    cond: FrameCondition,
    plate: Tensor,
    *,
    layers: Sequence[str] | None = None,
    chunk: int | None = None,
    amp: str = "auto",
) -> Tensor:
    """Some of the model's layers over the plate along some rays (no gradients).

    The same values as :func:`render_frame` at those pixels, for callers that need only part of a
    frame.

    Args:
        model: The trained model.
        rays: Camera rays ``(R,)``.
        cond: The frame's condition.
        plate: Plate colours of those pixels ``(R, 3)`` in ``[0, 1]``.
        layers: Names of the layers to draw (all when ``None``), in the model's order.
        chunk: Rays per batch (default :func:`render_chunk` of the device).
        amp: Mixed precision of the fields (see :func:`mixed_precision`).

    Returns:
        ``(R, 3)`` float32 colours.
    """
    plate = plate.to(torch.float32)
    drawn = render_layers(model, rays, cond, layers=layers, chunk=chunk, amp=amp)
    return composite_layers(list(reversed(drawn.values())), plate).rgb


@torch.no_grad()
def render_frame(
    model: TalkingHead,
    camera: Camera,
    pose: HeadPose,
    code: Tensor,
    plate: Tensor,
    *,
    eye: float | Tensor | None = None,
    layers: Sequence[str] | None = None,
    chunk: int | None = None,
    amp: str = "auto",
    read_pose: HeadPose | None = None,
    box: tuple[int, int, int, int] | None = None,
    given: Mapping[str, tuple[Layer, Tensor]] | None = None,
    signals: Mapping[str, Tensor | np.ndarray | float] | None = None,
) -> FrameRender:
    """Render a full frame, or the pixels of ``box`` (no gradients): the layers composited front
    to back over the plate.

    Args:
        model: The trained model.
        camera: The static camera.
        pose: The frame's head pose (single ``R (3, 3)``, ``t (3,)``).
        code: The frame's audio code ``(audio_dim,)``.
        plate: Background ``(H, W, 3)`` in ``[0, 1]``.
        eye: The frame's eye openness (1 open, 0 closed; ``None``: open), for models that read it.
        layers: Names of the layers to draw (all when ``None``; ``("head",)``: the stage-1
            picture), in the model's order.
        chunk: Rays per batch (default :func:`render_chunk` of the device).
        amp: Mixed precision of the fields (see :func:`mixed_precision`; default: bfloat16 on CUDA).
        read_pose: The pose the layers read as a signal (the torso), where it differs from ``pose``
            (:meth:`TalkingHead.condition`).
        box: ``(x0, y0, x1, y1)`` (end exclusive): only these pixels' rays are rendered (the same
            pixels as in the whole frame), and every image of the result is the box's ``(h, w)``.
        given: Layers already drawn for this frame's pixels under the same conditions (an edit
            the layer does not read, e.g. the torso under a turn of the head), by name: each one's
            :class:`~adnerf.compositor.Layer` (colour ``(H, W, 3)``, opacity ``(H, W)``) and depth
            ``(H, W)`` (:meth:`FrameRender.layer`); they are composited, not rendered again.
        signals: The frame's values of :attr:`ModelConfig.frame_signals` by name (the torso's
            motion, ``torso_motion``); one left out gets the signal's ``rest`` value.
    """
    rays = camera.rays()
    if box is not None:
        x0, y0, x1, y1 = box
        if not (0 <= x0 < x1 <= camera.width and 0 <= y0 < y1 <= camera.height):
            raise ValueError(f"box {box} is not a non-empty box inside the {camera.width}x{camera.height} frame")
        rays, plate = rays[y0:y1, x0:x1], plate[y0:y1, x0:x1]
    H, W = rays.shape
    flat = None
    if given is not None:
        drawing = [layer.name for layer in _stack(model, layers)]
        for name, (layer, depth) in given.items():
            if name not in drawing:
                raise ValueError(f"a {name!r} layer is given, but the layers drawn are {', '.join(drawing)}")
            if layer.rgb.shape != (H, W, 3) or layer.opacity.shape != (H, W) or depth.shape != (H, W):
                raise ValueError(f"the given {name} layer is not a {W}x{H} picture (colour {tuple(layer.rgb.shape)}, opacity {tuple(layer.opacity.shape)}, depth {tuple(depth.shape)})")
        flat = {name: (Layer(layer.rgb.reshape(-1, 3), layer.opacity.reshape(-1)), depth.reshape(-1)) for name, (layer, depth) in given.items()}
    drawn = _render_layers(model, rays.flatten(), model.condition(code, pose, eye, read_pose=read_pose, signals=signals), layers, chunk, amp, H * W, plate.device, flat)
    stack = composite_layers([layer for layer, _ in reversed(drawn.values())])
    stacked = Layer(stack.rgb.reshape(H, W, 3), stack.opacity.reshape(H, W))
    return FrameRender(
        rgb=_over(stacked, plate.to(torch.float32)),
        opacity={name: layer.opacity.reshape(H, W) for name, (layer, _) in drawn.items()},
        depth={name: depth.reshape(H, W) for name, (_, depth) in drawn.items()},
        layers=stacked,
        colour={name: layer.rgb.reshape(H, W, 3) for name, (layer, _) in drawn.items()},
    )
