"""``adnerf features``: per-frame speech feature windows of a video or audio file."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..audio.features import FEATURE_KINDS, MODEL_RATE, FeatureError, FeatureSpec, save_npy_atomic, speech_windows
from ..formats.outputs import check_file_output
from ..io import AudioTrack, MediaError, audio_span, frame_times, probe, read_audio
from .options import CliError, add_overwrite, number, positive

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("features", help="per-frame speech feature windows (N, 16, D) of a video or audio file")
    p.add_argument("media", help="video (frames timed by its timestamps) or audio file (wav, mp3, m4a, flac, ...)")
    p.add_argument("-o", "--output", required=True, help="output .npy file")
    p.add_argument("--kind", choices=FEATURE_KINDS, default="phonemes", help="extractor (default: phonemes, hama's IPA log-probs)")
    p.add_argument("--model-dir", default=None, help="local wav2vec2 / HuBERT model directory for --kind wav2vec2")
    p.add_argument("--fps", type=positive, default=None, help="frame rate (> 0) for audio-only input (default 25); overrides a video's timestamps")
    p.add_argument("--start", type=number(float, 0.0), default=0.0, help="seconds from the first frame (or the audio's start) to begin at, as preprocess --start: earlier frames and sound are left out")
    p.add_argument("--end", type=number(float, 0.0, open_lo=True), default=None, help="seconds from the first frame to stop at (frames and sound from then on are left out)")
    add_overwrite(p, "replace an existing output file (never an input)")
    p.set_defaults(func=run)


def _trimmed(media: Path, audio: AudioTrack, times: np.ndarray, start: float, end: float | None) -> tuple[AudioTrack, np.ndarray, str]:
    """The frames' times and the sound from ``start`` to ``end`` seconds after the first frame,
    cut as preprocess cuts them: frames and sound alike."""
    if end is not None and not end > start:
        raise CliError(f"a trim needs 0 <= start < end; got --start {start:g}, --end {end:g}")
    t0 = float(times[0])
    keep = (times >= t0 + start - 1e-6) & (True if end is None else times < t0 + end - 1e-6)
    if not keep.any():
        raise CliError(f"{media}: no frame from {start:g} s on (the trim's start lies past the clip's end)")
    return audio_span(audio, t0 + start, None if end is None else t0 + end), times[keep], f", {start:g}-{'end' if end is None else f'{end:g} s'}"


def run(args: argparse.Namespace) -> int:
    media, out = Path(args.media), Path(args.output)
    if out.suffix != ".npy":
        raise CliError(f"{out}: the output must be a .npy file")
    check_file_output(out, inputs=[media], overwrite=args.overwrite)
    try:
        audio = read_audio(media)  # raises "has no audio track" itself
        if len(audio.samples) == 0:
            raise CliError(f"{media}: the audio track holds no samples")
        if args.fps is None and probe(media)["video"]:
            times = frame_times(media)
            source = "video timestamps"
        else:
            fps = 25.0 if args.fps is None else args.fps
            times = np.arange(max(1, math.ceil(audio.duration * fps))) / fps + audio.start
            source = f"{fps:g} fps"
        if args.start or args.end is not None:
            audio, times, trim = _trimmed(media, audio, times, args.start, args.end)
            source += trim
        with tqdm(total=round(audio.duration, 1), unit="s", desc=f"{args.kind} features", disable=audio.duration < 30 or None) as bar:
            spec = FeatureSpec(args.kind, model_dir=args.model_dir)
            windows = speech_windows(audio, times, spec, progress=lambda n: bar.update(round(n / MODEL_RATE, 2)))
    except (MediaError, FeatureError) as exc:
        raise CliError(str(exc)) from exc
    save_npy_atomic(out, windows)
    print(f"{out}: {windows.shape[0]} frames ({source}) x {windows.shape[1]} x {windows.shape[2]} {args.kind} features from {audio.duration:.2f} s of audio")
    return 0
