"""``adnerf import-adnerf``: a dataset the original AD-NeRF code preprocessed, as an adnerf dataset."""

from __future__ import annotations

import argparse
import sys
import warnings

from tqdm import tqdm

from ..lock import FolderLock
from ..preprocess.adnerf_import import import_adnerf
from .options import add_overwrite, positive

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("import-adnerf", help="convert a dataset preprocessed by the original AD-NeRF code into an adnerf dataset")
    p.add_argument("source", help="AD-NeRF dataset folder (transforms_train.json, ori_imgs/, parsing/, bc.jpg, aud.npy, aud.wav)")
    p.add_argument("-o", "--output", required=True, help="dataset folder to create")
    p.add_argument("--fps", type=positive, default=25.0, help="frame rate of the original video (> 0; AD-NeRF assumes 25)")
    p.add_argument("--audio", default=None, help="the original audio (default SOURCE/aud.wav)")
    add_overwrite(p, "replace an existing adnerf dataset folder (never another folder, nor one holding the source)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    with FolderLock(args.output, "dataset"), tqdm(desc="import frames", unit="frame") as bar, warnings.catch_warnings(record=True) as caught:  # the lock before the bar
        warnings.simplefilter("always")

        def tick(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        summary = import_adnerf(args.source, args.output, fps=args.fps, audio=args.audio, overwrite=args.overwrite, progress=tick)
    for w in caught:
        print(f"adnerf: warning: {w.message}", file=sys.stderr)
    print(
        f"{summary['dataset']}: {summary['frames']} frames ({summary['train']} train, {summary['test']} test), "
        f"{summary['size'][0]}x{summary['size'][1]}, DeepSpeech features {tuple(summary['features'])}, poses rescaled by {summary['scale']:.4g}; "
        f"train with `adnerf train {summary['dataset']} -o RUN`"
    )
    return 0
