"""``adnerf preprocess``: a user's video -> an adnerf dataset, step by step and resumable.

Steps (each timed, each with a progress bar, each stored in a work folder beside the destination
so that a re-run after a failure or a kill redoes only the steps that did not finish, or whose
settings changed):

1. ``decode``   frames and audio (PyAV); checks length and audio presence.
2. ``features`` per-frame audio feature windows (:mod:`adnerf.audio.features`).
3. ``parse``    background / head / torso label maps (:mod:`adnerf.preprocess.parsing`), a
                person in each frame, camera-motion check.
4. ``face``     face box and 68 landmarks per frame (:mod:`.landmarks`, dlib by default; searched
                around the parsed head), failures interpolated and counted; a video whose face is
                detected in too few frames is refused.
5. ``pose``     point tracks on the rigid head (dense flow; above the nose base when there are
                landmarks), bundle adjustment, re-observation of every track against its seed
                frame, adjustment again (:mod:`.tracking`, :mod:`.bundle`, :mod:`.headpose`);
                clips longer than ``pose_segment`` frames in overlapping segments, joined by
                similarity alignment (:func:`.headpose.chain_segments`).
6. ``plate``    background plate (:mod:`.plate`).
7. ``write``    bounds (the mouth point triangulated from the lip landmarks under the head
                poses), splits, ``meta.json``, ``landmarks.npy``, the torso's motion in the
                image (``torso.npy``, :mod:`.torso_motion`), the report
                (``preprocess_report.json`` and ``preprocess_report.png``); the dataset is written
                to a temporary folder and renamed into place, then the work folder is removed.

Scene units: the head is 1.6 units wide (as in the synthetic scene), so boxes and near/far have
the same meaning in both.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
import time
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable, NamedTuple

import cv2
import numpy as np

from ..atomic import atomic_path
from ..audio.features import BUILTIN_KINDS
from ..io import AudioTrack, MediaError, read_audio, read_video
from ..lock import writes_folder
from ..formats.dataset import (
    LABEL_HEAD,
    LABEL_TORSO,
    DatasetError,
    DatasetFolder,
    SceneMeta,
    save_dataset,
    tail_split,
    write_wav,
)
from ..formats.outputs import OutputError, check_folder_output
from .clothes import complete_torso
from .cuts import find_cuts
from .feature_choice import choose_features
from .frame_grid import nominal_rate, regular_grid
from .framing import Framing, auto_crop, parse_crop, plan_framing
from .stillness import moving_regions
from .headpose import project_points
from .landmarks import (
    NOSE_BASE,
    eye_centres_px,
    eye_openness,
    mouth_centres,
    pose_landmarks,
)
from .parsing import JAW_MARGIN, layer_check, split_at_landmarks, torso_check
from .torso_motion import torso_motion

__all__ = ["PIPELINE", "PreprocessConfig", "PreprocessError", "STEPS", "Step", "StepContext", "preprocess_video", "run_step", "step_bars"]

# Below these the report warns that the mouth is not in the head layer (issue measured on a real
# clip: a row cut at the upper lip left 20% of the lip landmarks in the head).
LIP_IN_HEAD_MIN, MIDPOINT_IN_HEAD_MIN = 0.98, 0.9
# Below this median share of the bottom edge under the face labelled person, the report warns that
# clothes were taken for background (parsing.torso_check). On the shared sample clip the mediapipe
# parser scores 1.0 (worst frame 0.97), the classical parser 0.73 (worst 0.33: her dark jacket
# never moves) and 1.0 (worst 0.95) once the clothes are completed (clothes.complete_torso); on
# the synthetic test clip the truth scores 1.0, the classical parser 0.78 without completion.
PERSON_AT_BOTTOM_MIN = 0.8
#: What ``--features`` accepts: auto (the clip chooses), the built-in extractors, none (silent).
FEATURE_CHOICES = ("auto", *BUILTIN_KINDS, "none")


class PreprocessError(ValueError):
    """The video cannot become a dataset (no face, too short, no audio, ...); nothing is written."""


@dataclass
class PreprocessConfig:
    """Settings of :func:`preprocess_video`.

    Attributes:
        parser: Parsing backend: ``"classical"`` (no weights), ``"mediapipe"`` (opt-in install;
            :mod:`adnerf.preprocess.mediapipe_parser`) or ``"bisenet:PATH"`` (a user's
            CelebAMask-HQ BiSeNet checkpoint; :mod:`adnerf.preprocess.bisenet`).
        features: Audio features: ``"auto"`` (default), ``"logmel"``, ``"phonemes"``,
            ``"logmel+phonemes"`` (both side by side; :class:`~adnerf.audio.features.FeatureSpec`)
            or ``"none"`` (silent dataset). ``"auto"`` measures how well the log-mel windows predict the training
            frames' mouth opening (:func:`adnerf.model.mouth_target.opening_signal`) and adds the
            phonemes beside them (``"logmel+phonemes"``) from ``auto_min_signal`` on, else keeps
            ``"logmel"`` (also without landmarks); the dataset records the kind it got
            (``meta.json`` ``feature_kind``) and the report why (``features``).
        auto_min_signal: Under ``features="auto"``, the cross-validated correlation of the log-mel
            windows with the opening from which the phonemes are added.
        face: Face box and landmark backend: ``"dlib"`` (bundled 68-point model),
            ``"dlib:PATH"`` (a user's 68-point dlib shape predictor) or ``"none"`` (no landmarks;
            the mouth point is then a fixed guess on the head).
        flow: Dense optical flow: ``"dis"`` or ``"deepflow"``.
        cut: Where head meets torso when the parser does not cut at the jaw itself: ``"jaw"``
            (the landmarks' jaw line; needs ``face``) or ``"neck-row"`` (the silhouette's
            narrowest row, as before the jaw cut existed: for comparisons).
        clothes: When the parser finds the person by motion (the classical one) and landmarks are
            there: ``"grabcut"`` adds the clothes it took for background to the torso layer
            (:mod:`adnerf.preprocess.clothes`); ``"none"`` leaves the parse as it is.
        focal: Focal length in pixels; ``None`` assumes ``1.33 * max(width, height)`` (a 41 degree
            field of view; the synthetic scene's camera). Pose accuracy depends on it: give the
            real value when it is known.
        test_fraction: Fraction of frames, at the end, held out for testing.
        head_width: Head width in scene units.
        min_seconds: Shortest accepted video.
        fps: Frame rate of the dataset: the decoded frames are placed on a grid of this rate by
            their timestamps (:mod:`.frame_grid`); ``None`` takes the clip's nominal rate.
        min_face_fraction: Fewest frames, as a fraction, that must show a face.
        extend_passes: Passes of re-observing tracks against their seed frames (0: chained tracks only).
        shape_sigma: Weight of the ellipsoid prior in bundle adjustment (0: none).
        pose_landmarks: Weight of one rigid face landmark's observation (nose and eye corners,
            :data:`.landmarks.POSE_LANDMARKS`) against one flow track's in the head-pose bundle
            adjustment (0: the tracks alone; unused with ``face="none"``). The tracks are chained
            from frame to frame and drift; the landmarks are found afresh in every frame.
        smooth_sigma: Temporal smoothing of the poses in frames.
        pose_segment: Longest stretch of frames solved in one bundle adjustment; longer clips are
            solved in overlapping segments joined by similarity alignment (the adjustment's cost
            grows with the square of the frames, as every track is re-observed in all of them).
        pose_overlap: Frames shared by consecutive segments.
        track_size: Longest side, pixels, of the frames the head's points are tracked in (larger
            frames are shrunk for the flows and Lucas-Kanade, the tracks scaled back; the
            adjustment and the landmarks stay at full size); ``None`` (default): the frames' own
            size. A speed for accuracy trade (docs/decisions.md): on a 512 px synthetic clip,
            256 halved the pose step and doubled its median rotation error.
        start: Trim: seconds from the video's first frame where the dataset begins (frames and
            audio cut alike).
        end: Trim: seconds from the video's first frame where the dataset ends (``None``: the
            video's end).
        crop: The part of the frame the dataset shows (:mod:`.framing`): ``"auto"`` (a fixed
            square around the face's range over the clip, with the shoulders; a frame whose
            longer side is within ``size`` is used whole), ``"none"`` (the whole frame) or
            ``"X,Y,W,H"`` in the source's pixels. The dataset records it (``meta.json``
            ``framing``) so that renders can be pasted back.
        allow_cuts: Keep a clip with shot cuts or reframings (:mod:`.cuts`); by default it is refused
            with the longest clean stretch named.
        size: Longest side of the dataset's frames in pixels: the crop is scaled down to it
            (never up); ``None`` keeps the crop's size.
    """

    parser: str = "classical"
    features: str = "auto"
    face: str = "dlib"
    flow: str = "dis"
    cut: str = "jaw"
    clothes: str = "grabcut"
    focal: float | None = None
    test_fraction: float = 0.1
    head_width: float = 1.6
    min_seconds: float = 2.0
    fps: float | None = None
    min_face_fraction: float = 0.5
    extend_passes: int = 2
    shape_sigma: float = 0.0
    pose_landmarks: float = 30.0
    smooth_sigma: float = 0.0
    pose_segment: int = 300
    pose_overlap: int = 60
    track_size: int | None = None
    start: float = 0.0
    end: float | None = None
    crop: str = "auto"
    size: int | None = 512
    allow_cuts: bool = False
    auto_min_signal: float = 0.2

    def validate(self) -> None:
        """Raise :class:`PreprocessError` on impossible settings."""
        if self.features not in FEATURE_CHOICES:
            raise PreprocessError(f"--features must be one of {', '.join(FEATURE_CHOICES)}; got {self.features!r}")
        if not -1 <= self.auto_min_signal <= 1:
            raise PreprocessError(f"auto_min_signal is a correlation, in [-1, 1]; got {self.auto_min_signal}")
        if self.flow not in ("dis", "deepflow"):
            raise PreprocessError(f"--flow must be dis or deepflow; got {self.flow!r}")
        if self.parser not in ("classical", "mediapipe") and not self.parser.startswith("bisenet:"):
            raise PreprocessError(f"--parser must be classical, mediapipe or bisenet:CHECKPOINT; got {self.parser!r}")
        if self.parser == "mediapipe":
            from .mediapipe_parser import import_mediapipe

            try:
                import_mediapipe()
            except ImportError as exc:
                raise PreprocessError(str(exc)) from exc
        if self.parser.startswith("bisenet:") and not Path(self.parser.split(":", 1)[1]).is_file():
            raise PreprocessError(f"--parser {self.parser}: no checkpoint file there (adnerf downloads no weights; give your 19-class face-parsing BiSeNet .pth)")
        if self.clothes not in ("grabcut", "none"):
            raise PreprocessError(f"--clothes must be grabcut or none; got {self.clothes!r}")
        if self.cut not in ("jaw", "neck-row"):
            raise PreprocessError(f"--cut must be jaw or neck-row; got {self.cut!r}")
        if self.face not in ("dlib", "none") and not self.face.startswith("dlib:"):
            raise PreprocessError(f"--face must be dlib, dlib:PREDICTOR.dat or none; got {self.face!r}")
        if self.face.startswith("dlib:") and not Path(self.face.split(":", 1)[1]).is_file():
            raise PreprocessError(f"--face {self.face}: no shape predictor file there")
        try:
            parse_crop(self.crop)
        except ValueError as exc:
            raise PreprocessError(f"--crop: {exc}") from exc
        if self.track_size is not None and not 32 <= self.track_size <= 4096:
            raise PreprocessError(f"track_size must be 32 to 4096 pixels or None; got {self.track_size}")
        if self.size is not None and not 16 <= self.size <= 4096:
            raise PreprocessError(f"--size must be 16 to 4096 pixels; got {self.size}")
        if not (self.start >= 0 and np.isfinite(self.start)) or (self.end is not None and not self.end > self.start):
            raise PreprocessError(f"--start and --end must satisfy 0 <= start < end (seconds); got {self.start:g} and {self.end}")
        if self.focal is not None and not self.focal > 0:
            raise PreprocessError(f"--focal must be positive; got {self.focal}")
        if not 2 <= self.pose_overlap < self.pose_segment:
            raise PreprocessError(f"pose_overlap must lie in [2, pose_segment); got {self.pose_overlap} and {self.pose_segment}")
        if not (np.isfinite(self.pose_landmarks) and self.pose_landmarks >= 0):
            raise PreprocessError(f"pose_landmarks must be a finite weight >= 0; got {self.pose_landmarks}")
        if self.fps is not None and not (np.isfinite(self.fps) and 1.0 <= self.fps <= 240.0):
            raise PreprocessError(f"--fps must lie in [1, 240] frames per second; got {self.fps}")
        if not 0.0 < self.test_fraction < 0.5:
            raise PreprocessError(f"--test-fraction must lie in (0, 0.5); got {self.test_fraction}")


def code_fingerprint() -> str:
    """A hash of adnerf's own source files: the code that makes a step's outputs.

    Part of every step's key in the work folder, so that a run resumed after adnerf changed (an
    upgrade that fixes a step, an edit) makes every step again instead of reading outputs the
    old code made.
    """
    root = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


class _Work:
    """The work folder: step outputs plus ``steps.json`` (per step: settings key and seconds).

    A step's key covers the video (path, size, modification time), the settings it and the steps
    before it read, and adnerf's code (:func:`code_fingerprint`).
    """

    def __init__(self, folder: Path, video: Path, config: PreprocessConfig) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.record_path = folder / "steps.json"
        self.record = json.loads(self.record_path.read_text()) if self.record_path.exists() else {}
        stat = video.stat()
        base = f"{video.resolve()}|{stat.st_size}|{stat.st_mtime_ns}|{code_fingerprint()}"
        self.keys = {}
        for step in STEPS:
            base += "|" + json.dumps({k: getattr(config, k) for k in _STEP_KEYS[step]}, sort_keys=True)
            self.keys[step] = hashlib.sha256(base.encode()).hexdigest()[:16]

    @property
    def audio(self) -> Path:
        """The decoded audio track (16 kHz mono WAV, clock at the first frame's time)."""
        return self.folder / "decoded_audio.wav"

    @property
    def plate(self) -> Path:
        """The plate step's background plate (PNG)."""
        return self.folder / "plate.png"

    def done(self, step: str) -> bool:
        return self.record.get(step, {}).get("key") == self.keys[step]

    def finish(self, step: str, seconds: float) -> None:
        self.record[step] = {"key": self.keys[step], "seconds": round(seconds, 3)}
        with atomic_path(self.record_path) as tmp:
            tmp.write_text(json.dumps(self.record, indent=1))

    def save(self, name: str, array: np.ndarray) -> None:
        with atomic_path(self.folder / f"{name}.npy") as tmp:
            np.save(tmp, array)

    def load(self, name: str) -> np.ndarray:
        """A step output, memory-mapped read-only: a long clip's frames and labels are paged in
        from the work folder as a step reads them (and can be dropped again under memory
        pressure) instead of being copied into the process's own memory by every step."""
        return np.load(self.folder / f"{name}.npy", mmap_mode="r")

    def save_json(self, name: str, doc: dict) -> None:
        with atomic_path(self.folder / f"{name}.json") as tmp:
            tmp.write_text(json.dumps(doc, indent=1))

    def load_json(self, name: str) -> dict:
        return json.loads((self.folder / f"{name}.json").read_text())


Bar = Callable[[str, int, int], None]


class StepContext(NamedTuple):
    """What a step works with: the video, the work folder (where it reads the earlier steps'
    outputs and saves its own), the settings and the progress callback."""

    video: Path
    work: "_Work"
    config: PreprocessConfig
    bar: Bar


@dataclass(frozen=True)
class Step:
    """One cached step of preprocessing.

    Attributes:
        name: The step's name: its progress bar, its seconds in the report, its cache entry.
        keys: The :class:`PreprocessConfig` fields its result depends on; a change re-runs it and
            every step after it (with the video and adnerf's code, :class:`_Work`).
        run: The work: reads the earlier steps' outputs from ``ctx.work``, saves its own there and
            returns its part of the report.
    """

    name: str
    keys: tuple[str, ...]
    run: Callable[[StepContext], dict]


def run_step(step: Step, ctx: StepContext) -> dict:
    """A step's part of the report: read back when the step finished in the work folder under the
    same key, else run, its part saved, its seconds recorded (the step then counts as finished)."""
    if ctx.work.done(step.name):
        ctx.bar(f"{step.name} (done before)", 1, 1)
        return ctx.work.load_json(f"report_{step.name}")
    t0 = time.perf_counter()
    doc = step.run(ctx)
    ctx.work.save_json(f"report_{step.name}", doc)
    ctx.work.finish(step.name, time.perf_counter() - t0)
    return doc


def _report_warning(doc: dict, key: str, msg: str) -> None:
    """Keep a warning in a report (``doc[key]``) and print it on stderr."""
    doc[key] = msg
    print(f"warning: {msg}", file=sys.stderr)


class step_bars:
    """A ``progress`` for :func:`preprocess_video` that shows one progress bar per step.

    Use it as a context manager: leaving the block closes the bars still open (an interrupted or
    failed step's), so that the line printed after it starts on a line of its own.
    """

    def __init__(self) -> None:
        self._bars: dict[str, Any] = {}

    def __call__(self, step: str, done: int, total: int) -> None:
        from tqdm import tqdm

        bar = self._bars.get(step)
        if bar is None:
            bar = self._bars[step] = tqdm(total=total, desc=step, unit="step" if total == 1 else "frame", leave=True)
        bar.update(done - bar.n)
        if done >= total:
            bar.close()

    def close(self) -> None:
        """Close every bar still open."""
        for bar in self._bars.values():
            bar.close()

    def __enter__(self) -> "step_bars":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _skin_fraction(frame: np.ndarray, mask: np.ndarray) -> float:
    """Fraction of ``mask`` pixels with a skin-like chroma (YCrCb box of Chai and Ngan, widened)."""
    if not mask.any():
        return 0.0
    ycc = cv2.cvtColor(frame, cv2.COLOR_RGB2YCrCb)[mask]
    cr, cb = ycc[:, 1].astype(int), ycc[:, 2].astype(int)
    return float(((cr >= 130) & (cr <= 180) & (cb >= 75) & (cb <= 135)).mean())


def _camera_motion(frames: np.ndarray, labels: np.ndarray, pairs: int = 8, gap: int = 5) -> float:
    """Median flow magnitude (pixels per frame) on background far from the person, over a few pairs."""
    n = len(frames)
    if n <= gap:
        return 0.0
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (15, 15))
    out = []
    for i in np.linspace(0, n - 1 - gap, min(pairs, n - gap)).round().astype(int):
        bg = (labels[i] == 0) & (labels[i + gap] == 0)
        bg = cv2.erode(bg.astype(np.uint8), kernel) > 0
        if bg.sum() < 100:
            continue
        a, b = (cv2.cvtColor(frames[j], cv2.COLOR_RGB2GRAY) for j in (i, i + gap))
        flow = dis.calc(a, b, None)
        out.append(float(np.median(np.linalg.norm(flow[bg], axis=1))) / gap)
    return float(np.median(out)) if out else 0.0


