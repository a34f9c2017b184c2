"""Device tests: every path that trains or renders runs on the ``--device`` given to pytest.

``pytest`` runs them on the CPU; ``pytest --device cuda tests/test_devices.py`` on a GPU (they skip
without one). They compare against the CPU, so a device-specific mistake shows as a difference:
a CPU generator handed to a CUDA draw (which PyTorch refuses), a tensor left on the CPU, a
checkpoint that does not load across devices.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from adnerf.analytic import UniformSphere
from adnerf.cameras import intrinsics_matrix, pixel_rays
from adnerf.commands.render_video import render_frames
from adnerf.model.blinks import blinks_in
from adnerf.formats.dataset import load_dataset
from adnerf.model.talking_head import model_config
from adnerf.model.train import TrainConfig, Trainer, load_run, train
from adnerf.occupancy import OccupancyGrid
from adnerf.renderer import VolumeRenderer
from adnerf.rng import uniform
from adnerf.samplers import NearFarBounds, sample_pdf, stratified_edges
from adnerf.synth import SynthConfig, synthesize

TINY = SynthConfig(seconds=1.2, size=24, voice="formant", seed=11)
CFG = TrainConfig(head_iters=8, torso_iters=4, rays=64, log_every=4, checkpoint_every=4, occupancy_start=0.25, occupancy_every=2)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("dev") / "data", TINY)


def test_cpu_generator_draws_land_on_the_data_device(device: torch.device) -> None:
    """The training generator lives on the CPU; draws for data elsewhere must work and give the
    numbers the same seed gives on the CPU (fails on CUDA if a draw passes the generator to a
    CUDA ``torch.rand``)."""
    near = torch.full((5,), 1.0, dtype=torch.float64, device=device)
    far = torch.full((5,), 3.0, dtype=torch.float64, device=device)

    def draws(dev: torch.device) -> list[torch.Tensor]:
        g = torch.Generator(device="cpu").manual_seed(7)
        edges = stratified_edges(near.to(dev), far.to(dev), 8, jitter=True, generator=g)
        bins = torch.linspace(1.0, 3.0, 9, dtype=torch.float64, device=dev).expand(5, 9)
        weights = torch.rand(5, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(1)).to(dev)
        samples = sample_pdf(bins, weights, 16, generator=g)
        grid = OccupancyGrid((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), resolution=4).to(dev)
        grid.update(lambda p: (p.norm(dim=-1) < 0.9).float() * 10.0, generator=g)
        return [edges, samples, grid.density, uniform((3,), dtype=torch.float32, device=dev, generator=g)]

    here, cpu = draws(device), draws(torch.device("cpu"))
    for a, b in zip(here, cpu):
        assert a.device.type == device.type
        torch.testing.assert_close(a.cpu(), b, rtol=1e-6, atol=1e-6)


def test_rendering_an_analytic_sphere_matches_the_cpu(device: torch.device) -> None:
    K = intrinsics_matrix(40.0, 40.0, 16.0, 16.0)
    rays = pixel_rays(K, 32, 32)
    sphere = UniformSphere(torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64), 1.0, 10.0)
    renderer = VolumeRenderer(NearFarBounds(1.0, 5.0), n_coarse=32, n_fine=32)

    def render(dev: torch.device) -> torch.Tensor:  # training-style: jittered, with a CPU generator
        out = renderer.render_rays(rays.map(lambda x: x.to(dev)), sphere, jitter=True, generator=torch.Generator().manual_seed(0))
        return torch.cat([out.final.rgb, out.final.opacity[..., None], out.final.depth[..., None]], dim=-1)

    torch.testing.assert_close(render(device).cpu(), render(torch.device("cpu")), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("frames", [1, 4])
def test_training_resumes_on_the_device_and_runs_render_across_devices(tiny: Path, tmp_path: Path, device: torch.device, frames: int) -> None:
    """Train on the device with a kill and a resume (the checkpointed CPU generator state must
    load there), then render the run on the CPU and on the device: the same frames (bfloat16 on
    CUDA allows a small difference). With ``frames=4`` each step renders four frames' rays in one
    call, each under its own condition (``--scale``'s path: per-ray gathers of codes and poses)."""
    dev = device.type
    root = tmp_path / "run"
    train(tiny, root, config=replace(CFG, frames=frames), device=dev, progress=False, max_steps=6)
    train(tiny, root, device=dev, progress=False, resume=True)
    ckpt = torch.load(root / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert (ckpt["stages"]["head"]["step"], ckpt["stages"]["torso"]["step"]) == (8, 4)
    ds = load_dataset(tiny)
    idx = list(ds.meta.test)
    plate = ds.background.astype(np.float32) / 255.0
    on_cpu = render_frames(load_run(root, "cpu"), ds.features[idx], ds.poses[idx], plate).frames.astype(np.float64)
    on_dev = render_frames(load_run(root, dev), ds.features[idx], ds.poses[idx], plate).frames.astype(np.float64)
    tolerance = 0.0 if dev == "cpu" else 3.0  # mean absolute difference in 8-bit levels
    assert np.abs(on_cpu - on_dev).mean() <= tolerance


def test_trainer_draws_frames_on_the_cpu_and_fuses_adam(tiny: Path, tmp_path: Path, device: torch.device) -> None:
    """The frame pools stay on the CPU (a draw read back from a GPU waits for its queue); the
    optimisers are fused on every device (on two CPU cores the head's update takes a sixth of the
    per-parameter loop's time)."""
    ds = load_dataset(tiny, truth=False)
    tcfg = TrainConfig(head_iters=3, torso_iters=0, rays=32)
    flushes = torch.set_flush_denormal(False)
    tr = Trainer(tmp_path, ds, model_config(ds.meta, "fast", eye=blinks_in(ds.eye, ds.meta.train)), tcfg, str(device), False)
    assert float(torch.tensor(1e-30) * torch.tensor(1e-10)) == 0.0 or not flushes  # the trainer flushes subnormals (adnerf.subnormals)
    assert tr.train_frames.device.type == "cpu" and tr.blinking.device.type == "cpu"
    assert tr.pick_frame() in set(ds.meta.train)
    assert tr.opt_head.defaults.get("fused") and tr.opt_torso.defaults.get("fused")
    tr.head_stage(None)
    assert tr.head_step == 3 and all(torch.isfinite(p).all() for p in tr.model.parameters())


def test_collectives_take_tensors_on_the_backends_device(device: torch.device) -> None:
    """Under ``torchrun`` on GPUs the backend is NCCL, which refuses CPU tensors: the averaged loss
    and the gradients must be reduced on the process's GPU (``gloo`` on the CPU). A process group
    of one process, which ``Ranks`` counts as two, so each reduction returns this process's values
    halved."""
    from adnerf.model.distributed import Ranks

    backend = "nccl" if device.type == "cuda" else "gloo"
    available = torch.distributed.is_available() and (torch.distributed.is_nccl_available() if backend == "nccl" else torch.distributed.is_gloo_available())
    if not available:
        pytest.skip(f"torch.distributed with {backend} is not available")
    if device.type == "cuda":
        torch.cuda.set_device(device)
    torch.distributed.init_process_group(backend, store=torch.distributed.HashStore(), rank=0, world_size=1)
    try:
        ranks = Ranks(0, 2, backend, str(device) if backend == "nccl" else "cpu")
        assert ranks.mean([2.0, 5.0]) == [1.0, 2.5]
        p = torch.nn.Parameter(torch.ones(3, device=device))
        p.grad = torch.full((3,), 4.0, device=device)
        assert ranks.average_gradients([p])
        assert p.grad.device == p.device and torch.equal(p.grad.cpu(), torch.full((3,), 2.0))
    finally:
        torch.distributed.destroy_process_group()
