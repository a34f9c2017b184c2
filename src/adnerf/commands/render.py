"""``adnerf render``: a trained run saying new audio, as an mp4 with that audio (:mod:`.render_video`)."""

from __future__ import annotations

import argparse

from tqdm import tqdm

from ..model.run_folder import load_run
from .options import CliError, add_device, add_overwrite, angle, checked_device
from .render_video import check_render_outputs, render_audio_video

__all__ = ["register", "run"]

EDIT = "; or a .npy of one angle per frame, or sway:AMPLITUDE,PERIOD (degrees, seconds: an idle motion kept inside the poses the run was taught)"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="render a trained run saying new audio, as an mp4 with that audio")
    p.add_argument("run", help="run folder")
    p.add_argument("--audio", required=True, help="speech (any audio or video file)")
    poses = p.add_mutually_exclusive_group()
    poses.add_argument("--poses", default=None, help=".npy of (N, 4, 4) head poses, one per output frame")
    poses.add_argument("--from", dest="from_dataset", default=None, help="take the pose track of this dataset (played back and forth)")
    p.add_argument("--yaw", type=angle, default="0", metavar="DEG|FILE.npy|sway:A,P", help="degrees added about the head's vertical axis, -180 to 180; positive turns the face towards the image's left (the person's right)" + EDIT)
    p.add_argument("--pitch", type=angle, default="0", metavar="DEG|FILE.npy|sway:A,P", help="degrees added about the horizontal axis; positive nods the face down" + EDIT)
    p.add_argument("--roll", type=angle, default="0", metavar="DEG|FILE.npy|sway:A,P", help="degrees added about the viewing axis; positive turns the head clockwise in the image" + EDIT)
    p.add_argument("--strict-pose", action="store_true", help="refuse poses farther outside the range the training frames showed than the margin (5 degrees, 0.1 head widths), instead of warning")
    p.add_argument("--features", default=None, help=".npy of precomputed feature windows (M, 16, D) for the audio, one per frame (e.g. AD-NeRF's DeepSpeech aud.npy); required for runs trained on imported DeepSpeech features")
    p.add_argument("--background", default=None, help="replacement background image")
    p.add_argument("--blink", default="auto", metavar="auto|none|FILE.npy", help="eye openness for runs trained with eyes (datasets with an eye track): auto plays natural blinks (one every 2-6 s, 0.2 s long), none keeps the eyes open, a .npy gives one value per frame (1 open, 0 closed)")
    p.add_argument("--frames", default=None, help="also write the rendered squares as PNGs (000000.png, ...) into this folder; never inside a dataset or run")
    p.add_argument("--paste-back", action=argparse.BooleanOptionalAction, default=None, help="paste the render back into the source video's full frames, at its size (default: when the dataset was cropped from a larger video and that video is at hand; --no-paste-back writes the square)")
    p.add_argument("--source", default=None, metavar="VIDEO", help="with paste-back: the video the dataset was made from, when it has moved since preprocessing")
    p.add_argument("--frame", dest="still_frame", default=None, metavar="IMAGE", help="with paste-back: paste every rendered square into this full-size image instead of the source video's frames")
    add_overwrite(p, "replace an existing output .mp4 and existing frame PNGs (never an input)")
    add_device(p)
    p.add_argument("-o", "--output", required=True, help="output .mp4")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not args.output.endswith(".mp4"):
        raise CliError(f"{args.output}: the output must be an .mp4 file")
    inputs = [args.audio, args.poses, args.features, args.background, args.source, args.still_frame, None if args.blink in ("auto", "none") else args.blink, *(a.file for a in (args.yaw, args.pitch, args.roll) if a.file is not None)]
    check_render_outputs(args.output, args.frames, inputs=inputs, overwrite=args.overwrite)  # before loading and rendering
    loaded = load_run(args.run, checked_device(args.device))
    bars: list[tqdm] = []  # opened at the first frame, so a refused input prints no bar

    def tick(done: int, total: int) -> None:
        if not bars:
            bars.append(tqdm(total=total, desc="render", unit="frame"))
        bars[0].update(done - bars[0].n)

    options = dict(poses_file=args.poses, from_dataset=args.from_dataset, yaw=args.yaw, pitch=args.pitch, roll=args.roll, strict_pose=args.strict_pose, background=args.background, features=args.features)
    try:
        summary = render_audio_video(
            loaded, args.audio, args.output, **options, frames_dir=args.frames, blink=args.blink, overwrite=args.overwrite, progress=tick,
            paste_back=args.paste_back, source=args.source, still_frame=args.still_frame,
        )  # fmt: skip
    finally:
        for bar in bars:
            bar.close()
    blinks = "" if summary["blinks"] is None else f", {summary['blinks']} blinks"
    pasted = f" ({summary['size'][0]}x{summary['size'][1]}, pasted back into the source frames)" if summary["pasted_back"] else ""
    print(f"{summary['output']}: {summary['frames']} frames{pasted}, {summary['audio_seconds']:.2f} s{blinks}, rendered at {summary['render_fps']:.2f} frames/s")
    return 0
