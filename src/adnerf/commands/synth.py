"""``adnerf synth``: the built-in synthetic talking head, with exact truth, as a dataset."""

from __future__ import annotations

import argparse

from tqdm import tqdm

from ..audio.espeak import EspeakError, check_voice
from ..formats.outputs import check_folder_output
from ..lock import FolderLock
from ..synth import SynthConfig, espeak_available, synthesize
from .options import CliError, add_overwrite, number

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("synth", help="create a synthetic talking-head dataset with exact ground truth")
    p.add_argument("-o", "--output", required=True, help="dataset folder to create")
    p.add_argument("--seconds", type=number(float, 1.0, 600.0), default=18.0, help="length of the scene, 1 to 600 s")
    p.add_argument("--size", type=number(int, 16, 1024), default=128, help="frame width and height in pixels, 16 to 1024")
    p.add_argument("--fps", type=number(float, 1.0, 120.0), default=25.0, help="frame rate, 1 to 120")
    p.add_argument("--seed", type=number(int, 0), default=0, help="random seed of the pose track and the speech (>= 0)")
    p.add_argument("--voice", choices=("auto", "formant", "espeak"), default="auto", help="speech source (auto: espeak-ng when installed)")
    p.add_argument("--speaker", default="en", help="espeak-ng voice of the speech, e.g. en, en+f3 (female), en-us+klatt (espeak-ng --voices lists them)")
    p.add_argument("--wpm", type=number(int, 80, 450), default=150, help="speaking rate of the espeak-ng speech, 80 to 450 words per minute")
    p.add_argument("--mouth", choices=("auto", "visemes", "loudness"), default="auto", help="what opens the jaw: the phonemes spoken (visemes; needs espeak-ng) or the voice's loudness (auto: visemes with espeak-ng)")
    p.add_argument("--features", choices=("logmel", "phonemes"), default="logmel", help="audio features stored with the dataset")
    add_overwrite(p, "replace an existing adnerf dataset folder (never another folder)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    cfg = SynthConfig(seconds=args.seconds, size=args.size, seed=args.seed, voice=args.voice, speaker=args.speaker, words_per_minute=args.wpm, mouth=args.mouth, features=args.features, fps=args.fps)
    try:
        cfg.validate()
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    check_folder_output(args.output, "dataset", overwrite=args.overwrite)  # before the progress bar
    try:
        if cfg.voice == "espeak" or (cfg.voice == "auto" and espeak_available()):
            check_voice(cfg.speaker)
        with FolderLock(args.output, "dataset"), tqdm(total=cfg.n_frames, desc="synth frames", unit="frame") as bar:  # the lock before the bar
            out = synthesize(args.output, cfg, progress=lambda step, done, total: bar.update(done - bar.n), overwrite=args.overwrite)
    except EspeakError as exc:  # an unknown --speaker, or no espeak-ng for --voice espeak
        raise CliError(str(exc)) from exc
    print(f"{out}: synthetic talking head, {cfg.seconds:g} s at {cfg.fps:g} fps, {cfg.size}x{cfg.size}")
    return 0
