"""``adnerf preprocess``: a user's video -> a dataset (:mod:`adnerf.preprocess.pipeline`)."""

from __future__ import annotations

import argparse
import json

from ..formats.dataset import DatasetFolder
from ..preprocess.pipeline import FEATURE_CHOICES, PreprocessConfig, preprocess_video, step_bars
from .options import add_overwrite, number, positive

__all__ = ["register", "run"]

# What the command prints of the report (the whole report is in the dataset).
REPORT_KEYS = ("frames", "decode", "parse_face_failures", "face_detected", "face_interpolated", "face_head_torso_cut", "face_clothes", "layers", "layers_warning", "torso", "torso_warning", "pose_reprojection_rms_px", "pose_landmark_rms_px", "plate_filled_fraction", "timings_s")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("preprocess", help="turn a static-camera talking-head video into a dataset (parsing, head pose, plate)")
    p.add_argument("video", help="video file with an audio track")
    p.add_argument("-o", "--output", required=True, help="dataset folder to create")
    p.add_argument("--parser", default="classical", help="face parser: classical (default, needs no weights), mediapipe (opt-in install, see docs/preprocessing.md) or bisenet:CHECKPOINT (your 19-class face-parsing BiSeNet .pth, e.g. the 79999_iter.pth AD-NeRF uses)")
    p.add_argument("--features", choices=FEATURE_CHOICES, default="auto", help="audio features (logmel+phonemes: both side by side; auto: log-mel, with the phonemes beside it where the log-mel predicts the training frames' mouth opening, needs landmarks; none: silent dataset, allowed without audio)")
    p.add_argument("--face", default="dlib", help="face box and 68 landmarks: dlib (default; HOG detector and the 68-point model of the face-recognition-models package), dlib:PREDICTOR.dat (your own 68-point model) or none")
    p.add_argument("--flow", choices=("dis", "deepflow"), default="dis", help="dense optical flow for head tracking")
    p.add_argument("--cut", choices=("jaw", "neck-row"), default="jaw", help="where head meets torso for the classical parser: the landmarks' jaw line, or the silhouette's narrowest row (the earlier cut, for comparisons)")
    p.add_argument("--clothes", choices=("grabcut", "none"), default="grabcut", help="clothes the classical parser took for background (they never move): grabcut (default) adds them to the torso by colour below the chin; none leaves them")
    p.add_argument("--focal", type=positive, default=None, help="focal length of the camera in the video's pixels, > 0 (default 1.33 x the larger frame side); the crop and --size scale it")
    p.add_argument("--pose-landmarks", type=number(float, 0.0, 1000.0), default=None, help="weight of a rigid landmark (nose, eye corners) against a flow track in the head-pose bundle adjustment, 0 to 1000 (default: PreprocessConfig.pose_landmarks, 30; 0: the tracks alone, as before)")
    p.add_argument("--test-fraction", type=number(float, 0.0, 0.9, open_lo=True), default=0.1, help="fraction of frames at the end held out for testing, in (0, 0.9]")
    p.add_argument("--fps", type=number(float, 1.0, 240.0), default=None, help="frame rate of the dataset, 1 to 240: frames are placed on this constant rate by their timestamps, repeated or left out where a variable-rate file (phones) has gaps (default: the clip's nominal rate)")
    p.add_argument("--start", type=number(float, 0.0), default=0.0, help="seconds into the video (from its first frame) where the dataset begins; frames and audio are cut alike")
    p.add_argument("--end", type=positive, default=None, help="seconds into the video where the dataset ends (default: its end)")
    p.add_argument("--crop", default="auto", help="the part of the frame the dataset shows: auto (a fixed square around the face's range over the clip, with the shoulders; a frame already within --size is used whole), none (the whole frame) or X,Y,W,H in the video's pixels")
    p.add_argument("--size", type=number(int, 0, 4096), default=512, help="longest side of the dataset's frames in pixels: the crop is scaled down to it, never up; 0 keeps the crop's size")
    p.add_argument("--allow-cuts", action="store_true", help="keep a clip whose picture jumps (shot cuts, reframings); by default it is refused with the longest clean stretch named")
    add_overwrite(p, "replace an existing adnerf dataset folder (never another folder, nor one holding the video)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    extra = {} if args.pose_landmarks is None else {"pose_landmarks": args.pose_landmarks}
    cfg = PreprocessConfig(parser=args.parser, features=args.features, face=args.face, flow=args.flow, cut=args.cut, clothes=args.clothes, focal=args.focal, test_fraction=args.test_fraction, fps=args.fps, start=args.start, end=args.end, crop=args.crop, size=args.size or None, allow_cuts=args.allow_cuts, **extra)
    with step_bars() as bars:  # closed before an error line is printed
        report = preprocess_video(args.video, args.output, cfg, progress=bars, overwrite=args.overwrite)
    print(json.dumps({k: report[k] for k in REPORT_KEYS if k in report}, indent=1))
    files = DatasetFolder(args.output)
    print(f"{args.output}: dataset written (report: {files.report}, {files.report_image.suffix})")
    return 0
