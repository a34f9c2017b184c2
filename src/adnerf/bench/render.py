"""Benchmarks: error against run time.

``adnerf bench render`` renders a uniform-density sphere, whose opacity and expected depth are
known in closed form (:mod:`adnerf.analytic`), with stratified sampling and with coarse +
importance sampling at the same total number of samples per ray, and reports the quadrature
error of opacity and depth next to the time per million rays.
"""

from __future__ import annotations

import platform
import time
from dataclasses import asdict, dataclass

import torch

from ..analytic import UniformSphere
from ..cameras import intrinsics_matrix, pixel_rays
from ..renderer import VolumeRenderer
from ..samplers import NearFarBounds

__all__ = ["RenderBenchRow", "bench_features", "bench_render", "format_table"]

DEFAULT_SAMPLES = (8, 16, 32, 64, 128, 256)


@dataclass
class RenderBenchRow:
    """One line of the render benchmark.

    Attributes:
        samples_per_ray: Total samples per ray (coarse + fine).
        method: ``"stratified"`` or ``"importance"`` (half coarse, half importance samples).
        opacity_rel_err: ``sum |a - a*| / sum a*`` over rays that hit the sphere.
        depth_rel_err: Mean of ``|d - d*| / d*`` over rays that hit the sphere.
        depth_abs_err: Mean ``|d - d*|`` in scene units (sphere radius 1).
        seconds_per_mrays: Wall time to render one million rays (best of the repeats).
        rays: Rays rendered per repeat.
        device: Device used.
        dtype: Floating point type used.
    """

    samples_per_ray: int
    method: str
    opacity_rel_err: float
    depth_rel_err: float
    depth_abs_err: float
    seconds_per_mrays: float
    rays: int
    device: str
    dtype: str


def bench_render(
    samples: tuple[int, ...] = DEFAULT_SAMPLES,
    *,
    size: int = 128,
    repeats: int = 3,
    device: str = "cpu",
    dtype: torch.dtype = torch.float32,
    chunk: int = 16384,
    sigma: float = 10.0,
) -> list[RenderBenchRow]:
    """Run the render benchmark.

    The scene: a sphere of radius 1 and density ``sigma`` at distance 3 in front of a pinhole
    camera whose image (``size`` x ``size``, 40 degrees field of view) it mostly fills; every ray
    is sampled in ``[1, 5]`` as a fixed near/far renderer would. The default density 10 makes a
    surface-like object (light penetrates ~0.1 radius), as a trained head is.

    Args:
        samples: Total samples per ray to test.
        size: Image side in pixels.
        repeats: Timed repeats per configuration (the best is reported).
        device: ``"cpu"`` or ``"cuda"``.
        dtype: Floating point type of rays and samples.
        chunk: Rays per chunk.
        sigma: Density of the sphere (1 / radius).

    Returns:
        One :class:`RenderBenchRow` per (samples, method).
    """
    dev = torch.device(device)
    focal = 0.5 * size / torch.tan(torch.deg2rad(torch.tensor(20.0))).item()
    K = intrinsics_matrix(focal, focal, size / 2, size / 2, dtype=dtype, device=dev)
    rays = pixel_rays(K, size, size).flatten()
    sphere = UniformSphere(torch.tensor([0.0, 0.0, 3.0], dtype=dtype, device=dev), 1.0, sigma)
    truth_opacity, truth_depth, hit = sphere.truth(rays.origins.double(), rays.directions.double())
    bounds = NearFarBounds(1.0, 5.0)
    with torch.no_grad():  # one untimed render: first-call start-up must not count against row one
        VolumeRenderer(bounds, n_coarse=8, n_fine=8).render_chunked(rays[:chunk], sphere, chunk=chunk)
    rows = []
    for n in samples:
        for method in ("stratified", "importance"):
            if method == "stratified":
                renderer = VolumeRenderer(bounds, n_coarse=n, n_fine=0)
            else:
                if n < 2:
                    continue
                renderer = VolumeRenderer(bounds, n_coarse=n // 2, n_fine=n - n // 2)
            best = float("inf")
            with torch.no_grad():
                for _ in range(max(1, repeats)):
                    if dev.type == "cuda":
                        torch.cuda.synchronize(dev)
                    start = time.perf_counter()
                    out = renderer.render_chunked(rays, sphere, chunk=chunk).final
                    if dev.type == "cuda":
                        torch.cuda.synchronize(dev)
                    best = min(best, time.perf_counter() - start)
            opacity = out.opacity.double()
            depth = out.depth.double()
            op_err = ((opacity - truth_opacity).abs()[hit].sum() / truth_opacity[hit].sum()).item()
            depth_abs = (depth - truth_depth).abs()[hit]
            rows.append(
                RenderBenchRow(
                    samples_per_ray=n,
                    method=method,
                    opacity_rel_err=op_err,
                    depth_rel_err=(depth_abs / truth_depth[hit]).mean().item(),
                    depth_abs_err=depth_abs.mean().item(),
                    seconds_per_mrays=best * 1e6 / rays.origins.shape[0],
                    rays=rays.origins.shape[0],
                    device=str(dev),
                    dtype=str(dtype).replace("torch.", ""),
                )
            )
    return rows


def format_table(rows: list[RenderBenchRow]) -> str:
    """A readable fixed-width table of benchmark rows."""
    head = f"{'samples':>7}  {'method':<10}  {'opacity rel err':>15}  {'depth rel err':>13}  {'s / Mray':>9}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r.samples_per_ray:>7}  {r.method:<10}  {r.opacity_rel_err:>15.3e}  {r.depth_rel_err:>13.3e}  {r.seconds_per_mrays:>9.2f}"
        )
    lines.append(f"({rows[0].rays if rows else 0} rays, {rows[0].device if rows else ''}, {platform.processor() or platform.machine()}, torch {torch.__version__}, {torch.get_num_threads()} threads)")
    return "\n".join(lines)


