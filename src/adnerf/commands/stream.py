"""``adnerf stream``: a run rendered frame by frame as its speech arrives (:mod:`.stream_video`)."""

from __future__ import annotations

import argparse
import json

from tqdm import tqdm

from ..model.run_folder import load_run
from .options import CliError, add_device, add_json, add_overwrite, checked_device, number
from .render_video import check_render_outputs
from .stream_video import stream_to_video

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "stream",
        help="render a run frame by frame as its speech arrives (a file played as a stream, or raw PCM on stdin), each frame as soon as no later audio can change it",
        description="Frames wait for about 0.3 s of speech after their time at 25 fps (the look-ahead: 140 ms of feature window, 16 ms of FFT, "
        "and AudioAttNet's 3 following frames) and equal adnerf render's frames of the same audio; with --causal about 0.18 s "
        "(AudioAttNet reads no later frame; the frames then differ a little from adnerf render's). Runs trained on log-mel features only.",
    )
    p.add_argument("run", help="run folder")
    p.add_argument("--audio", required=True, help="speech file, or - for raw 16 kHz mono signed 16-bit little-endian PCM on standard input (arecord -f S16_LE -r 16000 -c 1)")
    p.add_argument("--chunk-ms", type=number(float, 1, 10000), default=40.0, help="milliseconds of audio taken at a time (default 40)")
    p.add_argument("--yaw", type=number(float, -180, 180), default=0.0, help="degrees added about the head's vertical axis (as render --yaw)")
    p.add_argument("--pitch", type=number(float, -180, 180), default=0.0, help="degrees added about the horizontal axis")
    p.add_argument("--roll", type=number(float, -180, 180), default=0.0, help="degrees added about the viewing axis")
    p.add_argument("--blink", choices=("auto", "none"), default="auto", help="natural blinks or open eyes, for runs trained with eyes")
    p.add_argument("--causal", action="store_true", help="lower latency: AudioAttNet smooths each frame's audio code over that frame and the ones before it only (its window clamped there), so a frame waits for its feature window alone")
    p.add_argument("--background", default=None, help="replacement background image")
    p.add_argument("--frames", default=None, help="also write the frames as PNGs into this folder as they come")
    add_overwrite(p, "replace an existing output .mp4 and frame PNGs")
    add_device(p)
    add_json(p, "print the summary (frames, look-ahead, first-frame latency, real-time factor) as one JSON object")
    p.add_argument("-o", "--output", required=True, help="output .mp4")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not args.output.endswith(".mp4"):
        raise CliError(f"{args.output}: the output must be an .mp4 file")
    check_render_outputs(args.output, args.frames, inputs=[None if args.audio == "-" else args.audio, args.background], overwrite=args.overwrite)
    loaded = load_run(args.run, checked_device(args.device))
    with tqdm(desc="stream", unit="frame") as bar:
        summary = stream_to_video(
            loaded, args.audio, args.output, chunk_s=args.chunk_ms / 1000.0, yaw=args.yaw, pitch=args.pitch, roll=args.roll,
            blink=args.blink, background=args.background, frames_dir=args.frames, progress=lambda n: bar.update(n - bar.n), causal=args.causal,
        )  # fmt: skip
    if args.json:
        print(json.dumps(summary))
        return 0
    first = "-" if summary["first_frame_s"] is None else f"{summary['first_frame_s']:.2f} s"
    print(
        f"{summary['output']}: {summary['frames']} frames, {summary['audio_seconds']:.2f} s of speech; look-ahead {summary['lookahead_s'] * 1000:.0f} ms, "
        f"first frame after {first} of work, {summary['realtime_factor']:.2f}x real time"
    )
    return 0