def _framing(video: Path, config: PreprocessConfig) -> tuple[Framing, dict]:
    """The crop and scale of the dataset's frames in the source's (:mod:`.framing`), and what the
    automatic crop found."""
    from .landmarks import make_face_detector

    first = read_video(video, audio=False, max_frames=1).frames[0]  # upright
    source = (first.shape[1], first.shape[0])
    crop = parse_crop(config.crop)
    found: dict = {}
    if crop == "auto":
        if config.size is None or max(source) <= config.size:
            crop = "none"  # the frame is already the model's size
        else:
            detector = make_face_detector(config.face)
            if detector is None:
                raise PreprocessError(f"{video}: --crop auto finds the face with the face detector, and --face is none; give --crop X,Y,W,H or --crop none")
            try:
                crop, found = auto_crop(video, detector, source, config.start, config.end)
            except ValueError as exc:
                raise PreprocessError(str(exc)) from exc
    try:
        return replace(plan_framing(source, crop, config.size, config.start), video=str(video.resolve())), found
    except ValueError as exc:
        raise PreprocessError(f"{video}: {exc}") from exc


def _cut_check(video: Path, frames: np.ndarray, fps: float, config: PreprocessConfig, doc: dict) -> None:
    """Refuse a clip whose picture jumps (cuts, reframings) unless ``--allow-cuts``; the jumps go
    in the decode step's report ``doc``."""
    n = len(frames)
    cuts = find_cuts(frames)
    doc["cuts"] = [{"frame": k, "time_s": round(config.start + k / fps, 3), "changed": round(float(cuts.changed[k - 1]), 3)} for k in cuts.frames]
    if cuts.frames:
        a, b = cuts.longest(n)
        at = ", ".join(f"{c['time_s']:.2f} s" for c in doc["cuts"][:6]) + (" ..." if len(cuts.frames) > 6 else "")
        what = f"{len(cuts.frames)} cut(s) or reframing(s) (the picture jumps at {at} into the video)"
        t0, t1 = config.start + a / fps, config.start + b / fps
        if not config.allow_cuts:
            raise PreprocessError(
                f"{video}: the clip has {what}; a static camera is assumed, and two framings would train as one. "
                f"The longest clean stretch is {t0:.2f}-{t1:.2f} s ({(b - a) / fps:.1f} s): --start {t0:.2f} --end {t1:.2f} uses it; --allow-cuts keeps every frame"
            )
        _report_warning(doc, "cuts_warning", f"{video}: the clip has {what}; kept (--allow-cuts)")


