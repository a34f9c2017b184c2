"""Files as phones and webcams make them: variable frame rate, a rotation flag, audio that starts
late or ends early, a copy cut off mid-write. Each file is built here with PyAV."""

from __future__ import annotations

import json
import struct
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pytest

from adnerf.cli import main
from adnerf.io import MediaError, read_video
from adnerf.formats.dataset import load_dataset
from adnerf.preprocess.frame_grid import nominal_rate, regular_grid
from adnerf.synth import SynthConfig, synthesize

PORTRAIT = (0, 1, -1, 0)  # the display matrix (a, b, c, d) of a phone held upright: turn 90 degrees clockwise
MATRICES = {90: PORTRAIT, 180: (-1, 0, 0, -1), 270: (0, -1, 1, 0)}


def write_phone_file(path: Path, frames: np.ndarray, times: np.ndarray, audio: np.ndarray | None = None, rate: int = 16000, *, audio_start: float = 0.0, matrix: tuple | None = None, faststart: bool = False) -> Path:
    """An mp4 as a phone writes it: each frame at its own presentation time (seconds), an AAC track
    whose first sample plays at ``audio_start``, and optionally a display matrix in the video
    track's header (where phones put the rotation)."""
    h, w = frames.shape[1:3]
    with av.open(str(path), "w", options={"movflags": "faststart"} if faststart else {}) as container:
        video = container.add_stream("h264", rate=30)
        video.width, video.height, video.pix_fmt = w, h, "yuv420p"
        video.codec_context.time_base = video.time_base = Fraction(1, 90000)
        sound = None
        if audio is not None:
            sound = container.add_stream("aac", rate=rate)
            sound.layout = "mono"
        for frame, t in zip(frames, times):
            vf = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            vf.pts, vf.time_base = int(round(t * 90000)), Fraction(1, 90000)
            for packet in video.encode(vf):
                container.mux(packet)
        for packet in video.encode():
            container.mux(packet)
        if sound is not None:
            for k in range(0, len(audio), 1024):
                af = av.AudioFrame.from_ndarray(audio[None, k : k + 1024].astype(np.float32), format="fltp", layout="mono")
                af.sample_rate, af.pts, af.time_base = rate, int(round(audio_start * rate)) + k, Fraction(1, rate)
                for packet in sound.encode(af):
                    container.mux(packet)
            for packet in sound.encode():
                container.mux(packet)
    if matrix is not None:  # the video track's tkhd (its width is not 0): a, b, u, c, d, v, x, y, w in 16.16 / 2.30
        data = bytearray(path.read_bytes())
        at = 0
        while True:
            i = data.index(b"tkhd", at)
            off = i + 8 + (28 if data[i + 4] == 1 else 20) + 16
            if struct.unpack(">I", data[off + 36 : off + 40])[0]:
                break
            at = i + 4
        a, b, c, d = matrix
        data[off : off + 36] = struct.pack(">9i", a << 16, b << 16, 0, c << 16, d << 16, 0, 0, 0, 1 << 30)
        path.write_bytes(bytes(data))
    return path


