"""adnerf preprocess: parsing, tracking, head pose, plate, resumable steps and bad input."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from adnerf.cli import main
from adnerf.io import AudioTrack, MediaError, write_video
from adnerf.formats.dataset import LABEL_HEAD, LABEL_TORSO, load_dataset
from adnerf.pose import rotation_angle
from adnerf.preprocess import PreprocessConfig, PreprocessError, preprocess_video
from adnerf.preprocess.headpose import align_poses, estimate_head_poses, mean_rotation
from adnerf.preprocess.parsing import (
    SHOULDER_HALF_WIDTH,
    person_hull,
    split_head_torso,
    torso_check,
)
from adnerf.preprocess.pipeline import PERSON_AT_BOTTOM_MIN, _camera_motion
from adnerf.preprocess.stillness import moving_regions
from adnerf.preprocess.plate import background_plate
from adnerf.preprocess.tracking import TrackConfig, Tracks, rigid_region, track_points
from adnerf.synth import SynthConfig, synthesize
from adnerf.synth import background_plate as synth_background


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("pre") / "scene", SynthConfig(seconds=3.0, size=96, voice="formant", seed=3))


@pytest.fixture(scope="module")
def preprocessed(scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("pre_out") / "data"
    focal = json.loads((scene / "meta.json").read_text())["intrinsics"][0]
    assert main(["preprocess", str(scene / "video.mp4"), "-o", str(out), "--focal", str(focal)]) == 0
    return out


def test_preprocess_recovers_the_synthetic_truth(preprocessed: Path, scene: Path, capsys: pytest.CaptureFixture) -> None:
    capsys.readouterr()
    assert main(["check-preprocess", str(preprocessed), "--truth", str(scene), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    # A 3-second, 96-pixel clip (a 36-pixel head): far looser than the bars, which are set for a
    # 10 s, 256 px clip (see README); these catch a broken step (a flipped axis or a failed
    # adjustment gives tens of degrees), not the last degree. The parse of this clip is not the
    # same in every process: alone it scores 0.864 / 0.910, but one full-suite run on a fresh
    # clone gave 0.854 / 0.877 (cause not found yet; every rerun gave 0.910), so the IoU bars
    # leave room for that spread; a lost head layer scores far lower.
    assert out["iou_mean"] > 0.8 and out["iou_head"] > 0.85
    assert out["rotation_median_deg"] < 10.0
    assert out["translation_median_head_widths"] < 0.1
    assert out["plate_psnr_seen"] > 28.0
    # The mouth point triangulated from the lip landmarks lands on the true mouth (measured 1.8 px
    # here; the fixed guess that --face none keeps lands 14.7 px away).
    assert out["mouth_error_median_px"] < 4.0
    # The eye points are triangulated like the mouth (eye rays of heads that blink): on the eyes.
    assert out["eye_error_median_px"] < 4.0
    ds = load_dataset(preprocessed)
    assert ds.eye is not None and ds.eye.shape == (75,) and 0.0 <= ds.eye.min() and ds.eye.max() <= 1.25 and np.median(ds.eye) == pytest.approx(1.0)
    report = json.loads((preprocessed / "preprocess_report.json").read_text())
    assert set(report["timings_s"]) == {"decode", "features", "parse", "face", "pose", "plate", "write"}
    assert report["parse_face_failures"] == 0
    assert report["face_detected"] == 75 and report["face_interpolated"] == 0 and report["face_backend"] == "dlib"
    landmarks = np.load(preprocessed / "landmarks.npy")
    assert landmarks.shape == (75, 68, 2) and np.isfinite(landmarks).all()
    assert report["pose_reprojection_rms_px"] < 1.0
    # The nose and eye corners joined the pose's adjustment, and the poses agree with them.
    assert report["pose_landmark_weight"] == PreprocessConfig.pose_landmarks > 0 and report["pose_landmark_rms_px"] < 1.0
    assert (preprocessed / "preprocess_report.png").stat().st_size > 0
    assert report["parse_background_moving"] == [] and "parse_background_warning" not in report  # the scene's wall is still
    assert not any(p.name.startswith(".") for p in preprocessed.parent.iterdir()), "work folder left behind"
    # The mouth is in the head layer: the classical parser's row cut is replaced by the jaw line.
    assert report["face_head_torso_cut"].startswith("the jaw line") and "layers_warning" not in report
    assert report["layers"]["lip_in_head"] >= 0.98 and report["layers"]["chin_lip_midpoint_in_head"] >= 0.9
    assert out["passed"]["layers"] and out["layers_truth_lip_in_head"] >= 0.98
    # The clothes: the suit fills the bottom edge under the face in the truth. The classical parser
    # leaves out its left part (it finds the person by motion: 0.78 of the edge, torso IoU 0.73
    # with --clothes none); the completion below the chin adds it (measured 1.0, IoU 0.93).
    assert out["torso_truth_person_at_bottom"] == 1.0 and out["torso_truth_frames"] == 75
    share = report["torso"]["person_at_bottom"]
    assert report["torso"]["frames"] == 75 and share == out["torso_person_at_bottom"] >= 0.95
    assert out["iou_torso"] > 0.88 and "torso_warning" not in report and out["passed"]["torso"]
    assert report["face_clothes"]["frames"] == 75 and report["face_clothes"]["added_fraction"] > 0


def test_sigterm_during_preprocessing_keeps_the_finished_steps_and_says_which_was_cut(scene: Path, tmp_path: Path) -> None:
    # A scheduler's SIGTERM in the middle of a step: one line that names the step cut and what
    # was kept, exit 143, no traceback, no dataset; the same command then resumes there.
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "data"
    argv = ["preprocess", str(scene / "video.mp4"), "-o", str(out), "--focal", str(1.33 * 96)]
    # The child's pose step says when it has begun and then waits, so that the signal lands in it
    # however busy the machine is (a 3 s scene's pose step can end before a busy parent polls).
    begun = tmp_path / "pose_begun"
    child_code = (
        "import sys, time; from dataclasses import replace; from pathlib import Path; from adnerf.preprocess import pipeline\n"
        "def pose(step):\n    def run(ctx):\n        Path(sys.argv[1]).touch(); time.sleep(120); return step.run(ctx)\n    return replace(step, run=run)\n"
        "pipeline.PIPELINE = tuple(pose(s) if s.name == 'pose' else s for s in pipeline.PIPELINE)\nfrom adnerf.cli import main; sys.exit(main(sys.argv[2:]))"
    )
    child = subprocess.Popen([sys.executable, "-c", child_code, str(begun), *argv], stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    steps = tmp_path / ".data.preprocess" / "steps.json"
    deadline = time.time() + 300
    while not begun.exists():
        assert child.poll() is None and time.time() < deadline, child.stderr.read() if child.poll() is not None else "no pose step"
        time.sleep(0.05)
    assert "face" in json.loads(steps.read_text())
    child.send_signal(signal.SIGTERM)  # in the pose step
    _, err = child.communicate(timeout=120)
    lines = [line for line in err.splitlines() if line.startswith("adnerf:")]
    assert child.returncode == 143 and len(lines) == 1 and "Traceback" not in err, err
    assert "stopped in the pose step; 4 finished step(s) kept in" in lines[0] and "(decode, features, parse, face): the same command resumes there" in lines[0]
    assert not out.exists() and steps.exists()
    seen: list[str] = []
    preprocess_video(scene / "video.mp4", out, PreprocessConfig(focal=1.33 * 96), progress=lambda s, d, t: seen.append(s))
    assert {"decode (done before)", "parse (done before)", "face (done before)"} <= set(seen) and "pose (done before)" not in seen


def test_preprocess_resumes_finished_steps(scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from adnerf.preprocess import pipeline

    out = tmp_path / "data"
    cfg = PreprocessConfig(focal=1.33 * 96)
    seen: list[str] = []

    def crash_at_plate(step: str, done: int, total: int) -> None:
        seen.append(step)
        if step == "plate":
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        preprocess_video(scene / "video.mp4", out, cfg, progress=crash_at_plate)
    assert not out.exists()
    assert (tmp_path / ".data.preprocess" / "steps.json").exists()
    seen.clear()
    preprocess_video(scene / "video.mp4", out, cfg, progress=lambda s, d, t: seen.append(s))
    assert {"decode (done before)", "features (done before)", "parse (done before)", "pose (done before)"} <= set(seen)
    assert "plate" in seen and out.is_dir()
    # Interrupted again, and resumed by changed code (an upgrade): every step is made again.
    with pytest.raises(KeyboardInterrupt):
        preprocess_video(scene / "video.mp4", tmp_path / "upgraded", cfg, progress=crash_at_plate)
    monkeypatch.setattr(pipeline, "code_fingerprint", lambda: "another version")
    seen.clear()
    preprocess_video(scene / "video.mp4", tmp_path / "upgraded", cfg, progress=lambda s, d, t: seen.append(s))
    assert not any("done before" in step for step in seen) and {"decode", "features", "parse", "plate"} <= set(seen)
    # A changed setting re-runs its step and the ones after it, not the ones before.
    seen.clear()
    report = preprocess_video(scene / "video.mp4", tmp_path / "again", PreprocessConfig(focal=1.33 * 96, test_fraction=0.2, face="none", features="auto"), progress=lambda s, d, t: seen.append(s))
    assert "parse" in seen  # the first run's work folder was removed after success
    # --features auto without landmarks: the mouth's signal is not known, so log-mel alone.
    again = json.loads((tmp_path / "again" / "meta.json").read_text())
    assert report["features"]["kind"] == again["feature_kind"] == "logmel" and again["feature_dim"] == 80
    assert "no landmarks" in report["features"]["why"] and report["features"]["chosen"] == "auto"
    # Without landmarks: no landmarks.npy, and the mouth point is the fixed guess.
    assert report["face_backend"] == "none" and "face_detected" not in report
    assert not (tmp_path / "again" / "landmarks.npy").exists() and (out / "landmarks.npy").exists()
    guess = json.loads((tmp_path / "again" / "meta.json").read_text())["mouth"]
    assert guess[0] == 0.0 and json.loads((out / "meta.json").read_text())["mouth"] != guess
    # ... and the head / torso cut is the neck-row guess, which the report says.
    assert "a guess" in report["face_head_torso_cut"] and "not known" in report["layers"]["note"]
    assert report["pose_landmark_weight"] == 0.0 and report["pose_landmark_rms_px"] is None  # no landmarks for the pose either
    # --cut neck-row keeps the parser's row cut with landmarks and --clothes none its clothes (for
    # comparisons): other layers, a smaller person, and the report warns of the missing clothes.
    row = preprocess_video(scene / "video.mp4", tmp_path / "row", PreprocessConfig(focal=1.33 * 96, cut="neck-row", clothes="none"))
    assert "narrowest row" in row["face_head_torso_cut"] and "lip_in_head" in row["layers"]
    # Without the completion the person covers less of the bottom edge; on this 96 px scene that is
    # 78-81% (29 of 36 or 37 columns, the strip's width moving by a column from run to run), on
    # both sides of the bar, so the report is held to warning exactly when it is under the bar.
    completed = json.loads((out / "preprocess_report.json").read_text())["torso"]["person_at_bottom"]
    share = row["torso"]["person_at_bottom"]
    assert row["face_clothes"] == "left as parsed" and share < completed - 0.1
    assert ("torso_warning" in row) == (share < PERSON_AT_BOTTOM_MIN)
    jaw, neck = load_dataset(out, truth=False).parsing, load_dataset(tmp_path / "row", truth=False).parsing
    assert not np.array_equal(jaw, neck) and ((jaw > 0) | ~(neck > 0)).all() and (jaw > 0).sum() > (neck > 0).sum()
    assert np.array_equal(jaw[neck == 0] > 0, jaw[neck == 0] == LABEL_TORSO)  # what was added is torso
    with pytest.raises(PreprocessError, match="--cut"):
        PreprocessConfig(cut="ear").validate()
    with pytest.raises(PreprocessError, match="--clothes"):
        PreprocessConfig(clothes="paint").validate()
    with pytest.raises(PreprocessError, match="pose_landmarks"):
        PreprocessConfig(pose_landmarks=-1.0).validate()


def _write(path: Path, frames: np.ndarray, audio: bool = True, fps: float = 25.0) -> Path:
    n = len(frames)
    track = AudioTrack(0.1 * np.sin(np.arange(int(16000 * n / fps)) * 0.05).astype(np.float32), 16000) if audio else None
    write_video(path, frames, fps, track)
    return path


def test_long_clips_are_split_into_overlapping_segments() -> None:
    from adnerf.preprocess.pipeline import _segments

    assert _segments(250, 300, 60) == [(0, 250)]
    assert _segments(750, 300, 60) == [(0, 300), (240, 540), (450, 750)]
    assert _segments(301, 300, 60) == [(0, 300), (1, 301)]


def test_segmented_pose_matches_the_truth(scene: Path, tmp_path: Path) -> None:
    """The 75-frame clip in three segments of 40 frames: joined, the poses still match the truth
    as loosely as the one-segment solve does at this size."""
    from adnerf.formats.dataset import load_dataset
    from adnerf.preprocess.check import align_poses

    report = preprocess_video(scene / "video.mp4", tmp_path / "seg", PreprocessConfig(focal=1.33 * 96, pose_segment=40, pose_overlap=10))
    assert report["pose_segments"] == [[0, 40], [30, 70], [35, 75]]
    assert all(j < 3.0 for j in report["pose_segment_joint_rotation_deg"])
    rot, trans, _ = align_poses(load_dataset(tmp_path / "seg").poses, load_dataset(scene).truth.poses)
    assert np.median(rot) < 10.0 and np.median(trans) / 1.6 < 0.1


def test_bad_input_gives_clear_errors_and_leaves_nothing(tmp_path: Path) -> None:
    plate = (synth_background(64) * 255).astype(np.uint8)
    still = np.repeat(plate[None], 60, axis=0)
    with pytest.raises(PreprocessError, match="at least 2 s"):
        preprocess_video(_write(tmp_path / "short.mp4", still[:25]), tmp_path / "a")
    with pytest.raises(PreprocessError, match="no audio track"):
        preprocess_video(_write(tmp_path / "mute.mp4", still, audio=False), tmp_path / "b")
    with pytest.raises(PreprocessError, match="no face"):
        preprocess_video(_write(tmp_path / "empty.mp4", still), tmp_path / "c")
    with pytest.raises(MediaError, match="no such file"):
        preprocess_video(tmp_path / "missing.mp4", tmp_path / "d")
    (tmp_path / "junk.mp4").write_bytes(b"not a video")
    with pytest.raises(MediaError):
        preprocess_video(tmp_path / "junk.mp4", tmp_path / "e")
    with pytest.raises(PreprocessError, match="--features"):
        preprocess_video(tmp_path / "short.mp4", tmp_path / "f", PreprocessConfig(features="mfcc"))
    left = sorted(p.name for p in tmp_path.iterdir() if not p.suffix == ".mp4")
    assert left == [], left


def test_face_in_too_few_frames_is_refused(scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from adnerf.preprocess.parsing import ClassicalParser

    real = ClassicalParser.parse

    def late_face(self: ClassicalParser, frames: np.ndarray, progress: object = None) -> np.ndarray:
        labels = real(self, frames, progress)
        labels[: int(0.7 * len(labels))] = 0  # the parser finds the person only in the last 30 %
        return labels

    monkeypatch.setattr(ClassicalParser, "parse", late_face)
    with pytest.raises(PreprocessError, match=r"only 23 of 75 frames \(31%\)"):
        preprocess_video(scene / "video.mp4", tmp_path / "out")
    assert not (tmp_path / "out").exists() and not (tmp_path / ".out.preprocess").exists()


def test_a_parse_without_background_is_refused(scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """No pixel labelled background in any frame leaves nothing to make the plate from: a clear
    error at the parse step (not the plate step's traceback), and nothing left behind."""
    from adnerf.preprocess.parsing import ClassicalParser

    def all_person(self: ClassicalParser, frames: np.ndarray, progress: object = None) -> np.ndarray:
        labels = np.full(frames.shape[:3], LABEL_TORSO, np.uint8)
        labels[:, : frames.shape[1] // 2] = LABEL_HEAD
        return labels

    monkeypatch.setattr(ClassicalParser, "parse", all_person)
    with pytest.raises(PreprocessError, match="every pixel of every frame as the person"):
        preprocess_video(scene / "video.mp4", tmp_path / "out")
    assert not (tmp_path / "out").exists() and not (tmp_path / ".out.preprocess").exists()


def test_face_detector_failures_are_refused_or_counted(scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from adnerf.preprocess.landmarks import DlibFaceDetector

    real = DlibFaceDetector.detect
    calls = {"n": 0}

    def flaky(self: DlibFaceDetector, image: np.ndarray) -> list:
        calls["n"] += 1
        return real(self, image) if calls["n"] % 3 == 0 else []  # a face in every third frame

    monkeypatch.setattr(DlibFaceDetector, "detect", flaky)
    with pytest.raises(PreprocessError, match=r"found a face in only 25 of 75 frames \(33%\).*--face none"):
        preprocess_video(scene / "video.mp4", tmp_path / "out")
    assert not (tmp_path / "out").exists() and not (tmp_path / ".out.preprocess").exists()
    monkeypatch.setattr(DlibFaceDetector, "detect", lambda self, image: [])
    with pytest.raises(PreprocessError, match="found no face in any frame"):
        preprocess_video(scene / "video.mp4", tmp_path / "out")
    for bad, message in (("haar", "--face must be"), (f"dlib:{tmp_path / 'none.dat'}", "no shape predictor file")):
        with pytest.raises(PreprocessError, match=message):
            preprocess_video(scene / "video.mp4", tmp_path / "out", PreprocessConfig(face=bad))


def test_moving_camera_is_measured() -> None:
    big = (synth_background(160) * 255).astype(np.uint8)
    frames = np.stack([big[20:84, 10 + i : 74 + i] for i in range(20)])  # a pan of 1 px per frame
    labels = np.zeros(frames.shape[:3], np.uint8)
    assert _camera_motion(frames, labels) == pytest.approx(1.0, abs=0.2)
    assert _camera_motion(np.repeat(frames[:1], 20, 0), labels) < 0.05


def test_a_moving_part_of_the_background_is_named() -> None:
    """A flickering patch (a screen) in the top right of a still wall is named there; the person
    moving and a parse whose outline is 3 px off in every frame are not motion of the background."""
    rng = np.random.default_rng(0)
    wall = (synth_background(96) * 255).astype(np.uint8)
    frames = np.repeat(wall[None], 40, 0)
    labels = np.zeros(frames.shape[:3], np.uint8)
    for i in range(40):
        x = 30 + (i % 7)  # the person sways
        frames[i, 40:, x : x + 30] = rng.integers(0, 255)
        labels[i, 40:, x + 3 : x + 33] = 1  # the parse's outline is off by 3 px
    assert moving_regions(frames, labels) == []
    frames[:, 5:25, 70:90] = rng.integers(0, 255, (40, 20, 20, 1))  # a screen: every frame another picture
    found = moving_regions(frames, labels)
    assert [m["region"] for m in found] == ["top right"] and found[0]["share"] > 0.3


def test_split_head_torso_cuts_at_the_neck() -> None:
    person = np.zeros((120, 100), bool)
    cv2.ellipse(person.view(np.uint8), (50, 35), (22, 28), 0, 0, 360, 1, -1)
    person[60:85, 42:58] = True  # neck, 16 px wide
    person[85:, 10:90] = True  # shoulders
    labels, cut = split_head_torso(person)
    assert cut is not None and 58 <= cut <= 64
    assert (labels[:55][person[:55]] == LABEL_HEAD).all()
    assert (labels[70:][person[70:]] == LABEL_TORSO).all()
    assert (labels[~person] == 0).all()
    only_head = np.zeros_like(person)
    only_head[20:100, 20:80] = True  # no narrowing: all head
    assert (split_head_torso(only_head)[0][only_head] == LABEL_HEAD).all()


def test_rigid_region_stays_above_the_fraction_and_the_landmark_limit() -> None:
    labels = np.zeros((100, 60), np.uint8)
    labels[10:90, 10:50] = LABEL_HEAD  # a head label 80 rows tall (say, hair past the chin)
    free = rigid_region(labels, rigid_fraction=0.5, edge_margin=0.0)
    assert np.flatnonzero(free.any(1))[[0, -1]].tolist() == [10, 49]  # top half: rows 10-49
    below = rigid_region(labels, rigid_fraction=0.5, edge_margin=0.0, limit=70.0)
    np.testing.assert_array_equal(below, free)  # a limit under the cut changes nothing
    nose = rigid_region(labels, rigid_fraction=0.5, edge_margin=0.0, limit=30.2)
    assert np.flatnonzero(nose.any(1))[-1] == 29  # row 29's centre (29.5) is above the nose base at 30.2
    assert not rigid_region(labels, 0.5, 0.0, limit=-5.0).any()
    np.testing.assert_array_equal(rigid_region(labels, 0.5, 0.0, limit=float("nan")), free)


def test_rigid_region_erodes_its_box_as_the_whole_frame_would() -> None:
    """The region is eroded only in the box its kept rows can reach; the answer must be the
    whole frame's erosion, also where the head touches the frame's edges (OpenCV treats the
    outside as set there) and where the head below the cut holds up the rows above it."""
    def whole_frame(labels: np.ndarray, fraction: float, margin: float) -> np.ndarray:
        head = labels == LABEL_HEAD
        rows, cols = np.flatnonzero(head.any(1)), np.flatnonzero(head.any(0))
        r = int(round(margin * (cols[-1] - cols[0] + 1)))
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        head = cv2.erode(head.astype(np.uint8), kernel) > 0
        head[max(0, int(np.ceil(rows[0] + fraction * (rows[-1] - rows[0] + 1)))) :] = False
        return head

    rng = np.random.default_rng(0)
    for centre in ((60, 70), (5, 70), (60, 3), (118, 60), (60, 157)):  # inside, at the top, left, bottom, right edge
        labels = np.zeros((120, 160), np.uint8)
        cv2.ellipse(labels, centre, (35, 45), float(rng.uniform(-20, 20)), 0, 360, LABEL_HEAD, -1)
        labels[rng.random(labels.shape) < 0.02] = 0  # holes: the erosion opens them
        for fraction in (0.3, 0.62, 1.0):
            np.testing.assert_array_equal(rigid_region(labels, fraction, 0.1), whole_frame(labels, fraction, 0.1))


def test_lucas_kanade_on_the_points_crop_matches_the_whole_frames() -> None:
    """Lucas-Kanade on the part of the frames around the points: the whole frames' positions up
    to rounding and the same status, and the known motion of the image."""
    from skimage import data

    from adnerf.preprocess.tracking import _lucas_kanade

    img = cv2.cvtColor(data.astronaut(), cv2.COLOR_RGB2GRAY)  # 512 x 512
    M = np.float32([[1, 0, 1.3], [0, 1, -0.6]])
    moved = cv2.warpAffine(img, M, (512, 512), flags=cv2.INTER_LINEAR)
    p0 = cv2.goodFeaturesToTrack(img[60:220, 180:340], 40, 0.01, 6).reshape(-1, 2) + np.float32([180, 60])
    guess = p0 + np.float32([1.0, 0.0])
    win, crit = (15, 15), (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    whole, st_whole, _ = cv2.calcOpticalFlowPyrLK(img, moved, p0.reshape(-1, 1, 2), guess.reshape(-1, 1, 2).copy(), winSize=win, maxLevel=1, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, criteria=crit)
    got, st = _lucas_kanade(img, moved, p0, guess, win, crit)
    np.testing.assert_array_equal(st, st_whole)
    assert st.all()
    np.testing.assert_allclose(got.reshape(-1, 2), whole.reshape(-1, 2), atol=1e-2)
    assert np.median(np.abs(got.reshape(-1, 2) - p0 - [1.3, -0.6])) < 0.05


def test_flows_on_the_heads_box_track_as_well_as_on_the_whole_frames() -> None:
    """The dense flows are computed on the box of the two frames' rigid regions (a small head in
    a large frame here). Tracks chained by flow alone (no re-anchoring) then follow the face's
    known motion as closely as with flows on the whole frames; a flow read at the whole frame's
    coordinates would carry them pixels away."""
    frames, labels, _, affines = _astronaut_clip(256, 40)
    A = np.concatenate([affines, np.tile([[[0.0, 0.0, 1.0]]], (len(affines), 1, 1))], 1)

    def error(margin: float | None) -> tuple[int, float]:
        tr = track_points(frames, labels, TrackConfig(rigid_fraction=1.0, anchor_window=0, flow_margin=margin))
        errs = []
        for j, s in enumerate(tr.seed_frame):
            seed = np.append(tr.uv[s, j] - 0.5, 1.0)  # OpenCV coordinates
            for i in np.flatnonzero(tr.observed[:, j]):
                errs.append(np.linalg.norm(tr.uv[i, j] - (A[i] @ np.linalg.solve(A[s], seed))[:2] - 0.5))
        return len(errs), float(np.median(errs))

    (n_box, box), (n_whole, whole) = error(0.15), error(None)
    assert n_box > 0.9 * n_whole > 2000
    assert box < 1.1 * whole and whole < 0.6


def test_person_hull_fills_down_from_the_first_moving_pixel() -> None:
    moving = np.zeros((10, 6), bool)
    moving[3, 2] = moving[6, 4] = True
    hull = person_hull(moving, margin=0)
    assert hull[3:, 2].all() and not hull[:3, 2].any()
    assert hull[6:, 4].all() and not hull[:, 0].any()


def _close_crop_clip(n: int = 40, size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """A head too big for its frame: as it sways, its hair crosses the top edge in every column,
    and the wall shows beside its neck. Returns frames ``(n, size, size, 3)`` uint8 and the
    person's truth ``(n, size, size)`` bool."""
    rng = np.random.default_rng(0)
    wall = (synth_background(size) * 255).astype(np.uint8)
    grain = rng.normal(0, 25, (size, size, 1))  # moves with the head, so its inside changes too
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    frames, truth = np.repeat(wall[None], n, 0), np.zeros((n, size, size), bool)
    for i in range(n):
        shift = round(0.1 * size * math.sin(2 * math.pi * i / n))
        cx = 0.5 * size + shift
        skin = np.clip(np.array([205.0, 150.0, 125.0]) + np.roll(grain, shift, 1), 0, 255)
        hair = np.clip(np.array([90.0, 70.0, 55.0]) + np.roll(grain, shift, 1), 0, 255)
        head = ((xx - cx) / (0.45 * size)) ** 2 + ((yy - 0.2 * size) / (0.5 * size)) ** 2 <= 1
        neck = (np.abs(xx - cx) < 0.14 * size) & (yy > 0.5 * size)
        top = head & (yy < 0.2 * size)
        frames[i][head | neck] = skin[head | neck]
        frames[i][top] = hair[top]
        truth[i] = head | neck
    return frames, truth


def test_classical_parser_finds_the_wall_in_a_close_crop() -> None:
    """The motion hull (every column below its first moving pixel) covers the whole frame here,
    which left GrabCut no background seed: every pixel of every frame became person. Seeded by
    motion instead, the wall beside the neck is background and the head and neck are person."""
    from adnerf.preprocess.parsing import ClassicalParser

    frames, truth = _close_crop_clip()
    parser = ClassicalParser()
    assert person_hull(parser.moving_pixels(frames), parser.hull_margin).mean() > 0.98  # the case the fallback is for
    person = parser.parse(frames) > 0
    wall_found = (~person & ~truth).sum((1, 2)) / (~truth).sum((1, 2))
    person_found = (person & truth).sum((1, 2)) / truth.sum((1, 2))
    assert wall_found.min() > 0.9, wall_found.min()
    assert person_found.min() > 0.95, person_found.min()


def test_plate_is_the_median_of_background_and_inpaints_the_rest() -> None:
    rng = np.random.default_rng(0)
    truth = rng.integers(0, 255, (32, 32, 3)).astype(np.uint8)
    frames = np.repeat(truth[None], 9, 0).copy()
    labels = np.zeros((9, 32, 32), np.uint8)
    for i in range(9):  # an occluder that moves; its colour differs from the background
        frames[i, 10:20, 2 + 2 * i : 8 + 2 * i] = 255 - truth[10:20, 2 + 2 * i : 8 + 2 * i]
        labels[i, 10:20, 2 + 2 * i : 8 + 2 * i] = LABEL_TORSO
    labels[:, 28:, 28:] = LABEL_HEAD  # never seen
    plate = background_plate(frames, labels, margin=0)
    assert plate.filled_fraction == pytest.approx(16 / 1024)
    seen = plate.seen > 0
    assert np.array_equal(plate.image[seen], truth[seen])
    assert np.all(plate.image[28:, 28:] > 0)  # filled, not left black


@pytest.mark.parametrize("n", [1, 2, 7, 8])
def test_median_plate_equals_the_masked_median(n: int) -> None:
    """The partition-based median equals numpy's nanmedian of the background values (the mean of
    the middle two for even counts, rounded half to even) for every count of background frames a
    pixel can have, odd and even, none included; a wrong rank (off by one) or a wrong number of
    low fillers moves it."""
    from adnerf.preprocess.plate import median_plate

    rng = np.random.default_rng(n)
    frames = rng.integers(0, 256, (n, 6, 40, 3)).astype(np.uint8)
    person = np.zeros((n, 6, 40), bool)
    for col in range(40):  # column col hides the pixel in (col % (n + 1)) frames, chosen at random
        for row in range(6):
            person[rng.permutation(n)[: (col + row) % (n + 1)], row, col] = True
    block = frames.astype(np.float64)
    block[person] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ref = np.nanmedian(block, axis=0)
    plate, count = median_plate(frames, person, margin=0, rows_per_chunk=4)
    assert np.array_equal(count, n - person.sum(0))
    seen = count > 0
    assert (~seen).any() and (count % 2 == 1).any() and (n < 3 or (count % 2 == 0)[seen].any())
    assert np.array_equal(plate[seen], np.round(ref[seen]).astype(np.uint8))
    assert not plate[~seen].any()


def test_median_plate_reads_memory_mapped_frames_without_a_warning(tmp_path) -> None:  # noqa: ANN001
    """The plate step reads the decoded frames memory-mapped read-only; torch warned ("The given
    NumPy array is not writable ... undefined behavior") in every preprocessing run. A fresh
    process (torch warns once a process) runs the plate on read-only maps with warnings as errors."""
    frames = np.random.default_rng(0).integers(0, 256, (5, 8, 12, 3)).astype(np.uint8)
    person = np.zeros((5, 8, 12), bool)
    person[:2, 2:5, 3:7] = True
    np.save(tmp_path / "frames.npy", frames)
    np.save(tmp_path / "person.npy", person)
    code = (
        "import numpy as np, sys\n"
        "from adnerf.preprocess.plate import median_plate\n"
        "f = np.load(sys.argv[1], mmap_mode='r'); p = np.load(sys.argv[2], mmap_mode='r')\n"
        "assert not f.flags.writeable\n"
        "plate, count = median_plate(f, p, margin=0)\n"
        "print(int(count.sum()))\n"
    )
    done = subprocess.run([sys.executable, "-W", "error", "-c", code, str(tmp_path / "frames.npy"), str(tmp_path / "person.npy")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert int(done.stdout) == 5 * 8 * 12 - int(person.sum())


def test_frozen_grabcut_ignores_which_probable_class_a_pixel_starts_in() -> None:
    """The classical parser's pass 2 seeds frames that pass 1 did not cut with the person hull
    instead of pass 1's cut: right only because GrabCut with frozen colour models scores every
    probable pixel by both models, whatever its starting class. Two masks with the same sure
    pixels and opposite probable classes cut alike."""
    frames, _ = _close_crop_clip(n=4)
    img = cv2.cvtColor(frames[1], cv2.COLOR_RGB2BGR)
    rng = np.random.default_rng(0)
    sure = np.full(img.shape[:2], 255, np.uint8)
    sure[:, :4], sure[-6:, 28:36] = cv2.GC_BGD, cv2.GC_FGD
    a = np.where(rng.random(img.shape[:2]) < 0.5, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
    a[sure != 255] = sure[sure != 255]
    b = a.copy()
    probable = sure == 255
    b[probable] = np.where(a[probable] == cv2.GC_PR_FGD, cv2.GC_PR_BGD, cv2.GC_PR_FGD)
    bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
    cv2.grabCut(img, a.copy(), None, bgd, fgd, 2, cv2.GC_INIT_WITH_MASK)
    cuts = []
    for m in (a.copy(), b.copy()):
        cv2.grabCut(img, m, None, bgd.copy(), fgd.copy(), 1, cv2.GC_EVAL_FREEZE_MODEL)
        cuts.append(np.isin(m, (cv2.GC_FGD, cv2.GC_PR_FGD)))
    assert 0.05 < cuts[0].mean() < 0.95  # a real cut, not all one class
    assert np.array_equal(cuts[0], cuts[1])


def test_classical_parser_cuts_a_long_clip_about_once_a_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """Pass 1 (whose cuts only make the plate) cuts at most ``plate_frames`` frames plus the
    statistics' frames; pass 2 cuts every frame. The person is found as well as when pass 1 cuts
    every frame."""
    from adnerf.preprocess import parsing

    frames, truth = _close_crop_clip(n=40)
    calls = []
    real = cv2.grabCut

    def counted(img, mask, rect, bgd, fgd, iters, mode):  # type: ignore[no-untyped-def]
        calls.append(mode)
        return real(img, mask, rect, bgd, fgd, iters, mode)

    monkeypatch.setattr(parsing.cv2, "grabCut", counted)
    few = parsing.ClassicalParser(max_stat_frames=8, plate_frames=10).parse(frames) > 0
    frozen = calls.count(cv2.GC_EVAL_FREEZE_MODEL)
    assert 40 < frozen <= 40 + 18, frozen
    calls.clear()
    every = parsing.ClassicalParser(max_stat_frames=8, plate_frames=40).parse(frames) > 0
    assert calls.count(cv2.GC_EVAL_FREEZE_MODEL) == 80
    for person in (few, every):
        assert ((person & truth).sum((1, 2)) / truth.sum((1, 2))).min() > 0.95
        assert ((~person & ~truth).sum((1, 2)) / (~truth).sum((1, 2))).min() > 0.9
    assert (few == every).mean() > 0.99


def _astronaut_clip(size: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The astronaut's face (64 px) turned and moved in the image plane over a static background
    of ``size`` px: ``(frames (n, size, size, 3), labels, angles (n,) degrees, affines (n, 2, 3))``."""
    from skimage import data

    face = cv2.resize(data.astronaut()[20:220, 130:330], (64, 64), interpolation=cv2.INTER_AREA)
    bg = (synth_background(size) * 255).astype(np.uint8)
    angles = 8.0 * np.sin(np.linspace(0, 2 * np.pi, n))  # degrees
    shifts = np.stack([6.0 * np.sin(np.linspace(0, np.pi, n)), 3.0 * np.cos(np.linspace(0, np.pi, n))], 1)
    mask0 = np.zeros((64, 64), np.uint8)
    cv2.ellipse(mask0, (32, 32), (28, 31), 0, 0, 360, 1, -1)
    frames, labels, affines = [], [], []
    for a, (dx, dy) in zip(angles, shifts):
        M = cv2.getRotationMatrix2D((32.0, 32.0), a, 1.0)
        M[:, 2] += (size / 2 - 32 + dx, size / 2 - 40 + dy)
        affines.append(M)
        img = cv2.warpAffine(face, M, (size, size), flags=cv2.INTER_LINEAR)
        m = cv2.warpAffine(mask0, M, (size, size), flags=cv2.INTER_NEAREST).astype(bool)
        frames.append(np.where(m[..., None], img, bg))
        labels.append(np.where(m, LABEL_HEAD, 0).astype(np.uint8))
    return np.stack(frames), np.stack(labels), angles, np.stack(affines)


def test_astronaut_in_plane_motion_is_recovered() -> None:
    """Real photographic texture: the astronaut's face moved by known in-plane similarity
    transforms over a static background; the recovered roll and image translation match."""
    size = 128
    frames, labels, angles, affines = _astronaut_clip(size, 30)
    f = 1.33 * size
    tracks = track_points(frames, labels, TrackConfig(rigid_fraction=1.0, edge_margin=0.1))
    est = estimate_head_poses(tracks, labels, (f, f, size / 2, size / 2), reference=0)
    rel = est.poses[:, :3, :3] @ est.poses[0, :3, :3].T  # rotation since frame 0, camera frame
    roll = np.degrees(np.arctan2(rel[:, 1, 0], rel[:, 0, 0]))
    # OpenCV's angle is counter-clockwise on screen; with y down that is a negative roll about z.
    np.testing.assert_allclose(roll, -(angles - angles[0]), atol=1.0)
    # Where the tracked points are: their centroid, projected, follows the known image motion.
    X = est.points[np.isfinite(est.points[:, 0])].mean(0)
    q = X @ est.poses[:, :3, :3].transpose(0, 2, 1) + est.poses[:, :3, 3]
    proj = f * q[:, :2] / q[:, 2:3] + size / 2
    A = [np.vstack([m, [0, 0, 1]]) for m in affines]
    c0 = np.append(proj[0] - 0.5, 1.0)  # OpenCV pixel coordinates (centres at integers)
    pred = np.stack([(a @ np.linalg.inv(A[0]) @ c0)[:2] + 0.5 for a in A])
    assert np.abs(proj - pred).max() < 1.0
    assert math.isfinite(est.rms) and est.rms < 0.5
    # The gauge: the canonical axes are the mean head orientation, so the poses' chordal mean is
    # the identity (the head here is tilted by up to 8 degrees, so a wrong gauge shows).
    assert rotation_angle_deg(mean_rotation(est.poses[:, :3, :3])) < 1e-6
    assert rotation_angle_deg(est.poses[0, :3, :3]) > 1.0  # not trivially: frame 0 is off the mean


def test_head_pose_gauge_is_the_mean_orientation() -> None:
    """Single-segment path: tracks of points on an ellipsoidal head turning by 0..16 degrees of
    yaw, anchored at frame 0 (8 degrees off the mean). The written poses' mean rotation is the
    identity, the relative motion is the true one, and points and poses still reproject."""
    true, pts, uv, labels, K = _turning_head()
    n, f, size, R = len(true), K[0], 2 * K[2], true[:, :3, :3]
    est = estimate_head_poses(Tracks(uv, np.zeros(len(pts), int)), labels, K, reference=0, shape_sigma=0.0)
    Re = est.poses[:, :3, :3]
    assert rotation_angle_deg(mean_rotation(Re)) < 1e-6
    assert abs(rotation_angle_deg(Re[0]) - 8.0) < 0.5  # frame 0 lies 8 degrees from the mean
    for i in range(n):  # the motion since frame 0 is the true one (gauge-free)
        assert rotation_angle_deg((Re[i] @ Re[0].T) @ (R[i] @ R[0].T).T) < 0.05
    q = np.einsum("nij,pj->npi", Re, est.points) + est.poses[:, None, :3, 3]
    assert np.abs(f * q[..., :2] / q[..., 2:] + size / 2 - uv).max() < 0.05


def _turning_head(points: int = 400, roll: float = 0.0, n: int = 24, size: int = 128, f: float = 170.0) -> tuple:
    """An ellipsoidal head turning by 0..16 degrees of yaw (and rolling by ``roll`` degrees times
    a half sine wave), seen by a pinhole camera: its true poses ``(n, 4, 4)``, the canonical points
    on its face side ``(P, 3)`` (of ``points`` drawn on the whole ellipsoid), their projections
    ``(n, P, 2)``, the head's silhouettes and the intrinsics."""
    rng = np.random.default_rng(0)
    radii = np.array([0.8, 1.0, 0.88])
    d = rng.normal(size=(points, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = (d * radii)[d[:, 2] < -0.3]  # the face side, towards the camera
    yaw, rol = np.radians(np.linspace(0.0, 16.0, n)), np.radians(roll * np.sin(np.linspace(0, np.pi, n)))
    R = np.stack([[[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]] @ np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]) for a, r in zip(yaw, rol)])
    t = np.array([0.1, -0.05, 5.0])
    true = np.tile(np.eye(4), (n, 1, 1))
    true[:, :3, :3], true[:, :3, 3] = R, t
    cam = np.einsum("nij,pj->npi", R, pts) + t
    uv = f * cam[..., :2] / cam[..., 2:] + size / 2
    labels = np.zeros((n, size, size), np.uint8)
    for i in range(n):  # the head's silhouette: the projected ellipsoid's box, filled as an ellipse
        (x0, y0), (x1, y1) = uv[i].min(0), uv[i].max(0)
        cv2.ellipse(labels[i], (int((x0 + x1) / 2), int((y0 + y1) / 2)), (int((x1 - x0) / 2), int((y1 - y0) / 2)), 0, 0, 360, LABEL_HEAD, -1)
    return true, pts, uv, labels, (f, f, size / 2, size / 2)


def test_landmarks_in_the_adjustment_hold_the_pose_against_drifting_tracks() -> None:
    """Chained flow tracks drift; landmarks found afresh in every frame do not. Tracks whose
    observations slide sideways by 0.06 px a frame (1.4 px by the last) pull the poses along;
    the landmarks, weighted as in preprocessing, pull them back to the true motion. Landmarks
    given to the wrong frames (reversed) make it worse, not better."""
    true, _, seen, labels, K = _turning_head(points=413, roll=3.0)
    uv, marks = seen[:, 13:], seen[:, :13]  # 13 of the points are the landmarks
    n = len(true)
    drift = uv + np.arange(n)[:, None, None] * np.array([0.06, 0.0])
    tracks = Tracks(drift, np.zeros(drift.shape[1], int))
    kw = {"reference": 0, "shape_sigma": 0.0}
    plain = estimate_head_poses(tracks, labels, K, **kw)
    marks = marks.copy()
    marks[5] = np.nan  # a frame without a detected face: its tracks alone place it
    held = estimate_head_poses(tracks, labels, K, landmarks=marks, landmark_weight=30.0, **kw)
    rot_plain, trans_plain, _ = align_poses(plain.poses, true)
    rot_held, trans_held, _ = align_poses(held.poses, true)
    assert trans_held.max() < 0.4 * trans_plain.max()
    assert rot_held.max() < 0.6 * rot_plain.max()
    assert held.points.shape == plain.points.shape  # the landmarks' points are not track points
    assert math.isnan(plain.landmark_rms) and held.landmark_rms < 0.5
    # Weight 0 leaves them out exactly; landmarks in the wrong frames do not help.
    np.testing.assert_array_equal(estimate_head_poses(tracks, labels, K, landmarks=marks, landmark_weight=0.0, **kw).poses, plain.poses)
    unseen = estimate_head_poses(tracks, labels, K, landmarks=np.full_like(marks, np.nan), landmark_weight=30.0, **kw)  # never detected
    np.testing.assert_array_equal(unseen.poses, plain.poses)
    assert math.isnan(unseen.landmark_rms)
    wrong = estimate_head_poses(tracks, labels, K, landmarks=marks[::-1], landmark_weight=30.0, **kw)
    assert align_poses(wrong.poses, true)[1].max() > trans_plain.max()
    with pytest.raises(ValueError, match="landmarks must be"):
        estimate_head_poses(tracks, labels, K, landmarks=marks[1:], landmark_weight=30.0, **kw)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees (the pose module's stable formula)."""
    return math.degrees(float(rotation_angle(torch.as_tensor(R, dtype=torch.float64))))


# ----------------------------------------------------------------------------- import-adnerf


def _adnerf_folder(scene: Path, root: Path, units: float = 0.1, first_id: int = 0, lms: bool = False) -> Path:
    """Write the synthetic scene as the original AD-NeRF preprocessing would leave it (with
    ``lms``: landmark files whose lip points sit on the true mouth point's image)."""
    from adnerf.formats.dataset import load_dataset
    from adnerf.preprocess.adnerf_import import ours_pose_to_adnerf

    ds = load_dataset(scene, truth=True)
    meta = ds.meta
    (root / "ori_imgs").mkdir(parents=True)
    (root / "parsing").mkdir()
    bgr_colours = np.array([[255, 255, 255], [255, 0, 0], [0, 0, 255]], np.uint8)  # background, head, clothes
    for k in range(meta.n_frames):
        cv2.imwrite(str(root / "ori_imgs" / f"{k + first_id}.jpg"), cv2.cvtColor(ds.frames[k], cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 98])
        cv2.imwrite(str(root / "parsing" / f"{k + first_id}.png"), bgr_colours[ds.truth.parsing[k]])
    cv2.imwrite(str(root / "bc.jpg"), cv2.cvtColor(ds.background, cv2.COLOR_RGB2BGR))
    poses = ds.truth.poses.copy()
    poses[:, :3, 3] *= units
    M = ours_pose_to_adnerf(poses)
    fx, fy, cx, cy = meta.intrinsics
    rng = np.random.default_rng(0)
    np.save(root / "aud.npy", rng.normal(size=(meta.n_frames + first_id, 16, 29)).astype(np.float32))
    if lms:
        mouth = ds.truth.poses[:, :3, :3] @ np.array(meta.mouth) + ds.truth.poses[:, :3, 3]
        uv = np.stack([fx * mouth[:, 0] / mouth[:, 2] + cx, fy * mouth[:, 1] / mouth[:, 2] + cy], 1) - 0.5  # AD-NeRF's pixel centres
        for k in range(meta.n_frames):
            points = np.tile(uv[k], (68, 1)) + rng.normal(scale=5.0, size=(68, 2))
            a = np.arange(8) * np.pi / 4
            points[60:68] = uv[k] + 2.0 * np.stack([np.cos(a), np.sin(a)], 1)  # inner lips centred on the mouth
            np.savetxt(root / "ori_imgs" / f"{k + first_id}.lms", points, "%f")
    for name, idx in (("train", meta.train), ("val", meta.test)):
        doc = {"focal_len": fx, "cx": cx - 0.5, "cy": cy - 0.5, "frames": [{"img_id": k + first_id, "aud_id": k + first_id, "transform_matrix": M[k].tolist(), "face_rect": [0, 0, 10, 10]} for k in idx]}
        (root / f"transforms_{name}.json").write_text(json.dumps(doc))
    from adnerf.formats.dataset import write_wav

    write_wav(root / "aud.wav", ds.audio)
    return root


def test_import_adnerf_converts_poses_parsing_and_features(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from adnerf.formats.dataset import load_dataset
    from adnerf.preprocess.headpose import project_points

    src = _adnerf_folder(scene, tmp_path / "obama", lms=True)
    out = tmp_path / "imported"
    assert main(["import-adnerf", str(src), "-o", str(out)]) == 0
    assert "frames" in capsys.readouterr().out
    truth = load_dataset(scene, truth=True)
    ds = load_dataset(out)
    assert ds.meta.feature_kind == "deepspeech" and ds.features.shape == (truth.meta.n_frames, 16, 29)
    np.testing.assert_array_equal(ds.features, np.load(src / "aud.npy"))
    assert ds.meta.train == truth.meta.train and ds.meta.test == truth.meta.test
    np.testing.assert_array_equal(ds.parsing, truth.truth.parsing)
    np.testing.assert_allclose(ds.meta.intrinsics, truth.meta.intrinsics)
    # Rotations exactly; translations up to the one scale that makes the head 1.6 units wide.
    np.testing.assert_allclose(ds.poses[:, :3, :3], truth.truth.poses[:, :3, :3], atol=1e-9)
    scale = ds.poses[:, :3, 3] / truth.truth.poses[:, :3, 3]
    np.testing.assert_allclose(scale, scale.flat[0], rtol=1e-6)
    assert 0.7 < scale.flat[0] < 1.3, scale.flat[0]
    # The widened head box holds the true head box; the frames survive the JPEG round trip.
    lo, hi = np.array(ds.meta.head_aabb) / scale.flat[0]
    t_lo, t_hi = np.array(truth.meta.head_aabb)
    assert (lo[[0, 2]] <= t_lo[[0, 2]]).all() and (hi[[0, 2]] >= t_hi[[0, 2]]).all()
    assert np.abs(ds.frames.astype(int) - truth.frames.astype(int)).mean() < 3.0
    assert abs(ds.audio.duration - truth.audio.duration) < 0.05
    # The mouth point, triangulated from the landmark files, projects where the true one does.
    lms = np.load(out / "landmarks.npy")
    assert lms.shape == (truth.meta.n_frames, 68, 2)
    def project(point: tuple, poses: np.ndarray, K: tuple) -> np.ndarray:
        return project_points(poses[:, :3, :3] @ np.array(point) + poses[:, :3, 3], K)

    err = np.linalg.norm(project(ds.meta.mouth, ds.poses, ds.meta.intrinsics) - project(truth.meta.mouth, truth.truth.poses, truth.meta.intrinsics), axis=1)
    assert err.max() < 0.1, err.max()


def test_import_adnerf_trims_audio_to_the_first_frame_and_reports_bad_folders(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from adnerf.formats.dataset import load_dataset
    from adnerf.preprocess.adnerf_import import import_adnerf

    src = _adnerf_folder(scene, tmp_path / "late", first_id=5)
    with pytest.warns(UserWarning, match="no ori_imgs/<img_id>.lms"):
        import_adnerf(src, tmp_path / "late_out")
    assert not (tmp_path / "late_out" / "landmarks.npy").exists()
    ds = load_dataset(tmp_path / "late_out")
    full = load_dataset(scene).audio
    assert abs((full.duration - ds.audio.duration) - 5 / 25.0) < 1e-3
    np.testing.assert_array_equal(ds.features, np.load(src / "aud.npy")[5:])

    (src / "aud.npy").unlink()
    assert main(["import-adnerf", str(src), "-o", str(tmp_path / "x")]) == 2
    assert "aud.npy" in capsys.readouterr().err
    assert main(["import-adnerf", str(tmp_path / "missing"), "-o", str(tmp_path / "y")]) == 2
    assert "not a folder" in capsys.readouterr().err
    (src / "transforms_train.json").write_text("{}")
    assert main(["import-adnerf", str(src), "-o", str(tmp_path / "z")]) == 2
    assert "not an AD-NeRF transforms file" in capsys.readouterr().err
    assert not any((tmp_path / n).exists() for n in ("x", "y", "z"))


def test_adnerf_parsing_colours() -> None:
    from adnerf.preprocess.adnerf_import import parse_adnerf_parsing

    bgr = np.array([[[255, 255, 255], [255, 0, 0], [0, 255, 0], [0, 0, 255], [250, 3, 5], [251, 252, 249]]], np.uint8)
    np.testing.assert_array_equal(parse_adnerf_parsing(bgr), [[0, LABEL_HEAD, LABEL_TORSO, LABEL_TORSO, LABEL_HEAD, 0]])


def test_torso_check_measures_the_bottom_edge_under_the_face() -> None:
    """Known answers: a face 20 px wide (landmarks 0 and 16) with its chin at (50, 60) in a
    100 x 100 frame spans columns 30-70 of the bottom row (a face width either side)."""
    lm = np.zeros((3, 68, 2))
    lm[:, 0], lm[:, 16], lm[:, 8] = (40.0, 40.0), (60.0, 40.0), (50.0, 60.0)
    labels = np.zeros((3, 100, 100), np.uint8)
    labels[0, 80:, 30:70] = 2  # the whole span: torso
    labels[1, 99, 30:50] = 2  # its left half, as a jacket taken for background on the right
    labels[1, 99, 70:] = 2  # outside the span: does not count
    labels[2, 99, 40:60] = 1  # head pixels count as person too (a close crop's hair)
    got = torso_check(labels, lm)
    assert got == {"person_at_bottom": 0.5, "person_at_bottom_worst": 0.5, "frames": 3}
    assert SHOULDER_HALF_WIDTH == 1.0 and 0.5 < PERSON_AT_BOTTOM_MIN
    # The span is clipped to the image; frames without a face or whose face reaches the bottom are left out.
    lm2 = lm.copy()
    lm2[0, :, 0] -= 40.0  # chin at x = 10: span [-10, 30) -> [0, 30)
    labels2 = np.zeros_like(labels)
    labels2[0, 99, :15] = 2
    lm2[1] = np.nan
    lm2[2, 8, 1] = 97.0  # 3 px above the bottom: less than a quarter of a face width
    assert torso_check(labels2, lm2) == {"person_at_bottom": 0.5, "person_at_bottom_worst": 0.5, "frames": 1}
    assert torso_check(labels2[1:], lm2[1:]) == {"person_at_bottom": None, "person_at_bottom_worst": None, "frames": 0}


def test_the_parse_is_the_same_on_one_thread_and_on_several() -> None:
    """GrabCut with frozen colour models cuts each frame on its own, so frames cut side by side in
    threads give exactly the labels of a plain loop (the models are not shared state)."""
    import torch

    from adnerf.preprocess.parsing import ClassicalParser

    frames, _ = _close_crop_clip(n=24)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        serial = ClassicalParser().parse(frames)
        torch.set_num_threads(3)
        threaded = ClassicalParser().parse(frames)
    finally:
        torch.set_num_threads(before)
    assert (serial > 0).mean() > 0.3
    np.testing.assert_array_equal(serial, threaded)


def test_in_threads_keeps_order_bounds_what_waits_and_raises_in_turn() -> None:
    import threading
    import time

    from adnerf.threads import in_threads

    names: set[str] = set()
    started: list[int] = []

    def work(i: int) -> int:
        started.append(i)
        names.add(threading.current_thread().name)
        time.sleep(0.002 * ((7 * i) % 5))  # later items may finish first
        return i * i

    results = []
    for r in in_threads(work, range(40), workers=3):
        results.append(r)
        assert len(started) <= len(results) + 6  # at most 2 x workers wait to be taken
    assert results == [i * i for i in range(40)]
    assert any(n.startswith("adnerf") for n in names)
    assert list(in_threads(work, range(5), workers=1)) == [0, 1, 4, 9, 16]

    def fails_at_3(i: int) -> int:
        if i == 3:
            raise KeyError(i)
        return i

    got = []
    with pytest.raises(KeyError):
        for r in in_threads(fails_at_3, range(10), workers=2):
            got.append(r)
    assert got == [0, 1, 2]


def test_tracks_are_the_same_on_one_thread_and_on_several(scene: Path) -> None:
    """The flows of the frame pairs are computed ahead in threads (a flow object per thread) and
    the re-observation measures each frame in its own thread: neither may change a track."""
    import torch

    from adnerf.formats.dataset import load_dataset
    from adnerf.preprocess.tracking import TrackConfig, extend_tracks, track_points

    ds = load_dataset(scene)
    frames, labels = ds.frames[:40], ds.parsing[:40]
    before = torch.get_num_threads()
    got = []
    try:
        for threads in (1, 3):
            torch.set_num_threads(threads)
            tracks = track_points(frames, labels, TrackConfig())
            seeds = tracks.uv[tracks.seed_frame, np.arange(tracks.uv.shape[1])]
            got.append((tracks, extend_tracks(frames, labels, tracks, lambda i, idx: seeds[idx], TrackConfig(), reach=40)))
    finally:
        torch.set_num_threads(before)
    (t1, e1), (t3, e3) = got
    assert t1.observed.sum() > 200 and e1.observed.sum() > t1.observed.sum()  # the re-observation adds observations
    np.testing.assert_array_equal(t1.uv, t3.uv)
    np.testing.assert_array_equal(e1.uv, e3.uv)



def test_the_pose_tracked_at_a_working_size_keeps_the_frames_pixels(scene: Path) -> None:
    """Frames twice the scene's size tracked at the scene's size (``track_size``): the tracks are
    found in the shrunk frames and handed back in the big frames' pixels (twice the coordinates:
    edges aligned, centres at +0.5), and the adjustment at full size gives the poses of the
    shrunk clip with its own camera."""
    import cv2
    from dataclasses import replace

    from adnerf.formats.dataset import load_dataset
    from adnerf.preprocess.pipeline import PreprocessConfig, _pose_segment

    ds = load_dataset(scene)
    n = 40
    big = np.stack([cv2.resize(f, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC) for f in ds.frames[:n]])
    big_labels = np.stack([cv2.resize(x, None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST) for x in ds.parsing[:n]])
    small = np.stack([cv2.resize(f, (96, 96), interpolation=cv2.INTER_AREA) for f in big])
    fx, fy, cx, cy = ds.meta.intrinsics
    cfg = replace(PreprocessConfig(), pose_landmarks=0.0, extend_passes=0)  # the chained tracks: no prediction from the poses in between
    own, tracks, _ = _pose_segment(small, ds.parsing[:n], None, None, (fx, fy, cx, cy), replace(cfg, track_size=None), lambda *a: None, "")
    half, big_tracks, _ = _pose_segment(big, big_labels, None, None, (2 * fx, 2 * fy, 2 * cx, 2 * cy), replace(cfg, track_size=96), lambda *a: None, "")
    assert tracks.observed.sum() > 200
    np.testing.assert_array_equal(big_tracks.observed, tracks.observed)
    np.testing.assert_allclose(big_tracks.uv[big_tracks.observed], 2 * tracks.uv[tracks.observed], rtol=1e-12)
    R = np.einsum("nij,nkj->nik", own.poses[:, :3, :3], half.poses[:, :3, :3])
    angle = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    # the same problem, but its residuals are in pixels twice the size, which the robust loss's
    # pixel threshold weighs otherwise: 0.35 degrees apart here
    assert np.median(angle) < 1.0, np.median(angle)


def test_a_step_runs_once_and_reads_back_until_its_settings_change(tmp_path: Path) -> None:
    """The generic runner (:func:`run_step`): a finished step is read back from the work folder,
    not run again; a change of one of its settings runs it again, a change of another step's
    setting does not; a change of the video (its modification time) does."""
    from adnerf.preprocess.pipeline import PreprocessConfig, Step, StepContext, _Work, run_step

    video = tmp_path / "clip.mp4"
    video.write_bytes(b"not decoded here")
    calls = []

    def work_of(ctx: StepContext) -> dict:
        calls.append(ctx.config.flow)
        ctx.work.save("marker", np.arange(3))
        return {"flow": ctx.config.flow}

    pose = Step("pose", ("flow",), work_of)
    folder = tmp_path / "work"

    def run(config: PreprocessConfig) -> dict:
        return run_step(pose, StepContext(video, _Work(folder, video, config), config, lambda *a: None))

    assert run(PreprocessConfig()) == {"flow": "dis"} and calls == ["dis"]
    assert run(PreprocessConfig()) == {"flow": "dis"} and calls == ["dis"]  # read back
    assert run(PreprocessConfig(test_fraction=0.2)) == {"flow": "dis"} and calls == ["dis"]  # the write step's setting
    assert run(PreprocessConfig(flow="deepflow")) == {"flow": "deepflow"} and calls == ["dis", "deepflow"]
    os.utime(video, ns=(0, 0))
    assert run(PreprocessConfig(flow="deepflow")) == {"flow": "deepflow"} and calls == ["dis", "deepflow", "deepflow"]
