"""Footage as people film it: the crop and scale of the dataset's square in the source frame, the
trim, and the camera that follows them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from adnerf.cli import main
from adnerf.io import AudioTrack, read_audio, read_video, write_video
from adnerf.preprocess.framing import Framing, parse_crop, plan_framing, square_around
from adnerf.synth import SynthConfig, synthesize

SR = 16000


def _project(K: tuple[float, float, float, float], X: np.ndarray) -> np.ndarray:
    fx, fy, cx, cy = K
    return np.stack([fx * X[:, 0] / X[:, 2] + cx, fy * X[:, 1] / X[:, 2] + cy], axis=1)


def test_the_dataset_camera_sees_each_point_where_the_crop_puts_its_source_pixel() -> None:
    framing = plan_framing((1280, 720), (400, 100, 480, 480), 256)
    assert framing.size == (256, 256) and framing.scale == pytest.approx(256 / 480)
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(-1, 1, 50), rng.uniform(3, 6, 50)])
    source = _project((900.0, 900.0, 640.0, 360.0), X)  # the source camera: principal point at the frame's centre
    expected = (source - np.array([400.0, 100.0])) * framing.scale  # the crop's map of source pixels (centres at +0.5 on both sides)
    np.testing.assert_allclose(_project(framing.intrinsics(900.0), X), expected, atol=1e-9)
    fx, _, cx, cy = plan_framing((1280, 720), "none", None).intrinsics()
    assert (fx, cx, cy) == (1.33 * 1280, 640.0, 360.0)  # uncropped: the guess it always was


def test_the_transform_puts_a_source_pixel_where_the_framing_says() -> None:
    frame = np.zeros((720, 1280, 3), np.uint8)
    frame[300:310, 600:610] = 255  # a 10 px marker, centre (605, 305) in source pixel coordinates
    framing = Framing((1280, 720), (400, 100, 480, 480), (240, 240))
    out = framing.transform(frame)
    assert out.shape == (240, 240, 3)
    ys, xs = np.nonzero(out[..., 0] > 60)
    np.testing.assert_allclose([xs.mean() + 0.5, ys.mean() + 0.5], [(605 - 400) * 0.5, (305 - 100) * 0.5], atol=0.5)
    assert Framing.from_dict(json.loads(json.dumps(framing.to_dict()))) == framing


def test_crops_are_parsed_planned_and_kept_inside_the_frame() -> None:
    assert parse_crop("auto") == "auto" and parse_crop("None") == "none" and parse_crop("1,2,3,4") == (1, 2, 3, 4)
    for bad in ("1,2,3", "a,b,c,d", "0,0,0,5", "-1,0,4,4"):
        with pytest.raises(ValueError):
            parse_crop(bad)
    with pytest.raises(ValueError, match="reaches past"):
        plan_framing((640, 480), (400, 0, 300, 300), 512)
    assert plan_framing((640, 480), (0, 0, 300, 300), 512).size == (300, 300)  # never enlarged
    x, y, side, _ = square_around((1180.0, 20.0, 1270.0, 130.0), 90.0, (1280, 720))  # a face at the top-right corner
    assert 0 <= x and x + side <= 1280 and y == 0 and side == round(3.2 * 90 + 110 - 90)
    assert square_around((100.0, 100.0, 600.0, 700.0), 500.0, (1280, 720))[2] == 720  # never larger than the frame


@pytest.fixture(scope="module")
def webcam(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The synthetic scene (96 px) placed at (60, 30) in a 200x150 frame whose rest is a still
    wall: a wide shot with the person off-centre."""
    folder = tmp_path_factory.mktemp("webcam")
    scene = synthesize(folder / "scene", SynthConfig(seconds=3.0, size=96, voice="formant", seed=3))
    clip = read_video(scene / "video.mp4")
    wide = np.empty((len(clip.frames), 150, 200, 3), np.uint8)
    wide[:] = np.linspace(40, 200, 200, dtype=np.uint8)[None, None, :, None]
    wide[:, 30:126, 60:156] = clip.frames
    write_video(folder / "wide.mp4", wide, clip.fps, clip.audio.starting_at(float(clip.timestamps[0])))
    return scene, folder / "wide.mp4"


