"""One GPU check, sized for a short lease: correctness on CUDA, the demo, render speed, error vs time.

Run from the repository root on a machine with one CUDA GPU::

    python tools/gpu_check.py                      # writes docs/bench/gpu.json (about 8 minutes)
    python tools/gpu_check.py --out gpu.json --skip bench_render,fields --demo-scales 2 --real DATA --real-scale 4

Steps, each timed, each written to the JSON as soon as it ends (so a run stopped part-way keeps
what it measured), each with its own time limit:

1. ``tests``: the device tests on CUDA (``pytest --device cuda tests/test_devices.py``).
2. ``demo``: ``adnerf demo --device cuda --scale K`` (``--demo-scale K``, default 1): wall time,
   training time and the demo's metrics.
3. ``render``: frames per second of the demo's trained model at 450x450 (head and torso, and head
   alone), steady state, in whole-frame batches of 262144 rays (the GPU default of
   :func:`adnerf.model.talking_head.render_chunk`).
4. ``stream``: ``adnerf stream`` of the demo's run on its own speech, on the device, with the
   offline render's look-ahead and with ``--causal``: look-ahead, first-frame latency, frames
   per second and the real-time factor (a file is pushed as fast as it is read).
5. ``steps``: seconds per stage-1 training iteration on the demo's data against the rays per
   iteration (1024, the CPU's default, to 8192), drawn from one frame and from ``rays / 1024``
   frames (rendered in one call), timed over ``--steps-counts`` iterations after a warm-up
   (empty-space skipping is on after a tenth of them).
6. ``demo_scaled``: the demo's scene trained again with ``TrainConfig().scaled(k)`` for each
   ``k`` of ``--demo-scales`` (``k`` times the rays, from ``k`` times the frames, in ``k`` times
   fewer steps): time and bars.
7. ``real``: with ``--real DATA`` (a preprocessed real clip), a run trained on the GPU with
   ``TrainConfig(HEAD, TORSO).scaled(K)`` (``--real-iters HEAD,TORSO``, ``--real-scale K``), its
   training time and its held-out metrics without the landmark ones (``adnerf evaluate
   --no-landmarks``); the run stays in the scratch folder for the landmark metrics elsewhere.
8. ``bench_render``: ``adnerf bench render --device cuda`` (quadrature error and time per Mray).
9. ``fields``: a shortened ``adnerf bench fields --device cuda`` (held-out PSNR against time).

The JSON records the device name, torch and CUDA versions and, per step, its figures or the error.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STEPS = ("tests", "demo", "render", "stream", "steps", "demo_scaled", "real", "bench_render", "fields")


def _run(cmd: list[str], limit: float) -> tuple[int, str, float]:
    """Run a command with a time limit; returns (exit code, its output, seconds)."""
    t0 = time.perf_counter()
    try:
        done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=limit, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        return done.returncode, done.stdout + done.stderr, time.perf_counter() - t0
    except subprocess.TimeoutExpired as exc:
        out = (exc.stdout or b"").decode(errors="replace") if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        return 124, out + f"\n(stopped after {limit:.0f} s)", time.perf_counter() - t0


def _sync(device: str) -> None:
    """Wait for the device's queued work (timings on CUDA)."""
    if device.startswith("cuda"):
        import torch

        torch.cuda.synchronize()


def _ints(text: str) -> tuple[int, ...]:
    """A comma-separated list of integers (an option's value)."""
    return tuple(int(x) for x in text.split(",") if x)


def _json_lines(text: str) -> list[dict]:
    rows = []
    for line in text.splitlines():
        if line.startswith("{"):
            try:
                rows.append(json.loads(line))
            except ValueError:
                pass
    return rows


def step_tests(args: argparse.Namespace) -> dict:
    code, out, seconds = _run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--device", args.device, "tests/test_devices.py"], args.limit)
    summary = [line for line in out.splitlines() if " passed" in line or " failed" in line or " skipped" in line]
    return {"exit_code": code, "summary": summary[-1] if summary else out[-500:], "seconds": seconds}


DEMO_FIGURES = ("psnr_test", "ssim_test", "psnr_mouth_test", "mouth_open_corr", "mouth_open_corr_gt", "blink_corr", "blink_corr_gt", "train_seconds", "synth_seconds", "render_fps", "total_seconds")


