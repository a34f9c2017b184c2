"""``adnerf evaluate``: a run's renders of a dataset's frames against the truth."""

from __future__ import annotations

import argparse
import json

from ..evaluation.evaluate import evaluate_run
from ..evaluation.fitted_poses import POSE_CHOICES
from ..evaluation.lpips import lpips_if_available
from ..evaluation.pose_sweep import SWEEP_YAWS, pose_sweep, spread, sweep_sheet
from ..evaluation.syncnet import load_syncnet
from ..formats.dataset import load_dataset
from ..model.run_folder import load_run
from .options import CliError, add_device, add_json, add_metric_weights, checked_device, count

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="PSNR / SSIM (full frame, head, mouth), LMD, lip sync, and LPIPS and SyncNet LSE-D / LSE-C (with local weights) on held-out frames")
    p.add_argument("run", help="run folder")
    p.add_argument("dataset", help="dataset folder")
    p.add_argument("--split", choices=("train", "test"), default="test")
    p.add_argument("--poses", choices=POSE_CHOICES, default="fitted", help="the head poses the frames are rendered under: fitted (default: the tracked poses aligned to each frame's head outside the mouth box, as training aligns its own frames) or tracked (the preprocessing's poses as they are)")
    add_device(p)
    p.add_argument("--no-landmarks", action="store_true", help="skip the landmark metrics (LMD, lip-sync correlation and offset; dlib on every frame twice)")
    add_metric_weights(p)
    p.add_argument("--sweep", type=count, default=0, metavar="FRAMES", help="also render this many frames of the split with the head turned by 0, 5, 10, 15 and 20 degrees of yaw and measure how the face, the neck and the torso hold up (pose_sweep in the output); 0: no sweep")
    p.add_argument("--sweep-sheet", default=None, metavar="PNG", help="with --sweep: a contact sheet of the sweep's renders")
    add_json(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    device = checked_device(args.device)
    try:
        model = lpips_if_available(args.lpips_backbone, args.lpips_linear, device)
        sync = load_syncnet(args.syncnet, device) if args.syncnet else None
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    loaded = load_run(args.run, device)
    ds = load_dataset(args.dataset)
    metrics, _ = evaluate_run(loaded, ds, args.split, landmarks=not args.no_landmarks, lpips=model, syncnet=sync, poses=args.poses, progress=True)
    metrics["lpips"] = metrics.get("lpips", "no weights")
    if args.sweep:
        frames = spread(getattr(ds.meta, args.split), args.sweep)
        metrics["pose_sweep"], renders = pose_sweep(loaded, ds, frames)
        if args.sweep_sheet:
            sweep_sheet(args.sweep_sheet, renders, SWEEP_YAWS, [f"frame {f}" for f in frames])
    metrics.pop("syncnet_curve", None)
    metrics = {k: v for k, v in metrics.items() if not k.startswith("mouth_opening_")}  # the per-frame series: bench real --plot draws them
    if args.json:
        print(json.dumps(metrics))
    else:
        for key, value in metrics.items():
            print(f"{key:>20}: {value:.4f}" if isinstance(value, float) else f"{key:>20}: {value}")
    return 0
