"""``adnerf bench fields``: error against training time, per field configuration.

Every configuration trains the head (stage 1, the audio-conditioned canonical-space field) of the
same synthetic scene for the same budget of wall time. At fixed times the training clock is
stopped and the head is rendered, without jitter, along a fixed set of held-out rays: 512 pixels
inside the head box of each of 8 test frames, against the stage-1 target (the frame on head
pixels, the plate elsewhere). Reported per configuration: that PSNR at every checkpoint, field
evaluations per second of training, head frames per second at the dataset size, and the peak
memory of its process (each configuration runs in a fresh process by default).

Each configuration's schedule (learning-rate decay, when AudioAttNet and empty-space skipping
start) is fitted to the budget: the number of iterations is estimated from the measured speed
after a few iterations, corrected at a fifth of the budget, and stretched again whenever it runs
out before the budget does.
"""

from __future__ import annotations

import json
import platform
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from multiprocessing import get_context
from pathlib import Path
from typing import Sequence

import torch

from ..allocator import tune_allocator
from ..memory import peak_rss_bytes
from ..metrics import psnr_from_mse
from ..model.blinks import blinks_in
from ..formats.dataset import SceneMeta, load_dataset
from ..model.talking_head import ModelConfig, model_config, render_frame
from ..model.train import TrainConfig, Trainer
from ..synth import SynthConfig, synthesize

__all__ = [
    "CONFIGS",
    "DEFAULT_CHECKPOINTS",
    "FieldBenchConfig",
    "bench_fields",
    "bench_model_config",
    "format_fields_table",
    "load_rows",
    "plot_fields",
    "run_config",
]

DEFAULT_CHECKPOINTS = (5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0)
EVAL_FRAMES = 8
EVAL_RAYS_PER_FRAME = 512


@dataclass(frozen=True)
class FieldBenchConfig:
    """One benchmarked configuration.

    Attributes:
        name: Short name (``--configs``).
        description: What it is.
        preset: Field preset of :func:`~adnerf.model.talking_head.model_config`.
        occupancy: Empty-space skipping with occupancy grids.
        fine: Hierarchical sampling with a fine field. Without it, one field (the fine field's
            architecture) is evaluated at as many stratified samples as both passes had.
    """

    name: str
    description: str
    preset: str
    occupancy: bool
    fine: bool


CONFIGS: tuple[FieldBenchConfig, ...] = (
    FieldBenchConfig("paper", "AD-NeRF: PE(10) + 8x256 MLP, 64 + 128 samples", "paper", False, True),
    FieldBenchConfig("fast", "tri-planes + 2x64 MLP, 16 + 16 samples, empty-space skipping (default)", "fast", True, True),
    FieldBenchConfig("fast-no-skip", "as fast, without empty-space skipping", "fast", False, True),
    FieldBenchConfig("fast-coarse-only", "as fast, one field at 32 stratified samples, no fine pass", "fast", True, False),
)


def bench_model_config(meta: SceneMeta, cfg: FieldBenchConfig, eye: bool = False) -> ModelConfig:
    """The model a benchmark configuration trains (``eye``: the head reads the eye openness)."""
    m = model_config(meta, cfg.preset, eye=eye)  # type: ignore[arg-type]
    if not cfg.occupancy:
        m = replace(m, occupancy_resolution=0)
    if not cfg.fine:
        m = replace(
            m,
            head=m.head_fine,
            torso=m.torso_fine,
            head_samples=(sum(m.head_samples), 0),
            torso_samples=(sum(m.torso_samples), 0),
        )
    return m