def _demo_result(folder: Path, code: int, out: str, seconds: float) -> dict:
    """A demo's figures and schedule from ``folder/metrics.json``, or its output's tail."""
    result: dict = {"exit_code": code, "wall_seconds": seconds}
    if (folder / "metrics.json").exists():
        metrics = json.loads((folder / "metrics.json").read_text())
        result.update({k: metrics.get(k) for k in DEMO_FIGURES})
        result["schedule"] = {k: metrics["train"][k] for k in ("rays", "head_iters", "torso_iters")}
        result["voice"] = json.loads((folder / "data" / "meta.json").read_text())["source"].split("voice=")[-1]
    else:
        result["output_tail"] = out[-2000:]
    return result


def step_demo(args: argparse.Namespace) -> dict:
    folder = Path(args.work) / "demo"
    code, out, seconds = _run([sys.executable, "-m", "adnerf.cli", "demo", "-o", str(folder), "--device", args.device, "--scale", str(args.demo_scale)], args.demo_limit)
    return {"scale": args.demo_scale, **_demo_result(folder, code, out, seconds)}


def step_render(args: argparse.Namespace) -> dict:
    import torch

    from adnerf.cameras import Camera, intrinsics_matrix
    from adnerf.formats.dataset import load_dataset
    from adnerf.model.talking_head import render_frame
    from adnerf.model.train import load_run

    folder = Path(args.work) / "demo"
    run = load_run(folder / "run", args.device)
    ds = load_dataset(folder / "data")
    size = args.render_size
    scale = size / ds.meta.width
    fx, fy, cx, cy = (v * scale for v in ds.meta.intrinsics)
    camera = Camera(intrinsics_matrix(fx, fy, cx, cy).to(args.device), size, size)
    plate = torch.nn.functional.interpolate(torch.as_tensor(ds.background, dtype=torch.float32).permute(2, 0, 1)[None] / 255.0, size=(size, size), mode="bilinear")[0].permute(1, 2, 0).to(args.device)
    with torch.no_grad():
        codes = run.model.frame_codes(torch.as_tensor(ds.features, device=args.device))
    frames = list(ds.meta.test)
    result: dict = {"size": size, "frames": len(frames)}

    for torso in (True, False):
        for chunk in (262144,):  # 1024 (the CPU's) gave 0.8 frames/s on an H100, 65536 19-22
            def one(i: int) -> None:
                pose = ds.head_pose(frames[i % len(frames)], device=args.device)
                render_frame(run.model, camera, pose, codes[frames[i % len(frames)]], plate, layers=None if torso else ("head",), chunk=chunk, amp=run.train_config.amp)

            for i in range(3):  # warm-up
                one(i)
            _sync(args.device)
            t0, n = time.perf_counter(), 0
            while n < 10 or (time.perf_counter() - t0 < 5.0 and n < 200):
                one(n)
                n += 1
            _sync(args.device)
            key = f"{'head_torso' if torso else 'head'}_chunk{chunk}_fps"
            result[key] = n / (time.perf_counter() - t0)
    if args.device == "cuda":
        result["max_memory_gb"] = torch.cuda.max_memory_allocated() / 1e9
    return result


def step_stream(args: argparse.Namespace) -> dict:
    folder = Path(args.work) / "demo"
    rows = []
    for mode, extra in (("offline look-ahead", []), ("causal", ["--causal"])):
        cmd = [sys.executable, "-m", "adnerf.cli", "stream", str(folder / "run"), "--audio", str(folder / "data" / "audio.wav"), "-o", str(Path(args.work) / "stream.mp4"), "--overwrite", "--device", args.device, "--json", *extra]
        code, out, seconds = _run(cmd, args.limit)
        if code != 0:
            return {"exit_code": code, "mode": mode, "output_tail": out[-2000:]}
        summary = _json_lines(out)[-1]
        rows.append({"mode": mode, "seconds": seconds, **summary, "frames_per_s": summary["frames"] / max(summary["wall_seconds"], 1e-9)})
    return {"rows": rows}


