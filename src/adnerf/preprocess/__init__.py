"""Preprocessing of a user's video into a dataset: parsing, head pose, background plate.

The flow of data follows the files: ``parsing`` (labels) -> ``tracking`` (point tracks on the
rigid head) -> ``bundle`` (bundle adjustment) -> ``headpose`` (poses in scene units) -> ``plate``
(background) -> ``pipeline`` (the resumable ``adnerf preprocess`` steps); ``check`` compares a
preprocessed synthetic video with its truth and ``adnerf_import`` reads datasets of the original
AD-NeRF code.
"""

from .pipeline import PreprocessConfig, PreprocessError, preprocess_video

__all__ = ["PreprocessConfig", "PreprocessError", "preprocess_video"]
