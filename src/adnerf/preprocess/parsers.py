"""The parsing backends by name, as ``adnerf preprocess --parser`` takes them.

Each backend lives in its own module behind the :class:`~adnerf.preprocess.parsing.Parser`
protocol; this module only chooses one, so it depends on them and none depends on it.
"""

from __future__ import annotations

import torch

from .bisenet import BiSeNetParser
from .mediapipe_parser import MediapipeParser, import_mediapipe
from .parsing import ClassicalParser, Parser

__all__ = ["PARSERS", "make_parser"]

PARSERS = ("classical", "mediapipe", "bisenet:CHECKPOINT")


def make_parser(spec: str) -> Parser:
    """A parser by name: ``"classical"`` (no weights), ``"mediapipe"`` (mediapipe 0.10.21's bundled
    models, an opt-in install, see :mod:`adnerf.preprocess.mediapipe_parser`) or ``"bisenet:PATH"``
    (a user's 19-class face-parsing checkpoint, see :mod:`adnerf.preprocess.bisenet`; on CUDA when
    available).

    Raises:
        ValueError: Unknown name, a checkpoint that cannot be loaded, or mediapipe missing.
    """
    if spec == "classical":
        return ClassicalParser()
    if spec == "mediapipe":
        try:
            import_mediapipe()
        except ImportError as exc:
            raise ValueError(str(exc)) from exc
        return MediapipeParser()
    if spec.startswith("bisenet:"):
        return BiSeNetParser(spec.split(":", 1)[1], device="cuda" if torch.cuda.is_available() else "cpu")
    raise ValueError(f"unknown parser {spec!r}; available: {', '.join(PARSERS)}")
