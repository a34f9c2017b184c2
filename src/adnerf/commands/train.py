"""``adnerf train``: the head (stage 1) and torso (stage 2) of a dataset, into a run folder."""

from __future__ import annotations

import argparse
import os

from ..formats.run_folder import RunError, RunFolder
from ..model.run_folder import stored_config
from ..model.train import train
from ..model.train_config import TrainConfig
from .options import CliError, add_device, checked_device, config_file, count, number

__all__ = ["register", "run", "train_config"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train the head (stage 1) and torso (stage 2) fields on a dataset")
    p.add_argument("dataset", help="dataset folder")
    p.add_argument("-o", "--output", required=True, help="run folder")
    p.add_argument("--stage", choices=("head", "torso", "all"), default="all", help="head (stage 1), torso (stage 2; needs a finished head stage and --resume) or all")
    p.add_argument("--iters", type=count, default=None, help="iterations of the stage, >= 0 (with all: head; the torso gets half); with --resume, trains the run longer")
    p.add_argument("--amp", choices=("auto", "bf16", "off"), default=None, help="mixed precision of the fields (default auto: bfloat16 on CUDA, off on CPU)")
    p.add_argument("--scale", type=number(int, 1, 64), default=1, help="train the schedule (after --config and --iters) in K times fewer steps of K times the rays, drawn from K times the frames, with the learning rates times sqrt(K) (for GPUs, where a larger step costs little more; K=4 is measured in docs/benchmarks.md, K=8 leaves the torso too few steps); a new run only")
    add_device(p)
    p.add_argument("--config", default=None, help="JSON file of TrainConfig fields (e.g. {\"rays\": 2048, \"preset\": \"paper\"}); with --resume only head_iters, torso_iters, amp, checkpoint_every and log_every may differ from the run's")
    p.add_argument("--resume", action="store_true", help="continue from the run's checkpoint, with its stored config, on the same dataset")
    p.set_defaults(func=run)


def train_config(args: argparse.Namespace) -> TrainConfig:
    """The schedule: ``--config`` keys, then ``--amp`` and ``--iters``, over the defaults (a new
    run) or over the run's stored schedule (``--resume``), so a resume changes only what is given."""
    doc = config_file(args.config)
    if getattr(args, "amp", None):
        doc["amp"] = args.amp
    base = TrainConfig()
    if args.resume:
        if not RunFolder(args.output).is_run():
            raise RunError(f"{args.output}: nothing to resume (no {RunFolder(args.output).run_json.name}); drop --resume to start a new run")
        base = stored_config(args.output)
    if args.iters is not None:
        if args.stage in ("head", "all"):
            doc["head_iters"] = args.iters
        if args.stage in ("torso", "all"):
            doc["torso_iters"] = args.iters if args.stage == "torso" else args.iters // 2
    scale = getattr(args, "scale", 1)
    if scale > 1 and args.resume:
        raise CliError("--scale sets a new run's schedule; a resumed run keeps its own (drop --scale)")
    try:
        cfg = TrainConfig.from_dict(doc, base)
        cfg.validate()
        cfg = cfg.scaled(scale)
        cfg.validate()
    except (TypeError, ValueError) as exc:
        raise CliError(f"invalid training config: {exc}") from exc
    return cfg


def run(args: argparse.Namespace) -> int:
    cfg = train_config(args)
    root = train(args.dataset, args.output, stage=args.stage, config=cfg, device=checked_device(args.device), resume=args.resume)
    if os.environ.get("RANK", "0") == "0":  # under torchrun, process 0 speaks for all
        print(f"{root}: trained ({args.stage}); render with `adnerf render {root} --audio SPEECH -o out.mp4`")
    return 0
