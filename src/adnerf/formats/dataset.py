"""The dataset folder: what training, rendering and evaluation read, and what preprocessing writes.

Layout (format ``adnerf-dataset``, version 1)::

    DATASET/
      meta.json            format, version, fps, size, intrinsics, near/far, head and torso boxes,
                           mouth point, audio feature kind and width, train/test frame indices
      frames/000000.png    RGB frames
      parsing/000000.png   label maps: 0 background, 1 head, 2 torso (uint8 PNG)
      background.png       the background plate (RGB)
      poses.npy            (N, 4, 4) float64 head-canonical -> camera transforms
      audio.wav            the audio track (mono PCM, clock starts at frame 0's time)
      features.npy         (N, 16, D) float32 audio feature windows, one per frame
      eye.npy              optional: (N,) float32 eye openness per frame (1: open as usual in this
                           clip, 0: closed), the head's eye condition; from the landmarks' eye
                           aspect ratio (adnerf preprocess, import-adnerf) or exact (synth)
      landmarks.npy        optional: (N, 68, 2) float64 face landmarks (iBUG layout, pixel centres at
                           +0.5) from adnerf preprocess or an imported AD-NeRF folder; the mouth
                           point in meta.json was derived from them, and training asks the audio
                           code to predict their mouth opening and width (model/mouth_target.py)
      torso.npy            optional: (N, 2, 3) float64 the torso's motion in the image: frame i's
                           affine map from the reference torso's pixels to its own (x' = A x + b,
                           pixels as landmarks.npy's); the torso layer follows it
                           (preprocess/torso_motion.py)
      preprocess_report.json, preprocess_report.png
                           adnerf preprocess's report and contact sheet
      video.mp4            synthetic scenes only: the rendered clip with its audio
      truth/               synthetic scenes only: poses.npy, parsing.npy (N, H, W) uint8,
                           depth.npy (N, H, W) float32 (distance along the unit pixel ray,
                           +inf where no surface), jaw.npy (N,) mouth opening in [0, 1],
                           eye.npy (N,) eye openness in [0, 1] (older scenes: absent)

Conventions: the camera is static with OpenCV axes (x right, y down, z forward) and is the world
frame; a pose maps head-canonical points ``p`` to camera points ``R p + t``; the head box
(``head_aabb``) is in canonical space, the torso box (``torso_aabb``) in camera space; lengths are
in scene units (the synthetic head is 1.6 units wide). A dataset is written to a temporary folder
and renamed into place, so a folder that exists is complete. :class:`DatasetFolder` is the one
place these file names are spelled.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np
import torch

from ..cameras import Camera, intrinsics_matrix
from ..io import AudioTrack, MediaError, read_audio
from ..memory import require
from ..pose import HeadPose
from .outputs import check_folder_output

__all__ = [
    "EYE_CROP", "FORMAT", "LABEL_BACKGROUND", "LABEL_HEAD", "LABEL_TORSO", "MOUTH_CROP", "TRUTH_FILES", "VERSION", "DatasetError", "DatasetFolder",
    "DatasetTracks", "SceneMeta", "TalkingHeadDataset", "Truth", "check_poses", "check_torso", "frame_bytes", "load_dataset", "meta_from_dict", "read_meta", "read_tracks", "save_dataset", "tail_split", "write_wav",
]  # fmt: skip

FORMAT = "adnerf-dataset"
VERSION = 1
LABEL_BACKGROUND, LABEL_HEAD, LABEL_TORSO = 0, 1, 2


@dataclass(frozen=True)
class DatasetFolder:
    """Where each file of a dataset folder lies (the layout of the module docstring): the one
    place in adnerf that spells their names.

    Attributes:
        root: The dataset folder (it need not exist: a writer names the files of a folder it is
            about to fill).
    """

    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    @property
    def meta(self) -> Path:
        return self.root / "meta.json"

    @property
    def frames(self) -> Path:
        """The folder of RGB frames (:meth:`frame`)."""
        return self.root / "frames"

    @property
    def parsing(self) -> Path:
        """The folder of label maps (:meth:`labels`)."""
        return self.root / "parsing"

    def frame(self, i: int) -> Path:
        return self.frames / f"{i:06d}.png"

    def labels(self, i: int) -> Path:
        return self.parsing / f"{i:06d}.png"

    @property
    def background(self) -> Path:
        return self.root / "background.png"

    @property
    def poses(self) -> Path:
        return self.root / "poses.npy"

    @property
    def features(self) -> Path:
        return self.root / "features.npy"

    @property
    def audio(self) -> Path:
        return self.root / "audio.wav"

    @property
    def eye(self) -> Path:
        return self.root / "eye.npy"

    @property
    def landmarks(self) -> Path:
        return self.root / "landmarks.npy"

    @property
    def torso(self) -> Path:
        return self.root / "torso.npy"

    @property
    def report(self) -> Path:
        """``adnerf preprocess``'s report (JSON)."""
        return self.root / "preprocess_report.json"

    @property
    def report_image(self) -> Path:
        """``adnerf preprocess``'s report (contact sheet)."""
        return self.root / "preprocess_report.png"

    @property
    def video(self) -> Path:
        """A synthetic scene's clip (mp4 with its audio): the input its preprocessing is checked on."""
        return self.root / "video.mp4"

    @property
    def truth(self) -> Path:
        """The folder of a synthetic scene's exact quantities (:meth:`truth_file`)."""
        return self.root / "truth"

    def truth_file(self, name: str) -> Path:
        """``truth/NAME.npy`` for ``name`` in ``poses``, ``parsing``, ``depth``, ``jaw``, ``eye``."""
        if name not in TRUTH_FILES:
            raise ValueError(f"no truth file {name!r}; the truth holds {', '.join(TRUTH_FILES)}")
        return self.truth / f"{name}.npy"

    def is_dataset(self) -> bool:
        """Whether the folder holds a dataset's ``meta.json`` (complete: datasets are renamed into place)."""
        return self.meta.exists()


