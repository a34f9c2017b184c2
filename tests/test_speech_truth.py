"""The synthetic scene's speech truth: espeak-ng's phoneme timings, the viseme track, and the jaw
of the rendered frames, all aligned to the audio to the frame."""

from __future__ import annotations

import numpy as np
import pytest

from adnerf.audio.espeak import PAUSE, EspeakError, Phoneme, espeak_ready, speak
from adnerf.audio.features import voiced_loudness
from adnerf.audio.visemes import jaw_target, jaw_track

needs_espeak = pytest.mark.skipif(not espeak_ready(), reason="espeak-ng's library is not installed (apt install espeak-ng)")


# ----------------------------------------------------------------------------------- visemes


def test_jaw_targets_follow_articulation() -> None:
    assert jaw_target("p") == jaw_target("b") == jaw_target("m") == 0.0  # lips closed
    assert jaw_target(PAUSE) == 0.0
    assert jaw_target("ɑː") == jaw_target("ˈa") == 1.0  # length and stress marks ignored
    assert jaw_target("aɪ") == 1.0  # a diphthong starts at its first vowel
    assert jaw_target("ɑ") > jaw_target("ɛ") > jaw_target("ɪ") > jaw_target("f") > jaw_target("m")
    assert jaw_target("ʉ") == 0.2 and jaw_target("ɤ") == 0.2  # not in the table: a consonant's opening


def test_jaw_track_holds_targets_and_smooths_symmetrically() -> None:
    phonemes = [Phoneme(0.10, "m"), Phoneme(0.20, "ɑː"), Phoneme(0.40, "p"), Phoneme(0.50, PAUSE)]
    t = np.array([0.05, 0.15, 0.25, 0.35, 0.45, 0.55])
    np.testing.assert_allclose(jaw_track(phonemes, t, end=0.6, smoothing=0.0), [0, 0, 1, 1, 0, 0])
    # Smoothed, the vowel's span [0.2, 0.4) peaks at its centre and is symmetric about it.
    fine = np.linspace(0.1, 0.5, 401)
    smooth = jaw_track(phonemes, fine, end=0.6, smoothing=0.03)
    assert abs(fine[np.argmax(smooth)] - 0.30) < 0.002
    np.testing.assert_allclose(jaw_track(phonemes, 0.3 - np.array([0.05, 0.08]), end=0.6), jaw_track(phonemes, 0.3 + np.array([0.05, 0.08]), end=0.6), atol=1e-9)
    assert smooth.min() >= 0.0 and smooth.max() <= 1.0
    # Before the first phoneme and after the end the mouth is closed.
    np.testing.assert_allclose(jaw_track(phonemes, np.array([-1.0, 2.0]), end=0.6), [0.0, 0.0], atol=1e-12)


def test_jaw_track_refuses_unordered_phonemes() -> None:
    with pytest.raises(ValueError, match="order"):
        jaw_track([Phoneme(0.3, "a"), Phoneme(0.1, "m")], np.array([0.2]))
    assert np.all(jaw_track([], np.array([0.0, 1.0])) == 0.0)


# ------------------------------------------------------------------------------------ espeak


@needs_espeak
def test_speak_reports_phonemes_in_audio_time() -> None:
    u = speak("Ah, mama.")
    names = [p.ipa for p in u.phonemes]
    assert u.sample_rate == 22050 and u.duration > 0.5
    assert jaw_target(names[0]) == 1.0 and "m" in names and PAUSE in names
    starts = np.array([p.start for p in u.phonemes])
    assert np.all(np.diff(starts) >= 0) and 0 <= starts[0] and starts[-1] <= u.duration
    # The first phoneme, a vowel, starts where the sound starts: within half a 25 fps frame.
    env = np.convolve(u.samples.astype(np.float64) ** 2, np.ones(110) / 110, mode="same")
    onset = np.argmax(env > 0.02 * env.max()) / u.sample_rate
    assert abs(onset - starts[0]) < 0.02


