"""``adnerf import-adnerf``: a dataset preprocessed by the original AD-NeRF code -> an adnerf dataset.

What the original preprocessing (``data_util/process_data.py`` of AD-NeRF) leaves in its folder,
and what we take from it:

============================  =====================================================================
``transforms_train.json``     ``focal_len``, ``cx``, ``cy``, and per frame ``img_id``, ``aud_id``,
``transforms_val.json``       ``transform_matrix`` (4x4 camera-to-head, OpenGL camera) and
                              ``face_rect``. The train file's frames become our train split, the
                              val file's our test split.
``ori_imgs/<img_id>.jpg``     The frames (``com_imgs/`` is used when ``ori_imgs/`` is missing).
``ori_imgs/<img_id>.lms``     68 face landmarks (``x y`` per line, face_alignment's iBUG layout),
                              when present for every frame: the mouth point is triangulated from
                              the inner lips under the poses, and they are kept as
                              ``landmarks.npy``.
``parsing/<img_id>.png``      Colour-coded parsing written by OpenCV: white background, head where
                              the file's first (blue) channel is 255 and the others 0; every other
                              colour (neck, clothes) is torso.
``bc.jpg``                    The background plate.
``aud.npy``                   DeepSpeech windows ``(M, 16, 29)``; frame ``k`` takes row
                              ``min(aud_id, M - 1)``, as the original loader does.
``aud.wav``                   The audio (or give it with ``audio=``).
============================  =====================================================================

Conventions converted:

* **Poses.** AD-NeRF stores the camera in the head's frame with an OpenGL camera (x right, y up,
  looking down -z), and its head frame has y up and the face towards +z. Ours are head-canonical
  to camera with an OpenCV camera (x right, y down, looking down +z) and a canonical head with y
  down and the face towards -z. With ``F = diag(1, -1, -1)`` for both flips and the file's
  ``M = [R_M | t_M]``::

      R = F R_M^T F,    t = -F R_M^T t_M

  so that a head-frame point ``X`` seen by AD-NeRF's camera is ``F X`` in our canonical space and
  lands on the same pixel.
* **Pixel centres.** AD-NeRF casts the ray of pixel ``(i, j)`` through ``(i - cx, j - cy)``, so
  its pixel centres sit at integers; ours sit at ``+0.5``: ``cx_ours = cx + 0.5``.
* **Scale.** Translations are rescaled so that the head is ``head_width`` units wide (1.6, as in
  ``adnerf preprocess`` and the synthetic scene), measured from the parsing's head width at the
  head's depth; densities, boxes and near/far then mean the same as in our other datasets.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..audio.features import load_npy_windows
from ..io import AudioTrack, MediaError, read_audio
from ..lock import writes_folder
from ..formats.dataset import LABEL_HEAD, LABEL_TORSO, SceneMeta, save_dataset
from ..formats.outputs import check_folder_output
from .landmarks import eye_centres_px, eye_openness, mouth_centres
from .pipeline import PreprocessError, scene_bounds
from .torso_motion import torso_motion

__all__ = ["adnerf_pose_to_ours", "import_adnerf", "ours_pose_to_adnerf", "parse_adnerf_parsing"]

SOURCE_PARSING = "parsing"  # the AD-NeRF folder's label images (its format, not ours)

FLIP = np.diag([1.0, -1.0, -1.0])
FEATURE_KIND = "deepspeech"
AUDIO_RATE = 16000


def adnerf_pose_to_ours(transform: np.ndarray) -> np.ndarray:
    """Convert AD-NeRF ``transform_matrix`` values to our head poses.

    Args:
        transform: Camera-to-head matrices, OpenGL camera, ``(..., 4, 4)`` (or ``(..., 3, 4)``).

    Returns:
        Head-canonical-to-camera poses ``(..., 4, 4)`` float64 in our conventions (see the module
        docstring); translations in the file's units.
    """
    M = np.asarray(transform, dtype=np.float64)
    if M.shape[-2:] not in ((4, 4), (3, 4)):
        raise ValueError(f"transform matrices must be (..., 4, 4) or (..., 3, 4); got {M.shape}")
    Rt = np.swapaxes(M[..., :3, :3], -1, -2)
    out = np.zeros(M.shape[:-2] + (4, 4))
    out[..., :3, :3] = FLIP @ Rt @ FLIP
    out[..., :3, 3] = -np.einsum("ij,...jk,...k->...i", FLIP, Rt, M[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def ours_pose_to_adnerf(pose: np.ndarray) -> np.ndarray:
    """Inverse of :func:`adnerf_pose_to_ours`: our head poses ``(..., 4, 4)`` -> AD-NeRF camera-to-head
    matrices. The conversion is its own inverse (``F R^T F`` and ``-F R^T t`` map back the same
    way), so this is the same map; the name says which way the data goes."""
    return adnerf_pose_to_ours(pose)


def parse_adnerf_parsing(bgr: np.ndarray) -> np.ndarray:
    """Labels ``(H, W)`` uint8 (0 background, 1 head, 2 torso) of an AD-NeRF parsing image.

    Args:
        bgr: The parsing PNG as OpenCV reads it, ``(H, W, 3)`` uint8 in BGR order.

    Thresholds at 128 per channel keep the classes apart after any resampling or compression.
    """
    hi = bgr >= 128
    white = hi.all(-1)
    head = hi[..., 0] & ~hi[..., 1] & ~hi[..., 2]
    labels = np.full(bgr.shape[:2], LABEL_TORSO, dtype=np.uint8)
    labels[white] = 0
    labels[head] = LABEL_HEAD
    return labels


def _read_json(path: Path) -> dict:
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise PreprocessError(f"{path}: cannot read it as JSON ({exc})") from exc
    for key in ("focal_len", "cx", "cy", "frames"):
        if key not in doc:
            raise PreprocessError(f"{path}: not an AD-NeRF transforms file (no {key!r})")
    for i, f in enumerate(doc["frames"]):
        if not {"img_id", "transform_matrix"} <= set(f):
            raise PreprocessError(f"{path}: frame {i} lacks img_id or transform_matrix")
    return doc


def _read_image(path: Path, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
    img = cv2.imread(str(path), flags) if path.exists() else None
    if img is None:
        raise PreprocessError(f"{path}: missing or unreadable")
    return img


def _read_landmarks(path: Path) -> np.ndarray:
    """One ``.lms`` file as ``(68, 2)`` pixel positions in our centre convention."""
    try:
        lms = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise PreprocessError(f"{path}: not a landmark file ({exc})") from exc
    if lms.shape != (68, 2) or not np.isfinite(lms).all():
        raise PreprocessError(f"{path}: {lms.shape} values; AD-NeRF landmark files hold 68 rows of x y")
    return lms + 0.5  # AD-NeRF's pixel centres sit at integers


def _scale_to_head_width(labels: np.ndarray, poses: np.ndarray, focal: float, head_width: float) -> float:
    """Factor that makes the head ``head_width`` wide: median over frames of head pixel width x depth / focal."""
    widths = []
    for i in np.linspace(0, len(labels) - 1, min(len(labels), 50)).round().astype(int):
        cols = np.flatnonzero((labels[i] == LABEL_HEAD).any(0))
        if len(cols) and poses[i, 2, 3] > 0:
            widths.append((cols[-1] + 1 - cols[0]) * poses[i, 2, 3] / focal)
    if not widths:
        raise PreprocessError("the parsing maps show no head (no pixel of the head colour); cannot import")
    return head_width / float(np.median(widths))


@writes_folder("out", "dataset")  # one writer per dataset folder
def _frame_entries(src: Path, notes: list[str]) -> tuple[dict, dict[int, tuple[dict, str]], list[int]]:
    """The transforms files' frames: ``(train doc, {img_id: (entry, split)}, sorted img_ids)``."""
    train_doc = _read_json(src / "transforms_train.json")
    val_path = src / "transforms_val.json"
    val_doc = _read_json(val_path) if val_path.exists() else {"frames": []}
    if not val_path.exists():
        notes.append("no transforms_val.json: the test split is empty")
    entries = [(f, "train") for f in train_doc["frames"]] + [(f, "test") for f in val_doc["frames"]]
    seen: dict[int, tuple[dict, str]] = {}
    for f, split in entries:
        seen.setdefault(int(f["img_id"]), (f, split))
    ids = sorted(seen)
    if not ids:
        raise PreprocessError(f"{src}: the transforms files list no frames")
    gaps = int(np.sum(np.diff(ids) != 1))
    if gaps:
        notes.append(f"img_ids are not contiguous ({gaps} gaps): frames after a gap are shown earlier than in the original video, so the audio track drifts there")
    return train_doc, seen, ids