TRUTH_FILES = ("poses", "parsing", "depth", "jaw", "eye")
MOUTH_CROP = 0.8  # side of the square around the mouth point (scene units) that evaluation crops and training favours
EYE_CROP = 0.4  # side of the square around each eye point (scene units) that training favours in heads that blink


class DatasetError(ValueError):
    """A dataset folder is missing, of another format or version, or inconsistent."""


@dataclass
class SceneMeta:
    """The scalar description of a dataset (``meta.json``).

    Attributes:
        fps: Frame rate (frame ``i`` is shown at ``i / fps`` seconds on the audio clock).
        width: Frame width in pixels.
        height: Frame height in pixels.
        intrinsics: ``(fx, fy, cx, cy)`` in pixels, pixel centres at ``+0.5``.
        near: Nearest distance along a ray that can hold the person (scene units).
        far: Farthest such distance.
        head_aabb: Head box in canonical space, ``((x, y, z)_min, (x, y, z)_max)``.
        torso_aabb: Torso box in camera space.
        mouth: Mouth centre in canonical space ``(x, y, z)`` (the mouth crop of evaluation).
        feature_kind: Audio feature extractor (see :class:`adnerf.audio.features.FeatureSpec`).
        feature_dim: Width ``D`` of the feature windows.
        n_frames: Number of frames ``N``.
        train: Training frame indices.
        test: Held-out frame indices.
        source: Where the dataset came from (free text).
        eyes: Both eyes' centres in canonical space (image-left first), or ``None`` (datasets
            without landmarks or made before blinks): where training favours rays for the eyes.
        framing: Where the frames lie in the source video, when preprocessing cropped, scaled or
            trimmed it (:class:`adnerf.preprocess.framing.Framing` as a dict: ``source_size``,
            ``crop``, ``size``, ``start_s``); ``None`` when the frames are the video's own.
    """

    fps: float
    width: int
    height: int
    intrinsics: tuple[float, float, float, float]
    near: float
    far: float
    head_aabb: tuple[tuple[float, float, float], tuple[float, float, float]]
    torso_aabb: tuple[tuple[float, float, float], tuple[float, float, float]]
    mouth: tuple[float, float, float]
    feature_kind: str
    feature_dim: int
    n_frames: int
    train: list[int]
    test: list[int]
    source: str = ""
    eyes: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    framing: dict | None = None

    def to_dict(self) -> dict:
        """JSON-ready fields; ``eyes`` only when known (so metadata from before it reads and
        fingerprints as it did)."""
        d = asdict(self)
        for key in ("eyes", "framing"):
            if d[key] is None:
                del d[key]
        return d

    def validate(self, where: str = "meta.json") -> None:
        """Raise :class:`DatasetError` on values that cannot describe a scene."""
        if not (self.fps > 0 and self.width > 0 and self.height > 0 and self.n_frames > 0):
            raise DatasetError(f"{where}: fps, width, height and n_frames must be positive")
        if not 0 <= self.near < self.far:
            raise DatasetError(f"{where}: need 0 <= near < far; got {self.near}, {self.far}")
        for name in ("head_aabb", "torso_aabb"):
            lo, hi = (np.asarray(v, dtype=float) for v in getattr(self, name))
            if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
                raise DatasetError(f"{where}: {name} must be two 3-vectors with max > min")
        if self.eyes is not None and (np.shape(self.eyes) != (2, 3) or not np.isfinite(np.asarray(self.eyes, dtype=float)).all()):
            raise DatasetError(f"{where}: eyes must be two finite 3-vectors (canonical eye centres)")
        if not self.train:
            raise DatasetError(f"{where}: the train split is empty")
        indices = list(self.train) + list(self.test)
        if min(indices) < 0 or max(indices) >= self.n_frames:
            raise DatasetError(f"{where}: split indices must lie in [0, {self.n_frames})")
        if set(self.train) & set(self.test):
            raise DatasetError(f"{where}: train and test splits overlap")

    def camera(self, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> Camera:
        """The static camera (world = camera frame)."""
        K = intrinsics_matrix(*self.intrinsics, dtype=dtype).to(device)
        return Camera(K, self.height, self.width)

    def eyes_in_image(self, pose: HeadPose) -> tuple[torch.Tensor, torch.Tensor]:
        """Where the canonical eye points appear under one head pose: pixels ``(2, 2)`` and camera
        depths ``(2,)``.

        Raises:
            ValueError: The dataset has no eye points.
        """
        if self.eyes is None:
            raise ValueError("this dataset has no eye points (meta.json eyes)")
        eyes = torch.tensor(self.eyes, dtype=pose.R.dtype, device=pose.R.device)
        p = pose.from_canonical(eyes)
        return self.camera(pose.R.dtype, pose.R.device).project(p), p[..., 2]

    def mouth_in_image(self, pose: HeadPose) -> tuple[torch.Tensor, torch.Tensor]:
        """Where the canonical mouth point appears under head pose(s) ``pose`` (batch ``(...)``):
        pixel coordinates ``(..., 2)`` and camera depth ``z`` ``(...)``."""
        mouth = torch.tensor(self.mouth, dtype=pose.R.dtype, device=pose.R.device)
        p = pose.from_canonical(mouth.expand(*pose.t.shape[:-1], 3))
        return self.camera(pose.R.dtype, pose.R.device).project(p), p[..., 2]

    def mouth_boxes(self, pose: HeadPose, crop: float = MOUTH_CROP) -> np.ndarray:
        """Square pixel boxes ``(n, 4)`` as ``(x0, y0, x1, y1)`` (end exclusive) around the mouth
        under head poses ``pose`` (batch ``(n,)``).

        The side is ``crop`` scene units at the mouth's depth, the same for every frame (its mean),
        and boxes are shifted to lie inside the image.
        """
        uv_t, depth = self.mouth_in_image(pose)
        uv = uv_t.cpu().numpy()
        side = int(round(crop * self.intrinsics[0] / float(depth.mean())))
        side = max(8, min(side, self.width, self.height))
        x0 = np.clip(np.round(uv[:, 0] - side / 2).astype(int), 0, self.width - side)
        y0 = np.clip(np.round(uv[:, 1] - side / 2).astype(int), 0, self.height - side)
        return np.stack([x0, y0, x0 + side, y0 + side], axis=1)

    def box(self, name: str, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``head_aabb`` or ``torso_aabb`` as two ``(3,)`` tensors."""
        lo, hi = getattr(self, name)
        return torch.tensor(lo, dtype=dtype, device=device), torch.tensor(hi, dtype=dtype, device=device)


@dataclass
class Truth:
    """Exact quantities of a synthetic scene (``truth/``).

    Attributes:
        poses: ``(N, 4, 4)`` float64 head poses.
        parsing: ``(N, H, W)`` uint8 label maps.
        depth: ``(N, H, W)`` float32 distance along the unit pixel ray (``inf``: background).
        jaw: ``(N,)`` mouth opening in ``[0, 1]``.
        eye: ``(N,)`` eye openness in ``[0, 1]`` (``None`` for scenes made before blinks).
    """

    poses: np.ndarray
    parsing: np.ndarray
    depth: np.ndarray
    jaw: np.ndarray
    eye: np.ndarray | None = None


@dataclass
class TalkingHeadDataset:
    """A loaded dataset; arrays are numpy, in the shapes of the module docstring.

    Attributes:
        root: The folder.
        meta: Its :class:`SceneMeta`.
        frames: ``(N, H, W, 3)`` uint8 RGB.
        parsing: ``(N, H, W)`` uint8 labels.
        background: ``(H, W, 3)`` uint8 RGB plate.
        poses: ``(N, 4, 4)`` float64.
        features: ``(N, 16, D)`` float32.
        audio: The audio track.
        truth: :class:`Truth` for synthetic scenes, else ``None``.
        eye: ``(N,)`` float32 eye openness (``eye.npy``), ``None`` when the dataset has none.
        landmarks: ``(N, 68, 2)`` float64 face landmarks (``landmarks.npy``), ``None`` when the
            dataset has none.
        torso: ``(N, 2, 3)`` float64 torso motion (``torso.npy``: each frame's affine map from
            the reference torso's pixels to its own), ``None`` when the dataset has none.
    """

    root: Path
    meta: SceneMeta
    frames: np.ndarray
    parsing: np.ndarray
    background: np.ndarray
    poses: np.ndarray
    features: np.ndarray
    audio: AudioTrack
    truth: Truth | None = field(default=None, repr=False)
    eye: np.ndarray | None = None
    landmarks: np.ndarray | None = None
    torso: np.ndarray | None = None

    def fingerprint(self) -> str:
        """SHA-256 of the dataset's content (metadata, frames, parsing, plate, poses, features,
        audio): equal for the same data wherever the folder lies, different after any change.
        The landmarks are left out: they are found in the frames, and runs trained before
        training read them keep their fingerprint."""
        h = hashlib.sha256(json.dumps(self.meta.to_dict(), sort_keys=True).encode())
        arrays = [self.frames, self.parsing, self.background, self.poses, self.features, self.audio.samples]
        # datasets without eyes or torso motion keep their fingerprint
        for arr in arrays + [a for a in (self.eye, self.torso) if a is not None]:
            a = np.ascontiguousarray(arr)
            h.update(f"{a.dtype}{a.shape}".encode())
            h.update(a.data)
        return h.hexdigest()

    def audio_of(self, first: int, stop: int) -> AudioTrack:
        """The audio under frames ``first .. stop - 1``, from ``first / fps`` to ``stop / fps`` on
        the audio clock (silence where the track does not reach), with its clock starting at 0."""
        rate = self.audio.sample_rate
        t0 = first / self.meta.fps - self.audio.start
        a, b = int(round(t0 * rate)), int(round((t0 + (stop - first) / self.meta.fps) * rate))
        piece = np.zeros(max(b - a, 0), np.float32)
        src = self.audio.samples[max(a, 0) : max(min(b, len(self.audio.samples)), 0)]
        piece[max(-a, 0) : max(-a, 0) + len(src)] = src
        return AudioTrack(piece, rate, 0.0)

    def head_pose(self, index: int | Sequence[int] | np.ndarray, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> HeadPose:
        """The head pose(s) of frame(s) ``index`` as a :class:`HeadPose`."""
        return HeadPose.from_matrix(torch.as_tensor(self.poses[index], dtype=dtype, device=device))


def tail_split(n_frames: int, test_fraction: float) -> tuple[list[int], list[int]]:
    """Train and test frame indices: the last ``test_fraction`` of the clip (at least one frame)
    is held out, so test frames are never neighbours of training frames except at one cut."""
    n_test = max(1, int(round(n_frames * test_fraction)))
    return list(range(n_frames - n_test)), list(range(n_frames - n_test, n_frames))


def _write_png(path: Path, image: np.ndarray) -> None:
    img = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    if not cv2.imwrite(str(path), img):
        raise DatasetError(f"{path}: could not write the image")


def _read_png(path: Path, color: bool) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR if color else cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{path}: missing or unreadable image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if color else img


def write_wav(path: Path, audio: AudioTrack) -> None:
    """Write mono 16-bit PCM (samples clipped to ``[-1, 1]``)."""
    from scipy.io import wavfile

    pcm = np.round(np.clip(audio.samples, -1.0, 1.0) * 32767.0).astype(np.int16)
    wavfile.write(str(path), int(audio.sample_rate), pcm)


def save_dataset(
    root: str | Path,
    meta: SceneMeta,
    *,
    frames: np.ndarray,
    parsing: np.ndarray,
    background: np.ndarray,
    poses: np.ndarray,
    features: np.ndarray,
    audio: AudioTrack,
    truth: Truth | None = None,
    eye: np.ndarray | None = None,
    landmarks: np.ndarray | None = None,
    torso: np.ndarray | None = None,
    extra: "Callable[[DatasetFolder], None] | None" = None,
    overwrite: bool = False,
    inputs: Sequence[str | Path] = (),
) -> Path:
    """Write a dataset folder atomically (a temporary sibling renamed into place).

    Args:
        root: Destination folder; must not exist unless ``overwrite``.
        meta: Scene description; validated and checked against the arrays.
        frames: ``(N, H, W, 3)`` uint8.
        parsing: ``(N, H, W)`` uint8 labels in {0, 1, 2}.
        background: ``(H, W, 3)`` uint8.
        poses: ``(N, 4, 4)``.
        features: ``(N, 16, D)``.
        audio: Audio whose sample 0 plays with frame 0.
        truth: Exact quantities of a synthetic scene.
        eye: ``(N,)`` eye openness (``eye.npy``), or ``None``.
        landmarks: ``(N, 68, 2)`` face landmarks (``landmarks.npy``), or ``None``.
        torso: ``(N, 2, 3)`` torso motion (``torso.npy``), or ``None``.
        extra: Called with the temporary folder's :class:`DatasetFolder` to add more files (e.g.
            the preprocessing report) before the rename.
        overwrite: Replace an existing adnerf dataset there (never another folder: see
            :func:`adnerf.formats.outputs.check_folder_output`).
        inputs: The writing command's input files; a folder holding one is never replaced.

    Returns:
        The dataset folder.

    Raises:
        adnerf.formats.outputs.OutputError: ``root`` must not be written (see :mod:`adnerf.formats.outputs`).
        DatasetError: Inconsistent metadata or arrays.
    """
    root = Path(root)
    check_folder_output(root, "dataset", inputs=inputs, overwrite=overwrite)
    meta.validate()
    _check_arrays(meta, frames, parsing, background, poses, features, str(root))
    _check_eye(eye, meta.n_frames, str(root))
    check_torso(torso, meta.n_frames, str(root))
    tmp = root.with_name(f".{root.name}.tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    files = DatasetFolder(tmp)
    files.frames.mkdir(parents=True)
    files.parsing.mkdir()
    try:
        for i in range(meta.n_frames):
            _write_png(files.frame(i), frames[i])
            _write_png(files.labels(i), parsing[i])
        _write_png(files.background, background)
        np.save(files.poses, np.asarray(poses, dtype=np.float64))
        np.save(files.features, np.asarray(features, dtype=np.float32))
        write_wav(files.audio, audio)
        if eye is not None:
            np.save(files.eye, np.asarray(eye, dtype=np.float32))
        if landmarks is not None:
            np.save(files.landmarks, np.asarray(landmarks, dtype=np.float64))
        if torso is not None:
            np.save(files.torso, np.asarray(torso, dtype=np.float64))
        if truth is not None:
            files.truth.mkdir()
            np.save(files.truth_file("poses"), np.asarray(truth.poses, dtype=np.float64))
            np.save(files.truth_file("parsing"), np.asarray(truth.parsing, dtype=np.uint8))
            np.save(files.truth_file("depth"), np.asarray(truth.depth, dtype=np.float32))
            np.save(files.truth_file("jaw"), np.asarray(truth.jaw, dtype=np.float64))
            if truth.eye is not None:
                np.save(files.truth_file("eye"), np.asarray(truth.eye, dtype=np.float64))
        if extra is not None:
            extra(files)
        doc = {"format": FORMAT, "version": VERSION, **meta.to_dict()}
        files.meta.write_text(json.dumps(doc, indent=1))
        if root.exists():
            shutil.rmtree(root)
        os.replace(tmp, root)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return root


def check_torso(torso: np.ndarray | None, n: int, where: str) -> None:
    """Check a torso motion track: ``(n, 2, 3)`` finite affine maps whose linear part is
    invertible (``None`` passes).

    Raises:
        DatasetError: Another shape, a value that is not finite, or a singular map.
    """
    if torso is None:
        return
    torso = np.asarray(torso)
    if torso.shape != (n, 2, 3) or not np.isfinite(torso).all():
        raise DatasetError(f"{where}: torso motion must be ({n}, 2, 3) finite affine maps; got shape {torso.shape}")
    det = np.linalg.det(torso[:, :, :2])
    if (np.abs(det) < 1e-6).any():
        raise DatasetError(f"{where}: torso motion of frame {int(np.argmin(np.abs(det)))} is singular")


def _check_eye(eye: np.ndarray | None, n: int, where: str) -> None:
    if eye is None:
        return
    eye = np.asarray(eye)
    if eye.shape != (n,) or not np.isfinite(eye).all():
        raise DatasetError(f"{where}: eye openness must be ({n},) finite values; got shape {eye.shape}")


def _check_arrays(meta: SceneMeta, frames: np.ndarray, parsing: np.ndarray, background: np.ndarray, poses: np.ndarray, features: np.ndarray, where: str) -> None:
    n, h, w = meta.n_frames, meta.height, meta.width
    expect = {
        "frames": (frames, (n, h, w, 3)),
        "parsing": (parsing, (n, h, w)),
        "background": (background, (h, w, 3)),
        "poses": (poses, (n, 4, 4)),
    }
    for name, (arr, shape) in expect.items():
        if tuple(arr.shape) != shape:
            raise DatasetError(f"{where}: {name} has shape {tuple(arr.shape)}; meta.json says {shape}")
    if features.ndim != 3 or features.shape[0] != n or features.shape[1] != 16 or features.shape[2] != meta.feature_dim:
        raise DatasetError(f"{where}: features have shape {tuple(features.shape)}; expected ({n}, 16, {meta.feature_dim})")
    if parsing.size and int(parsing.max()) > LABEL_TORSO:
        raise DatasetError(f"{where}: parsing labels must be 0 (background), 1 (head) or 2 (torso)")
    check_poses(poses, where)
    if not np.all(np.isfinite(features)):
        raise DatasetError(f"{where}: features contain NaN or inf")


def check_poses(poses: np.ndarray, where: str) -> None:
    """Raise :class:`DatasetError` unless ``poses (N, 4, 4)`` are finite rigid motions: last row
    ``(0, 0, 0, 1)``, orthonormal rotations (``|R R^T - I| <= 1e-4``) and ``det R = +1`` (a
    reflection would mirror the head)."""
    poses = np.asarray(poses)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise DatasetError(f"{where}: poses must have shape (N, 4, 4); got {poses.shape}")
    if not np.all(np.isfinite(poses)) or not np.allclose(poses[:, 3], [0, 0, 0, 1]):
        raise DatasetError(f"{where}: poses must be finite rigid 4x4 matrices with last row (0, 0, 0, 1)")
    if not len(poses):
        return
    rot = poses[:, :3, :3]
    err = np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max()
    if err > 1e-4:
        raise DatasetError(f"{where}: pose rotations are not orthonormal (max |R R^T - I| = {err:.2e})")
    det = np.linalg.det(rot)
    if np.any(det < 0):
        raise DatasetError(f"{where}: {int(np.sum(det < 0))} pose rotation(s) have det -1 (a mirror image, not a rotation), first at frame {int(np.argmax(det < 0))}")


@dataclass
class DatasetTracks:
    """A dataset's per-frame tracks without its frames: what rendering new audio over the
    dataset's pose track reads (the torso's motion with the pose of the frame it moved in).

    Attributes:
        meta: The scene's metadata.
        poses: ``(N, 4, 4)`` head poses.
        eye: ``(N,)`` eye openness, or ``None``.
        torso: ``(N, 2, 3)`` torso motion, or ``None``.
    """

    meta: SceneMeta
    poses: np.ndarray
    eye: np.ndarray | None = None
    torso: np.ndarray | None = None


def read_tracks(root: str | Path) -> DatasetTracks:
    """A dataset folder's :class:`DatasetTracks` (checked as :func:`load_dataset` checks them).

    Raises:
        DatasetError: No dataset there, or a track of the wrong shape.
    """
    files = DatasetFolder(Path(root))
    meta = read_meta(root)
    if not files.poses.exists():
        raise DatasetError(f"{root}: no {files.poses.name}")
    poses = np.load(files.poses)
    check_poses(poses, str(files.poses))
    if len(poses) != meta.n_frames:
        raise DatasetError(f"{files.poses}: {len(poses)} poses for {meta.n_frames} frames")
    return DatasetTracks(meta, poses, *_eye_and_torso(files, meta.n_frames))


def _eye_and_torso(files: DatasetFolder, n: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The optional per-frame tracks ``eye.npy`` and ``torso.npy`` of ``n`` frames, checked."""
    eye = np.load(files.eye) if files.eye.exists() else None
    _check_eye(eye, n, str(files.root))
    torso = np.load(files.torso) if files.torso.exists() else None
    check_torso(torso, n, str(files.root))
    return eye, torso


