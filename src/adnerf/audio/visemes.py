"""Visemes: how far the jaw opens for each phoneme, and the articulation track it makes over time.

A viseme is the mouth shape of a phoneme. Here it is one number per phoneme, the jaw opening in
[0, 1] (1: the open vowel of "father"), from the phoneme's IPA name: lips closed for p / b / m,
nearly closed for f / v and w, a little open for the tongue consonants, half open for mid vowels
and wide open for open vowels; pauses close the mouth.

The track over time (:func:`jaw_track`) holds each phoneme's target from its start to the next
phoneme's start, and smooths it with a Gaussian of ``smoothing`` seconds (35 ms by default):
real articulators move continuously and overlap neighbouring phonemes (coarticulation), and a
rendered mouth cannot jump either. A phoneme's effect is centred on its own time span, so the
track is centred on the audio's own timing: a vowel between two closures peaks at its middle.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .espeak import PAUSE, Phoneme

__all__ = ["PAUSE", "jaw_target", "jaw_track"]

# First IPA symbol of a phoneme -> jaw opening. Diphthongs take their first vowel (the jaw then
# closes towards the second within the smoothing); length and stress marks are ignored.
_JAW: dict[str, float] = {
    # open vowels
    "a": 1.0, "ɑ": 1.0, "æ": 0.9, "ɒ": 0.85, "ʌ": 0.8, "ɐ": 0.75, "ɔ": 0.7,
    # mid vowels
    "ɛ": 0.65, "e": 0.55, "ɜ": 0.55, "ə": 0.5, "ø": 0.45, "œ": 0.6, "o": 0.5, "ɵ": 0.45,
    # close vowels
    "ɪ": 0.35, "i": 0.3, "y": 0.3, "ʊ": 0.3, "u": 0.25, "ɨ": 0.3, "ɯ": 0.3,
    # consonants
    "h": 0.45, "ɦ": 0.45, "k": 0.3, "g": 0.3, "ɡ": 0.3, "ŋ": 0.3, "x": 0.3, "ç": 0.25,
    "j": 0.25, "ɹ": 0.25, "r": 0.25, "ɾ": 0.25, "ʁ": 0.3, "l": 0.25, "ɫ": 0.25,
    "t": 0.2, "d": 0.2, "n": 0.2, "θ": 0.2, "ð": 0.2, "ʔ": 0.2,
    "s": 0.12, "z": 0.12, "ʃ": 0.15, "ʒ": 0.15, "ɕ": 0.15, "ʂ": 0.15,
    "f": 0.1, "v": 0.1, "w": 0.1, "ʋ": 0.1,
    "p": 0.0, "b": 0.0, "m": 0.0,
}
_MARKS = "ːˑˈˌ'ʰʲʷ̩̯̃ \u0361"
_UNKNOWN_VOWEL, _UNKNOWN_CONSONANT = 0.5, 0.2
_VOWEL_LIKE = set("aɑæɒʌɐɔɛeɜəøœoɵɪiyʊuɨɯ")


def jaw_target(ipa: str) -> float:
    """The jaw opening in [0, 1] that phoneme ``ipa`` aims at (0 for a pause).

    Symbols not in the table take 0.5 when they are vowels and 0.2 otherwise (a tongue
    consonant's opening)."""
    base = ipa.strip(_MARKS)
    if not base or base == PAUSE:
        return 0.0
    first = base[0]
    if first in _JAW:
        return _JAW[first]
    return _UNKNOWN_VOWEL if first in _VOWEL_LIKE else _UNKNOWN_CONSONANT


def jaw_track(phonemes: Sequence[Phoneme], times: np.ndarray, *, end: float | None = None, smoothing: float = 0.035) -> np.ndarray:
    """The jaw opening at ``times`` while ``phonemes`` are spoken.

    The piecewise-constant targets convolved with a Gaussian, evaluated exactly (no time grid):
    a target ``v`` held on ``[a, b)`` contributes ``v (Phi((t - a) / s) - Phi((t - b) / s))``.

    Args:
        phonemes: Phonemes in order of start time (seconds on the same clock as ``times``); each
            lasts until the next one starts.
        times: ``(n,)`` seconds at which to read the track (e.g. video frame times).
        end: When the last phoneme ends (default: its start plus 0.1 s). Before the first
            phoneme and after ``end`` the mouth is closed.
        smoothing: Standard deviation ``s`` of the Gaussian articulation smoothing, in seconds
            (0: the targets themselves).

    Returns:
        ``(n,)`` float64 openings in [0, 1].
    """
    from scipy.special import ndtr

    times = np.asarray(times, dtype=np.float64)
    if not smoothing >= 0:
        raise ValueError(f"smoothing must be >= 0 seconds; got {smoothing}")
    if not phonemes:
        return np.zeros_like(times)
    starts = np.array([p.start for p in phonemes], dtype=np.float64)
    if np.any(np.diff(starts) < 0):
        raise ValueError("phonemes must be in order of their start times")
    last = float(starts[-1] + 0.1 if end is None else max(end, starts[-1]))
    # The track as steps: at edge k the target changes by jumps[k].
    targets = np.array([jaw_target(p.ipa) for p in phonemes])
    edges = np.concatenate([starts, [last]])
    jumps = np.diff(np.concatenate([[0.0], targets, [0.0]]))
    out = np.empty_like(times)
    flat = times.reshape(-1)
    for lo in range(0, flat.size, 4096):  # bounded memory for long clips
        t = flat[lo : lo + 4096, None]
        steps = ndtr((t - edges) / smoothing) if smoothing > 0 else (t >= edges).astype(np.float64)
        out.reshape(-1)[lo : lo + 4096] = steps @ jumps
    return np.clip(out, 0.0, 1.0)