def _eval_set(tr: Trainer, generator: torch.Generator) -> list[tuple[int, torch.Tensor]]:
    """``EVAL_RAYS_PER_FRAME`` pixels inside the head box of each of ``EVAL_FRAMES`` test frames."""
    test = tr.ds.meta.test or tr.ds.meta.train
    picks = [test[round(i * (len(test) - 1) / max(EVAL_FRAMES - 1, 1))] for i in range(min(EVAL_FRAMES, len(test)))]
    out = []
    for frame in dict.fromkeys(picks):
        near, far = tr.model.layers["head"].crossing(tr.rays, tr.ds.head_pose(frame, device=tr.device))
        candidates = torch.nonzero(far > near)[:, 0]
        if candidates.numel() == 0:
            continue
        idx = torch.randint(candidates.numel(), (EVAL_RAYS_PER_FRAME,), generator=generator).to(candidates.device)
        out.append((frame, candidates[idx]))
    return out


@torch.no_grad()
def _eval_psnr(tr: Trainer, evalset: list[tuple[int, torch.Tensor]]) -> float:
    """PSNR of the head over the plate along the held-out rays, against the stage-1 target."""
    model = tr.model
    model.eval()
    se, n = 0.0, 0
    for frame, pix in evalset:
        pose = tr.ds.head_pose(frame, device=tr.device)
        code = model.frame_codes(tr.windows, [frame])[0]
        out = model.layers["head"].render(tr.rays[pix], tr.condition(frame, code, pose), background=tr.plate[pix])
        target = tr.head_target(frame, pix)
        se += float((out.final.rgb.float().clamp(0, 1) - target).square().sum())
        n += target.numel()
    model.train()
    return psnr_from_mse(se / max(n, 1))


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _peak_memory_mb(device: str) -> float:
    if device.startswith("cuda"):
        return torch.cuda.max_memory_allocated() / 2**20
    peak = peak_rss_bytes()
    return float("nan") if peak is None else peak / 2**20


def run_config(dataset: str, cfg: FieldBenchConfig, budget: float, checkpoints: Sequence[float], device: str, seed: int, progress: bool) -> dict:
    """Train one configuration for ``budget`` seconds of training time and measure it (one JSON row)."""
    from tqdm.auto import tqdm

    ds = load_dataset(dataset, truth=False)
    mcfg = bench_model_config(ds.meta, cfg, eye=blinks_in(ds.eye, ds.meta.train))
    times = sorted({float(t) for t in checkpoints if 0 < t < budget} | {float(budget)})
    with tempfile.TemporaryDirectory() as tmp:
        tcfg = TrainConfig(head_iters=10**9, checkpoint_every=10**9, log_every=10**9, seed=seed)
        tr = Trainer(Path(tmp), ds, mcfg, tcfg, device, progress=False)
        evalset = _eval_set(tr, torch.Generator().manual_seed(seed + 1))
        bar = tqdm(total=round(budget), desc=f"bench {cfg.name}", unit="s", disable=not progress, dynamic_ncols=True)

        def train_until(seconds: float) -> None:
            while tr.elapsed["head"] < seconds:
                if tr.head_step >= tr.tcfg.head_iters:
                    fit_schedule()  # the estimate ran out before the budget: stretch the schedule
                tr.head_stage(1)
                _sync(device)
                bar.n = min(round(tr.elapsed["head"]), bar.total)
                bar.set_postfix(it=tr.head_step)
                bar.refresh()

        def fit_schedule() -> None:  # iterations that fit the rest of the budget at the current speed
            rate = tr.head_step / max(tr.elapsed["head"], 1e-9)
            tr.set_iterations("head", max(tr.head_step + 1, tr.head_step + round((budget - tr.elapsed["head"]) * rate)))

        while tr.head_step < 3 and tr.elapsed["head"] < budget:
            tr.head_stage(1)
        fit_schedule()
        rows = []
        refitted = False
        for t in times:
            if not refitted and t > 0.2 * budget:
                train_until(0.2 * budget)
                fit_schedule()
                refitted = True
            train_until(t)
            rows.append({"seconds": t, "elapsed": round(tr.elapsed["head"], 3), "iterations": tr.head_step, "psnr": round(_eval_psnr(tr, evalset), 3)})
        bar.close()
        train_samples_per_s = tr.samples / max(tr.elapsed["head"], 1e-9)

        # Head frames per second at the dataset size: one untimed frame, then up to 24 frames or
        # 10 s (a few frames take a fraction of a second: too short on a machine whose speed
        # varies from one moment to the next).
        model = tr.model.eval()
        plate = tr.plate.reshape(tr.camera.height, tr.camera.width, 3)
        frames = [f for f, _ in evalset] or ds.meta.train[:1]
        codes = dict(zip(frames, model.frame_codes(tr.windows, frames).detach()))
        render_frame(model, tr.camera, ds.head_pose(frames[0], device=device), codes[frames[0]], plate, layers=("head",))
        n_frames, start = 0, time.perf_counter()
        while n_frames < 24 and (n_frames == 0 or time.perf_counter() - start < 10):
            f = frames[n_frames % len(frames)]
            render_frame(model, tr.camera, ds.head_pose(f, device=device), codes[f], plate, layers=("head",))
            _sync(device)
            n_frames += 1
        render_fps = n_frames / (time.perf_counter() - start)
    return {
        "config": cfg.name,
        "description": cfg.description,
        "device": device,
        "size": ds.meta.width,
        "budget_s": budget,
        "checkpoints": rows,
        "psnr_final": rows[-1]["psnr"],
        "iterations": tr.head_step,
        "train_samples_per_s": round(train_samples_per_s),
        "render_fps": round(render_fps, 3),
        "peak_memory_mb": round(_peak_memory_mb(device), 1),
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip() + f", torch {torch.__version__}, {torch.get_num_threads()} threads",
    }