def _step_decode(ctx: StepContext) -> dict:
    video, work, config, bar = ctx
    framing, found = _framing(video, config)
    v = read_video(video, audio=True, start=config.start, end=config.end, transform=framing.transform if framing.cropped else None)
    doc: dict = {"source_frames": len(v.frames), "rotation_deg": v.rotation, "framing": framing.to_dict()}
    if found:
        doc["crop_auto"] = found
    if v.truncated is not None:
        _report_warning(doc, "truncated_warning", f"{video}: the file ends early ({v.truncated}); the frames that decode are used")
    fps = float(config.fps or nominal_rate(v.timestamps, v.fps))
    grid = regular_grid(v.timestamps, fps)
    frames = v.frames if grid.identity else v.frames[grid.index]
    del v.frames  # the source frames are not held twice
    n, h, w = frames.shape[:3]
    seconds = n / fps
    if seconds < config.min_seconds:
        raise PreprocessError(f"{video}: the video is {seconds:.2f} s long" + (" where it decodes" if v.truncated else "") + f"; preprocessing needs at least {config.min_seconds:g} s")
    if v.audio is None and config.features != "none":
        raise PreprocessError(f"{video}: the video has no audio track (use --features none to make a silent dataset)")
    doc.update(fps=fps, duplicated=grid.duplicated, dropped=grid.dropped)
    _cut_check(video, frames, fps, config, doc)
    if not grid.identity:
        own = nominal_rate(v.timestamps, v.fps)
        if config.fps and regular_grid(v.timestamps, own).identity:  # a steady clip, asked for another rate
            why = f"--fps {fps:g} resamples the clip's steady {own:g} fps by its timestamps, {grid.duplicated} frame(s) repeated and {grid.dropped} left out"
        else:
            why = (
                f"the frames do not come at a constant rate (variable frame rate): placed on a {fps:g} fps grid by their timestamps, "
                f"{grid.duplicated} frame(s) repeated where the file skipped one and {grid.dropped} left out where two fell in one slot (--fps sets the rate)"
            )
        _report_warning(doc, "timing_warning", f"{video}: {why}")
    work.save("frames", frames)
    work.save("times", grid.times)
    if v.audio is not None:
        # Sample 0 of the dataset's audio plays with frame 0: shift the audio to the first frame's time
        # and pad what it lacks at either end with silence (audio past the last frame is kept: the
        # last frames' feature windows reach into it).
        rate = v.audio.sample_rate
        late = max(v.audio.start - float(v.timestamps[0]), 0.0)
        samples = v.audio.starting_at(float(v.timestamps[0])).samples
        short = int(round(seconds * rate)) - len(samples)
        if short > 0:
            samples = np.concatenate([samples, np.zeros(short, np.float32)])
        early = max(short, 0) / rate
        doc.update(audio_late_s=round(late, 3), audio_short_s=round(early, 3))
        gaps = [f"starts {late:.2f} s after the first frame" if late > 1.0 / fps else "", f"ends {early:.2f} s before the last frame" if early > 1.0 / fps else ""]
        if any(gaps):
            _report_warning(doc, "audio_warning", f"{video}: the audio track {' and '.join(g for g in gaps if g)}: padded with silence there (the mouth of those frames is trained on silence)")
        write_wav(work.audio, AudioTrack(samples.astype(np.float32), rate, 0.0))
    work.save_json("decode", {"fps": fps, "n": n, "width": w, "height": h, "seconds": seconds, "audio": v.audio is not None, "framing": framing.to_dict()})
    bar("decode", 1, 1)
    return doc


