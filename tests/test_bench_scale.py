"""``adnerf bench scale``: clips looped to a length (frames and audio in step), and the benchmark's
rows; the streaming video writer they are written with."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from adnerf.bench.scale import looped_clip
from adnerf.cli import main
from adnerf.io import AudioTrack, MediaError, VideoWriter, read_video, write_video
from adnerf.synth import SynthConfig, synthesize

SR = 16000


def _numbered_clip(path: Path, n: int = 10, fps: float = 30.0, extra_audio_s: float = 0.13) -> Path:
    """``n`` flat frames of brightness ``20 k`` and audio that is silent but for a click at frame
    3's time; the track runs ``extra_audio_s`` past the last frame (so a loop of the whole track
    would drift off the frames)."""
    frames = np.stack([np.full((32, 32, 3), 20 * k, np.uint8) for k in range(n)])
    audio = np.zeros(int(round((n / fps + extra_audio_s) * SR)), np.float32)
    s = int(round(3 / fps * SR))
    audio[s : s + 80] = 0.9 * np.sin(2 * np.pi * 1000 * np.arange(80) / SR)
    return write_video(path, frames, fps, AudioTrack(audio, SR))


def _clicks(samples: np.ndarray) -> np.ndarray:
    """Start times (s) of the clicks: where the envelope first rises above half its peak."""
    loud = np.abs(samples) > 0.45
    starts = np.flatnonzero(loud[1:] & ~np.convolve(loud, np.ones(400), "full")[: len(loud)][:-1].astype(bool)) + 1
    return starts / SR


def test_a_looped_clip_repeats_its_frames_and_its_sound_together(tmp_path: Path) -> None:
    src = _numbered_clip(tmp_path / "src.mp4")
    out, info = looped_clip(src, 25 / 30, tmp_path / "loop.mp4")
    assert info["frames"] == 25 and info["clip_frames"] == 10 and info["passes"] == pytest.approx(2.5)
    video = read_video(out)
    assert len(video.frames) == 25
    brightness = video.frames.reshape(25, -1).mean(axis=1)
    np.testing.assert_allclose(brightness, 20 * (np.arange(25) % 10), atol=3)  # frame k is frame k mod n: no frame skipped or doubled
    track = video.audio.starting_at(float(video.timestamps[0]))
    assert track.duration == pytest.approx(25 / 30, abs=0.07)  # up to one AAC frame (1024 samples) of padding
    np.testing.assert_allclose(_clicks(track.samples), np.array([3, 13, 23]) / 30, atol=1.5e-3)  # each pass's click at its frame 3

    short, info = looped_clip(src, 0.2, tmp_path / "short.mp4")  # shorter than the clip: cut
    assert info["frames"] == 6 and len(read_video(short).frames) == 6
    with pytest.raises(ValueError, match="positive"):
        looped_clip(src, 0.0, tmp_path / "none.mp4")


def test_the_video_writer_streams_and_leaves_nothing_on_failure(tmp_path: Path) -> None:
    out = tmp_path / "w.mp4"
    with VideoWriter(out, 25.0, np.zeros(SR // 2, np.float32), SR) as writer:
        for k in range(5):
            writer.write(np.full((17, 21, 3), 40 * k, np.uint8))  # odd sizes: padded
    video = read_video(out)
    assert video.frames.shape == (5, 18, 22, 3) and video.audio is not None
    with pytest.raises(MediaError, match="the first was 22x18"):
        with VideoWriter(tmp_path / "bad.mp4", 25.0) as writer:
            writer.write(np.zeros((18, 22, 3), np.uint8))
            writer.write(np.zeros((20, 22, 3), np.uint8))
    with pytest.raises(MediaError, match="no frames"):
        with VideoWriter(tmp_path / "empty.mp4", 25.0):
            pass
    with pytest.raises(KeyboardInterrupt):
        with VideoWriter(tmp_path / "cut.mp4", 25.0) as writer:
            writer.write(np.zeros((18, 22, 3), np.uint8))
            raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w.mp4"]


def test_bench_scale_measures_each_length_and_the_loop_keeps_audio_on_its_frames(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    scene = synthesize(tmp_path / "scene", SynthConfig(seconds=2.0, size=96, voice="formant", seed=3))
    assert main(["bench", "scale", str(scene / "video.mp4"), "--seconds", "4,2", "--size", "0", "--steps", "2", "--work", str(tmp_path / "w"), "--json"]) == 0
    out, err = capsys.readouterr()
    result = json.loads(out)
    short, long = result["rows"]
    assert (short["seconds"], short["frames"], long["frames"]) == (2.0, 50, 100)
    for row in (short, long):
        assert set(row["preprocess_ms_per_frame"]) >= {"parse", "face", "pose", "plate"}
        assert all(v >= 0 for v in row["preprocess_ms_per_frame"].values())
        assert row["preprocess_peak_rss_gib"] > 0.1 and row["train_peak_rss_gib"] > 0.1
        assert row["train_seconds_per_step"]["head"] > 0 and row["train_seconds_per_step"]["torso"] > 0
        assert row["data_bytes_per_frame"] == 4 * 96 * 96
    assert result["growth"]["from_seconds"] == 2.0 and result["growth"]["to_seconds"] == 4.0
    assert "4 s against 2 s" in err
    # the 4 s dataset is the 2 s clip twice: its second pass's pictures and audio features are its first's
    data = tmp_path / "w" / "video_native" / "4s" / "data"
    first, second = (cv2.imread(str(data / "frames" / f"{k:06d}.png")).astype(float) for k in (20, 70))
    assert np.abs(first - second).mean() < 2.0
    features = np.load(data / "features.npy")
    same = np.abs(features[10:40] - features[60:90]).mean()
    shifted = np.abs(features[10:40] - features[61:91]).mean()  # a pass one frame off
    assert same < 0.25 * shifted


def test_a_childs_peak_memory_is_its_own_not_its_parents(tmp_path: Path) -> None:
    """The parent holds 1.5 GiB; a child that runs ``adnerf --help`` peaks far below that (the
    rusage of a forked child also counts the parent's pages it shared before exec)."""
    from adnerf.bench.scale import _child

    held = np.ones(3 * 2**27, np.float32)  # 1.5 GiB, resident
    held[:: 4096 // 4] = 2.0
    wall, peak = _child(["--help"], tmp_path / "help.log")
    assert peak is not None and 0.01 < peak < 0.75, peak
    assert "usage: adnerf" in (tmp_path / "help.log").read_text()
    del held
