"""``adnerf check-preprocess``: a preprocessed synthetic video against the scene's truth."""

from __future__ import annotations

import argparse
import json

from ..preprocess.check import check_preprocess
from .options import add_json

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("check-preprocess", help="compare a preprocessed synthetic video with the scene's truth (pose, parsing, plate)")
    p.add_argument("dataset", help="dataset written by adnerf preprocess from a synthetic scene's video")
    p.add_argument("--truth", required=True, help="the synthetic scene folder (adnerf synth output)")
    add_json(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = check_preprocess(args.dataset, args.truth)
    if args.json:
        print(json.dumps(out))
    else:
        for k, v in out.items():
            print(f"{k:32s} {v}")
    return 0
