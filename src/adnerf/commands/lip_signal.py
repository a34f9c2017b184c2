"""``adnerf lip-signal``: how much a preprocessed clip's audio predicts its mouth opening."""

from __future__ import annotations

import argparse
import json

from tqdm import tqdm

from ..audio.features import BUILTIN_KINDS
from ..evaluation.lip_signal import dataset_lip_signal
from ..formats.dataset import DatasetError
from .options import CliError, add_json

__all__ = ["register", "run"]

WORDS = {
    "loudness_corr": "opening vs voiced loudness (corr, same frame)",
    "loudness_offset_frames": "best shift, frames (> 0: mouth after sound)",
    "loudness_corr_at_offset": "corr at that shift",
    "ridge_tail_corr": "audio -> opening, fit on train, held-out corr",
    "ridge_cv_corr": "audio -> opening, {blocks}-block cross-validated corr",
}
ENCODER_SEEDS = 3  # networks of --encoder's ensemble
ENCODER_WORDS = {
    "encoder_tail_corr": "encoder -> opening, held-out corr ({seeds} nets{jitter})",
    "encoder_tail_single_corr": "the same, one net on average",
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("lip-signal", help="how much a preprocessed clip's audio predicts its mouth opening: the lip-sync ceiling of training on it")
    p.add_argument("dataset", help="dataset written by adnerf preprocess (needs its face landmarks)")
    p.add_argument("--blocks", type=int, default=6, help="contiguous cross-validation blocks")
    p.add_argument("--guard", type=int, default=8, help="frames left out on either side of a tested block")
    p.add_argument("--features", choices=BUILTIN_KINDS, default=None, help="compute these features from the dataset's audio instead of reading its own (which extractor carries this clip's mouth, before preprocessing again)")
    p.add_argument("--encoder", type=int, default=0, metavar="EPOCHS", help="also train training's audio encoder (AudioNet and a linear read-out) on the training frames' opening alone for EPOCHS epochs, three networks, and score their mean on the held-out frames: the lip sync a run's audio code can carry at best (e.g. 50; about a minute for a minute of footage on a CPU)")
    p.add_argument("--encoder-jitter", type=int, default=0, metavar="FEATURES", help="with --encoder: train on windows moved in time by up to FEATURES speech features (20 ms each) either way, as training's audio_jitter does (default: 0, none)")
    add_json(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.encoder < 0:
        raise CliError(f"--encoder takes a number of epochs (0: off); got {args.encoder}")
    if args.encoder_jitter and not args.encoder:
        raise CliError("--encoder-jitter moves the windows the encoder trains on: give --encoder EPOCHS too")
    try:
        with tqdm(total=ENCODER_SEEDS * args.encoder, desc="encoder", unit="epoch", disable=args.encoder == 0 or args.json) as bar:
            signal = dataset_lip_signal(args.dataset, args.features, blocks=args.blocks, guard=args.guard, encoder_epochs=args.encoder, encoder_seeds=ENCODER_SEEDS, encoder_jitter=args.encoder_jitter, progress=bar.update)
    except DatasetError:  # not a dataset, no landmarks: main prints it
        raise
    except ValueError as exc:  # too few frames for the folds, a jitter out of range or of imported features
        raise CliError(str(exc)) from exc
    doc = signal.to_dict()
    if args.json:
        print(json.dumps(doc))
        return 0
    print(f"{args.dataset}: {doc['frames']} frames" + (f", {args.features} features from its audio" if args.features else ""))
    for key, text in WORDS.items():
        value = doc[key]
        text = text.format(blocks=args.blocks)
        print(f"{text:>48}: {value:.3f}" if isinstance(value, float) else f"{text:>48}: {value}")
    print(f"{'per block':>48}: " + " ".join(f"{c:.2f}" for c in doc["ridge_cv_blocks"]))
    if args.encoder:
        for key, text in ENCODER_WORDS.items():
            value = doc[key]
            text = text.format(seeds=ENCODER_SEEDS, jitter=f", moved up to {args.encoder_jitter}" if args.encoder_jitter else "")
            print(f"{text:>48}: {value:.3f}" if isinstance(value, float) else f"{text:>48}: {value} (the dataset has no held-out frames)")
    if doc["ridge_cv_corr"] is not None and doc["ridge_cv_corr"] < 0.3:
        print("a cross-validated correlation this low means the clip is too short (or its mouth too little tied to its sound) for any audio encoder to learn its lip movements; AD-NeRF trains on 3-5 minutes")
    return 0
