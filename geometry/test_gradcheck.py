"""torch.autograd.gradcheck in float64 on warping, weights, compositing and the encodings."""

from __future__ import annotations

import math

import torch
from kornia.geometry.liegroup import So3
from torch.autograd import gradcheck

from adnerf.compositor import composite, over, render_weights
from adnerf.encodings import PositionalEncoding, TriPlaneEncoding
from adnerf.fields import FieldConfig, RadianceField
from adnerf.model.conditions import FrameCondition
from adnerf.model.layers import RadianceLayer
from adnerf.pose import HeadPose, from_canonical, perturb_pose, to_canonical
from adnerf.rays import RayBundle

D = torch.float64


def _g(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def test_warping() -> None:
    x = torch.randn(5, 3, dtype=D, generator=_g(), requires_grad=True)
    R = So3.exp(torch.tensor([0.2, -0.4, 1.1], dtype=D)).matrix().requires_grad_(True)
    t = torch.randn(3, dtype=D, generator=_g(1), requires_grad=True)
    assert gradcheck(to_canonical, (x, R, t))
    assert gradcheck(from_canonical, (x, R, t))
    # Through kornia's exponential map near the identity and near pi.
    for angle in (1e-8, math.pi - 1e-6):
        w = (torch.tensor([0.0, 0.6, 0.8], dtype=D) * angle).requires_grad_(True)
        assert gradcheck(lambda w: to_canonical(x.detach(), So3.exp(w).matrix(), t.detach()), (w,))
    yaw = torch.tensor(0.3, dtype=D, requires_grad=True)
    assert gradcheck(lambda y: perturb_pose(R.detach(), t.detach(), yaw=y)[1], (yaw,))


def test_weights_and_compositing() -> None:
    dens = (torch.rand(4, 7, dtype=D, generator=_g()) * 3).requires_grad_(True)
    deltas = (torch.rand(4, 7, dtype=D, generator=_g(1)) * 0.5).requires_grad_(True)
    assert gradcheck(lambda s, d: render_weights(s, d), (dens, deltas))
    colors = torch.rand(4, 7, 3, dtype=D, generator=_g(2), requires_grad=True)
    edges = torch.cumsum(torch.rand(4, 8, dtype=D, generator=_g(3)), dim=-1).requires_grad_(True)
    bg = torch.rand(4, 3, dtype=D, generator=_g(4), requires_grad=True)

    def f(c, s, e, b):
        out = composite(c, s, e[:, :-1], e[:, 1:], b)
        return out.rgb, out.opacity, out.depth

    assert gradcheck(f, (colors, dens, edges, bg))
    a = torch.rand(4, dtype=D, generator=_g(5), requires_grad=True)

    class L:
        def __init__(self, rgb, opacity):
            self.rgb, self.opacity = rgb, opacity

    assert gradcheck(lambda c, a, b: over(L(c * a[:, None], a), L(b, torch.ones_like(a))).rgb, (colors[:, 0].detach().requires_grad_(), a, bg))


def test_encodings() -> None:
    x = torch.rand(6, 3, dtype=D, generator=_g(), requires_grad=True)
    assert gradcheck(PositionalEncoding(3, 4), (x,))
    tri = TriPlaneEncoding(n_levels=2, channels=2, base_resolution=4, max_resolution=8).double()
    # Interior points (away from cell boundaries, where bilinear interpolation has kinks).
    xi = (torch.rand(6, 3, dtype=D, generator=_g(1)) * 1.6 - 0.8).requires_grad_(True)
    assert gradcheck(tri, (xi,))
    plane = tri.planes[0]
    assert gradcheck(lambda p: torch.nn.functional.grid_sample(p, xi.detach()[None, None, :, :2].expand(3, 1, 6, 2), align_corners=True), (plane.detach().clone().requires_grad_(True),))


def test_head_layer_through_the_warp() -> None:
    """Gradients of a canonical head layer's rendered pixels with respect to the audio code and
    the head translation, through the warp, the sampling bounds and the compositing."""
    cfg = FieldConfig(encoding="pe", pe_frequencies=2, dir_frequencies=1, depth=2, width=8, skips=(1,), cond_dim=4)
    torch.manual_seed(0)
    field = RadianceField(cfg).double()
    head = RadianceLayer("head", field, None, ((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5)), (6, 0), space="canonical", conditions=("audio",))
    origins = torch.zeros(3, 3, dtype=D)
    dirs = torch.nn.functional.normalize(torch.tensor([[0.05, 0.0, 1.0], [-0.1, 0.08, 1.0], [0.0, -0.12, 1.0]], dtype=D), dim=-1)
    a = torch.randn(4, dtype=D, generator=_g(2), requires_grad=True)
    t = torch.tensor([0.0, 0.1, 2.0], dtype=D, requires_grad=True)
    R = So3.exp(torch.tensor([0.3, 0.2, -0.1], dtype=D)).matrix()

    def f(a, t):
        out = head.render(RayBundle(origins, dirs), FrameCondition(a, HeadPose(R, t))).final
        return out.rgb, out.opacity

    assert gradcheck(f, (a, t))