def rows_as_dicts(rows: list[RenderBenchRow]) -> list[dict]:
    """Rows as plain dicts (for JSON)."""
    return [asdict(r) for r in rows]


def bench_features(media: str | None = None, seconds: float = 60.0, repeats: int = 2) -> list[dict]:
    """Speech-feature extraction speed (seconds of audio per second of wall time) per extractor.

    Args:
        media: An audio or video file to use; ``None`` synthesises ``seconds`` of a vowel-like
            harmonic signal with pauses at 16 kHz.
        seconds: Length of the synthetic audio.
        repeats: Timed repeats (the best is reported).

    Returns:
        One dict per extractor: ``kind``, ``audio_seconds``, ``wall_seconds``, ``realtime_factor``.
    """
    import numpy as np

    from ..audio.features import FeatureSpec, extract_features
    from ..io import AudioTrack, read_audio

    if media is not None:
        audio = read_audio(media)
    else:
        sr = 16000
        t = np.arange(int(seconds * sr)) / sr
        f0 = 120 + 20 * np.sin(2 * np.pi * 0.5 * t)
        voice = sum(np.sin(2 * np.pi * k * np.cumsum(f0) / sr) / k for k in range(1, 8))
        gate = (np.sin(2 * np.pi * 0.8 * t) > -0.3).astype(np.float64)
        audio = AudioTrack((0.1 * voice * gate).astype(np.float32), sr)
    rows = []
    for kind in ("logmel", "phonemes"):
        extract_features(AudioTrack(audio.samples[: audio.sample_rate], audio.sample_rate), FeatureSpec(kind))  # warm up
        best = float("inf")
        for _ in range(max(1, repeats)):
            start = time.perf_counter()
            extract_features(audio, FeatureSpec(kind))
            best = min(best, time.perf_counter() - start)
        rows.append({"kind": kind, "audio_seconds": round(audio.duration, 3), "wall_seconds": best, "realtime_factor": audio.duration / best})
    return rows
