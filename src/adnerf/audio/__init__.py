"""Audio: from speech to the per-frame windows and codes a talking head is conditioned on.

- :mod:`~adnerf.audio.features`: feature windows per video frame (log-mel, wav2vec2 / HuBERT /
  phoneme posteriors from local checkpoints, DeepSpeech ``.npy``).
- :mod:`~adnerf.audio.nets`: AudioNet (a window to a code) and AudioAttNet (codes filtered over
  neighbouring frames), AD-NeRF's audio encoders.
- :mod:`~adnerf.audio.espeak` and :mod:`~adnerf.audio.visemes`: speech with phoneme timings
  from espeak-ng and the jaw track it implies (the synthetic scene's voice and truth).
"""

from .nets import AudioAttNet, AudioNet

__all__ = ["AudioAttNet", "AudioNet"]