def _reference_times(rows: list[dict], reference: str) -> None:
    """Add, to every row, the first checkpoint at which it reaches the reference's final PSNR."""
    ref = next((r for r in rows if r["config"] == reference), None)
    if ref is None:
        return
    for r in rows:
        reached = next((c["seconds"] for c in r["checkpoints"] if c["psnr"] >= ref["psnr_final"]), None)
        r["reference"] = reference
        r["seconds_to_reference_psnr"] = reached
        r["speedup_vs_reference"] = None if reached is None else round(ref["budget_s"] / reached, 2)


def bench_fields(
    dataset: str | Path | None = None,
    *,
    configs: Sequence[str] | None = None,
    budget: float = 300.0,
    checkpoints: Sequence[float] = DEFAULT_CHECKPOINTS,
    size: int = 128,
    synth_seconds: float = 18.0,
    device: str = "cpu",
    seed: int = 0,
    isolate: bool = True,
    progress: bool = True,
    synth_config: SynthConfig | None = None,
) -> list[dict]:
    """Train every configuration on one scene for the same time budget and measure it.

    Args:
        dataset: A dataset folder; ``None`` synthesises the built-in scene (``size`` px,
            ``synth_seconds`` of speech) in a temporary folder.
        configs: Names from :data:`CONFIGS` (default: all, the paper's first).
        budget: Seconds of training per configuration (evaluation is not counted).
        checkpoints: Training times (s) at which the held-out PSNR is measured; the budget is
            always one.
        size: Frame size of the synthesised scene.
        synth_seconds: Audio length of the synthesised scene.
        device: ``"cpu"`` or ``"cuda"``.
        seed: Seed of initialisation, sampling and the held-out rays.
        isolate: Run each configuration in a fresh process (honest peak memory, no shared
            allocator state; the process tunes its allocator as the ``adnerf`` command does,
            see :mod:`adnerf.allocator`); off for tests.
        progress: Progress bars.
        synth_config: Overrides ``size`` and ``synth_seconds`` for the synthesised scene.

    Returns:
        One dict per configuration (see the module docstring), plus ``seconds_to_reference_psnr``
        and ``speedup_vs_reference`` against ``paper`` when it is among them.
    """
    by_name = {c.name: c for c in CONFIGS}
    names = list(configs) if configs else [c.name for c in CONFIGS]
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise ValueError(f"unknown field configurations {unknown}; choose from {sorted(by_name)}")
    if budget <= 0:
        raise ValueError(f"budget must be > 0 seconds; got {budget}")
    with tempfile.TemporaryDirectory() as tmp:
        if dataset is None:
            dataset = Path(tmp) / "scene"
            if progress:
                print(f"synthesising the scene ({size} px) in {dataset}", file=sys.stderr)
            synthesize(dataset, synth_config or SynthConfig(seconds=synth_seconds, size=size, seed=seed))
        rows = []
        for name in names:
            args = (str(dataset), by_name[name], budget, tuple(checkpoints), device, seed, progress)
            if isolate:
                # The worker tunes the allocator as the adnerf command does (see adnerf.allocator).
                with ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn"), initializer=tune_allocator) as pool:
                    rows.append(pool.submit(run_config, *args).result())
            else:
                rows.append(run_config(*args))
    _reference_times(rows, "paper")
    return rows