def _step_features(ctx: StepContext) -> dict:
    from ..audio.features import FeatureSpec, speech_windows

    _, work, config, bar = ctx
    times = work.load("times")
    if config.features == "none":
        work.save("features", np.zeros((len(times), 16, 1), np.float32))
    else:
        audio = read_audio(work.audio)
        # auto: both; the write step, with the landmarks, keeps what the clip carries
        work.save("features", speech_windows(audio, times, FeatureSpec(kind="logmel" if config.features == "auto" else config.features)))
        if config.features == "auto":
            work.save("phonemes", speech_windows(audio, times, FeatureSpec(kind="phonemes")))
    bar("features", 1, 1)
    return {}


def _step_parse(ctx: StepContext) -> dict:
    from .parsers import make_parser

    video, work, config, bar = ctx
    frames = work.load("frames")
    try:
        parser = make_parser(config.parser)
    except ValueError as exc:
        raise PreprocessError(str(exc)) from exc
    labels = parser.parse(frames, progress=lambda d, t: bar("parse", d, t))
    n, h, w = labels.shape
    if not (labels == 0).any():  # the plate is made of background pixels; there is none
        raise PreprocessError(
            f"{video}: the parser ({parser.name}) labelled every pixel of every frame as the person, so no background plate can be made; "
            "frame the clip wider (some wall beside the head), or try --parser mediapipe"
        )
    head_area = (labels == LABEL_HEAD).mean((1, 2))
    skin = np.array([_skin_fraction(frames[i], labels[i] == LABEL_HEAD) for i in range(n)])
    face = (head_area > 0.01) & (skin > 0.15)
    if not face.any():
        raise PreprocessError(f"{video}: no face found in any frame (parser {parser.name})")
    if face.mean() < config.min_face_fraction:
        raise PreprocessError(f"{video}: a face was found in only {face.sum()} of {n} frames ({face.mean():.0%}); at least {config.min_face_fraction:.0%} are needed")
    # Frames without a face take the labels of the nearest frame with one (counted in the report).
    good = np.flatnonzero(face)
    for i in np.flatnonzero(~face):
        labels[i] = labels[good[np.argmin(np.abs(good - i))]]
    motion = _camera_motion(frames, labels)
    doc = {
        "parser": parser.name,
        "cuts_at_jaw": bool(getattr(parser, "cuts_at_jaw", False)),
        "finds_clothes": bool(getattr(parser, "finds_clothes", False)),
        "face_frames": int(face.sum()),
        "face_failures": int((~face).sum()),
        "camera_motion_px_per_frame": motion,
    }
    if motion > 0.3:
        msg = f"{video}: the background moves ({motion:.2f} px per frame): the camera does not look static; parsing, pose and the plate assume it is"
        warnings.warn(msg, stacklevel=2)
        _report_warning(doc, "warning", msg)
    else:  # a still camera: does part of the background move (a screen, a window, a flag)?
        doc["background_moving"] = moving_regions(frames, labels)
        if doc["background_moving"]:
            where = ", ".join(f"{m['region']} ({m['share']:.0%} of its background)" for m in doc["background_moving"][:3])
            msg = (
                f"{video}: part of the background moves while the camera stands still: {where}; the plate holds one still picture "
                "there (a screen, a window or a moving object behind the person: film without it, or cover it)"
            )
            warnings.warn(msg, stacklevel=2)
            _report_warning(doc, "background_warning", msg)
    work.save("parsing", labels)
    work.save_json("parse", doc)  # the face step reads how the parser cut
    return doc