def read_meta(root: str | Path) -> SceneMeta:
    """Read and validate ``meta.json`` (format and version checked)."""
    root = Path(root)
    path = DatasetFolder(root).meta
    if not root.is_dir():
        raise DatasetError(f"{root}: no such dataset folder")
    if not path.exists():
        raise DatasetError(f"{root}: not an adnerf dataset (no {path.name})")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from exc
    if doc.get("format") != FORMAT:
        raise DatasetError(f"{path}: format is {doc.get('format')!r}, not {FORMAT!r}")
    if doc.get("version") != VERSION:
        raise DatasetError(
            f"{path}: dataset version {doc.get('version')!r}; this adnerf reads version {VERSION} (re-create the dataset with this version)"
        )
    body = {k: v for k, v in doc.items() if k not in ("format", "version")}
    known = set(SceneMeta.__dataclass_fields__)
    missing = known - set(body) - {"source", "eyes", "framing"}
    if missing:
        raise DatasetError(f"{path}: missing keys {sorted(missing)}")
    unknown = set(body) - known
    if unknown:
        raise DatasetError(f"{path}: unknown keys {sorted(unknown)}")
    meta = meta_from_dict(body)
    meta.validate(str(path))
    return meta


def meta_from_dict(body: dict) -> SceneMeta:
    """A :class:`SceneMeta` from its JSON form (:meth:`SceneMeta.to_dict`): lists back to tuples.
    Not validated."""
    body = dict(body)
    body["intrinsics"] = tuple(body["intrinsics"])
    body["head_aabb"] = tuple(tuple(v) for v in body["head_aabb"])
    body["torso_aabb"] = tuple(tuple(v) for v in body["torso_aabb"])
    body["mouth"] = tuple(body["mouth"])
    if body.get("eyes") is not None:
        body["eyes"] = tuple(tuple(v) for v in body["eyes"])
    return SceneMeta(**body)


