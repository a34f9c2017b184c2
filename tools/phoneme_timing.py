"""Are hama's phoneme features late? Measured against espeak-ng's own phoneme timings.

Isolated words (pauses between them) are spoken by espeak-ng, whose library reports when each
phoneme starts (:mod:`adnerf.audio.espeak`); hama's per-frame non-blank probability (1 - p(blank)) is
computed on the same audio (:func:`adnerf.audio.features.phoneme_logprobs`, feature ``k`` at ``k * 20``
ms). For each word, the first frame with non-blank probability above 0.5 is compared with the
word's first phoneme, and the last such frame with the end of its sound.

    python tools/phoneme_timing.py            # voices en and en+f3
"""

from __future__ import annotations

import sys

import numpy as np
from adnerf.audio.espeak import PAUSE, speak
from adnerf.audio.features import FEATURE_RATE, MODEL_RATE, _hama_model, phoneme_logprobs, resample
from adnerf.io import AudioTrack

WORDS = "father map ball open ocean apple eagle umbrella mother table water sun garden yellow window pocket".split()


def measure(voice: str) -> tuple[np.ndarray, np.ndarray]:
    """Per word: (first non-blank frame - first phoneme start, last non-blank frame - end of sound), seconds."""
    pieces, spans, t = [np.zeros(MODEL_RATE // 2, np.float32)], [], 0.5
    for word in WORDS:
        said = speak(word, voice)
        x = resample(AudioTrack(said.samples, said.sample_rate, 0.0), MODEL_RATE)
        first = next(p.start for p in said.phonemes if p.ipa != PAUSE)
        spans.append((t + first, t + len(x) / MODEL_RATE))
        pieces += [x, np.zeros(int(0.8 * MODEL_RATE), np.float32)]
        t += len(x) / MODEL_RATE + 0.8
    probs = np.exp(phoneme_logprobs(np.concatenate(pieces)))
    speaking = 1.0 - probs[:, _hama_model().blank_id]
    onsets, ends = [], []
    for start, end in spans:
        k0 = int(round((start - 0.3) * FEATURE_RATE))
        above = np.flatnonzero(speaking[k0 : k0 + int((end - start + 0.6) * FEATURE_RATE)] > 0.5)
        onsets.append((k0 + above[0]) / FEATURE_RATE - start)
        ends.append((k0 + above[-1]) / FEATURE_RATE - end)
    return np.array(onsets), np.array(ends)


if __name__ == "__main__":
    for voice in sys.argv[1:] or ["en", "en+f3"]:
        on, end = measure(voice)
        print(f"{voice}: hama's first non-blank frame - first phoneme: median {1e3 * np.median(on):+.0f} ms "
              f"(range {1e3 * on.min():+.0f} to {1e3 * on.max():+.0f}); last non-blank frame - end of sound: median {1e3 * np.median(end):+.0f} ms")
