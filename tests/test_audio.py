"""Audio pathway: media I/O, timestamp alignment, resampling, speech features, audio networks, bad input."""

from __future__ import annotations

import shutil
import subprocess
import sys
import wave
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import torch

from adnerf.audio import features as F
from adnerf.audio import AudioAttNet, AudioNet
from adnerf.cli import main
from adnerf.io import (
    AudioTrack,
    MediaError,
    frame_times,
    read_audio,
    read_video,
    write_video,
)

SR = 16000


def _burst_audio(t0: float, duration: float = 3.0, sr: int = SR) -> np.ndarray:
    """Silence with a 30 ms 1 kHz tone burst starting at t0."""
    x = np.zeros(int(duration * sr), np.float32)
    n0, n = int(t0 * sr), int(0.03 * sr)
    x[n0 : n0 + n] = 0.8 * np.sin(2 * np.pi * 1000 * np.arange(n) / sr)
    return x


def _check_burst_alignment(windows: np.ndarray, times: np.ndarray, t_burst: float, fps: float) -> None:
    energy = windows.max(axis=-1)  # (N, 16): loudest band per feature
    shown = int(np.floor(t_burst * fps + 1e-9))  # the frame on screen when the burst plays
    peak = int(np.argmax(energy[shown]))
    # The burst sits at the centre of the window of the frame that shows it (+-2 features = 40 ms).
    assert abs(peak - F.WINDOW // 2) <= 2, (peak, shown)
    quiet = np.abs(times - t_burst) > 0.3
    assert energy[quiet].max() < energy[shown].max() - 10  # far frames do not hear it


@pytest.mark.parametrize("fps", [25.0, 30000 / 1001, 30.0])
def test_burst_lands_in_its_frames_window(fps: float) -> None:
    t0 = 1.37
    audio = AudioTrack(_burst_audio(t0), SR)
    times = np.arange(int(3.0 * fps)) / fps
    windows = F.speech_windows(audio, times, F.FeatureSpec("logmel"))
    assert windows.shape == (len(times), 16, 80)
    _check_burst_alignment(windows, times, t0 + 0.015, fps)


@pytest.mark.parametrize("fps", [25.0, 30000 / 1001])
def test_alignment_survives_an_mp4_round_trip(tmp_path: Path, fps: float) -> None:
    t0 = 1.37
    n = int(2.4 * fps)
    frames = np.full((n, 32, 48, 3), 100, np.uint8)
    path = write_video(tmp_path / "clip.mp4", frames, fps, _burst_audio(t0, 2.4), SR)
    video = read_video(path)
    assert video.frames.shape == (n, 32, 48, 3)
    np.testing.assert_allclose(video.timestamps, np.arange(n) / fps, atol=1e-3)
    np.testing.assert_allclose(frame_times(path), video.timestamps, atol=1e-9)
    assert video.audio is not None and abs(video.audio.start) < 1e-3
    windows = F.speech_windows(video.audio, video.timestamps, F.FeatureSpec("logmel"))
    _check_burst_alignment(windows, video.timestamps, t0 + 0.015, fps)
    # The burst is where it was written, to within a millisecond (aac priming is accounted for).
    x = video.audio.samples
    onset = (np.argmax(np.abs(x) > 0.2) / video.audio.sample_rate) + video.audio.start
    assert abs(onset - t0) < 1e-3


def _write_wav(path: Path, samples: np.ndarray, sr: int) -> Path:
    data = np.clip(samples, -1, 1)
    channels = 1 if data.ndim == 1 else data.shape[1]
    with wave.open(str(path), "wb") as w:
        w.setnchannels(channels)
        w.setsampwidth(2)
        w.setframerate(sr)
        w.writeframes((data * 32767).astype("<i2").tobytes())
    return path


@pytest.mark.parametrize("rate", [8000, 16000, 22050, 44100, 48000])
def test_resampling_keeps_duration_and_pitch(tmp_path: Path, rate: int) -> None:
    t = np.arange(int(1.5 * rate)) / rate
    path = _write_wav(tmp_path / "tone.wav", 0.5 * np.sin(2 * np.pi * 440 * t), rate)
    native = read_audio(path)
    assert native.sample_rate == rate and len(native.samples) == len(t)
    a = read_audio(path, sample_rate=SR)
    assert a.sample_rate == SR and abs(len(a.samples) - 1.5 * SR) <= 64
    spectrum = np.abs(np.fft.rfft(a.samples))
    peak_hz = np.argmax(spectrum) * SR / len(a.samples)
    assert abs(peak_hz - 440) < 2
    assert 0.45 < np.abs(a.samples).max() < 0.55


def test_stereo_is_mixed_to_mono(tmp_path: Path) -> None:
    t = np.arange(SR) / SR
    tone = 0.6 * np.sin(2 * np.pi * 300 * t)
    path = _write_wav(tmp_path / "stereo.wav", np.stack([tone, np.zeros_like(tone)], axis=1), SR)
    a = read_audio(path)
    assert a.samples.ndim == 1
    np.testing.assert_allclose(np.abs(a.samples).max(), 0.3, atol=0.02)  # the average of the channels
    # Identical full-scale channels stay in [-1, 1] (FFmpeg's own downmix would give 1.41).
    loud = _write_wav(tmp_path / "loud.wav", np.stack([0.99 * np.sin(2 * np.pi * 300 * t)] * 2, axis=1), SR)
    assert 0.95 < np.abs(read_audio(loud).samples).max() <= 1.0


def test_silence_short_audio_and_coverage_policy() -> None:
    spec = F.FeatureSpec("logmel")
    silent = F.speech_windows(AudioTrack(np.zeros(SR, np.float32), SR), np.arange(25) / 25, spec)
    assert np.isfinite(silent).all()
    assert np.allclose(silent, silent[0, 0])  # nothing but silence
    tiny = F.speech_windows(AudioTrack(np.full(100, 0.1, np.float32), SR), np.arange(3) / 25, spec)
    assert tiny.shape == (3, 16, 80) and np.isfinite(tiny).all()
    # Audio shorter than the video: frames after its end see silence.
    noise = AudioTrack(0.3 * np.random.default_rng(0).standard_normal(SR).astype(np.float32), SR)
    times = np.arange(75) / 25  # 3 s of video, 1 s of audio
    w = F.speech_windows(noise, times, spec)
    assert w[10].mean() > silent[0, 0].mean() + 5
    np.testing.assert_allclose(w[60], silent[0], atol=1e-4)
    # Audio longer than the video: the tail is ignored, windows stay per frame.
    assert F.speech_windows(noise, np.arange(5) / 25, spec).shape == (5, 16, 80)


def test_frame_windows_are_edge_padded() -> None:
    feats = np.arange(10, dtype=np.float32)[:, None]
    w = F.frame_windows(feats, np.array([0.0, 0.1]), rate=50.0)
    assert w[0, :, 0].tolist() == [0] * 9 + list(range(1, 8))
    assert w[1, :, 0].tolist() == [0] * 4 + list(range(1, 10)) + [9] * 3
    with pytest.raises(ValueError):
        F.frame_windows(np.zeros((0, 3)), np.array([0.0]))


def test_features_are_cached(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    audio = AudioTrack(_burst_audio(0.5, 1.0), SR)
    times = np.arange(25) / 25
    first = F.speech_windows(audio, times, F.FeatureSpec("logmel"), cache_dir=tmp_path)
    assert len(list(tmp_path.glob("features_logmel_*.npy"))) == 1

    def boom(*args, **kwargs):
        raise AssertionError("recomputed despite the cache")

    monkeypatch.setattr(F, "extract_features", boom)
    np.testing.assert_array_equal(F.speech_windows(audio, times, F.FeatureSpec("logmel"), cache_dir=tmp_path), first)
    with pytest.raises(AssertionError):  # other settings are another key
        F.speech_windows(audio, times, F.FeatureSpec("logmel", n_mels=40), cache_dir=tmp_path)


def test_phoneme_features_shape() -> None:
    x = (0.05 * np.random.default_rng(0).standard_normal(int(2.5 * SR))).astype(np.float32)
    whole = F.phoneme_logprobs(x)
    assert whole.shape == (len(x) // 320 + 1, 191)
    np.testing.assert_allclose(np.exp(whole).sum(-1), 1.0, atol=1e-3)  # log-probabilities


def test_logmel_and_phonemes_side_by_side_keep_both_features_aligned() -> None:
    x = (0.05 * np.random.default_rng(1).standard_normal(int(1.7 * SR))).astype(np.float32)
    audio = AudioTrack(x, SR)
    both = F.extract_features(audio, F.FeatureSpec("logmel+phonemes"))
    samples = F.resample(audio, F.MODEL_RATE)
    # Log-mel first, then the phoneme log-probabilities, row k of each at k * 20 ms.
    np.testing.assert_array_equal(both[:, :80], F.logmel(samples))
    np.testing.assert_array_equal(both[:, 80:], F.phoneme_logprobs(samples))
    windows = F.speech_windows(audio, np.arange(40) / 25, F.FeatureSpec("logmel+phonemes"))
    assert windows.shape == (40, 16, 80 + 191) and "logmel+phonemes" in F.FEATURE_KINDS
    # The windows are the two kinds' own windows side by side (preprocessing's --features auto
    # joins them so; rendering other speech computes the joined kind).
    apart = [F.speech_windows(audio, np.arange(40) / 25, F.FeatureSpec(kind)) for kind in ("logmel", "phonemes")]
    np.testing.assert_array_equal(windows, np.concatenate(apart, axis=-1))


ESPEAK = shutil.which("espeak-ng")


def _speak(tmp_path: Path, text: str, pitch: int = 50) -> AudioTrack:
    path = tmp_path / f"s{abs(hash((text, pitch)))}.wav"
    subprocess.run([ESPEAK, "-p", str(pitch), "-w", str(path), text], check=True, capture_output=True)
    return read_audio(path)


@pytest.mark.skipif(ESPEAK is None, reason="espeak-ng is not installed (apt-get install espeak-ng); .ci/run installs it")
def test_phoneme_features_separate_vowels(tmp_path: Path) -> None:
    vowels = {"a": "[[A:]]", "i": "[[i:]]"}
    means = {}
    for name, text in vowels.items():
        for pitch in (20, 40, 60, 80):
            a = _speak(tmp_path, text, pitch)
            feats = F.extract_features(a, F.FeatureSpec("phonemes"))
            speech = feats[np.argsort(feats[:, -1])[: max(3, len(feats) // 4)]]  # least blank-like frames
            means[(name, pitch)] = speech.mean(axis=0)
    # Leave-one-pitch-out nearest-centroid classification of the vowel.
    for (name, pitch), vec in means.items():
        dist = {}
        for other in vowels:
            others = [v for (n, p), v in means.items() if n == other and p != pitch]
            dist[other] = np.linalg.norm(vec - np.mean(others, axis=0))
        assert min(dist, key=dist.get) == name, (name, pitch, dist)


@pytest.mark.skipif(ESPEAK is None, reason="espeak-ng is not installed (apt-get install espeak-ng); .ci/run installs it")
def test_recogniser_decodes_recognisable_phonemes(tmp_path: Path) -> None:
    import hama

    a = _speak(tmp_path, "see")
    model = F._hama_model()
    result = model.transcribe_waveform(a.samples, a.sample_rate)
    assert "i" in result.phonemes and "s" in result.phonemes
    # Our per-frame log-probabilities decode to the same argmax sequence as hama's own call.
    samples16 = F.resample(a, F.MODEL_RATE)
    ours = F.phoneme_logprobs(samples16).argmax(-1)
    theirs = np.asarray(model.transcribe_waveform(samples16, F.MODEL_RATE).frame_token_ids)
    agree = (ours[: len(theirs)] == theirs).mean()
    assert agree > 0.9 and isinstance(hama.ASRModel, type)


@pytest.mark.skipif(ESPEAK is None, reason="espeak-ng is not installed (apt-get install espeak-ng); .ci/run installs it")
def test_chunked_phonemes_match_unchunked_on_speech(tmp_path: Path) -> None:
    a = _speak(tmp_path, "the quick brown fox jumps over the lazy dog and runs far away into the forest")
    x = F.resample(a, F.MODEL_RATE)
    whole = F.phoneme_logprobs(x, chunk_seconds=100)
    chunked = F.phoneme_logprobs(x, chunk_seconds=1.5, context_seconds=2.0)
    assert chunked.shape == whole.shape
    assert (whole.argmax(-1) == chunked.argmax(-1)).mean() > 0.85
    assert 0.5 * np.abs(np.exp(whole) - np.exp(chunked)).sum(-1).mean() < 0.15


def test_audio_networks() -> None:
    net = AudioNet(in_dim=191, code_dim=64)
    x = torch.randn(5, 16, 191, requires_grad=True)
    code = net(x)
    assert code.shape == (5, 64)
    assert net(torch.randn(2, 3, 16, 191)).shape == (2, 3, 64)
    att = AudioAttNet(code_dim=64, seq_len=8)
    codes = code[None].expand(2, 5, 64)[:, :4].reshape(1, 8, 64)
    w = att.weights(codes)
    assert w.shape == (1, 8) and torch.allclose(w.sum(-1), torch.ones(1)) and (w >= 0).all()
    out = att(codes)
    assert out.shape == (1, 64)
    out.sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    assert all(p.grad is not None for p in att.parameters())
    # Identical codes pass through the filter unchanged (weights sum to 1).
    same = torch.randn(64).expand(3, 8, 64)
    torch.testing.assert_close(att(same), same[:, 0])
    with pytest.raises(ValueError):
        net(torch.randn(4, 15, 191))
    with pytest.raises(ValueError):
        att(torch.randn(4, 7, 64))


def test_attention_can_start_near_the_identity() -> None:
    torch.manual_seed(0)
    codes = AudioNet(in_dim=29, code_dim=64)(torch.randn(40, 8, 16, 29)).detach()  # (40, 8, 64)
    paper = AudioAttNet(64, 8).weights(codes)
    torch.manual_seed(1)
    centred = AudioAttNet(64, 8, centre_logit=4.0).weights(codes)
    # Paper initialisation: close to a uniform average. Centred: mostly the frame itself.
    assert paper.max() < 0.4
    assert centred.argmax(dim=-1).eq(4).all() and centred[:, 4].min() > 0.7
    # The frame itself sits where TalkingHead.neighbours puts it.
    from adnerf.fields import fast_config
    from adnerf.model.talking_head import ModelConfig, TalkingHead

    head = fast_config(64)
    model = TalkingHead(ModelConfig(29, head, head, fast_config(73), fast_config(73), ((-1, -1, -1), (1, 1, 1)), ((-1, -1, 1), (1, 1, 3))))
    rows = model.neighbours(torch.tensor([10, 0, 99]), 100)
    assert rows[:, model.config.att_len // 2].tolist() == [10, 0, 99]
    assert rows[0].tolist() == list(range(6, 14)) and rows[1].tolist() == [0, 0, 0, 0, 0, 1, 2, 3] and rows[2].tolist() == [95, 96, 97, 98, 99, 99, 99, 99]


def _tiny_head() -> "TalkingHead":  # noqa: F821
    from adnerf.fields import fast_config
    from adnerf.model.talking_head import ModelConfig, TalkingHead

    torch.manual_seed(0)
    head = fast_config(64)
    return TalkingHead(ModelConfig(29, head, head, fast_config(73), fast_config(73), ((-1, -1, -1), (1, 1, 1)), ((-1, -1, 1), (1, 1, 3))))


@torch.no_grad()
def test_frame_codes_is_one_path_for_one_frame_and_for_all() -> None:
    model = _tiny_head()
    with torch.no_grad():  # a filter far from the identity, so a wrong neighbourhood shows
        model.att_net.score.bias.copy_(torch.linspace(-1, 1, 8))
    windows = torch.randn(20, 16, 29)
    raw = model.audio_codes(windows)
    assert not model.smooths_audio
    torch.testing.assert_close(model.frame_codes(windows), raw)
    torch.testing.assert_close(model.frame_codes(windows, [7, 3]), raw[[7, 3]])
    model.set_audio_smoothing(True)
    every = model.frame_codes(windows)
    for f in (0, 2, 10, 19):  # the filter over the clamped neighbourhood, the frame at att_len // 2
        around = raw[[min(max(k, 0), 19) for k in range(f - 4, f + 4)]]
        torch.testing.assert_close(every[f], model.att_net(around), rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(model.frame_codes(windows, [f])[0], every[f], rtol=1e-6, atol=1e-7)
    assert not torch.allclose(every, raw, atol=1e-3)


def test_audio_smoothing_is_saved_with_the_model(tmp_path: Path) -> None:
    from adnerf.model.run_folder import RunError, load_model_state, scheduled_smoothing
    from adnerf.model.train_config import TrainConfig

    model = _tiny_head()
    model.set_audio_smoothing(True)
    state = model.state_dict()
    fresh = _tiny_head()
    load_model_state(fresh, state, tmp_path / "x.pt", smoothing=False)
    assert fresh.smooths_audio  # the stored switch wins over the schedule's
    # A checkpoint from before the model held the switch: the schedule decides.
    old = {k: v for k, v in state.items() if k != "audio_smoothing"}
    for step, want in ((60, False), (61, True)):
        again = _tiny_head()
        load_model_state(again, old, tmp_path / "x.pt", scheduled_smoothing(TrainConfig(head_iters=100, att_start=0.6), step))
        assert again.smooths_audio is want
    with pytest.raises(RunError, match="missing"):
        load_model_state(_tiny_head(), {k: v for k, v in old.items() if k != "feature_mean"}, tmp_path / "x.pt", False)


def test_npy_windows(tmp_path: Path) -> None:
    np.save(tmp_path / "aud.npy", np.zeros((10, 16, 29), np.float32))
    assert F.load_npy_windows(tmp_path / "aud.npy", 10).shape == (10, 16, 29)
    with pytest.raises(MediaError, match="10 windows but the video has 12"):
        F.load_npy_windows(tmp_path / "aud.npy", 12)
    np.save(tmp_path / "bad.npy", np.zeros((10, 29), np.float32))
    with pytest.raises(MediaError, match=r"\(N, 16, D\)"):
        F.load_npy_windows(tmp_path / "bad.npy")


def test_bad_media_gives_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(MediaError, match="missing.mp4: no such file"):
        read_video(tmp_path / "missing.mp4")
    junk = tmp_path / "junk.wav"
    junk.write_bytes(b"RIFF\x00\x00garbage" * 10)
    with pytest.raises(MediaError, match="junk.wav"):
        read_audio(junk)
    silent = write_video(tmp_path / "silent.mp4", np.zeros((5, 16, 16, 3), np.uint8), 25)
    with pytest.raises(MediaError, match="silent.mp4: has no audio track"):
        read_audio(silent)
    assert read_video(silent).audio is None
    full = write_video(tmp_path / "full.mp4", np.random.default_rng(0).integers(0, 255, (40, 64, 64, 3), dtype=np.uint8), 25, _burst_audio(0.5, 1.6), SR)
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 3])
    with pytest.raises(MediaError, match="cut.mp4"):
        read_video(cut)
    with pytest.raises(MediaError, match="frames must have shape"):
        write_video(tmp_path / "x.mp4", np.zeros((4, 4, 3), np.uint8), 25)
    assert not (tmp_path / "x.mp4").exists() and not list(tmp_path.glob(".x.*"))


def test_write_video_pads_odd_sizes(tmp_path: Path) -> None:
    p = write_video(tmp_path / "odd.mp4", np.full((3, 15, 17, 3), 200, np.uint8), 30)
    v = read_video(p)
    assert v.frames.shape == (3, 16, 18, 3)
    assert abs(int(v.frames[0, 5, 5, 0]) - 200) <= 3


def test_cli_features(tmp_path: Path, capsys) -> None:
    clip = write_video(tmp_path / "clip.mp4", np.zeros((30, 16, 16, 3), np.uint8), 25, _burst_audio(0.5, 1.2), SR)
    out = tmp_path / "f.npy"
    assert main(["features", str(clip), "-o", str(out), "--kind", "logmel"]) == 0
    assert np.load(out).shape == (30, 16, 80)
    assert "30 frames (video timestamps)" in capsys.readouterr().out
    wav = _write_wav(tmp_path / "a.wav", _burst_audio(0.3, 1.0), SR)
    assert main(["features", str(wav), "-o", str(tmp_path / "g.npy"), "--kind", "logmel", "--fps", "30"]) == 0
    assert np.load(tmp_path / "g.npy").shape == (30, 16, 80)
    silent = write_video(tmp_path / "silent.mp4", np.zeros((5, 16, 16, 3), np.uint8), 25)
    r = subprocess.run([sys.executable, "-m", "adnerf.cli", "features", str(silent), "-o", str(tmp_path / "none.npy")], capture_output=True, text=True)
    assert r.returncode == 2 and "has no audio track" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "none.npy").exists()
    assert Fraction(30000, 1001) == Fraction(30000 / 1001).limit_denominator(1001)


def test_audio_only_file_is_not_a_video(tmp_path: Path) -> None:
    wav = _write_wav(tmp_path / "only.wav", _burst_audio(0.1, 0.5), SR)
    with pytest.raises(MediaError, match="only.wav: has no video stream"):
        read_video(wav)
    with pytest.raises(MediaError, match="only.wav: has no video stream"):
        frame_times(wav)


@pytest.mark.parametrize("family", ["wav2vec2", "hubert"])
def test_local_transformers_model_round_trip(tmp_path: Path, family: str) -> None:
    transformers = pytest.importorskip("transformers")
    common = dict(hidden_size=16, num_hidden_layers=1, num_attention_heads=2, intermediate_size=32, conv_dim=(8,) * 7,
                  num_conv_pos_embeddings=16, num_conv_pos_embedding_groups=2)
    if family == "wav2vec2":
        model = transformers.Wav2Vec2Model(transformers.Wav2Vec2Config(**common))
    else:
        model = transformers.HubertModel(transformers.HubertConfig(**common))
    model.save_pretrained(tmp_path / "model")
    audio = AudioTrack(_burst_audio(0.7, 1.5), SR)
    times = np.arange(30) / 25
    spec = F.FeatureSpec("wav2vec2", model_dir=str(tmp_path / "model"))
    windows = F.speech_windows(audio, times, spec)
    assert windows.shape == (30, 16, 16) and np.isfinite(windows).all()
    # The loaded model computes what the saved one does (same weights through the loader).
    x = F.resample(audio, F.MODEL_RATE)
    ours = F.hidden_states(x, str(tmp_path / "model"))
    assert ours.shape == (len(x) // 320 + 1, 16)
    xn = torch.from_numpy(x)
    xn = torch.nn.functional.pad((xn - xn.mean()) / torch.sqrt(xn.var(unbiased=False) + 1e-7), (200, 200))
    with torch.no_grad():
        direct = model.eval()(xn[None]).last_hidden_state[0].numpy()
    np.testing.assert_allclose(ours, direct, rtol=1e-4, atol=1e-4)
    codes = AudioNet(in_dim=16)(torch.from_numpy(windows))
    assert codes.shape == (30, 64)


def test_wav2vec2_needs_a_local_model(tmp_path: Path) -> None:
    audio = AudioTrack(np.zeros(SR, np.float32), SR)
    with pytest.raises(F.FeatureError, match="model-dir"):
        F.extract_features(audio, F.FeatureSpec("wav2vec2"))
    with pytest.raises(F.FeatureError, match="no config.json"):
        F.extract_features(audio, F.FeatureSpec("wav2vec2", model_dir=str(tmp_path)))
    wav = _write_wav(tmp_path / "a.wav", np.zeros(SR), SR)
    r = subprocess.run([sys.executable, "-m", "adnerf.cli", "features", str(wav), "-o", str(tmp_path / "w.npy"), "--kind", "wav2vec2", "--model-dir", str(tmp_path / "nope")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "no config.json" in r.stderr and "Traceback" not in r.stderr