def format_fields_table(rows: list[dict]) -> str:
    """A readable table: held-out head PSNR at each checkpoint, speeds, memory."""
    times = sorted({c["seconds"] for r in rows for c in r["checkpoints"]})
    head = f"{'config':<17}" + "".join(f"{f'{t:g} s':>8}" for t in times) + f"{'its':>7}{'Msamp/s':>9}{'fps':>7}{'peak MB':>9}{'to paper':>10}"
    lines = ["held-out head PSNR (dB) after seconds of training", head, "-" * len(head)]
    for r in rows:
        psnr = {c["seconds"]: c["psnr"] for c in r["checkpoints"]}
        cells = "".join(f"{psnr[t]:>8.2f}" if t in psnr else f"{'':>8}" for t in times)
        reach = r.get("seconds_to_reference_psnr")
        to_ref = "-" if "reference" not in r else ("never" if reach is None else f"<= {reach:g} s")
        lines.append(
            f"{r['config']:<17}{cells}{r['iterations']:>7}{r['train_samples_per_s'] / 1e6:>9.3f}{r['render_fps']:>7.2f}{r['peak_memory_mb']:>9.0f}{to_ref:>10}"
        )
    if rows:
        lines.append(f"({rows[0]['size']}x{rows[0]['size']} px, {rows[0]['device']}, {rows[0]['machine']}; fps: head frames over the plate)")
    return "\n".join(lines)


def load_rows(path: str | Path) -> list[dict]:
    """Rows saved as JSON lines (``adnerf bench fields --json > FILE``)."""
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip().startswith("{")]


def plot_fields(rows: list[dict], path: str | Path | None = None, ax=None):  # noqa: ANN001 - matplotlib types
    """Plot held-out PSNR against training time per configuration (log time axis).

    Args:
        rows: Benchmark rows.
        path: Save the figure there (PNG) when given.
        ax: Draw into this matplotlib axis instead of a new figure.

    Returns:
        The matplotlib figure.
    """
    if ax is None:
        from matplotlib.figure import (
            Figure,  # no pyplot: no global state, no GUI backend
        )

        fig = Figure(figsize=(6.4, 4.2), dpi=110)
        ax = fig.subplots()
    else:
        fig = ax.figure
    for r in rows:
        t = [c["elapsed"] for c in r["checkpoints"]]
        p = [c["psnr"] for c in r["checkpoints"]]
        ax.plot(t, p, marker="o", label=f"{r['config']} ({r['train_samples_per_s'] / 1e3:.0f}k samples/s)")
    ref = next((r for r in rows if r["config"] == "paper"), None)
    if ref is not None:
        ax.axhline(ref["psnr_final"], color="gray", linestyle=":", linewidth=1, label=f"paper after {ref['budget_s']:g} s")
    ax.set_xscale("log")
    ax.set_xlabel("training time (s)")
    ax.set_ylabel("held-out head PSNR (dB)")
    if rows:
        ax.set_title(f"error against training time, {rows[0]['size']} px, {rows[0]['device']}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path)
    return fig