@needs_espeak
def test_speak_rate_changes_timing_not_phonemes() -> None:
    slow, fast = speak("open your mouth", words_per_minute=120), speak("open your mouth", words_per_minute=240)
    assert [p.ipa for p in slow.phonemes] == [p.ipa for p in fast.phonemes]
    assert fast.duration < 0.75 * slow.duration


@needs_espeak
def test_speak_refuses_bad_requests() -> None:
    with pytest.raises(EspeakError, match="no voice"):
        speak("hello", voice="no-such-voice")
    with pytest.raises(ValueError):
        speak("   ")
    with pytest.raises(ValueError):
        speak("hello", words_per_minute=20)


@needs_espeak
@pytest.mark.parametrize("fps", [25.0, 30.0])
def test_vowel_opens_the_mouth_in_the_frame_where_it_is_spoken(fps: float) -> None:
    """A known phoneme at a known time: "Ah." said over and over, with pauses between. Each "ah"
    opens the jaw past half in exactly the first frame (at 25 and at 30 fps) at or after the vowel's start and
    closes it below half in the first frame at or after its end (the smoothing is symmetric, so
    half-open is the moment the phoneme starts), and the audio's voiced band is loud in the
    vowel's frames and quiet in the pauses: truth, audio and frames share one clock."""
    from adnerf.synth import espeak_speech

    speech = espeak_speech(3.0, seed=0, sentences=["Ah."])
    times = np.arange(int(3.0 * fps)) / fps
    jaw = jaw_track(speech.phonemes, times, end=3.0)
    loud = voiced_loudness(speech.samples, 16000, times, window=0.03)
    phonemes = list(speech.phonemes)
    vowels = [(a.start, b.start) for a, b in zip(phonemes, phonemes[1:]) if jaw_target(a.ipa) == 1.0 and b.start - a.start > 0.15 and 0.1 < a.start and b.start < 2.9]
    assert len(vowels) >= 3
    for start, end in vowels:
        k_open, k_close = int(np.ceil(start * fps)), int(np.ceil(end * fps))  # first frames at or after
        assert jaw[k_open - 1] < 0.5 <= jaw[k_open], (start, jaw[k_open - 1 : k_open + 1])
        assert jaw[k_close - 1] >= 0.5 > jaw[k_close], (end, jaw[k_close - 1 : k_close + 1])
        assert loud[k_open + 1 : (k_open + k_close) // 2 + 1].min() > 0.5  # loud from the next frame on (it fades at its end)
    pauses = jaw < 0.02
    assert pauses.any() and loud[pauses].max() < 0.1


@needs_espeak
def test_synthetic_scene_jaw_is_the_viseme_track(tmp_path) -> None:
    from adnerf.evaluation.evaluate import mouth_boxes, mouth_darkness
    from adnerf.evaluation.landmark_metrics import pearson
    from adnerf.formats.dataset import load_dataset
    from adnerf.synth import SynthConfig, espeak_speech, synthesize

    cfg = SynthConfig(seconds=4.0, size=64, seed=3, speaker="en+f3", words_per_minute=170)
    ds = load_dataset(synthesize(tmp_path / "s", cfg))
    assert "mouth=visemes" in ds.meta.source and "speaker=en+f3" in ds.meta.source
    speech = espeak_speech(4.0, seed=3, speaker="en+f3", words_per_minute=170)
    times = np.arange(ds.meta.n_frames) / ds.meta.fps
    np.testing.assert_allclose(ds.truth.jaw, jaw_track(speech.phonemes, times, end=4.0))
    np.testing.assert_allclose(ds.audio.samples, speech.samples, atol=1e-4)
    # The frames show it: the mouth crop is darker where the jaw is open.
    frames = list(range(ds.meta.n_frames))
    dark = [mouth_darkness(ds.frames[i][y0:y1, x0:x1]) for i, (x0, y0, x1, y1) in zip(frames, mouth_boxes(ds, frames))]
    assert pearson(dark, ds.truth.jaw) > 0.5  # 0.66 here; 0.87 at 128 px over 30 s


def test_formant_scene_keeps_the_loudness_jaw(tmp_path) -> None:
    from adnerf.formats.dataset import load_dataset
    from adnerf.synth import SynthConfig, mouth_opening, synthesize

    ds = load_dataset(synthesize(tmp_path / "f", SynthConfig(seconds=2.0, size=32, voice="formant")))
    assert "mouth=loudness" in ds.meta.source
    times = np.arange(ds.meta.n_frames) / ds.meta.fps
    np.testing.assert_allclose(ds.truth.jaw, mouth_opening(ds.audio.samples, ds.audio.sample_rate, times), atol=1e-4)  # the WAV holds 16-bit samples
    with pytest.raises(ValueError, match="visemes"):
        SynthConfig(voice="formant", mouth="visemes").validate()
    with pytest.raises(ValueError, match="words_per_minute"):
        SynthConfig(words_per_minute=20).validate()


# ------------------------------------------------------------------------------ bench voices


def test_jaw_reader_reads_the_opening_off_exact_renders(tmp_path) -> None:
    from adnerf.bench.voices import JawReader
    from adnerf.formats.dataset import load_dataset
    from adnerf.synth import (
        HeadModel,
        SynthConfig,
        TorsoModel,
        render_frame,
        synthesize,
    )

    ds = load_dataset(synthesize(tmp_path / "s", SynthConfig(seconds=1.0, size=64, voice="formant", seed=1)))
    poses = ds.poses[[0, 12, 24]]
    reader = JawReader(ds, poses)
    head, torso = HeadModel(64), TorsoModel(64)
    plate = ds.background / 255.0
    truth = np.array([0.0, 0.33, 0.52, 0.9, 1.0, 0.71])
    which = np.array([0, 1, 2, 0, 1, 2])
    frames = np.stack([np.round(np.clip(render_frame(head, torso, poses[p], o, plate)[0], 0, 1) * 255).astype(np.uint8) for p, o in zip(which, truth)])
    # Within 0.02 (measured: 0.014 at most) of the truth between grid openings 0.05 apart: the
    # parabola refines the nearest template (a refinement of the wrong sign is 0.038 off).
    np.testing.assert_allclose(reader.read(frames, which), truth, atol=0.02)
    # Read with the wrong pose's templates, the answer is another one: the pose matters.
    assert np.abs(reader.read(frames, (which + 1) % 3) - truth).max() > 0.04


@needs_espeak
def test_bench_voices_runs_end_to_end(tmp_path, capsys) -> None:
    import json

    from adnerf.cli import main

    argv = ["bench", "voices", "--work", str(tmp_path / "w"), "--seconds", "5", "--drive-seconds", "1", "--size", "32", "--iters", "8,4", "--json"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [r["voice"] for r in result["rows"]] == ["A, new sentences", "A, faster (210 wpm)", "B, female (en+f3)", "C, US klatt (en-us+klatt)"]
    for row in result["rows"]:
        assert row["frames"] == 25 and row["reader_on_truth"]["corr"] > 0.9  # the measure itself is sound
        for kind in ("logmel", "phonemes"):
            assert set(row[kind]) == {"corr", "offset", "corr_at_offset", "mean_abs_error"}
    assert (tmp_path / "w" / "bench_voices.png").stat().st_size > 0
    assert main([*argv[:-1], "--iters", "8"]) == 2  # HEAD,TORSO: two numbers


@needs_espeak
def test_synth_refuses_an_unknown_speaker_before_writing(tmp_path, capsys) -> None:
    from adnerf.cli import main

    assert main(["synth", "-o", str(tmp_path / "s"), "--seconds", "1", "--size", "16", "--speaker", "no-such-voice"]) == 2
    assert "no voice 'no-such-voice'" in capsys.readouterr().err and not (tmp_path / "s").exists()
    assert main(["synth", "-o", str(tmp_path / "s"), "--voice", "formant", "--mouth", "visemes"]) == 2
    assert not (tmp_path / "s").exists()
