"""Per-frame speech features: one window of audio features per video frame.

AD-NeRF feeds its audio network a window of 16 DeepSpeech frames (50 Hz, so 0.32 s) centred on
each video frame. The extractors here produce features at 50 Hz too:

* ``phonemes`` (default): the ``hama`` phoneme recogniser (its model ships inside the wheel, so
  it works offline) gives 191 IPA log-probabilities per 20 ms, the same rate and role as
  DeepSpeech's 29 character logits.
* ``logmel``: an 80-band log-mel filterbank (25 ms windows, 20 ms hop); no model at all.
* ``logmel+phonemes``: both, side by side (80 + 191 values a feature): the spectrum's loudness and
  formants with the recogniser's phoneme evidence (``docs/decisions.md``, *Phoneme evidence beside
  the log-mel*).
* ``wav2vec2``: hidden states of a wav2vec2 / HuBERT model from a *local* directory (optional
  extra ``adnerf[wav2vec2]``; nothing is downloaded).
* ``npy``: precomputed windows, e.g. AD-NeRF's ``aud.npy`` ``(N, 16, 29)``.

Alignment is by timestamps: feature ``k`` of an extractor describes the audio around
``audio.start + k / 50`` seconds; the window of a frame shown at time ``t`` is the 16 features
whose centre index is ``round((t - audio.start) * 50)``, i.e. indices ``c - 8 .. c + 7``. Indices
outside the features repeat the edge feature.

Policy for audio that does not cover the video: frames outside the audio see silence (the audio
is padded with zeros to cover every frame's window before extraction); audio beyond the last
frame is ignored.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Literal

import numpy as np
import torch

from ..atomic import atomic_path
from ..io import AudioTrack, MediaError

__all__ = [
    "BUILTIN_KINDS",
    "FEATURE_RATE",
    "StreamingWindows",
    "FeatureError",
    "WINDOW",
    "FeatureSpec",
    "extract_features",
    "frame_windows",
    "hidden_states",
    "load_npy_windows",
    "save_npy_atomic",
    "logmel",
    "phoneme_logprobs",
    "resample",
    "speech_windows",
    "voiced_loudness",
]

FEATURE_RATE = 50.0  # features per second (DeepSpeech's and hama's rate)
WINDOW = 16  # features per video frame (AD-NeRF)
MODEL_RATE = 16000  # the extractors' working sample rate
HOP = int(MODEL_RATE / FEATURE_RATE)  # 320 samples


class FeatureError(RuntimeError):
    """A feature extractor cannot run (missing package or model); the message says what to do."""


#: The extractors that need nothing but adnerf's dependencies (hama ships its model in its wheel).
BUILTIN_KINDS = ("phonemes", "logmel", "logmel+phonemes")
#: The extractors adnerf computes itself (datasets may also carry imported ``"deepspeech"`` windows).
FEATURE_KINDS = (*BUILTIN_KINDS, "wav2vec2")


@dataclass(frozen=True)
class FeatureSpec:
    """Which extractor and its settings (part of the cache key).

    Attributes:
        kind: ``"phonemes"``, ``"logmel"``, ``"logmel+phonemes"`` (the two concatenated, log-mel
            first) or ``"wav2vec2"`` (any wav2vec2 / HuBERT model that
            ``transformers.AutoModel`` loads from ``model_dir``).
        n_mels: Mel bands of ``logmel``.
        model_dir: Local model directory of ``wav2vec2`` (never downloaded).
    """

    kind: Literal["phonemes", "logmel", "logmel+phonemes", "wav2vec2"] = "phonemes"
    n_mels: int = 80
    model_dir: str | None = None


def resample(audio: AudioTrack, rate: int) -> np.ndarray:
    """The samples of ``audio`` at ``rate`` Hz, float32 (band-limited polyphase resampling)."""
    if audio.sample_rate == rate:
        return audio.samples.astype(np.float32, copy=False)
    # Band-limited polyphase resampling (scipy is a dependency of scikit-image).
    from scipy.signal import resample_poly

    g = math.gcd(int(audio.sample_rate), rate)
    return resample_poly(audio.samples.astype(np.float64), rate // g, int(audio.sample_rate) // g).astype(np.float32)


def _mel_filterbank(n_mels: int, n_fft: int, sample_rate: int, fmin: float = 20.0, fmax: float | None = None) -> torch.Tensor:
    """Triangular HTK-mel filters, shape ``(n_mels, n_fft // 2 + 1)``."""
    fmax = fmax or sample_rate / 2

    def to_mel(f: np.ndarray | float) -> np.ndarray:
        return 2595.0 * np.log10(1.0 + np.asarray(f) / 700.0)

    def to_hz(m: np.ndarray) -> np.ndarray:
        return 700.0 * (10.0 ** (m / 2595.0) - 1.0)

    edges = to_hz(np.linspace(to_mel(fmin), to_mel(fmax), n_mels + 2))
    freqs = np.linspace(0.0, sample_rate / 2, n_fft // 2 + 1)
    lo, mid, hi = edges[:-2, None], edges[1:-1, None], edges[2:, None]
    up = (freqs[None] - lo) / (mid - lo)
    down = (hi - freqs[None]) / (hi - mid)
    return torch.from_numpy(np.maximum(0.0, np.minimum(up, down))).float()


N_FFT, MEL_WIN = 512, 400  # log-mel's FFT size and Hann window (25 ms), samples at 16 kHz


def _logmel_frames(segment: np.ndarray, n_mels: int) -> np.ndarray:
    """Log-mel features ``(T, n_mels)`` of the FFT frames ``segment[k * HOP : k * HOP + N_FFT]``
    (the segment already padded: no centring here)."""
    x = torch.from_numpy(np.ascontiguousarray(segment, dtype=np.float32))
    spec = torch.stft(x, n_fft=N_FFT, hop_length=HOP, win_length=MEL_WIN, window=torch.hann_window(MEL_WIN), center=False, return_complex=True)
    mel = _mel_filterbank(n_mels, N_FFT, MODEL_RATE) @ spec.abs().square()  # (n_mels, T)
    return torch.log(mel + 1e-6).T.numpy().astype(np.float32)


def logmel(samples: np.ndarray, n_mels: int = 80) -> np.ndarray:
    """Log-mel features of 16 kHz mono audio, ``(T, n_mels)``, feature ``k`` centred at ``k * 20 ms``.

    25 ms Hann windows, 20 ms hop, ``log(mel power + 1e-6)`` (the floor is the log of silence,
    an offset on a power, not a guard inside a product). The signal is padded with half an FFT of
    silence at either end, so feature ``k`` sees the samples within 16 ms of its time and nothing
    else (:class:`StreamingWindows` computes the same features as the audio arrives).
    """
    x = np.ascontiguousarray(samples, dtype=np.float32)
    n_expected = len(x) // HOP + 1
    if len(x) < N_FFT:
        x = np.pad(x, (0, N_FFT - len(x)))
    return _logmel_frames(np.pad(x, (N_FFT // 2, N_FFT // 2)), n_mels)[:n_expected]


_HAMA_MODEL = None


def _hama_model():
    global _HAMA_MODEL
    if _HAMA_MODEL is None:
        try:
            import hama
        except ImportError as exc:
            raise MediaError("the 'phonemes' extractor needs the hama package: pip install hama (or use --kind logmel)") from exc
        _HAMA_MODEL = hama.ASRModel()
    return _HAMA_MODEL


def _chunked(samples: np.ndarray, run: Callable[[np.ndarray], np.ndarray], chunk_seconds: float, context_seconds: float, progress: Callable[[int], None] | None) -> np.ndarray:
    """Apply a 50 Hz frame model in chunks with context; ``run(piece)`` returns ``(len // 320 + 1, D)``."""
    n_out = len(samples) // HOP + 1
    chunk = max(1, int(chunk_seconds * FEATURE_RATE)) * HOP
    ctx = int(context_seconds * FEATURE_RATE) * HOP
    parts: list[np.ndarray] = []
    for start in range(0, max(len(samples), 1), chunk):
        lo = max(0, start - ctx)
        hi = min(len(samples), start + chunk + ctx)
        piece = np.ascontiguousarray(samples[lo:hi], dtype=np.float32)
        if piece.size == 0:
            piece = np.zeros(HOP, np.float32)
        frames = run(piece)
        first = (start - lo) // HOP
        own = min(chunk // HOP, n_out - start // HOP)
        parts.append(frames[first : first + own])
        if progress is not None:
            progress(min(chunk, len(samples) - start))
    out = np.concatenate(parts, axis=0).astype(np.float32)
    if out.shape[0] < n_out:  # pad a short tail by its edge frame
        out = np.concatenate([out, np.repeat(out[-1:], n_out - out.shape[0], axis=0)])
    return out[:n_out]


def phoneme_logprobs(samples: np.ndarray, *, chunk_seconds: float = 20.0, context_seconds: float = 2.0, progress: Callable[[int], None] | None = None) -> np.ndarray:
    """hama's per-frame IPA log-probabilities of 16 kHz mono audio, ``(T, 191)``, 20 ms apart.

    Long audio is processed in chunks of ``chunk_seconds`` with ``context_seconds`` of audio on
    either side, keeping only each chunk's own frames, so memory stays bounded; feature ``k`` is
    centred at ``k * 20 ms`` as for an unchunked call. The recogniser sees its whole input, so
    chunk boundaries change the output slightly: measured on 10.9 s of real speech cut into 5 s
    chunks with 2 s of context, 95% of frames keep their argmax phoneme (total variation 0.06).

    Args:
        samples: 16 kHz mono float32 audio.
        chunk_seconds: Audio per model call.
        context_seconds: Extra audio on each side of a chunk.
        progress: Called with the number of samples finished after each chunk.
    """
    model = _hama_model()

    def run(piece: np.ndarray) -> np.ndarray:
        log_probs, lengths = model.session.run(
            [model._log_probs_output_name, model._out_lengths_output_name],
            {model._waveform_input_name: piece[None], model._waveform_lengths_input_name: np.array([piece.size], dtype=np.int64)},
        )
        return np.asarray(log_probs)[0, : int(np.asarray(lengths).reshape(-1)[0])]

    return _chunked(samples, run, chunk_seconds, context_seconds, progress)


_HF_MODELS: dict[str, object] = {}


def _hf_model(model_dir: str | None):
    if not model_dir:
        raise FeatureError("the 'wav2vec2' extractor needs a local model directory (--model-dir DIR)")
    path = Path(model_dir)
    if not (path / "config.json").exists():
        raise FeatureError(f"{path}: not a transformers model directory (no config.json)")
    key = str(path.resolve())
    if key not in _HF_MODELS:
        try:
            from transformers import AutoModel
        except ImportError as exc:
            raise FeatureError("the 'wav2vec2' extractor needs transformers: pip install 'adnerf[wav2vec2]'") from exc
        try:
            model = AutoModel.from_pretrained(str(path), local_files_only=True)
        except (OSError, ValueError) as exc:
            raise FeatureError(f"{path}: cannot load the model ({exc})") from exc
        _HF_MODELS[key] = model.eval()
    return _HF_MODELS[key]


def hidden_states(samples: np.ndarray, model_dir: str, *, chunk_seconds: float = 20.0, context_seconds: float = 2.0, progress: Callable[[int], None] | None = None) -> np.ndarray:
    """Last hidden states of a local wav2vec2 / HuBERT model for 16 kHz audio, ``(T, hidden)``.

    Their convolutional front end has a 400-sample receptive field and a 320-sample stride; the
    waveform is normalised (zero mean, unit variance, as their feature extractors do) and padded
    by 200 samples on each side so that frame ``k`` is centred at ``k * 20 ms`` like the other
    extractors.
    """
    model = _hf_model(model_dir)

    def run(piece: np.ndarray) -> np.ndarray:
        x = torch.from_numpy(piece)
        x = (x - x.mean()) / torch.sqrt(x.var(unbiased=False) + 1e-7)
        x = torch.nn.functional.pad(x, (HOP * 5 // 8, HOP * 5 // 8))  # 200 samples each side
        with torch.no_grad():
            out = model(x[None].to(next(model.parameters()).dtype)).last_hidden_state[0]
        return out.float().numpy()

    return _chunked(samples, run, chunk_seconds, context_seconds, progress)


def extract_features(audio: AudioTrack, spec: FeatureSpec = FeatureSpec(), progress: Callable[[int], None] | None = None) -> np.ndarray:
    """Features at 50 Hz of an audio track, ``(T, D)``; feature ``k`` at ``audio.start + k / 50`` s."""
    samples = resample(audio, MODEL_RATE)
    if spec.kind == "logmel":
        out = logmel(samples, spec.n_mels)
        if progress is not None:
            progress(len(samples))
        return out
    if spec.kind == "phonemes":
        return phoneme_logprobs(samples, progress=progress)
    if spec.kind == "logmel+phonemes":  # both have len // HOP + 1 features centred at k * 20 ms
        return np.concatenate([logmel(samples, spec.n_mels), phoneme_logprobs(samples, progress=progress)], axis=1)
    if spec.kind == "wav2vec2":
        return hidden_states(samples, spec.model_dir or "", progress=progress)
    raise ValueError(f"unknown feature kind {spec.kind!r}; choose one of {', '.join(FEATURE_KINDS)}")


def frame_windows(features: np.ndarray, frame_times: np.ndarray, *, feature_start: float = 0.0, rate: float = FEATURE_RATE, window: int = WINDOW) -> np.ndarray:
    """Cut one window of features per video frame, centred on the frame's timestamp.

    Args:
        features: ``(T, D)`` features; feature ``k`` describes time ``feature_start + k / rate``.
        frame_times: Frame timestamps in seconds ``(N,)``.
        feature_start: Time of feature 0.
        rate: Features per second.
        window: Features per window (even: ``window // 2`` before the centre, the rest after).

    Returns:
        ``(N, window, D)`` windows; indices outside ``[0, T)`` repeat the edge feature.
    """
    if features.ndim != 2 or features.shape[0] == 0:
        raise ValueError(f"features must have shape (T >= 1, D); got {features.shape}")
    return features[_window_index(frame_times, feature_start, features.shape[0], rate, window)]


def _window_index(frame_times: np.ndarray, feature_start: float, n_features: int | None, rate: float = FEATURE_RATE, window: int = WINDOW) -> np.ndarray:
    """The feature indices ``(N, window)`` of each frame's window (:func:`frame_windows`), clipped to
    ``[0, n_features)`` (``None``: not clipped above)."""
    centre = np.rint((np.asarray(frame_times, dtype=np.float64) - feature_start) * rate).astype(np.int64)
    idx = centre[:, None] + (np.arange(window) - window // 2)[None, :]
    return np.clip(idx, 0, None if n_features is None else n_features - 1)


PAD_S = (WINDOW // 2 + 1) / FEATURE_RATE  # silence speech_windows puts around the frames' windows


def _silence_after(begin: float, before: int, n_samples: int, rate: int, start: float, last_time: float) -> int:
    """Samples of silence :func:`speech_windows` appends to a track of ``n_samples`` that starts at
    ``start`` (padded with ``before`` samples from ``begin``) so that the last frame's window fits."""
    end = max(start + n_samples / rate, last_time + PAD_S)
    return max(0, int(math.ceil((end - begin) * rate)) - before - n_samples)


def _cache_key(audio: AudioTrack, frame_times: np.ndarray, spec: FeatureSpec) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(audio.samples, dtype=np.float32).tobytes())
    h.update(np.ascontiguousarray(frame_times, dtype=np.float64).tobytes())
    model = str(Path(spec.model_dir).resolve()) if spec.model_dir else None
    h.update(json.dumps({"rate": audio.sample_rate, "start": audio.start, "kind": spec.kind, "n_mels": spec.n_mels, "model": model, "v": 1}).encode())
    return h.hexdigest()[:20]


def speech_windows(
    audio: AudioTrack,
    frame_times: np.ndarray,
    spec: FeatureSpec = FeatureSpec(),
    *,
    cache_dir: str | Path | None = None,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """Feature windows for every video frame, ``(N, 16, D)``, aligned by timestamps.

    The audio is padded with silence to cover every frame's window (see the module policy),
    features are extracted, and one window is cut per frame. With ``cache_dir``, the result is
    stored there under a key of the audio content, the frame times and the extractor settings, and
    a second call with the same inputs loads it instead of recomputing.

    Args:
        audio: The audio track.
        frame_times: Frame timestamps ``(N,)`` in seconds on the audio's clock.
        spec: Extractor and settings.
        cache_dir: Folder for cached features, or ``None``.
        progress: Called with the number of samples (at 16 kHz) finished.
    """
    frame_times = np.asarray(frame_times, dtype=np.float64)
    if frame_times.ndim != 1 or frame_times.size == 0:
        raise ValueError("frame_times must be a non-empty 1-d array")
    cache_file = None
    if cache_dir is not None:
        cache_file = Path(cache_dir) / f"features_{spec.kind}_{_cache_key(audio, frame_times, spec)}.npy"
        if cache_file.exists():
            return np.load(cache_file)
    sr = audio.sample_rate
    begin = min(audio.start, float(frame_times.min()) - PAD_S)
    before = int(round((audio.start - begin) * sr))
    after = _silence_after(begin, before, len(audio.samples), sr, audio.start, float(frame_times.max()))
    padded = AudioTrack(np.pad(audio.samples.astype(np.float32), (before, after)), sr, begin)
    feats = extract_features(padded, spec, progress)
    windows = frame_windows(feats, frame_times, feature_start=padded.start)
    if cache_file is not None:
        save_npy_atomic(cache_file, windows)
    return windows


class StreamingWindows:
    """Log-mel feature windows of speech that arrives in pieces: the windows :func:`speech_windows`
    cuts from the whole track, handed out as soon as they are final.

    Frame ``i`` shows at ``start + i / fps``. Its window holds the 16 features centred on that time
    (8 before, 7 after, 20 ms apart); the padding, the features and the cut are those of
    :func:`speech_windows` on the whole track (silence before the first sample and after the
    last), so the windows equal the offline ones exactly. A window is final once the audio
    reaches :attr:`lookahead_s` past its frame's time: its last feature (140 ms on) and half an
    FFT more (16 ms), rounded to the feature grid; only the last frames wait for :meth:`finish`.

    Args:
        fps: Video frame rate.
        start: Time of the first sample and of frame 0, seconds.
        n_mels: Mel bands.
    """

    def __init__(self, fps: float, *, start: float = 0.0, n_mels: int = 80) -> None:
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a positive number; got {fps}")
        self.fps, self.start, self.n_mels = float(fps), float(start), int(n_mels)
        self._begin = min(self.start, self.start - PAD_S)  # speech_windows' padded.start (frame 0 at start)
        self._before = int(round((self.start - self._begin) * MODEL_RATE))
        # The padded signal, itself padded by half an FFT on the left (logmel's centring), from
        # sample _xp_from on: what the next feature's FFT and later ones read.
        self._xp = np.zeros(N_FFT // 2 + self._before, np.float32)
        self._xp_from = 0
        self._pushed = 0
        self._n_feats = 0  # features computed
        self._feats = np.zeros((0, self.n_mels), np.float32)  # features _feats_from .. _n_feats - 1: those windows to come read
        self._feats_from = 0
        self._done = 0  # windows handed out
        self.finished = False

    @property
    def lookahead_s(self) -> float:
        """Seconds of audio past a frame's time that its window waits for (at most)."""
        return (WINDOW - WINDOW // 2 - 1) / FEATURE_RATE + (N_FFT // 2) / MODEL_RATE + 1.0 / FEATURE_RATE

    @property
    def frames_done(self) -> int:
        """Windows handed out so far (frames ``0 .. frames_done - 1``)."""
        return self._done

    def _times(self, first: int, last: int) -> np.ndarray:
        return self.start + np.arange(first, last, dtype=np.float64) / self.fps

    def _features_to(self, count: int) -> None:
        k = self._n_feats
        if count > k:
            a = k * HOP - self._xp_from
            segment = self._xp[a : a + (count - 1 - k) * HOP + N_FFT]
            self._feats = np.concatenate([self._feats, _logmel_frames(segment, self.n_mels)])
            self._n_feats = count
            drop = count * HOP - self._xp_from  # the next feature's FFT starts there
            self._xp, self._xp_from = self._xp[drop:], self._xp_from + drop

    def _hand_out(self, last: int, n_features: int | None) -> np.ndarray:
        """The windows of frames ``_done .. last - 1`` (indices clipped to ``n_features``), and the
        features no later window reads let go."""
        if last <= self._done:
            return np.zeros((0, WINDOW, self.n_mels), np.float32)
        idx = _window_index(self._times(self._done, last), self._begin, n_features)
        out = self._feats[idx - self._feats_from]
        self._done = last
        keep = int(_window_index(self._times(last, last + 1), self._begin, n_features)[0, 0])  # the next window's first feature
        if keep > self._feats_from:
            self._feats, self._feats_from = self._feats[keep - self._feats_from :], keep
        return out

    def push(self, samples: np.ndarray) -> np.ndarray:
        """Add 16 kHz mono samples; the windows that became final, ``(m, 16, n_mels)``, in frame order."""
        if self.finished:
            raise ValueError("the stream has finished; start another")
        x = np.asarray(samples, dtype=np.float32).reshape(-1)
        self._xp = np.concatenate([self._xp, x])
        self._pushed += len(x)
        known = self._before + self._pushed  # samples of the padded signal that are final
        final = (known - N_FFT // 2) // HOP + 1 if known >= N_FFT // 2 else 0  # features whose FFT lies in them
        self._features_to(final)
        exist = int(math.floor(self._pushed / MODEL_RATE * self.fps))  # frames the audio already covers
        ready = self._done
        while ready < exist and _window_index(self._times(ready, ready + 1), self._begin, None)[0, -1] < final:
            ready += 1
        return self._hand_out(ready, None)

    def finish(self) -> np.ndarray:
        """End of the speech: the remaining windows (the track padded with silence as
        :func:`speech_windows` pads it)."""
        if self.finished:
            return np.zeros((0, WINDOW, self.n_mels), np.float32)
        self.finished = True
        n = int(math.floor(self._pushed / MODEL_RATE * self.fps))
        if n < 1:
            return np.zeros((0, WINDOW, self.n_mels), np.float32)
        after = _silence_after(self._begin, self._before, self._pushed, MODEL_RATE, self.start, self.start + (n - 1) / self.fps)
        padded = self._before + self._pushed + after
        if padded < N_FFT:  # logmel's own padding of a signal shorter than an FFT
            after += N_FFT - padded
        self._xp = np.concatenate([self._xp, np.zeros(after + N_FFT // 2, np.float32)])
        total = padded // HOP + 1
        self._features_to(total)
        return self._hand_out(n, total)


def save_npy_atomic(path: str | Path, array: np.ndarray) -> Path:
    """Write ``array`` to ``path`` (.npy) through a temporary file renamed into place.

    A reader never sees a half-written file, and a failure leaves no file at ``path``.
    """
    with atomic_path(path) as tmp:
        np.save(tmp, array)
    return Path(path)


def load_npy_windows(path: str | Path, n_frames: int | None = None) -> np.ndarray:
    """Load precomputed windows (e.g. AD-NeRF's DeepSpeech ``aud.npy``), ``(N, 16, D)``.

    Raises:
        MediaError: The file is missing or unreadable, or its shape is not ``(N, 16, D)`` with
            ``N == n_frames`` (when given).
    """
    p = Path(path)
    if not p.exists():
        raise MediaError(f"{p}: no such file")
    try:
        arr = np.load(p)
    except (ValueError, OSError) as exc:
        raise MediaError(f"{p}: not a readable .npy array ({exc})") from exc
    if arr.ndim != 3 or arr.shape[1] != WINDOW:
        raise MediaError(f"{p}: expected feature windows of shape (N, {WINDOW}, D); got {arr.shape}")
    if n_frames is not None and arr.shape[0] != n_frames:
        raise MediaError(f"{p}: has {arr.shape[0]} windows but the video has {n_frames} frames")
    return arr.astype(np.float32)


def voiced_loudness(samples: np.ndarray, rate: int, times: np.ndarray, window: float = 0.06) -> np.ndarray:
    """How loud the voiced band (150-1000 Hz, where vowels carry their energy) is around each
    time: the band's RMS over ``window`` seconds centred there, divided by its 98th percentile
    over the clip and clipped to [0, 1] (all zeros for silence).

    The synthetic scene's loudness-driven jaw, and the speech activity that a rendered mouth is
    compared with when no truth of the mouth exists (driving by another voice).

    Args:
        samples: ``(n,)`` mono samples.
        rate: Their sample rate.
        times: ``(m,)`` seconds from the first sample.
        window: Seconds of audio per value.
    """
    from scipy.signal import butter, sosfiltfilt

    sos = butter(4, [150, 1000], btype="bandpass", fs=rate, output="sos")
    band = sosfiltfilt(sos, np.asarray(samples, dtype=np.float64))
    energy = np.concatenate([[0.0], np.cumsum(band**2)])
    half = int(window * rate / 2)
    centre = np.round(np.asarray(times) * rate).astype(int)
    lo = np.clip(centre - half, 0, len(band))
    hi = np.clip(centre + half, 0, len(band))
    rms = np.sqrt(np.maximum(energy[hi] - energy[lo], 0.0) / np.maximum(hi - lo, 1))
    ref = np.percentile(rms, 98)
    if ref <= 0:
        return np.zeros_like(rms)
    return np.clip(rms / ref, 0.0, 1.0)