def _read_frames(src: Path, ids: list[int], notes: list[str], progress: Callable[[int, int], None] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(frames (N, H, W, 3), labels (N, H, W), background (H, W, 3))`` of the frames ``ids``."""
    image_dir = src / "ori_imgs"
    if not image_dir.is_dir():
        image_dir = src / "com_imgs"
        notes.append("no ori_imgs/: frames taken from com_imgs/ (background already replaced by bc.jpg)")
    background = cv2.cvtColor(_read_image(src / "bc.jpg"), cv2.COLOR_BGR2RGB)
    H, W = background.shape[:2]
    n = len(ids)
    frames = np.empty((n, H, W, 3), np.uint8)
    labels = np.empty((n, H, W), np.uint8)
    for k, img_id in enumerate(ids):
        img = _read_image(image_dir / f"{img_id}.jpg")
        par = _read_image(src / SOURCE_PARSING / f"{img_id}.png")
        if img.shape[:2] != (H, W) or par.shape[:2] != (H, W):
            raise PreprocessError(f"frame {img_id}: image {img.shape[:2]} or parsing {par.shape[:2]} does not match bc.jpg ({H}, {W})")
        frames[k] = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        labels[k] = parse_adnerf_parsing(par)
        if progress is not None:
            progress(k + 1, n)
    return frames, labels, background


def _features_and_audio(src: Path, aud_ids: list[int], first_id: int, fps: float, audio: str | Path | None) -> tuple[np.ndarray, AudioTrack]:
    """The frames' DeepSpeech windows (``aud.npy`` rows ``aud_ids``) and the audio from frame ``first_id`` on."""
    try:
        aud = load_npy_windows(src / "aud.npy")
    except MediaError as exc:
        raise PreprocessError(f"{exc} (AD-NeRF's DeepSpeech windows are (M, 16, 29))") from exc
    if len(aud) < 1:
        raise PreprocessError(f"{src / 'aud.npy'}: holds no windows")
    features = aud[np.minimum(aud_ids, len(aud) - 1)].astype(np.float32)
    audio_path = Path(audio) if audio is not None else src / "aud.wav"
    try:
        track = read_audio(audio_path, sample_rate=AUDIO_RATE)
    except (MediaError, FileNotFoundError, OSError) as exc:
        raise PreprocessError(f"{audio_path}: cannot read the audio ({exc}); give the original audio with --audio FILE") from exc
    first = int(round(first_id / fps * AUDIO_RATE))
    return features, AudioTrack(track.samples[first:], AUDIO_RATE, 0.0)


def _bounds(labels: np.ndarray, poses: np.ndarray, K: tuple[float, float, float, float], head_width: float, landmarks: np.ndarray | None) -> dict:
    """The scene's boxes and near / far (:func:`scene_bounds`), the head box widened across and in
    depth: AD-NeRF's head origin is the face model's, not the middle of the head."""
    b = scene_bounds(labels, poses, K, head_width, None if landmarks is None else mouth_centres(landmarks), None if landmarks is None else eye_centres_px(landmarks))
    (x0, y0, z0), (x1, y1, z1) = b["head_aabb"]
    b["head_aabb"] = ((x0 - 0.15 * head_width, y0, z0 - 0.3 * head_width), (x1 + 0.15 * head_width, y1, z1 + 0.3 * head_width))
    b["near"] = max(1e-3, b["near"] - 0.3 * head_width)
    b["far"] += 0.3 * head_width
    return b


def import_adnerf(
    source: str | Path,
    out: str | Path,
    *,
    fps: float = 25.0,
    audio: str | Path | None = None,
    head_width: float = 1.6,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Read an AD-NeRF dataset folder and write it as an adnerf dataset.

    Args:
        source: The AD-NeRF folder (``dataset/<id>`` of the original code).
        out: Destination dataset folder (written atomically).
        fps: Frame rate of the original video (AD-NeRF's DeepSpeech windows assume 25).
        audio: Audio file; default ``source/aud.wav``.
        head_width: Head width in scene units after rescaling.
        overwrite: Replace an existing destination.
        progress: Called as ``progress(done, total)`` while frames are read.

    Returns:
        A summary: frames, train/test sizes, scale factor, size, feature shape, warnings.

    Raises:
        PreprocessError: A missing or malformed file, with its path.
    """
    src = Path(source)
    if not src.is_dir():
        raise PreprocessError(f"{src}: not a folder")
    if not (math.isfinite(fps) and fps > 0 and math.isfinite(head_width) and head_width > 0):
        raise PreprocessError("fps and head width must be positive finite numbers")
    inputs = [src] + ([Path(audio)] if audio is not None else [])
    check_folder_output(out, "dataset", inputs=inputs, overwrite=overwrite)
    notes: list[str] = []
    train_doc, seen, ids = _frame_entries(src, notes)
    frames, labels, background = _read_frames(src, ids, notes, progress)
    n, (H, W) = len(ids), background.shape[:2]
    landmarks = None
    lms_files = [src / "ori_imgs" / f"{img_id}.lms" for img_id in ids]
    if all(p.is_file() for p in lms_files):
        landmarks = np.stack([_read_landmarks(p) for p in lms_files])
    else:
        notes.append("no ori_imgs/<img_id>.lms landmarks for every frame: the mouth point is a fixed guess on the head")
    features, track = _features_and_audio(src, [int(seen[i][0].get("aud_id", i)) for i in ids], ids[0], fps, audio)
    focal = float(train_doc["focal_len"])
    K = (focal, focal, float(train_doc["cx"]) + 0.5, float(train_doc["cy"]) + 0.5)
    poses = adnerf_pose_to_ours(np.stack([np.asarray(seen[i][0]["transform_matrix"], np.float64) for i in ids]))
    if not np.all(poses[:, 2, 3] > 0):
        raise PreprocessError(f"{src}: {int(np.sum(poses[:, 2, 3] <= 0))} poses put the head behind the camera; these are not AD-NeRF camera-to-head matrices")
    scale = _scale_to_head_width(labels, poses, focal, head_width)
    poses[:, :3, 3] *= scale
    b = _bounds(labels, poses, K, head_width, landmarks)
    train = [k for k, i in enumerate(ids) if seen[i][1] == "train"]
    test = [k for k, i in enumerate(ids) if seen[i][1] == "test"]
    meta = SceneMeta(
        fps=float(fps), width=W, height=H, intrinsics=K, **b, feature_kind=FEATURE_KIND, feature_dim=int(features.shape[-1]), n_frames=n,
        train=train, test=test, source=f"imported from the AD-NeRF dataset {src.resolve()} (scale {scale:.6g})",
    )  # fmt: skip
    for note in notes:
        warnings.warn(note, stacklevel=2)
    eye = None if landmarks is None else eye_openness(landmarks)
    torso = torso_motion(frames, labels)  # how the shoulders move, as preprocess measures it
    save_dataset(
        out, meta, frames=frames, parsing=labels, background=background, poses=poses, features=features, audio=track, eye=eye, landmarks=landmarks,
        torso=torso.maps, overwrite=overwrite, inputs=inputs,
    )  # fmt: skip
    return {
        "dataset": str(out),
        "frames": n,
        "train": len(train),
        "test": len(test),
        "size": [W, H],
        "scale": scale,
        "features": list(features.shape),
        "landmarks": landmarks is not None,
        "torso_motion": torso.report(),
        "notes": notes,
    }