def test_preprocess_crops_a_wide_shot_to_the_person_and_the_camera_follows(webcam: tuple[Path, Path], tmp_path: Path) -> None:
    scene, wide = webcam
    truth = json.loads((scene / "meta.json").read_text())
    out = tmp_path / "data"
    assert main(["preprocess", str(wide), "-o", str(out), "--crop", "60,30,96,96", "--size", "0", "--focal", str(truth["intrinsics"][0]), "--start", "0.4", "--end", "2.8", "--test-fraction", "0.2"]) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["framing"] == {"source_size": [200, 150], "crop": [60, 30, 96, 96], "size": [96, 96], "start_s": 0.4, "video": str(wide.resolve())}
    # the camera of the crop is the scene's own: focal kept, principal point moved by the crop
    np.testing.assert_allclose(meta["intrinsics"], [truth["intrinsics"][0], truth["intrinsics"][1], 100 - 60, 75 - 30])
    assert meta["n_frames"] == 60  # 0.4 s to 2.8 s at 25 fps
    source = read_video(scene / "video.mp4").frames
    import cv2

    for k in (0, 30, 59):  # dataset frame k is the scene's frame 10 + k
        got = cv2.cvtColor(cv2.imread(str(out / "frames" / f"{k:06d}.png")), cv2.COLOR_BGR2RGB).astype(float)
        errors = [np.abs(got - source[j]).mean() for j in (9 + k, 10 + k, 11 + k)]
        assert errors[1] < 3.0 and errors[1] < min(errors[0], errors[2]), errors
    # the audio is cut with the frames: sample 0 of the dataset's plays with source time 0.4 s
    own, src = read_audio(out / "audio.wav"), read_video(wide)
    track = src.audio.starting_at(float(src.timestamps[0]) + 0.4)
    scores = np.correlate(track.samples[: SR // 2 + 400], own.samples[: SR // 2], mode="valid")  # scores[k]: own against the source k samples on
    assert np.argmax(scores) == 0
    assert own.duration == pytest.approx(2.4, abs=0.01)


def test_preprocess_auto_crop_finds_the_face_in_a_wide_shot(webcam: tuple[Path, Path], tmp_path: Path) -> None:
    """The scene three times larger (its face about 75 px wide, as a webcam's) at (150, 60) in a
    600x450 frame: the automatic square holds the face with room for the shoulders below it."""
    import cv2

    scene, _ = webcam
    clip = read_video(scene / "video.mp4", end=2.0)
    wide = np.empty((len(clip.frames), 450, 600, 3), np.uint8)
    wide[:] = np.linspace(40, 200, 600, dtype=np.uint8)[None, None, :, None]
    wide[:, 60:348, 150:438] = [cv2.resize(f, (288, 288), interpolation=cv2.INTER_CUBIC) for f in clip.frames]
    video = write_video(tmp_path / "wide3.mp4", wide, clip.fps, clip.audio.starting_at(float(clip.timestamps[0])))
    out = tmp_path / "data"
    assert main(["preprocess", str(video), "-o", str(out), "--size", "96", "--features", "none"]) == 0
    meta = json.loads((out / "meta.json").read_text())
    x, y, w, h = meta["framing"]["crop"]
    assert w == h and meta["width"] == meta["height"] == 96
    face = (270, 144, 345, 216)  # the scene's face box, three times larger and moved
    assert x <= face[0] and x + w >= face[2] and y <= face[1] and y + h >= face[3] + 0.5 * (face[3] - face[1])
    assert w < 450  # a crop, not the frame
    report = json.loads((out / "preprocess_report.json").read_text())
    assert report["decode"]["crop_auto"]["found"] >= 3


def _spliced(webcam: tuple[Path, Path], tmp_path: Path) -> Path:
    """The scene's 3 s with its last 1.2 s reframed (zoomed by 20 %, as a splice of another
    take): the picture jumps between frames 44 and 45 (1.80 s)."""
    import cv2

    scene, _ = webcam
    clip = read_video(scene / "video.mp4")
    frames = clip.frames.copy()
    for k in range(45, len(frames)):
        frames[k] = cv2.resize(frames[k][8:88, 8:88], (96, 96), interpolation=cv2.INTER_LINEAR)
    return write_video(tmp_path / "spliced.mp4", frames, clip.fps, clip.audio.starting_at(float(clip.timestamps[0])))


def test_a_spliced_clip_is_refused_with_its_clean_stretch_named(webcam: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from adnerf.preprocess.cuts import find_cuts

    video = _spliced(webcam, tmp_path)
    cuts = find_cuts(read_video(video).frames)
    assert cuts.frames == [45] and cuts.longest(75) == (0, 45)
    assert main(["preprocess", str(video), "-o", str(tmp_path / "data")]) == 2
    err = capsys.readouterr().err
    assert "1.80 s into the video" in err and "--start 0.00 --end 1.80 uses it" in err and "--allow-cuts" in err
    assert not (tmp_path / "data").exists()


def test_allow_cuts_keeps_the_frames_and_reports_the_cut(webcam: tuple[Path, Path], tmp_path: Path) -> None:
    video = _spliced(webcam, tmp_path)
    assert main(["preprocess", str(video), "-o", str(tmp_path / "data"), "--allow-cuts", "--features", "none"]) == 0
    report = json.loads((tmp_path / "data" / "preprocess_report.json").read_text())
    assert [c["frame"] for c in report["decode"]["cuts"]] == [45] and report["decode"]["cuts"][0]["time_s"] == pytest.approx(1.8)
    assert "cuts_warning" in report["decode"]


def test_a_talking_head_without_an_edit_has_no_cut(webcam: tuple[Path, Path]) -> None:
    from adnerf.preprocess.cuts import find_cuts

    scene, wide = webcam
    for video in (scene / "video.mp4", wide):  # the head turns and speaks; the picture never jumps
        cuts = find_cuts(read_video(video).frames)
        assert cuts.frames == [] and cuts.changed.max() < 0.05


def test_features_trims_frames_and_sound_as_preprocess_does(tmp_path: Path) -> None:
    """``adnerf features --start 1 --end 2.6`` on a 10 fps video with clicks at 0.95 s and 1.5 s:
    frames from 1.0 s up to 2.6 s (16), the 1.5 s click at the centre of frame 5's window, and the
    click before the start not heard at all (the sound is cut with the frames)."""
    from adnerf.cli import main
    from adnerf.io import write_video

    sr, fps = 16000, 10.0
    x = np.zeros(3 * sr, np.float32)
    for t in (0.95, 1.5):
        x[int(t * sr) : int(t * sr) + 80] = 0.9
    video = write_video(tmp_path / "clicks.mp4", np.zeros((30, 32, 32, 3), np.uint8), fps, AudioTrack(x, sr, 0.0))
    out = tmp_path / "f.npy"
    assert main(["features", str(video), "-o", str(out), "--kind", "logmel", "--start", "1", "--end", "2.6"]) == 0
    windows = np.load(out)
    assert windows.shape[0] == 16
    loud = windows.mean(2)  # (N, 16): each window's loudness by column
    assert loud[5].argmax() == 8  # the 1.5 s click: frame 5 (1.5 s) at its window's centre column
    assert loud[0].max() < loud[5].max() - 5  # the 0.95 s click is not in frame 0's window (0.84-1.14 s)
    assert main(["features", str(video), "-o", str(tmp_path / "g.npy"), "--start", "2", "--end", "1"]) == 2