def _step_face(ctx: StepContext) -> dict:
    from .landmarks import make_face_detector, track_faces

    video, work, config, bar = ctx
    try:
        detector = make_face_detector(config.face)
    except (ValueError, ImportError) as exc:
        raise PreprocessError(f"--face {config.face}: {exc}") from exc
    (work.folder / "layers.npy").unlink(missing_ok=True)  # a re-run must not keep an older split
    parser_cut = work.load_json("parse").get("cuts_at_jaw", False)
    if detector is None:
        cut = "the parser's own" if parser_cut else "the silhouette's narrowest row: a guess (no landmarks with --face none)"
        doc = {"backend": "none", "head_torso_cut": cut}
        bar("face", 1, 1)
        return doc
    frames, labels = work.load("frames"), work.load("parsing")
    track = track_faces(frames, detector, labels, progress=lambda d, t: bar("face", d, t))
    n, found = len(frames), int(track.detected.sum())
    if found == 0:
        raise PreprocessError(f"{video}: the face detector ({detector.name}) found no face in any frame (try --face none to go on without landmarks)")
    if found < config.min_face_fraction * n:
        raise PreprocessError(
            f"{video}: the face detector ({detector.name}) found a face in only {found} of {n} frames ({found / n:.0%}); at least {config.min_face_fraction:.0%} are needed (or --face none)"
        )
    work.save("landmarks", track.landmarks)
    work.save("face_detected", track.detected)  # the pose step weighs only landmarks the detector found
    resplit = not parser_cut and config.cut == "jaw"  # the parser cut at a row: the mouth and chin may lie below it
    layers = split_at_landmarks(labels, track.landmarks) if resplit else labels
    clothes = None
    if config.clothes == "grabcut" and not work.load_json("parse").get("finds_clothes", False):
        layers, clothes = complete_torso(frames, layers, track.landmarks, progress=lambda d, t: bar("face: clothes", d, t))
    if resplit or clothes is not None:
        work.save("layers", layers)
    doc = {
        "backend": detector.name,
        "head_torso_cut": f"the jaw line of the 68 landmarks, {JAW_MARGIN:.0%} of the face width below it" if resplit else "the parser's own" if parser_cut else "the silhouette's narrowest row (--cut neck-row)",
        "detected": found,
        "interpolated": n - found,
        "score_median": float(np.nanmedian(track.scores)),
        "box_width_median_px": float(np.median(track.boxes[:, 2] - track.boxes[:, 0])),
        "clothes": "left as parsed" if clothes is None else {"completed_by": "grabcut below the chin (adnerf.preprocess.clothes)", **clothes},
    }
    return doc


def _labels(work: _Work) -> np.ndarray:
    """The final parsing: the face step's landmark split where it made one, else the parser's."""
    return work.load("layers") if (work.folder / "layers.npy").exists() else work.load("parsing")


def _landmarks(work: _Work, config: PreprocessConfig) -> np.ndarray | None:
    """The face step's ``(N, 68, 2)`` landmarks, ``None`` under ``--face none``."""
    return None if config.face == "none" else work.load("landmarks")


def _intrinsics(config: PreprocessConfig, info: dict) -> tuple[float, float, float, float]:
    """The dataset camera: the source's (``--focal`` in source pixels, or the guess) through the
    crop and scale of the decode step's framing."""
    framing = Framing.from_dict(info["framing"]) if "framing" in info else plan_framing((info["width"], info["height"]), "none", None)
    return framing.intrinsics(config.focal)


def _segments(n: int, length: int, overlap: int) -> list[tuple[int, int]]:
    """``(start, stop)`` of the overlapping segments the pose is solved in (one when ``n <= length``)."""
    if n <= length:
        return [(0, n)]
    step = length - overlap
    starts = list(range(0, n - length, step)) + [n - length]
    return [(a, a + length) for a in starts]