def frame_bytes(meta: SceneMeta) -> int:
    """Bytes a loaded frame holds: its uint8 RGB pixels and labels (the training data of a frame;
    what grows with the clip)."""
    return 4 * meta.width * meta.height


def _fit(image: np.ndarray, shape: tuple[int, ...], path: Path) -> np.ndarray:
    if image.shape != shape or image.dtype != np.uint8:
        raise DatasetError(f"{path}: image of shape {image.shape} ({image.dtype}); meta.json says {shape} uint8")
    return image


def load_dataset(root: str | Path, *, truth: bool = True) -> TalkingHeadDataset:
    """Load and validate a dataset folder.

    Args:
        root: The folder.
        truth: Also load ``truth/`` when present.

    Raises:
        DatasetError: Missing files, wrong format or version, or inconsistent shapes.
        adnerf.memory.MemoryNeedError: The frames and labels would not fit in the memory
            available (checked before any is read).
    """
    root = Path(root)
    meta = read_meta(root)
    n, h, w = meta.n_frames, meta.height, meta.width
    require(frame_bytes(meta) * n, f"{root}: {n} frames of {w}x{h} (uint8 frames and labels)")
    frames = np.empty((n, h, w, 3), np.uint8)  # filled in place: no list of frames beside the array
    parsing = np.empty((n, h, w), np.uint8)
    files = DatasetFolder(root)
    for i in range(n):
        frames[i] = _fit(_read_png(files.frame(i), True), (h, w, 3), files.frame(i))
        parsing[i] = _fit(_read_png(files.labels(i), False), (h, w), files.labels(i))
    background = _read_png(files.background, True)
    for path in (files.poses, files.features, files.audio):
        if not path.exists():
            raise DatasetError(f"{root}: missing {path.name}")
    poses = np.load(files.poses)
    features = np.load(files.features)
    _check_arrays(meta, frames, parsing, background, poses, features, str(root))
    try:
        audio = read_audio(files.audio)
    except MediaError as exc:
        raise DatasetError(str(exc)) from exc
    eye, torso = _eye_and_torso(files, n)
    landmarks = np.load(files.landmarks) if files.landmarks.exists() else None
    if landmarks is not None and landmarks.shape != (n, 68, 2):
        raise DatasetError(f"{root}: {files.landmarks.name} has shape {landmarks.shape}; expected ({n}, 68, 2)")
    tr = None
    if truth and files.truth.is_dir():
        true_eye = np.load(files.truth_file("eye")) if files.truth_file("eye").exists() else None
        tr = Truth(*(np.load(files.truth_file(k)) for k in ("poses", "parsing", "depth", "jaw")), true_eye)
    return TalkingHeadDataset(root, meta, frames, parsing, background, poses, features, audio, tr, eye, landmarks, torso)
