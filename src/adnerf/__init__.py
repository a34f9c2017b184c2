"""adnerf: audio-driven neural radiance fields for talking heads (AD-NeRF), as composable parts.

The flow of data is the flow of the modules::

    cameras -> RayBundle -> samplers -> RaySamples -> fields -> compositor -> pixels
                                                    (composed by renderer.VolumeRenderer)

and a talking head is a stack of layers.RadianceLayer (each: its space, box, samples, occupancy
grid, fields and the conditions.FrameCondition signals it reads) composited over a plate.
"""

from .cameras import Camera, intrinsics_matrix, pixel_rays, rays_through_pixels
from .compositor import (
    Composite,
    Layer,
    composite,
    composite_layers,
    over,
    render_weights,
)
from .encodings import PositionalEncoding, TriPlaneEncoding
from .fields import (
    FieldConfig,
    FieldOutput,
    RadianceField,
    fast_config,
    paper_config,
)
from .model.conditions import FrameCondition
from .model.layers import RadianceLayer
from .occupancy import OccupancyGrid
from .pose import HeadPose, from_canonical, perturb_pose, to_canonical
from .rays import RayBundle, RaySamples
from .renderer import RenderOutput, VolumeRenderer
from .samplers import (
    AABBBounds,
    ImportanceSampler,
    NearFarBounds,
    SphereBounds,
    StratifiedSampler,
    ray_aabb,
    ray_sphere,
    sample_pdf,
)

__version__ = "0.1.0"

__all__ = [
    "AABBBounds",
    "Camera",
    "Composite",
    "FieldConfig",
    "FieldOutput",
    "FrameCondition",
    "HeadPose",
    "ImportanceSampler",
    "Layer",
    "NearFarBounds",
    "OccupancyGrid",
    "PositionalEncoding",
    "RadianceField",
    "RadianceLayer",
    "RayBundle",
    "RaySamples",
    "RenderOutput",
    "SphereBounds",
    "StratifiedSampler",
    "TriPlaneEncoding",
    "VolumeRenderer",
    "composite",
    "composite_layers",
    "fast_config",
    "from_canonical",
    "intrinsics_matrix",
    "over",
    "paper_config",
    "perturb_pose",
    "pixel_rays",
    "ray_aabb",
    "ray_sphere",
    "rays_through_pixels",
    "render_weights",
    "sample_pdf",
    "to_canonical",
]
