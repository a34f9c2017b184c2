"""Streaming: the windows, codes and frames made as the speech arrives equal the offline ones, and
frames come out while the speech is still arriving, no later than the stated look-ahead."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from adnerf.audio.features import FeatureSpec, StreamingWindows, speech_windows
from adnerf.cli import main
from adnerf.commands.render_video import RenderError, render_audio_video
from adnerf.commands.stream_video import pcm_chunks
from adnerf.formats.dataset import DatasetFolder, read_meta
from adnerf.io import AudioTrack, read_audio, read_video, write_video
from adnerf.model.run_folder import load_run
from adnerf.model import render_clip
from adnerf.model.stream import Streamer, pingpong_index, stream_file_chunks
from adnerf.model.train import TrainConfig, train
from adnerf.synth import SynthConfig, synthesize


def _speech(seconds: float, rate: int = 16000, seed: int = 0) -> np.ndarray:
    """A voiced sound whose loudness and pitch move (so that every feature differs)."""
    t = np.arange(int(seconds * rate)) / rate
    rng = np.random.default_rng(seed)
    env = 0.5 + 0.5 * np.sin(2 * np.pi * 2.3 * t) ** 2
    return (0.3 * env * np.sin(2 * np.pi * (140 + 40 * np.sin(2 * np.pi * 0.7 * t)) * t) + 0.01 * rng.standard_normal(len(t))).astype(np.float32)


@pytest.mark.parametrize(("fps", "start"), [(25.0, 0.0), (30.0, 0.37), (30000 / 1001, 0.0), (24.0, 0.1), (50.0, 0.0)])
def test_streamed_windows_are_the_offline_windows(fps: float, start: float) -> None:
    """Pieces of random length, each holding at least two features: the windows of
    speech_windows of the whole track, to float32 rounding (the filterbank's product over a
    piece's frames may round the last bit otherwise than over the whole track's, by the torch
    build); fails with a window centred one feature off, a missing pad at either end, or a
    window handed out before its last feature is final, each of which moves values by far more."""
    x = _speech(2.3)
    audio = AudioTrack(x, 16000, start)
    n = int(np.floor(audio.duration * fps))
    offline = speech_windows(audio, start + np.arange(n) / fps, FeatureSpec("logmel"))
    stream = StreamingWindows(fps, start=start)
    rng = np.random.default_rng(1)
    got, pos = [], 0
    while pos < len(x):
        k = int(rng.integers(640, 2400))
        got.append(stream.push(x[pos : pos + k]))
        pos += k
        # Whatever is handed out has all of its features inside the audio so far.
        # (its last feature 140 ms on, half an FFT wide, from a centre rounded to the 20 ms grid)
        assert stream.frames_done == 0 or (stream.frames_done - 1) / fps + 0.14 + 0.016 - 0.01 <= pos / 16000 + 1e-9
    got.append(stream.finish())
    np.testing.assert_allclose(np.concatenate(got), offline, rtol=0, atol=1e-5)


def test_windows_of_one_feature_pieces_agree_to_rounding() -> None:
    x = _speech(1.0)
    offline = speech_windows(AudioTrack(x, 16000, 0.0), np.arange(25) / 25.0, FeatureSpec("logmel"))
    stream = StreamingWindows(25.0)
    got = [stream.push(x[k : k + 320]) for k in range(0, len(x), 320)] + [stream.finish()]
    np.testing.assert_allclose(np.concatenate(got), offline, atol=1e-5, rtol=0)


def test_the_pose_track_plays_back_and_forth() -> None:
    assert [pingpong_index(j, 4) for j in range(9)] == [0, 1, 2, 3, 2, 1, 0, 1, 2]
    assert pingpong_index(5, 1) == 0


def test_pcm_chunks_read_signed_16_bit_little_endian() -> None:
    data = np.array([0, 16384, -32768, 32767, 1], dtype="<i2").tobytes() + b"\x07"  # an odd trailing byte
    pieces = list(pcm_chunks(io.BytesIO(data), chunk_s=2 / 16000))
    np.testing.assert_allclose(np.concatenate(pieces), [0.0, 0.5, -1.0, 32767 / 32768, 1 / 32768])


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201
    root = tmp_path_factory.mktemp("stream")
    data = synthesize(root / "data", SynthConfig(seconds=1.2, size=32, voice="formant", seed=6))  # shorter than the speech: the track plays back
    n = read_meta(data).n_frames  # shoulders that sway: each frame's torso map must travel with its pose
    maps = np.repeat(np.eye(2, 3)[None], n, 0)
    maps[:, 0, 2] = 1.5 * np.sin(np.arange(n))
    np.save(DatasetFolder(data).torso, maps)
    r = load_run(train(data, root / "run", config=TrainConfig(head_iters=6, torso_iters=2, rays=64, log_every=2, checkpoint_every=6), progress=False))
    assert r.model.smooths_audio and r.model.config.torso_motion  # AudioAttNet's neighbours and the torso's motion are part of what is checked
    return r


@pytest.fixture(scope="module")
def speech(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("speechwav") / "speech.mp4"
    return write_video(path, np.zeros((3, 16, 16, 3), np.uint8), 2.0, AudioTrack(_speech(1.5, seed=3), 16000, 0.0))


RENDER_LAYERS = render_clip.render_layers


def _spy(monkeypatch: pytest.MonkeyPatch) -> list[tuple]:
    """Record what each frame is rendered from (pose, audio code, eye, the torso's pose), from now
    on: the offline loop and the streamer both render every frame with ``render_layers``."""
    seen: list[tuple] = []
    real = RENDER_LAYERS

    def spy(run, camera, plate, pose, code, *, eye=None, read_pose=None, box=None, given=None, signals=None):  # noqa: ANN001, ANN202
        further = sorted((name, np.asarray(v).tolist()) for name, v in (signals or {}).items())  # the torso's motion, where the run reads it
        seen.append((np.array(pose), code.detach().cpu().numpy().copy(), eye, None if read_pose is None else np.array(read_pose), further))
        return real(run, camera, plate, pose, code, eye=eye, read_pose=read_pose, box=box, given=given, signals=signals)

    monkeypatch.setattr(render_clip, "render_layers", spy)
    return seen


@pytest.mark.parametrize("edit", [{}, {"yaw": 8.0, "blink": "none"}])
def test_streamed_frames_are_the_offline_render(run, speech: Path, tmp_path: Path, edit: dict, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001
    """Frame for frame against adnerf render's PNGs (lossless), and what each frame is rendered
    from: the same poses and eyes, the audio codes to float rounding (AudioNet run on other
    batches), so the frames differ by at most one level of 255. A frame rendered before
    AudioAttNet's following neighbours arrived, or a pose, blink or torso map taken from the
    wrong frame, fails."""
    offline_inputs = _spy(monkeypatch)
    render_audio_video(run, speech, tmp_path / "off.mp4", frames_dir=tmp_path / "off", yaw=edit.get("yaw", 0.0), blink=edit.get("blink", "auto"))
    offline = np.stack([cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) for p in sorted((tmp_path / "off").glob("*.png"))])
    stream_inputs = _spy(monkeypatch)
    start, chunks = stream_file_chunks(speech, 0.013)
    streamer = Streamer(run, start=start, **edit)
    frames, out_by = [], []
    for k, piece in enumerate(chunks):
        new = streamer.push(piece)
        frames += new
        out_by.append(len(frames))
    frames += streamer.finish()
    assert len(frames) == len(offline) > 30
    assert len(stream_inputs) == len(offline_inputs) == len(offline)
    for (p0, c0, e0, r0, f0), (p1, c1, e1, r1, f1) in zip(offline_inputs, stream_inputs):
        assert f0 and f1 == f0  # the torso's motion of the pose's own frame
        np.testing.assert_array_equal(p1, p0)
        np.testing.assert_allclose(c1, c0, atol=1e-5, rtol=0)
        assert e1 == e0 and (r0 is None) == (r1 is None) and (r0 is None or np.array_equal(r0, r1))
    diff = np.abs(np.stack(frames).astype(int) - offline.astype(int))
    assert diff.max() <= 1 and (diff > 0).mean() < 0.01, (diff.max(), (diff > 0).mean())
    # Frames came out while the speech arrived, each no later than the look-ahead after its time.
    heard = np.cumsum([len(c) for c in chunks]) / 16000
    for k, count in enumerate(out_by):
        assert count >= min(len(offline), int(np.floor((heard[k] - streamer.lookahead_s - 0.013) * streamer.fps))), (k, count)
    assert out_by[len(chunks) // 2] > 10


def test_stream_refuses_what_it_cannot_stream(run) -> None:  # noqa: ANN001
    with pytest.raises(RenderError, match="auto' or 'none"):
        Streamer(run, blink="blinks.npy")
    run.meta["feature_kind"] = "phonemes"
    try:
        with pytest.raises(RenderError, match="log-mel"):
            Streamer(run)
    finally:
        run.meta["feature_kind"] = "logmel"


def test_adnerf_stream_writes_the_mp4_from_a_file_and_from_stdin(run, speech: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:  # noqa: ANN001
    assert main(["stream", str(run.root), "--audio", str(speech), "-o", str(tmp_path / "file.mp4"), "--chunk-ms", "20", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert 0.25 < summary["lookahead_s"] < 0.35 and summary["first_frame_s"] > 0 and summary["realtime_factor"] > 0
    v = read_video(tmp_path / "file.mp4")
    n = int(np.floor(read_audio(speech).duration * 25.0))
    assert len(v.frames) == n and v.audio is not None and abs(v.audio.duration - 1.5) < 0.1
    pcm = (np.clip(read_audio(speech, sample_rate=16000).samples, -1, 1) * 32767).astype("<i2").tobytes()
    proc = subprocess.run(
        [sys.executable, "-c", "import sys; from adnerf.cli import main; raise SystemExit(main(sys.argv[1:]))", "stream", str(run.root), "--audio", "-", "-o", str(tmp_path / "live.mp4")],
        input=pcm, capture_output=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr.decode()[-2000:]
    live = read_video(tmp_path / "live.mp4")
    assert len(live.frames) == n and live.audio is not None
    assert "look-ahead" in proc.stdout.decode()


def test_the_causal_stream_smooths_over_past_frames_only_and_waits_less(run, speech: Path, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001
    """``causal=True``: each frame's audio code is AudioAttNet over that frame and the ones before
    it, the window clamped at the frame (as the offline render clamps it at a clip's last frame),
    and the look-ahead drops by AudioAttNet's following frames. A code that read one frame ahead,
    or the full neighbourhood at the stream's end, fails."""
    import torch

    seen = _spy(monkeypatch)
    start, chunks = stream_file_chunks(speech, 0.02)
    causal, full = Streamer(run, start=start, causal=True), Streamer(run, start=start)
    after = run.model.config.att_len - run.model.config.att_len // 2 - 1
    assert after == 3 and causal.lookahead_s == pytest.approx(full.lookahead_s - after / causal.fps)
    frames = [f for piece in chunks for f in causal.push(piece)] + causal.finish()
    windows = speech_windows(read_audio(speech, sample_rate=16000), start + np.arange(len(frames)) / causal.fps, FeatureSpec("logmel"))
    with torch.no_grad():
        for i, (_, code, _, _, _) in enumerate(seen):
            want = run.model.frame_codes(torch.as_tensor(windows[: i + 1]), [i])[0].numpy()
            np.testing.assert_allclose(code, want, atol=1e-5, rtol=0, err_msg=f"frame {i}")
    with torch.no_grad():
        ahead = run.model.frame_codes(torch.as_tensor(windows), [5])[0].numpy()
    assert np.abs(seen[5][1] - ahead).max() > 1e-4  # the full neighbourhood gives another code
