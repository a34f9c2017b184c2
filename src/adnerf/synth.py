"""A synthetic talking head with exact ground truth: the built-in default scene.

The scene is built with trimesh and rendered by ray casting (Embree through ``embreex`` when it is
installed, trimesh's pure-python intersector otherwise), one ray per pixel centre, so that the
dataset is exactly what a radiance field rendered with our cameras can reproduce:

* a head (an ellipsoid mesh, 1.6 x 2.0 x 1.8 units) whose front carries the face of
  ``skimage.data.astronaut()`` (a real photograph that ships with scikit-image) and whose back
  carries hair sampled from the same photograph; colours are a function of the *rest* surface
  point (shading baked in canonical space), so the head is rigid in its canonical frame except for
* a jaw: the lower face rotates about a hinge behind the mouth by an angle proportional to the
  mouth opening, and a dark mouth interior painted at the lips grows with it;
* eyelids: skin-coloured lids close over both eyes from the top with a dark lash line at their
  edge, in blinks at random times independent of the speech (:func:`adnerf.model.blinks.blink_track`: one
  every 2-6 s, 0.2 s long), with the eye openness of every frame as exact truth;
* a torso (neck and shoulders wearing the photograph's orange suit) in camera space, whose smaller
  motion is a fixed function of the head pose (so a field conditioned on the pose can learn it);
* a static background (``skimage.data.rocket()``), a smooth random head pose track, and
* an audio track: real synthetic speech from espeak-ng (its library, which also reports when each
  phoneme is spoken; :mod:`adnerf.audio.espeak`) in any of its voices and rates, or, where espeak-ng is
  missing, speech-like sound (glottal pulses through vowel formants, bursts and pauses).

The jaw follows *what is said*, not how loud: with espeak-ng speech the opening of each frame is
the viseme track of the phonemes being spoken (:mod:`adnerf.audio.visemes`: closed lips for p / b / m,
wide open for "ah", smoothed as articulators move), so the same sentences in another voice or at
another speed have their own exact truth. Formant sound has no phonemes; its jaw opens with the
normalised loudness of the voiced band (150-1000 Hz), as ``mouth="loudness"`` does for any audio.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np
import trimesh

from .audio.espeak import PAUSE, Phoneme, espeak_ready, speak
from .audio.features import FeatureSpec, resample, speech_windows, voiced_loudness
from .audio.visemes import jaw_track
from .io import AudioTrack, write_video
from .lock import writes_folder
from .threads import in_threads
from .model.blinks import blink_track
from .formats.dataset import (
    LABEL_HEAD,
    LABEL_TORSO,
    DatasetFolder,
    SceneMeta,
    Truth,
    save_dataset,
    tail_split,
)
from .formats.outputs import check_folder_output

__all__ = ["SynthConfig", "Speech", "HeadModel", "TorsoModel", "background_plate", "blink_track", "eye_centres", "espeak_speech", "jaw_opening", "render_frame", "speech_audio", "mouth_opening", "pose_track", "synthesize"]

SAMPLE_RATE = 16000
HEAD_RADII = np.array([0.8, 1.0, 0.9])
HEAD_AABB = ((-0.95, -1.15, -1.05), (0.95, 1.35, 1.05))
MOUTH = (0.0, 0.42, -0.82)
HEAD_CENTER = np.array([0.0, -0.45, 6.0])
TORSO_AABB = ((-2.6, -0.2, 5.2), (2.6, 3.0, 7.4))
NEAR, FAR = 4.0, 8.5
FOCAL_PER_PIXEL = 1.33  # fx = fy = 1.33 * size: the frame spans 4.5 units at the head's distance
JAW_MAX_ANGLE = 0.14  # radians at full opening: the chin drops by about 7% of the head height
# The photograph's eyes on the rest surface (x, y) and the semi-axes of the lids' ellipses.
EYES = ((-0.195, -0.04), (0.203, -0.04))
EYE_AXES = (0.09, 0.055)
_LIGHT = np.array([-0.35, -0.5, -1.0]) / np.linalg.norm([-0.35, -0.5, -1.0])

SENTENCES = [
    "The quick brown fox jumps over the lazy dog.",
    "A radiance field can learn how a talking face looks from every side.",
    "Open your mouth wide and say ah, then close it again.",
    "We rendered the astronaut speaking words she never said.",
    "Every video frame hears a short window of the sound around it.",
    "Numbers like one, two, three and four are easy to hear.",
    "Bright colours and soft shadows make the picture look real.",
    "Please speak slowly, pause often, and smile at the camera.",
]


# Ranges of the synthetic scene's settings: a scene is held in memory while it is rendered
# (1024 px for 600 s at 25 fps would be 47 GB of frames alone), so their product is bounded too.
SYNTH_LIMITS: dict[str, tuple[float, float]] = {"seconds": (1.0, 600.0), "size": (16, 1024), "fps": (1.0, 120.0)}
SYNTH_MAX_PIXELS = 1e9  # frames x width x height: about 8 GB of frames, labels and depth


@dataclass
class SynthConfig:
    """Parameters of a synthetic scene.

    Attributes:
        seconds: Length of the video.
        size: Frame width and height in pixels.
        fps: Frame rate.
        seed: Seed of the pose track and the speech.
        voice: ``"formant"`` (built-in speech-like sound), ``"espeak"`` (espeak-ng speech; must be
            installed) or ``"auto"`` (espeak-ng when installed).
        speaker: espeak-ng voice of the speech (``"en"``, ``"en+f3"`` ...).
        words_per_minute: Speaking rate of the espeak-ng speech.
        mouth: What opens the jaw: ``"visemes"`` (the phonemes being spoken, from espeak-ng's
            timings; see :mod:`adnerf.audio.visemes`), ``"loudness"`` (the voiced band's loudness) or
            ``"auto"`` (visemes for espeak-ng speech, loudness for formant sound).
        features: Audio feature kind stored with the dataset (see :class:`FeatureSpec`).
        test_fraction: Fraction of frames, at the end of the clip, held out for testing.
        max_yaw: Amplitude of the head's yaw in degrees (pitch and roll are smaller).
        blinks: Whether the eyes blink (:func:`adnerf.model.blinks.blink_track`); off: always open.
    """

    seconds: float = 18.0
    size: int = 128
    fps: float = 25.0
    seed: int = 0
    voice: str = "auto"
    speaker: str = "en"
    words_per_minute: int = 150
    mouth: str = "auto"
    features: str = "logmel"
    test_fraction: float = 0.15
    max_yaw: float = 20.0
    blinks: bool = True

    @property
    def n_frames(self) -> int:
        """Frames of the video: ``seconds * fps``, rounded."""
        return int(round(self.seconds * self.fps))

    def validate(self) -> None:
        """Raise ``ValueError`` on impossible settings (ranges in :data:`SYNTH_LIMITS`)."""
        for name, (lo, hi) in SYNTH_LIMITS.items():
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi):
                raise ValueError(f"{name} must lie in [{lo:g}, {hi:g}]; got {value!r}")
        if not 0.0 < self.test_fraction < 1.0:
            raise ValueError(f"test_fraction must lie in (0, 1); got {self.test_fraction}")
        if self.voice not in ("auto", "formant", "espeak"):
            raise ValueError(f"voice must be auto, formant or espeak; got {self.voice!r}")
        if self.mouth not in ("auto", "visemes", "loudness"):
            raise ValueError(f"mouth must be auto, visemes or loudness; got {self.mouth!r}")
        if self.mouth == "visemes" and self.voice == "formant":
            raise ValueError("mouth='visemes' needs espeak-ng speech (voice 'espeak' or 'auto'); formant sound has no phonemes")
        if not (isinstance(self.words_per_minute, int) and 80 <= self.words_per_minute <= 450):
            raise ValueError(f"words_per_minute must be an integer in [80, 450]; got {self.words_per_minute!r}")
        if self.features not in ("logmel", "phonemes"):
            raise ValueError(f"features must be logmel or phonemes; got {self.features!r}")
        if self.n_frames * self.size**2 > SYNTH_MAX_PIXELS:
            raise ValueError(f"{self.n_frames} frames of {self.size}x{self.size} pixels would not fit in memory; make the scene shorter or smaller")


# ----------------------------------------------------------------------------------------- audio

_VOWELS = {  # (F1, F2, F3) in Hz and how open the mouth is
    "a": (750, 1200, 2500),
    "e": (500, 1800, 2500),
    "i": (300, 2250, 3000),
    "o": (500, 900, 2400),
    "u": (320, 800, 2300),
}


def _resonator(x: np.ndarray, freq: float, bandwidth: float, rate: int) -> np.ndarray:
    from scipy.signal import lfilter

    r = math.exp(-math.pi * bandwidth / rate)
    c = 2 * r * math.cos(2 * math.pi * freq / rate)
    return lfilter([1 - r], [1.0, -c, r * r], x)


def formant_speech(seconds: float, rate: int = SAMPLE_RATE, seed: int = 0) -> np.ndarray:
    """Speech-like sound: phrases of vowel syllables (glottal pulses through three formants),
    noise bursts as consonants, and pauses between phrases. Returns float32 ``(n,)`` in [-1, 1]."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds * rate))
    out = np.zeros(n)
    t = 0.25
    while t < seconds - 0.4:
        for _ in range(int(rng.integers(3, 8))):
            dur = float(rng.uniform(0.12, 0.32))
            if t + dur > seconds - 0.2:
                break
            start = int(t * rate)
            if rng.random() < 0.6:  # a consonant: a short noise burst
                m = int(rng.uniform(0.03, 0.07) * rate)
                burst = rng.standard_normal(m) * np.hanning(m) * 0.05
                out[start : start + m] += np.diff(burst, prepend=0.0)
                start += m
            m = int(dur * rate)
            f0 = rng.uniform(105, 145) * (1 + 0.08 * np.linspace(0.5, -0.5, m))
            phase = np.cumsum(f0 / rate)
            source = np.diff(np.floor(phase), prepend=0.0)  # one impulse per glottal period
            f1, f2, f3 = _VOWELS[str(rng.choice(list(_VOWELS)))]
            voice = _resonator(source, f1, 90, rate) + 0.6 * _resonator(source, f2, 110, rate) + 0.3 * _resonator(source, f3, 150, rate)
            ramp = min(int(0.04 * rate), m // 3)
            env = np.ones(m)
            env[:ramp] = np.sin(np.linspace(0, np.pi / 2, ramp)) ** 2
            env[-ramp:] = env[:ramp][::-1]
            voice = voice * env * rng.uniform(0.3, 1.0)
            out[start : start + m] += voice[: max(0, min(m, n - start))]
            t = (start + m) / rate + float(rng.uniform(0.0, 0.06))
        t += float(rng.uniform(0.25, 0.7))
    peak = np.abs(out).max()
    return (0.8 * out / peak if peak > 0 else out).astype(np.float32)


def espeak_available() -> bool:
    """Whether espeak-ng's library can speak here (see :mod:`adnerf.audio.espeak`)."""
    return espeak_ready()


@dataclass(frozen=True)
class Speech:
    """The scene's audio and what is known of what it says.

    Attributes:
        samples: ``(n,)`` float32 mono samples at :data:`SAMPLE_RATE`, peak 0.8.
        voice: ``"espeak"`` or ``"formant"``.
        phonemes: For espeak-ng speech, every phoneme with its start time in seconds from the
            first sample (pauses between sentences included); ``None`` for formant sound.
    """

    samples: np.ndarray
    voice: str
    phonemes: tuple[Phoneme, ...] | None = None


def espeak_speech(seconds: float, rate: int = SAMPLE_RATE, seed: int = 0, *, speaker: str = "en", words_per_minute: int = 150, sentences: Sequence[str] = SENTENCES) -> Speech:
    """Real synthetic speech from espeak-ng: ``sentences`` in an order drawn from ``seed``,
    separated by pauses of 0.25-0.6 s, cut or padded to ``seconds``, with each phoneme's time.

    Args:
        seconds: Length of the audio.
        rate: Sample rate of the result.
        seed: Seed of the sentence order and the pauses.
        speaker: espeak-ng voice (``"en"``, ``"en+f3"`` ...; see :func:`adnerf.audio.espeak.speak`).
        words_per_minute: Speaking rate.
        sentences: What is said, repeated as needed.
    """
    if not espeak_available():
        raise RuntimeError("espeak-ng is not installed (apt install espeak-ng), or use voice='formant'")
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(sentences))
    want = int(round(seconds * rate))
    pieces: list[np.ndarray] = []
    phonemes: list[Phoneme] = []
    total, k = 0, 0
    while total < want:
        said = speak(sentences[order[k % len(order)]], speaker, words_per_minute)
        samples = resample(AudioTrack(said.samples, said.sample_rate, 0.0), rate)
        phonemes += [Phoneme(total / rate + p.start, p.ipa) for p in said.phonemes]
        pause = np.zeros(int(rng.uniform(0.25, 0.6) * rate), dtype=np.float32)
        phonemes.append(Phoneme((total + len(samples)) / rate, PAUSE))
        pieces += [samples, pause]
        total += len(samples) + len(pause)
        k += 1
    out = np.concatenate(pieces)[:want]
    out = np.pad(out, (0, want - len(out)))
    peak = np.abs(out).max()
    out = (0.8 * out / peak if peak > 0 else out).astype(np.float32)
    return Speech(out, "espeak", tuple(p for p in phonemes if p.start < seconds))


def speech_audio(seconds: float, voice: str = "auto", seed: int = 0, rate: int = SAMPLE_RATE, *, speaker: str = "en", words_per_minute: int = 150) -> Speech:
    """The scene's audio: espeak-ng speech (``voice`` ``"espeak"``, or ``"auto"`` where espeak-ng
    is installed; ``speaker`` and ``words_per_minute`` as in :func:`espeak_speech`) or the
    built-in formant sound."""
    if voice == "espeak" or (voice == "auto" and espeak_available()):
        return espeak_speech(seconds, rate, seed, speaker=speaker, words_per_minute=words_per_minute)
    return Speech(formant_speech(seconds, rate, seed), "formant")


def jaw_opening(speech: Speech, times: np.ndarray, mouth: str = "auto") -> tuple[np.ndarray, str]:
    """The scene's jaw opening in [0, 1] at ``times`` and what drove it (``"visemes"`` or
    ``"loudness"``; ``mouth`` as in :class:`SynthConfig`).

    Raises:
        ValueError: ``mouth="visemes"`` for speech without phoneme timings.
    """
    if mouth == "visemes" or (mouth == "auto" and speech.phonemes is not None):
        if speech.phonemes is None:
            raise ValueError("mouth='visemes' needs speech with phoneme timings (espeak-ng)")
        return jaw_track(speech.phonemes, times, end=len(speech.samples) / SAMPLE_RATE), "visemes"
    return mouth_opening(speech.samples, SAMPLE_RATE, times), "loudness"


def mouth_opening(samples: np.ndarray, rate: int, times: np.ndarray, window: float = 0.06) -> np.ndarray:
    """The loudness-driven jaw: :func:`adnerf.audio.features.voiced_loudness` (the voiced band's RMS
    around each time, normalised by its 98th percentile over the clip, in [0, 1])."""
    return voiced_loudness(samples, rate, times, window)


# ------------------------------------------------------------------------------------------ pose


def _euler(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``R_y(yaw) R_x(pitch) R_z(roll)`` (radians), the convention of :func:`adnerf.pose.euler_rotation`."""
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    one, zero = np.ones_like(yaw), np.zeros_like(yaw)
    Ry = np.stack([np.stack([cy, zero, sy], -1), np.stack([zero, one, zero], -1), np.stack([-sy, zero, cy], -1)], -2)
    Rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, cp, -sp], -1), np.stack([zero, sp, cp], -1)], -2)
    Rz = np.stack([np.stack([cr, -sr, zero], -1), np.stack([sr, cr, zero], -1), np.stack([zero, zero, one], -1)], -2)
    return Ry @ Rx @ Rz


def _smooth_signal(n: int, fps: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth signal in [-1, 1]: three sinusoids of random frequencies (0.05-0.35 Hz) and phases."""
    t = np.arange(n) / fps
    s = sum(rng.uniform(0.5, 1.0) * np.sin(2 * np.pi * rng.uniform(0.05, 0.35) * t + rng.uniform(0, 2 * np.pi)) for _ in range(3))
    return s / max(np.abs(s).max(), 1e-9)


def pose_track(n: int, fps: float, seed: int = 0, max_yaw: float = 20.0) -> np.ndarray:
    """A smooth random head pose track ``(n, 4, 4)`` (head-canonical to camera).

    Yaw spans ``±max_yaw`` degrees, pitch half of it, roll a fifth; the head centre moves by up to
    0.08 units around :data:`HEAD_CENTER`.
    """
    rng = np.random.default_rng(seed + 1)
    yaw, pitch, roll = (np.deg2rad(max_yaw * f) * _smooth_signal(n, fps, rng) for f in (1.0, 0.5, 0.2))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = _euler(yaw, pitch, roll)
    poses[:, :3, 3] = HEAD_CENTER + 0.08 * np.stack([_smooth_signal(n, fps, rng) for _ in range(3)], -1)
    return poses


def torso_pose(head_pose: np.ndarray) -> np.ndarray:
    """The torso's rigid transform (torso frame -> camera) as a fixed function of the head pose:
    a third of the head's translation offset, a tenth of its yaw and a quarter of its roll
    (shoulders turn far less than the head)."""
    R = head_pose[:3, :3]
    yaw = math.atan2(R[0, 2], R[2, 2])
    roll = math.atan2(R[1, 0], R[1, 1])
    out = np.eye(4)
    out[:3, :3] = _euler(np.array(0.1 * yaw), np.array(0.0), np.array(0.25 * roll))
    out[:3, 3] = np.array([0.0, 1.2, 6.35]) + (head_pose[:3, 3] - HEAD_CENTER) / 3.0
    return out


# ------------------------------------------------------------------------------------- textures


def eye_centres() -> np.ndarray:
    """The eyes' centres in canonical space ``(2, 3)``: on the head's front surface at :data:`EYES`."""
    out = []
    for x, y in EYES:
        z = -HEAD_RADII[2] * math.sqrt(max(0.0, 1.0 - (x / HEAD_RADII[0]) ** 2 - (y / HEAD_RADII[1]) ** 2))
        out.append((x, y, z))
    return np.array(out)


def _photo() -> np.ndarray:
    from skimage import data

    return data.astronaut().astype(np.float32) / 255.0


def _sample(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``image (h, w, 3)`` at pixel coordinates ``u`` (column), ``v`` (row)."""
    n = u.size
    width = 1024  # remap's maps must be under 32767 wide: the points are laid out in rows
    rows = max(1, -(-n // width))
    mx = np.zeros(rows * width, np.float32)
    my = np.zeros(rows * width, np.float32)
    mx[:n], my[:n] = u.reshape(-1), v.reshape(-1)
    out = cv2.remap(image, mx.reshape(rows, width), my.reshape(rows, width), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return out.reshape(-1, 3)[:n]


def _shrink(image: np.ndarray, scale: float) -> np.ndarray:
    """``image`` resized by ``scale`` with area averaging when ``scale < 1``; unchanged otherwise."""
    return cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else image


class HeadModel:
    """The head mesh, its jaw and its colours, in canonical space.

    Args:
        size: Frame size the texture is band-limited for (texture detail finer than about half a
            pixel at that size is removed, so that one ray per pixel does not alias).
    """

    def __init__(self, size: int) -> None:
        sphere = trimesh.creation.icosphere(subdivisions=5)
        self.rest = np.asarray(sphere.vertices) * HEAD_RADII
        self.faces = np.asarray(sphere.faces)
        y, z = self.rest[:, 1], self.rest[:, 2]
        # Jaw weight: 0 above the mouth line, 1 on the chin, only on the front-lower part.
        wy = np.clip((y - 0.40) / 0.10, 0.0, 1.0)
        wz = np.clip((0.35 - z) / 0.35, 0.0, 1.0)
        self.jaw_weight = (wy * wy * (3 - 2 * wy)) * (wz * wz * (3 - 2 * wz))
        self.hinge = np.array([0.0, 0.12, 0.35])
        photo = _photo()
        head_px = FOCAL_PER_PIXEL * size / HEAD_CENTER[2]  # screen pixels per unit at the head
        face = photo[10:205, 120:330]  # rows span the head's 2 units of height
        scale = min(1.0, 2.0 * head_px * 1.9 / face.shape[0])  # about 2 texels per screen pixel
        self.face = _shrink(face, scale)
        self.face_scale = scale
        hair = photo[18:70, 175:285]
        self.hair = _shrink(hair, scale)
        # The faces the jaw never moves (every corner's weight 0) are cast against one mesh built
        # once; only the jaw's faces are rebuilt for each opening (_cast).
        moving = self.jaw_weight[self.faces].max(axis=1) > 0
        self.jaw_faces = np.flatnonzero(moving)
        self.fixed_faces = np.flatnonzero(~moving)
        self.fixed = _Target(trimesh.Trimesh(self.rest, self.faces[self.fixed_faces], process=False), shared=True)

    def vertices(self, opening: float) -> np.ndarray:
        """Canonical vertex positions ``(V, 3)`` with the jaw opened by ``opening`` in [0, 1]."""
        angle = JAW_MAX_ANGLE * float(opening) * self.jaw_weight
        p = self.rest - self.hinge
        c, s = np.cos(angle), np.sin(angle)
        out = self.rest.copy()
        out[:, 1] = p[:, 1] * c - p[:, 2] * s + self.hinge[1]
        out[:, 2] = p[:, 1] * s + p[:, 2] * c + self.hinge[2]
        still = angle == 0  # exactly the rest positions: the jaw's edge meets the fixed faces without a crack
        out[still] = self.rest[still]
        return out

    def colors(self, rest_points: np.ndarray, opening: float, eye: float = 1.0) -> np.ndarray:
        """Colours ``(n, 3)`` in [0, 1] at rest-surface points ``(n, 3)`` with the jaw opened by
        ``opening`` and the eyes open by ``eye`` (1: open, 0: the lids closed)."""
        x, y, z = rest_points.T
        n = rest_points / HEAD_RADII**2
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        s = self.face_scale
        face = _sample(self.face, (105.0 + x * 118.0) * s, (95.0 + y * 97.0) * s)
        hair = _sample(self.hair, (55.0 + x * 60.0) * s, (26.0 + z * 25.0) * s)  # mirrored beyond the crop
        front = np.clip((-n[:, 2] - 0.05) / 0.35, 0.0, 1.0)[:, None]
        rgb = front * face + (1 - front) * hair
        # The mouth: an ellipse at the lips (rest coordinates) that opens with the jaw.
        mx, my = MOUTH[0], MOUTH[1]
        half_h = 0.012 + 0.085 * float(opening)
        inside = ((x - mx) / 0.20) ** 2 + ((y - my - 0.5 * half_h) / half_h) ** 2 < 1.0
        inside &= z < 0
        rgb[inside] = np.array([0.22, 0.04, 0.06])
        # The lids: from the top of each eye's ellipse down to a line that falls as the eye closes;
        # skin from just above the eye (the texture's own lid), a dark lash line at the edge.
        closed = 1.0 - float(np.clip(eye, 0.0, 1.0))
        if closed > 0:
            a, b = EYE_AXES
            for ex, ey in EYES:
                in_eye = (((x - ex) / a) ** 2 + ((y - ey) / b) ** 2 < 1.0) & (z < 0)
                edge = ey - b + 2.0 * b * closed
                lid = in_eye & (y <= edge)
                if lid.any():
                    skin = _sample(self.face, (105.0 + x[lid] * 118.0) * s, (95.0 + (ey - 1.6 * b) * 97.0) * s + 0 * y[lid])
                    rgb[lid] = skin
                    lash = lid & (y > edge - 0.018)
                    rgb[lash] = np.array([0.18, 0.11, 0.09])
        shade = 0.72 + 0.28 * np.clip(n @ _LIGHT, 0.0, 1.0)
        return np.clip(rgb * shade[:, None], 0.0, 1.0)


class TorsoModel:
    """Neck and shoulders in the torso frame, wearing the photograph's suit."""

    def __init__(self, size: int) -> None:
        neck = trimesh.creation.cylinder(radius=0.36, height=1.3, sections=48)
        neck.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        neck.apply_translation([0.0, -0.25, 0.0])
        shoulders = trimesh.creation.capsule(height=2.0, radius=0.62, count=[24, 24])
        shoulders.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        shoulders.apply_scale([1.0, 1.0, 0.6])
        shoulders.apply_translation([0.0, 0.95, 0.1])
        self.parts = [neck, shoulders]
        self.mesh = trimesh.util.concatenate(self.parts)
        self.n_neck_faces = len(neck.faces)
        self.target = _Target(self.mesh, shared=True)
        photo = _photo()
        suit = photo[300:500, 40:340]
        scale = min(1.0, FOCAL_PER_PIXEL * size / 6.35 * 3.4 * 1.5 / suit.shape[1])
        self.suit = _shrink(suit, scale)
        self.skin = photo[150:175, 200:250].reshape(-1, 3).mean(0)

    def colors(self, points: np.ndarray, normals: np.ndarray, is_neck: np.ndarray) -> np.ndarray:
        """Colours at torso-frame surface points with their normals."""
        h, w = self.suit.shape[:2]
        u = (points[:, 0] / 3.4 + 0.5) * (w - 1)
        v = np.clip((points[:, 1] - 0.3) / 1.4, 0, 1) * (h - 1)
        rgb = _sample(self.suit, u, v)
        rgb[is_neck] = self.skin
        shade = 0.7 + 0.3 * np.clip(normals @ _LIGHT, 0.0, 1.0)
        return np.clip(rgb * shade[:, None], 0.0, 1.0)


class _Target:
    """A mesh in its own frame, ready to be ray-cast from any rigid placement of it (its
    acceleration structure is built once: :meth:`first_hits` moves the rays, not the mesh)."""

    def __init__(self, mesh: trimesh.Trimesh, shared: bool = False) -> None:
        self.mesh = mesh
        self.triangles = np.asarray(mesh.triangles)
        if trimesh.ray.has_embree:
            from trimesh.ray.ray_pyembree import RayMeshIntersector
        else:
            from trimesh.ray.ray_triangle import RayMeshIntersector  # type: ignore[assignment]
        self.intersector = RayMeshIntersector(mesh)
        if shared:  # cast from several threads: built now, before they share it
            self.first_hits(np.eye(4), np.array([[0.0, 0.0, 1.0]]))

    def first_hits(self, placement: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The first hit of each camera ray from the origin along unit ``dirs (n, 3)``, with the
        mesh placed by ``placement`` (mesh frame -> camera, rigid ``(4, 4)``).

        Returns:
            ``(ray (m,), face (m,), distance (m,), barycentric (m, 3))`` of the rays that hit.
        """
        R, t = placement[:3, :3], placement[:3, 3]
        origin = -(R.T @ t)
        local = dirs @ R  # R^T d of each direction: unit still
        face, ray, loc = self.intersector.intersects_id(np.broadcast_to(origin, local.shape), local, multiple_hits=False, return_locations=True)
        bary = trimesh.triangles.points_to_barycentric(self.triangles[face], loc) if len(face) else np.zeros((0, 3))
        return ray, face, np.linalg.norm(loc - origin, axis=1), bary


def pixel_ray_directions(size: int) -> np.ndarray:
    """Unit directions ``(size * size, 3)`` through pixel centres (row-major), camera frame."""
    f = FOCAL_PER_PIXEL * size
    ys, xs = np.mgrid[0:size, 0:size] + 0.5
    d = np.stack([(xs - size / 2) / f, (ys - size / 2) / f, np.ones_like(xs)], -1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclass
class _Hits:
    """Where one frame's pixel rays meet the scene (:func:`_cast`): what shading needs."""

    shape: tuple[int, int]  # (h, w) of the pixels cast
    ray: np.ndarray  # (M,) the pixels whose rays hit, row-major in the box
    depth: np.ndarray  # (M,) distance to the hit
    is_head: np.ndarray  # (M,) bool
    head_rest: np.ndarray  # (K, 3) the head hits' rest positions (K = is_head.sum())
    torso_rgb: np.ndarray  # (M - K, 3) the torso hits' colours


def _cast(head: HeadModel, torso: TorsoModel, pose: np.ndarray, opening: float, size: int, box: tuple[int, int, int, int] | None) -> _Hits:
    x0, y0, x1, y1 = (0, 0, size, size) if box is None else box
    if not (0 <= x0 < x1 <= size and 0 <= y0 < y1 <= size):
        raise ValueError(f"box {box} is not a non-empty box inside the {size}x{size} frame")
    dirs = pixel_ray_directions(size).reshape(size, size, 3)[y0:y1, x0:x1].reshape(-1, 3)
    # Three meshes, each cast in its own frame: the head's fixed faces and the torso (built once)
    # and the jaw at this opening; a pixel sees the nearest of their first hits.
    jaw = _Target(trimesh.Trimesh(head.vertices(opening), head.faces[head.jaw_faces], process=False))
    parts = [
        (head.fixed.first_hits(pose, dirs), head.fixed_faces),
        (jaw.first_hits(pose, dirs), head.jaw_faces),
        (torso.target.first_hits(torso_pose(pose), dirs), None),
    ]
    n = len(dirs)
    nearest = np.full(n, np.inf)
    which = np.full(n, -1)
    for k, ((ray, _, dist, _), _) in enumerate(parts):
        closer = dist < nearest[ray]
        nearest[ray[closer]] = dist[closer]
        which[ray[closer]] = k
    rays, depth, is_head, head_faces, head_bary, torso_faces, torso_bary = [], [], [], [], [], [], []
    for k, ((ray, face, dist, bary), faces) in enumerate(parts):
        won = which[ray] == k
        rays.append(ray[won])
        depth.append(dist[won])
        is_head.append(np.full(int(won.sum()), faces is not None))
        if faces is not None:
            head_faces.append(faces[face[won]])
            head_bary.append(bary[won])
        else:
            torso_faces.append(face[won])
            torso_bary.append(bary[won])
    ray, depth_all, head_mask = np.concatenate(rays), np.concatenate(depth), np.concatenate(is_head)
    order = np.argsort(ray, kind="stable")  # pixel order, as one cast would give
    hf, hb = np.concatenate(head_faces), np.concatenate(head_bary)
    head_rest = np.einsum("nk,nkj->nj", hb, head.rest[head.faces[hf]])
    local_tri, tb = torso_faces[0], torso_bary[0]
    torso_rgb = np.zeros((len(local_tri), 3))
    if len(local_tri):
        points = np.einsum("nk,nkj->nj", tb, np.asarray(torso.mesh.vertices)[np.asarray(torso.mesh.faces)[local_tri]])
        normals = np.asarray(torso.mesh.face_normals)[local_tri]
        torso_rgb = torso.colors(points, normals, local_tri < torso.n_neck_faces)
    # head_rest and torso_rgb follow the head and torso hits in pixel order.
    head_order = np.argsort(ray[head_mask], kind="stable")
    torso_order = np.argsort(ray[~head_mask], kind="stable")
    return _Hits((y1 - y0, x1 - x0), ray[order], depth_all[order], head_mask[order], head_rest[head_order], torso_rgb[torso_order])


def _box_of(background: np.ndarray, box: tuple[int, int, int, int] | None) -> np.ndarray:
    return background if box is None else background[box[1] : box[3], box[0] : box[2]]


def _shade(hits: _Hits, head: HeadModel, opening: float, eye: float, background: np.ndarray) -> np.ndarray:
    rgb = background.reshape(-1, 3).astype(np.float32)  # astype copies: the plate stays as it was
    if hits.is_head.any():
        rgb[hits.ray[hits.is_head]] = head.colors(hits.head_rest, opening, eye)
    if (~hits.is_head).any():
        rgb[hits.ray[~hits.is_head]] = hits.torso_rgb
    return rgb.reshape(*hits.shape, 3)


def render_frame(
    head: HeadModel, torso: TorsoModel, pose: np.ndarray, opening: float, background: np.ndarray, eye: float = 1.0, box: tuple[int, int, int, int] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast one frame (jaw opened by ``opening``, eyes open by ``eye``), or only the pixels
    of ``box`` ``(x0, y0, x1, y1)`` (end exclusive; the same pixels as in the whole frame).

    Returns:
        ``(rgb (h, w, 3) float in [0, 1], labels (h, w) uint8, depth (h, w) float32)``: the
        whole frame's ``(H, W)``, or the box's ``(y1 - y0, x1 - x0)``.
    """
    hits = _cast(head, torso, pose, opening, background.shape[0], box)
    labels = np.zeros(hits.shape[0] * hits.shape[1], dtype=np.uint8)
    labels[hits.ray] = np.where(hits.is_head, LABEL_HEAD, LABEL_TORSO)
    depth = np.full(labels.shape, np.inf, dtype=np.float32)
    depth[hits.ray] = hits.depth
    return _shade(hits, head, opening, eye, _box_of(background, box)), labels.reshape(hits.shape), depth.reshape(hits.shape)


def render_eye_openings(
    head: HeadModel, torso: TorsoModel, pose: np.ndarray, opening: float, background: np.ndarray, eyes: Sequence[float], box: tuple[int, int, int, int] | None = None
) -> np.ndarray:
    """The colours :func:`render_frame` gives at each eye openness of ``eyes``, ``(len(eyes), h, w, 3)``:
    the lids are painted, not modelled, so the rays are cast once for all of them."""
    hits = _cast(head, torso, pose, opening, background.shape[0], box)
    return np.stack([_shade(hits, head, opening, e, _box_of(background, box)) for e in eyes])


def background_plate(size: int) -> np.ndarray:
    """The static background: ``skimage.data.rocket()`` cropped square and resized, float [0, 1]."""
    from skimage import data

    img = data.rocket().astype(np.float32) / 255.0
    h, w = img.shape[:2]
    x0 = (w - h) // 2
    return cv2.resize(img[:, x0 : x0 + h], (size, size), interpolation=cv2.INTER_AREA)


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)


@writes_folder("out_dir", "dataset")  # one writer per dataset folder
def synthesize(out_dir: str | Path, config: SynthConfig = SynthConfig(), *, progress: Callable[[str, int, int], None] | None = None, overwrite: bool = False) -> Path:
    """Build a synthetic talking-head dataset (see :mod:`adnerf.formats.dataset` for the layout).

    Args:
        out_dir: Dataset folder to create.
        config: Scene parameters.
        progress: Called as ``progress(step, done, total)``.
        overwrite: Replace an existing adnerf dataset folder (see :mod:`adnerf.formats.outputs`).

    Returns:
        The dataset folder.

    Raises:
        ValueError: Impossible settings.
        adnerf.formats.outputs.OutputError: ``out_dir`` must not be written; raised before any work.
    """
    config.validate()
    check_folder_output(out_dir, "dataset", overwrite=overwrite)
    size = config.size
    n = config.n_frames
    speech = speech_audio(config.seconds, config.voice, config.seed, speaker=config.speaker, words_per_minute=config.words_per_minute)
    samples, voice = speech.samples, speech.voice
    times = np.arange(n) / config.fps
    jaw, mouth = jaw_opening(speech, times, config.mouth)
    eye = blink_track(times, config.seed) if config.blinks else np.ones(n)
    poses = pose_track(n, config.fps, config.seed, config.max_yaw)
    head, torso = HeadModel(size), TorsoModel(size)
    background = background_plate(size)
    frames = np.empty((n, size, size, 3), dtype=np.uint8)
    labels = np.empty((n, size, size), dtype=np.uint8)
    depth = np.empty((n, size, size), dtype=np.float32)
    # Frames are ray cast side by side (Embree and NumPy release the interpreter lock).
    for i, (rgb, labels[i], depth[i]) in enumerate(in_threads(lambda k: render_frame(head, torso, poses[k], jaw[k], background, eye[k]), range(n))):
        frames[i] = _to_u8(rgb)
        if progress is not None:
            progress("render", i + 1, n)
    audio = AudioTrack(samples, SAMPLE_RATE, 0.0)
    spec = FeatureSpec(kind=config.features)
    features = speech_windows(audio, times, spec)
    train, test = tail_split(n, config.test_fraction)
    meta = SceneMeta(
        fps=float(config.fps),
        width=size,
        height=size,
        intrinsics=(FOCAL_PER_PIXEL * size, FOCAL_PER_PIXEL * size, size / 2, size / 2),
        near=NEAR,
        far=FAR,
        head_aabb=HEAD_AABB,
        torso_aabb=TORSO_AABB,
        mouth=MOUTH,
        eyes=tuple(tuple(float(v) for v in e) for e in eye_centres()),  # type: ignore[arg-type]
        feature_kind=config.features,
        feature_dim=int(features.shape[-1]),
        n_frames=n,
        train=train,
        test=test,
        source=f"adnerf synth: seconds={config.seconds} size={size} fps={config.fps} seed={config.seed} voice={voice}" + (f" speaker={config.speaker} wpm={config.words_per_minute}" if voice == "espeak" else "") + f" mouth={mouth}" + ("" if config.blinks else " blinks=off"),
    )

    def add_video(folder: DatasetFolder) -> None:
        write_video(folder.video, frames, config.fps, audio)

    return save_dataset(
        out_dir,
        meta,
        frames=frames,
        parsing=labels,
        background=_to_u8(background),
        poses=poses,
        features=features,
        audio=audio,
        truth=Truth(poses=poses, parsing=labels, depth=depth, jaw=jaw, eye=eye),
        eye=eye.astype(np.float32),
        extra=add_video,
        overwrite=overwrite,
    )