def _pose_segment(frames: np.ndarray, labels: np.ndarray, landmarks: np.ndarray | None, detected: np.ndarray | None, K: tuple[float, float, float, float], config: PreprocessConfig, bar: Bar, name: str) -> tuple:
    """Tracks, bundle adjustment and re-observation passes on one segment of the clip
    (``landmarks`` ``(n, 68, 2)`` and ``detected`` ``(n,)``: the face step's, or both ``None``)."""
    from .headpose import estimate_head_poses
    from .tracking import TrackConfig, Tracks, extend_tracks, rigid_regions, track_points

    track_cfg = TrackConfig(flow=config.flow)
    # The points are tracked at a working size (config.track_size): the flows' and Lucas-Kanade's
    # cost then does not grow with the frame, and their pixel thresholds mean the same on any clip.
    h, w = frames.shape[1:3]
    s = 1.0 if not config.track_size or max(h, w) <= config.track_size else config.track_size / max(h, w)
    small, small_labels = frames, labels
    if s < 1.0:
        size = (max(1, round(w * s)), max(1, round(h * s)))
        small = np.stack([cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in frames])
        small_labels = np.stack([cv2.resize(lab, size, interpolation=cv2.INTER_NEAREST) for lab in labels])
    scale = np.array([small.shape[2] / w, small.shape[1] / h])  # working pixels per frame pixel, per axis (edges aligned)

    def full(tr: Tracks) -> Tracks:
        return tr if s == 1.0 else Tracks(uv=tr.uv / scale, seed_frame=tr.seed_frame)

    # With landmarks, the rigid region never reaches below the nose base.
    limits = None if landmarks is None else landmarks[:, NOSE_BASE, 1] * scale[1]
    regions = rigid_regions(small_labels, track_cfg, limits)  # made once for the tracks and every pass
    tracks = track_points(small, small_labels, track_cfg, progress=lambda d, t: bar(f"pose: tracks{name}", d, t), limits=limits, regions=regions)
    rigid = None if landmarks is None or detected is None else pose_landmarks(landmarks, detected)
    kw = dict(head_width=config.head_width, shape_sigma=config.shape_sigma, landmarks=rigid, landmark_weight=config.pose_landmarks)
    est = estimate_head_poses(full(tracks), labels, K, **kw)
    chained_obs = int(tracks.observed.sum())
    for k in range(config.extend_passes):
        P, X = est.poses, est.points

        def predict(i: int, idx: np.ndarray) -> np.ndarray:
            return project_points(X[idx] @ P[i, :3, :3].T + P[i, :3, 3], K) * scale

        tracks = extend_tracks(small, small_labels, tracks, predict, track_cfg, reach=len(frames), limits=limits, regions=regions)
        est = estimate_head_poses(full(tracks), labels, K, **kw, initial=est)  # from the last pass's solution
        bar(f"pose: adjust{name}", k + 1, config.extend_passes)
    return est, full(tracks), chained_obs


def _landmark_rms(per_segment: list[float]) -> float | None:
    """The segments' landmark RMS errors pooled (``None`` where no segment had landmarks in its
    adjustment: none given, weight 0, or no face detected; JSON has no NaN)."""
    finite = [r for r in per_segment if np.isfinite(r)]
    return float(np.sqrt(np.mean(np.square(finite)))) if finite else None


def _step_pose(ctx: StepContext) -> dict:
    from .headpose import chain_segments, smooth_poses

    _, work, config, bar = ctx
    # The parser's labels: the pose needs the rigid upper head (its box seeds the ellipsoid), not
    # the jaw-line layers, which reach down the jaw that moves with the speech.
    frames, labels = work.load("frames"), work.load("parsing")
    info = work.load_json("decode")
    K = _intrinsics(config, info)
    landmarks = _landmarks(work, config)
    detected = None if landmarks is None else work.load("face_detected")
    n = len(frames)
    spans = _segments(n, config.pose_segment, config.pose_overlap)
    results = []
    for k, (a, b) in enumerate(spans):
        name = "" if len(spans) == 1 else f" {k + 1}/{len(spans)}"
        results.append(_pose_segment(frames[a:b], labels[a:b], None if landmarks is None else landmarks[a:b], None if detected is None else detected[a:b], K, config, bar, name))
    poses, joints = chain_segments([(a, est.poses) for (a, _), (est, _, _) in zip(spans, results)], n)
    poses = smooth_poses(poses, config.smooth_sigma)
    work.save("poses", poses)
    obs = np.array([int(tr.observed.sum()) for _, tr, _ in results], dtype=np.float64)
    doc = {
        "intrinsics": K,
        "segments": [[a, b] for a, b in spans],
        "segment_joint_rotation_deg": joints,
        "tracks": int(sum(tr.uv.shape[1] for _, tr, _ in results)),
        "observations_chained": int(sum(c for _, _, c in results)),
        "observations": int(obs.sum()),
        "reprojection_rms_px": float(np.sqrt(np.sum(obs * np.array([est.rms for est, _, _ in results]) ** 2) / obs.sum())),
        "reprojection_median_px": float(np.median([est.median for est, _, _ in results])),
        "reprojection_rms_initial_px": float(np.sqrt(np.sum(obs * np.array([est.rms_before for est, _, _ in results]) ** 2) / obs.sum())),
        "inlier_fraction": float(np.sum(obs * np.array([est.inlier_fraction for est, _, _ in results])) / obs.sum()),
        "landmark_weight": config.pose_landmarks if landmarks is not None else 0.0,
        "landmark_rms_px": _landmark_rms([est.landmark_rms for est, _, _ in results]),
        "ba_iterations": int(max(est.iterations for est, _, _ in results)),
        "reference_frame": int(results[0][0].reference),
    }
    return doc


def _step_plate(ctx: StepContext) -> dict:
    from .plate import background_plate

    _, work, _, bar = ctx
    plate = background_plate(work.load("frames"), _labels(work))
    with atomic_path(work.plate) as tmp:
        cv2.imwrite(str(tmp), cv2.cvtColor(plate.image, cv2.COLOR_RGB2BGR))
    doc = {"filled_fraction": plate.filled_fraction}
    bar("plate", 1, 1)
    return doc


# The cached steps in order; ``write`` (the dataset itself) follows them and is never cached.
PIPELINE = (
    Step("decode", ("min_seconds", "fps"), _step_decode),
    Step("features", ("features",), _step_features),
    Step("parse", ("parser", "min_face_fraction"), _step_parse),
    Step("face", ("face", "cut", "clothes"), _step_face),
    Step("pose", ("flow", "focal", "head_width", "extend_passes", "shape_sigma", "pose_landmarks", "smooth_sigma", "pose_segment", "pose_overlap"), _step_pose),
    Step("plate", (), _step_plate),
)
STEPS = tuple(step.name for step in PIPELINE) + ("write",)
_STEP_KEYS = {**{step.name: step.keys for step in PIPELINE}, "write": ("test_fraction", "auto_min_signal")}