def _pattern(n: int = 12, h: int = 48, w: int = 64) -> np.ndarray:
    """Frames with a white band along the top and a red band down the left: every turn and mirror differs."""
    frames = np.zeros((n, h, w, 3), np.uint8)
    frames[:, : h // 4] = 255
    frames[:, :, : w // 8, 0] = 255
    return frames


# --- the constant grid --------------------------------------------------------------------------


def test_constant_rate_footage_maps_onto_the_grid_one_to_one() -> None:
    t = np.arange(50) / 30.0 + 1e-3 * np.sin(np.arange(50))  # millisecond jitter of rounded timestamps
    grid = regular_grid(t + 7.0, 30.0)
    assert grid.identity and np.array_equal(grid.index, np.arange(50)) and np.allclose(grid.times, np.arange(50) / 30.0)


def test_a_skipped_frame_is_repeated_and_two_frames_in_one_slot_lose_one() -> None:
    t = np.arange(20) / 25.0
    skipped = np.delete(t, 7)  # the phone dropped frame 7: slot 7 shows a neighbour
    grid = regular_grid(skipped, 25.0)
    assert (grid.duplicated, grid.dropped, len(grid.index)) == (1, 0, 20)
    assert grid.index[6] == 6 and grid.index[7] in (6, 7) and grid.index[8] == 7  # source index 7 is the true frame 8
    crowded = np.sort(np.append(t, t[12] + 0.012))  # an extra frame 12 ms after frame 12
    grid = regular_grid(crowded, 25.0)
    assert (grid.duplicated, grid.dropped, len(grid.index)) == (0, 1, 20) and grid.index[12] == 12 and grid.index[13] == 14


def test_the_nominal_rate_snaps_to_a_standard_rate_only_when_close() -> None:
    assert nominal_rate(np.arange(10) / 30.0, 30.4) == 30.0  # a phone's "30 fps" averaging a little off
    assert nominal_rate(np.arange(10) / 30.0, 29.6) == pytest.approx(30000 / 1001)
    assert nominal_rate(np.arange(10) / 25.0, None) == 25.0  # no average rate: the median gap decides
    assert nominal_rate(np.arange(10) / 27.0, None) == pytest.approx(27.0)  # no standard rate near: kept
    with pytest.raises(ValueError, match="sorted"):
        regular_grid(np.array([0.0, 0.2, 0.1]), 25.0)


# --- rotation and truncation at decoding ---------------------------------------------------------


@pytest.mark.parametrize("degrees", [90, 180, 270])
def test_rotation_metadata_stands_the_frames_upright(tmp_path: Path, degrees: int) -> None:
    # The file stores the frames turned counterclockwise and asks for the clockwise turn that undoes it.
    upright = _pattern()
    stored = np.rot90(upright, degrees // 90, axes=(1, 2))
    path = write_phone_file(tmp_path / "portrait.mp4", stored, np.arange(12) / 30.0, matrix=MATRICES[degrees])
    video = read_video(path, audio=False)
    assert video.rotation == degrees and video.frames.shape == upright.shape
    assert np.abs(video.frames.astype(int) - upright).mean() < 6.0  # codec noise; any other turn is ~100


def test_a_file_cut_off_mid_write_gives_the_frames_that_decode(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (60, 48, 64, 3), dtype=np.uint8)  # noise: every frame a large packet
    whole = write_phone_file(tmp_path / "whole.mp4", frames, np.arange(60) / 30.0, faststart=True)
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(whole.read_bytes()[: int(whole.stat().st_size * 0.6)])
    video = read_video(cut, audio=False)
    assert 10 < len(video.frames) < 50 and video.truncated is not None and "of the 60 the file declares" in video.truncated
    assert read_video(whole, audio=False).truncated is None
    # Without the streaming layout the index is written last: nothing decodes, and the line says why.
    plain = write_phone_file(tmp_path / "plain.mp4", frames, np.arange(60) / 30.0)
    cut.write_bytes(plain.read_bytes()[: int(plain.stat().st_size * 0.6)])
    with pytest.raises(MediaError, match="unfinished copy or recording"):
        read_video(cut)


# --- through the command line --------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("phone") / "scene", SynthConfig(seconds=3.0, size=96, voice="formant", seed=3))


def test_a_phone_file_preprocesses_upright_on_a_constant_clock_with_its_audio_in_place(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    # Variable frame rate (frame 30 skipped, an extra frame 12 ms after frame 49, jittered times),
    # held in portrait, the audio 0.5 s late and 0.4 s short: as a phone would write it.
    truth = read_video(scene / "video.mp4")
    n, rate = len(truth.frames), truth.audio.sample_rate
    times = np.arange(n) / 25.0 + 0.003 * np.sin(np.arange(n))
    order = [i for i in range(n) if i != 30] + [49]
    stamps = np.array([times[i] for i in order[:-1]] + [times[49] + 0.012])
    sort = np.argsort(stamps, kind="stable")
    stored = np.rot90(truth.frames[np.array(order)[sort]], 1, axes=(1, 2))
    audio = truth.audio.samples[int(0.5 * rate) : int(2.6 * rate)]
    phone = write_phone_file(tmp_path / "phone.mp4", stored, stamps[sort], audio, rate, audio_start=0.5, matrix=PORTRAIT)
    out = tmp_path / "data"
    assert main(["preprocess", str(phone), "-o", str(out), "--focal", str(1.33 * 96)]) == 0
    err = capsys.readouterr().err
    report = json.loads((out / "preprocess_report.json").read_text())["decode"]
    assert report["rotation_deg"] == 90 and report["fps"] == 25.0 and (report["duplicated"], report["dropped"]) == (1, 1)
    assert "1 frame(s) repeated" in err and "1 left out" in err
    # AAC's priming samples play before the first sound sample: the track starts up to 64 ms early.
    assert 0.43 <= report["audio_late_s"] <= 0.5 and 0.35 <= report["audio_short_s"] <= 0.41 and "padded with silence" in report["audio_warning"] in err
    ds = load_dataset(out)
    assert ds.frames.shape == truth.frames.shape and ds.meta.fps == 25.0
    kept = [k for k in range(n) if k != 30]
    assert np.abs(ds.frames[kept].astype(int) - truth.frames[kept]).mean() < 4.0  # upright, each in its slot
    assert np.abs(ds.frames[30].astype(int) - truth.frames[29]).mean() < np.abs(ds.frames[30].astype(int) - truth.frames[10]).mean()
    # The audio sits where it played: the dataset's track matches the truth at zero lag, silence before.
    got, want = ds.audio.samples, truth.audio.samples[: len(ds.audio.samples)]
    assert len(got) == round(3.0 * rate) and np.abs(got[: int(0.42 * rate)]).max() < 1e-3
    seg = slice(int(0.6 * rate), int(2.5 * rate))
    lags = range(-80, 81, 8)
    best = max(lags, key=lambda lag: float(np.dot(got[seg], np.roll(want, lag)[seg])))
    assert best == 0 and np.corrcoef(got[seg], want[seg])[0, 1] > 0.9


def test_a_file_that_decodes_too_little_is_refused_in_one_line(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    truth = read_video(scene / "video.mp4")
    whole = write_phone_file(tmp_path / "whole.mp4", truth.frames, np.arange(len(truth.frames)) / 25.0, truth.audio.samples, truth.audio.sample_rate, faststart=True)
    cut = tmp_path / "copy.mp4"
    cut.write_bytes(whole.read_bytes()[: int(whole.stat().st_size * 0.4)])
    assert main(["preprocess", str(cut), "-o", str(tmp_path / "data")]) != 0
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("adnerf:")]
    assert len(lines) == 1 and "where it decodes; preprocessing needs at least 2 s" in lines[0] and "ends early" in err
    assert not (tmp_path / "data").exists()


def test_fps_on_a_steady_clip_says_it_resamples_not_that_the_clip_is_variable(tmp_path: Path) -> None:
    from adnerf.preprocess.pipeline import PreprocessConfig, StepContext, _step_decode, _Work

    frames = _pattern(n=60)
    rate = 16000
    audio = 0.1 * np.sin(np.arange(2 * rate) / 10.0).astype(np.float32)
    steady = write_phone_file(tmp_path / "steady.mp4", frames, np.arange(60) / 30.0, audio, rate)

    def decode(fps: float | None) -> dict:
        config = PreprocessConfig(fps=fps, min_seconds=1.0)
        return _step_decode(StepContext(steady, _Work(tmp_path / f"work{fps}", steady, config), config, lambda *a: None))

    assert "timing_warning" not in decode(None) and "timing_warning" not in decode(30.0)
    doc = decode(25.0)
    assert doc["fps"] == 25.0 and (doc["duplicated"], doc["dropped"]) == (0, 10)
    assert doc["timing_warning"].endswith("--fps 25 resamples the clip's steady 30 fps by its timestamps, 0 frame(s) repeated and 10 left out")
    # A clip that is not steady keeps the variable-rate wording under --fps too.
    jitter = write_phone_file(tmp_path / "jitter.mp4", frames[:59], np.array([t for i, t in enumerate(np.arange(60) / 30.0) if i != 20]), audio, rate)
    config = PreprocessConfig(fps=30.0, min_seconds=1.0)
    assert "variable frame rate" in _step_decode(StepContext(jitter, _Work(tmp_path / "workj", jitter, config), config, lambda *a: None))["timing_warning"]