def step_steps(args: argparse.Namespace) -> dict:
    import torch

    from adnerf.model.blinks import blinks_in
    from adnerf.formats.dataset import load_dataset
    from adnerf.model.talking_head import model_config
    from adnerf.model.train import TrainConfig, Trainer

    ds = load_dataset(Path(args.work) / "demo" / "data", truth=False)
    rows = []
    warm, timed = args.steps_counts
    # Each ray count with the trainer's Adam (fused on CUDA) from one frame, and from as many frames
    # as it has times the smallest count (what scaled(k) draws: as many rays a frame, one render
    # call for all); the smallest also with the multi-tensor Adam PyTorch uses by default there:
    # what fusing saves per step.
    base = args.steps_rays[0]
    runs = [(r, 1, "trainer") for r in args.steps_rays]
    runs += [(r, r // base, "trainer") for r in args.steps_rays if r // base > 1 and r % (r // base) == 0]
    runs += [(base, 1, "foreach")]
    for rays, frames, adam in runs:
        tcfg = TrainConfig(rays=rays, frames=frames, head_iters=warm + timed, checkpoint_every=10**9, log_every=10**9)
        root = Path(args.work) / f"steps_{rays}_{frames}_{adam}"
        root.mkdir(parents=True, exist_ok=True)
        trainer = Trainer(root, ds, model_config(ds.meta, "fast", eye=blinks_in(ds.eye, ds.meta.train)), tcfg, args.device, False)
        if adam == "foreach":
            trainer.optimizers["head"] = torch.optim.Adam([{"params": g["params"], "lr": g["lr"]} for g in trainer.opt_head.param_groups], betas=(0.9, 0.99))
        trainer.head_stage(warm)  # past occupancy_start: empty-space skipping on, as in most of a run
        _sync(args.device)
        t0 = time.perf_counter()
        trainer.head_stage(timed)
        _sync(args.device)
        rows.append({"rays": rays, "frames": frames, "adam": adam, "seconds_per_iteration": (time.perf_counter() - t0) / timed, "eye_batch": bool(trainer.blinking.numel())})
    return {"stage": "head", "rows": rows}


def step_demo_scaled(args: argparse.Namespace) -> dict:
    """The demo's scene trained with ``TrainConfig().scaled(k)`` (k times the rays in k times fewer
    steps) for each ``k`` of ``--demo-scales``; the scene is the demo step's."""
    import shutil

    result: dict = {}
    for k in args.demo_scales:
        folder = Path(args.work) / f"demo_x{k}"
        if not (folder / "data").exists():
            shutil.copytree(Path(args.work) / "demo" / "data", folder / "data")
        script = (
            "import sys; from adnerf.commands.demo import run_demo; from adnerf.model.train_config import TrainConfig; "
            f"run_demo(sys.argv[1], device={args.device!r}, train_config=TrainConfig().scaled({k}), progress=False)"
        )
        result[f"x{k}"] = _demo_result(folder, *_run([sys.executable, "-c", script, str(folder)], args.demo_limit))
    return result


def step_real(args: argparse.Namespace) -> dict:
    if not args.real:
        return {"skipped": "no --real dataset"}
    return {Path(data).name if len(args.real) > 1 else "run": _real_run(args, data, i) for i, data in enumerate(args.real)}


def _real_run(args: argparse.Namespace, data: str, index: int) -> dict:
    """One ``--real`` dataset trained on the device and measured on its held-out frames."""
    import torch

    from adnerf.evaluation.evaluate import evaluate_run
    from adnerf.formats.dataset import load_dataset
    from adnerf.model.train import TrainConfig, load_run, train

    head, torso = args.real_iters
    tcfg = TrainConfig(head_iters=head, torso_iters=torso).scaled(args.real_scale)
    run_dir = Path(args.work) / ("real_run" if index == 0 else f"real_run{index}")
    t0 = time.perf_counter()
    try:
        train(data, run_dir, config=tcfg, device=args.device, progress=False)
    except Exception as exc:  # one dataset's failure leaves the next one its turn
        return {"data": data, "error": f"{type(exc).__name__}: {exc}"}
    seconds = time.perf_counter() - t0
    elapsed = torch.load(run_dir / "checkpoint.pt", map_location="cpu", weights_only=False)["elapsed"]  # seconds in each stage's loop
    ds = load_dataset(data)
    metrics, _ = evaluate_run(load_run(run_dir, args.device), ds, "test", landmarks=False)
    keep = ("frames", "psnr", "ssim", "psnr_mouth", "ssim_mouth", "psnr_head", "ssim_head", "render_fps")
    schedule = {"rays": tcfg.rays, "frames": tcfg.frames, "head_iters": tcfg.head_iters, "torso_iters": tcfg.torso_iters}
    return {"data": data, "size": [ds.meta.width, ds.meta.height], "schedule": schedule, "train_wall_seconds": seconds, "loop_seconds": elapsed, "run": str(run_dir), **{k: metrics.get(k) for k in keep}}


def step_bench_render(args: argparse.Namespace) -> dict:
    code, out, seconds = _run([sys.executable, "-m", "adnerf.cli", "bench", "render", "--device", args.device, "--json"], args.limit)
    return {"exit_code": code, "seconds": seconds, "rows": _json_lines(out)} if code == 0 else {"exit_code": code, "output_tail": out[-2000:]}


def step_fields(args: argparse.Namespace) -> dict:
    checkpoints = ",".join(str(c) for c in (5, 10, 20, 30, 60, 120, 300) if c <= args.fields_budget)
    cmd = [sys.executable, "-m", "adnerf.cli", "bench", "fields", "--device", args.device, "--json", "--budget", str(args.fields_budget), "--checkpoints", checkpoints, "--configs", args.fields_configs]
    code, out, seconds = _run(cmd, args.limit)
    return {"exit_code": code, "seconds": seconds, "budget": args.fields_budget, "rows": _json_lines(out)} if code == 0 else {"exit_code": code, "output_tail": out[-2000:]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default=str(ROOT / "docs" / "bench" / "gpu.json"), help="JSON to write (default docs/bench/gpu.json)")
    parser.add_argument("--work", default="/tmp/adnerf_gpu_check", help="scratch folder (the demo's data and run)")
    parser.add_argument("--device", default="cuda", help="cuda (default), or cpu to try the script itself")
    parser.add_argument("--skip", default="", help="comma-separated steps to skip: " + ", ".join(STEPS))
    parser.add_argument("--limit", type=float, default=300.0, help="seconds allowed per other step (default 300)")
    parser.add_argument("--demo-limit", type=float, default=420.0, help="seconds allowed for the demo step (default 420)")
    parser.add_argument("--render-size", type=int, default=450, help="frame side for the render speed (default 450, as AD-NeRF)")
    parser.add_argument("--fields-budget", type=float, default=30.0, help="training seconds per configuration in the fields bench (default 30)")
    parser.add_argument("--fields-configs", default="paper,fast", help="configurations of the fields bench (default paper,fast)")
    parser.add_argument("--steps-rays", default=(1024, 2048, 4096, 8192), type=_ints, help="rays per iteration of the steps step (default 1024,2048,4096,8192)")
    parser.add_argument("--steps-counts", default=(60, 60), type=_ints, help="WARM,TIMED iterations per ray count of the steps step (default 60,60)")
    parser.add_argument("--real", action="append", default=[], help="a preprocessed real clip (dataset folder) to train on the GPU (the real step); repeat for several (runs in real_run, real_run1, ...)")
    parser.add_argument("--real-iters", default=(4345, 3555), type=_ints, help="HEAD,TORSO iterations of the real step's schedule before --real-scale (default 4345,3555: the CPU bench's schedule)")
    parser.add_argument("--real-scale", type=int, default=1, help="the real step trains TrainConfig(HEAD, TORSO).scaled(this): this many times the rays in as many times fewer steps (default 1)")
    parser.add_argument("--demo-scale", type=int, default=1, help="the demo step runs adnerf demo --scale this (default 1; the render and steps steps use its scene and run)")
    parser.add_argument("--demo-scales", default=(), type=_ints, help="demo_scaled step: scales k of TrainConfig().scaled(k) to train the demo's scene with (default none)")
    args = parser.parse_args()

    import torch

    doc: dict = {
        "device": torch.cuda.get_device_name(0) if args.device == "cuda" and torch.cuda.is_available() else "cpu",
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "date": time.strftime("%Y-%m-%d"),
        "command": "python " + " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]]),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    skip = set(filter(None, args.skip.split(",")))
    for name in STEPS:
        if name in skip:
            continue
        print(f"== {name}", flush=True)
        t0 = time.perf_counter()
        try:
            doc[name] = globals()[f"step_{name}"](args)
        except Exception as exc:  # a failed step is recorded, and the next one still runs
            doc[name] = {"error": f"{type(exc).__name__}: {exc}"}
        doc[name]["step_seconds"] = round(time.perf_counter() - t0, 1)
        print(json.dumps(doc[name])[:1500], flush=True)
        out.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