def scene_bounds(labels: np.ndarray, poses: np.ndarray, K: tuple[float, float, float, float], head_width: float, mouth_pixels: np.ndarray | None = None, eye_pixels: np.ndarray | None = None) -> dict:
    """Head box (canonical), torso box (camera), near/far and mouth point from the tracked head.

    The mouth point is triangulated from ``mouth_pixels`` (``(N, 2)``, e.g. the centre of the inner
    lip landmarks per frame) under the poses (:func:`.headpose.triangulate_canonical`); without
    them, or for what the rays leave open, it is a guess on the front of the head at 55 % of its
    lower half.

    Returns:
        ``{"head_aabb", "torso_aabb", "near", "far", "mouth"}``: the :class:`SceneMeta` fields of
        those names, for ``SceneMeta(..., **bounds)``.
    """
    fx, fy, cx, cy = K
    z = poses[:, 2, 3]
    zc = float(np.median(z))
    # Vertical extent of the head around its centre, from the silhouettes (pixels -> units at the head's depth).
    tops, bottoms = [], []
    for i in np.linspace(0, len(labels) - 1, min(len(labels), 50)).round().astype(int):
        rows = np.flatnonzero((labels[i] == LABEL_HEAD).any(1))
        if len(rows):
            v0 = fy * poses[i, 1, 3] / poses[i, 2, 3] + cy
            tops.append((rows[0] - v0) * poses[i, 2, 3] / fy)
            bottoms.append((rows[-1] + 1 - v0) * poses[i, 2, 3] / fy)
    top = float(np.median(tops)) if tops else -0.65 * head_width
    bottom = float(np.median(bottoms)) if bottoms else 0.65 * head_width
    half = 0.6 * head_width
    head_aabb = ((-half, top - 0.1 * head_width, -0.66 * head_width), (half, bottom + 0.15 * head_width, 0.66 * head_width))
    torso = labels == LABEL_TORSO
    ys, xs = np.nonzero(torso.any(0))
    if len(xs):
        x0, x1 = (xs.min() - cx) / fx * zc, (xs.max() + 1 - cx) / fx * zc
        y0, y1 = (ys.min() - cy) / fy * zc, (ys.max() + 1 - cy) / fy * zc
    else:  # head-only footage: a token torso box under the head
        x0, x1, y0, y1 = -head_width, head_width, bottom, bottom + head_width
    depth = 0.5 * (x1 - x0)
    torso_aabb = ((x0 - 0.1 * head_width, y0 - 0.1 * head_width, zc - 0.5 * head_width), (x1 + 0.1 * head_width, y1 + 0.1 * head_width, zc + max(depth, head_width)))
    near = max(1e-3, float(z.min()) - 1.2 * head_width)
    far = float(z.max()) + max(depth, head_width) + 1.2 * head_width
    mouth = (0.0, 0.55 * bottom, -0.51 * head_width)
    if mouth_pixels is not None:
        from .headpose import triangulate_canonical

        mouth = tuple(float(v) for v in triangulate_canonical(mouth_pixels, poses, K, np.array(mouth)))
    eyes = None
    if eye_pixels is not None:  # (N, 2, 2): image-left eye first; triangulated like the mouth
        from .headpose import triangulate_canonical

        guesses = [np.array([side * 0.2 * head_width, 0.0, -0.5 * head_width]) for side in (-1.0, 1.0)]
        eyes = tuple(tuple(float(v) for v in triangulate_canonical(eye_pixels[:, k], poses, K, guesses[k])) for k in range(2))
    return {"head_aabb": head_aabb, "torso_aabb": torso_aabb, "near": near, "far": far, "mouth": mouth, "eyes": eyes}


