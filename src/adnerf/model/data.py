"""The dataset format, where it was first published: it lives in :mod:`adnerf.formats.dataset`
now (the room that owns the dataset and run folders); ``from adnerf.model.data import
load_dataset`` and the other names keep working."""

from ..formats.dataset import *  # noqa: F403 (the room's public names)
from ..formats.dataset import __all__  # noqa: F401