def _contact_sheet(
    frames: np.ndarray, labels: np.ndarray, poses: np.ndarray, K: tuple[float, float, float, float], head_width: float, landmarks: np.ndarray | None, count: int = 4
) -> np.ndarray:
    """Sample frames with the parsing overlaid, the landmarks dotted (yellow) and the head's
    canonical axes drawn (x red, y green, z blue)."""
    colours = np.array([[0, 0, 0], [255, 60, 60], [60, 200, 60]], np.uint8)
    tiles = []
    for i in np.linspace(0, len(frames) - 1, count).round().astype(int):
        img = frames[i].copy()
        over = labels[i] > 0
        img[over] = (0.55 * img[over] + 0.45 * colours[labels[i][over]]).astype(np.uint8)
        axes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) * 0.6 * head_width
        uv = project_points(axes @ poses[i, :3, :3].T + poses[i, :3, 3], K)
        thick = max(1, img.shape[0] // 200)
        if landmarks is not None:
            for q in landmarks[i]:
                cv2.circle(img, tuple(np.floor(q).astype(int)), thick, (255, 230, 0), -1, cv2.LINE_AA)
        for k, col in zip((1, 2, 3), ((255, 0, 0), (0, 255, 0), (0, 0, 255))):
            cv2.line(img, tuple(np.round(uv[0]).astype(int)), tuple(np.round(uv[k]).astype(int)), col, thick, cv2.LINE_AA)
        cv2.putText(img, f"{i}", (4, 14 + 2 * thick), cv2.FONT_HERSHEY_SIMPLEX, 0.4 * thick, (255, 255, 255), thick, cv2.LINE_AA)
        tiles.append(img)
    return np.concatenate(tiles, axis=1)


def _layer_checks(report: dict, labels: np.ndarray, landmarks: np.ndarray | None, config: PreprocessConfig) -> None:
    """The report's ``layers`` and ``torso`` checks of the final parsing, with their warnings."""
    if landmarks is not None:
        report["layers"] = layer_check(labels, landmarks)
        low = report["layers"]["lip_in_head"] < LIP_IN_HEAD_MIN or report["layers"]["chin_lip_midpoint_in_head"] < MIDPOINT_IN_HEAD_MIN
        if low:
            _report_warning(
                report,
                "layers_warning",
                f"only {report['layers']['lip_in_head']:.0%} of the lip landmarks and {report['layers']['chin_lip_midpoint_in_head']:.0%} of the points between chin "
                "and lower lip lie in the head layer: the mouth would be rendered by the torso, which does not follow the audio",
            )
        report["torso"] = torso_check(labels, landmarks)
        share = report["torso"]["person_at_bottom"]
        if share is not None and share < PERSON_AT_BOTTOM_MIN:
            _report_warning(
                report,
                "torso_warning",
                f"only {share:.0%} of the frame's bottom edge under the face (a face width either side of the chin) is labelled person "
                f"(the worst frame {report['torso']['person_at_bottom_worst']:.0%}): clothes were probably taken for background and will be rendered as the plate (see the report's contact sheet). "
                + (
                    "The classical parser finds the person by motion, and clothes that never move look like the wall; "
                    + ("--clothes grabcut adds them back by colour, or " if config.clothes == "none" else "adding them back by colour did not find them either (a colour like the wall's?); ")
                    + "--parser mediapipe segments the person by appearance"
                    if config.parser == "classical"
                    else "Check the parsing of this clip"
                ),
            )
    else:
        report["layers"] = {"note": "no landmarks (--face none): the fraction of the mouth in the head layer is not known"}


def _torso_motion(frames: np.ndarray, labels: np.ndarray, report: dict, bar: Bar) -> np.ndarray:
    """The torso's motion in each frame (``torso.npy``), with the report's ``torso_motion`` entry
    (and a warning where frames could not be registered)."""
    t0 = time.perf_counter()
    torso = torso_motion(frames, labels, progress=lambda done, total: bar("torso motion", done, total))
    report["torso_motion"] = {**torso.report(), "seconds": round(time.perf_counter() - t0, 3)}
    if torso.failed:
        msg = f"the torso's motion could not be measured in {len(torso.failed)} of {len(frames)} frames (given their neighbours'): check the parsing's torso"
        _report_warning(report, "torso_motion_warning", msg)
    return torso.maps


def _chosen_features(work: _Work, config: PreprocessConfig, landmarks: np.ndarray | None, train: list[int]) -> tuple[np.ndarray, str, dict]:
    """The dataset's feature windows ``(N, 16, D)``, their kind and the report's ``features``
    entry (under ``features="auto"``: :func:`.feature_choice.choose_features`)."""
    if config.features != "auto":
        return work.load("features"), config.features, {"kind": config.features}
    choice = choose_features(work.load("features"), work.load("phonemes"), landmarks, train, config.auto_min_signal)
    return choice.windows, choice.kind, {**choice.doc, "chosen": "auto"}


def _step_write(video: Path, out: Path, work: _Work, config: PreprocessConfig, docs: dict, bar: Bar, overwrite: bool) -> dict:
    t0 = time.perf_counter()
    info = work.load_json("decode")
    frames, labels, poses = work.load("frames"), _labels(work), work.load("poses")
    n = len(frames)
    K = _intrinsics(config, info)
    landmarks = _landmarks(work, config)
    b = scene_bounds(labels, poses, K, config.head_width, None if landmarks is None else mouth_centres(landmarks), None if landmarks is None else eye_centres_px(landmarks))
    train, test = tail_split(n, config.test_fraction)
    features, feature_kind, feature_doc = _chosen_features(work, config, landmarks, train)
    meta = SceneMeta(
        fps=float(info["fps"]),
        width=int(info["width"]),
        height=int(info["height"]),
        intrinsics=K,
        **b,
        feature_kind=feature_kind,
        feature_dim=int(features.shape[-1]),
        n_frames=n,
        train=train,
        test=test,
        source=f"adnerf preprocess {video.name}: parser={config.parser} face={config.face} flow={config.flow} focal={K[0]:g}",
        framing=info["framing"] if "framing" in info and (Framing.from_dict(info["framing"]).cropped or config.start or config.end is not None) else None,
    )
    audio = read_audio(work.audio) if info["audio"] else AudioTrack(np.zeros(int(16000 * info["seconds"]), np.float32), 16000, 0.0)
    plate = cv2.cvtColor(cv2.imread(str(work.plate)), cv2.COLOR_BGR2RGB)
    report = {
        "video": str(video),
        "frames": n,
        "width": info["width"],
        "height": info["height"],
        "fps": info["fps"],
        "seconds": info["seconds"],
        "config": asdict(config),
        "features": feature_doc,
        "decode": docs.get("decode", {}),
        **{f"parse_{k}": v for k, v in docs["parse"].items()},
        **{f"face_{k}": v for k, v in docs["face"].items()},
        **{f"pose_{k}": v for k, v in docs["pose"].items()},
        "plate_filled_fraction": docs["plate"]["filled_fraction"],
        "bounds": b,
        "timings_s": {step.name: work.record.get(step.name, {}).get("seconds") for step in PIPELINE},
    }
    _layer_checks(report, labels, landmarks, config)
    sheet = _contact_sheet(frames, labels, poses, K, config.head_width, landmarks)

    def extra(folder: DatasetFolder) -> None:
        report["timings_s"]["write"] = round(time.perf_counter() - t0, 3)  # all but the final rename
        folder.report.write_text(json.dumps(report, indent=1))
        cv2.imwrite(str(folder.report_image), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))

    eye = None if landmarks is None else eye_openness(landmarks)  # the head's eye condition
    torso = _torso_motion(frames, labels, report, bar)
    save_dataset(
        out, meta, frames=frames, parsing=labels, background=plate, poses=poses, features=features, audio=audio, eye=eye, landmarks=landmarks, torso=torso,
        extra=extra, overwrite=overwrite, inputs=[video],
    )  # fmt: skip
    bar("write", 1, 1)
    return report


@writes_folder("out", "dataset")  # one writer per dataset folder
def preprocess_video(video: str | Path, out: str | Path, config: PreprocessConfig = PreprocessConfig(), *, progress: Bar | None = None, overwrite: bool = False) -> dict:
    """Turn a static-camera talking-head video into a dataset folder (see the module docstring).

    Args:
        video: The video file (with an audio track unless ``config.features == "none"``).
        out: Dataset folder to create; must not exist unless ``overwrite``.
        config: Settings.
        progress: Called as ``progress(step, done, total)``.
        overwrite: Replace an existing dataset folder.

    Returns:
        The report (also written as ``out/preprocess_report.json``), with per-step timings.

    Raises:
        PreprocessError: Bad settings or a video that cannot become a dataset.
        adnerf.io.MediaError: The file is missing or unreadable.
    """
    config.validate()
    video, out = Path(video), Path(out)
    if not video.is_file():
        raise MediaError(f"{video}: no such file")
    check_folder_output(out, "dataset", inputs=[video], overwrite=overwrite)
    bar = progress or (lambda step, done, total: None)
    work = _Work(out.with_name(f".{out.name}.preprocess"), video, config)
    ctx = StepContext(video, work, config, bar)
    docs: dict = {}
    failed = True
    try:
        for step in PIPELINE:
            docs[step.name] = run_step(step, ctx)
        report = _step_write(video, out, work, config, docs, bar, overwrite)
        failed = False
    except (PreprocessError, MediaError, DatasetError, OutputError):
        # Bad input (also a scene the dataset check rejects at the write step): nothing worth resuming.
        shutil.rmtree(work.folder, ignore_errors=True)
        raise
    except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: the finished steps stay in the work folder
        kept = [step.name for step in PIPELINE if work.done(step.name)]
        cut = next((name for name in STEPS if name not in kept), STEPS[-1])
        raise type(exc)(f"stopped in the {cut} step; {len(kept)} finished step(s) kept in {work.folder} ({', '.join(kept) or 'none'}): the same command resumes there") from None
    finally:
        if not failed:
            shutil.rmtree(work.folder, ignore_errors=True)
    return report
