"""Training stages as data.

A :class:`Stage` names the layer it trains, the parameter groups its optimizer steps (each with
its learning rate), its iterations, and the layers it draws frozen beside the one it trains.
:func:`default_stages` is AD-NeRF's schedule: stage 1 (``"head"``) trains the head layer and the
audio encoders; stage 2 (``"torso"``) trains the torso layer under the frozen head and frozen
audio encoders. :meth:`adnerf.model.train.Trainer.fit` runs a list of them in order; checkpoints
hold each stage's step and optimizer under its name.

What a stage's step draws for its layer (which pixels, against which target) is the trainer's
per-layer code (:attr:`~adnerf.model.train.Trainer.layer_steps`); a stage is what varies between
schedules.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

from torch import nn

from .run_folder import RunError
from .talking_head import TalkingHead
from .train_config import TrainConfig

AUDIO = "audio"
"""The name of the audio encoders (AudioNet and AudioAttNet) in a :class:`ParamGroup`."""


@dataclass(frozen=True)
class ParamGroup:
    """Parameters one learning rate steps.

    Attributes:
        modules: Layer names of the model, or :data:`AUDIO` for the audio encoders.
        lr: The group's initial learning rate (decayed by the schedule to ``lr_final`` of it).
    """

    modules: tuple[str, ...]
    lr: float


@dataclass(frozen=True)
class Stage:
    """One stage of training.

    Attributes:
        name: The stage's name: the log's ``stage``, the checkpoint's key, the progress bar's.
        layer: The layer whose rays the stage renders and trains.
        iters: Iterations.
        groups: The optimizer's parameter groups.
        frozen: Layers drawn (without gradients) with the trained one; their stages must have
            finished before this one starts.
    """

    name: str
    layer: str
    iters: int
    groups: tuple[ParamGroup, ...]
    frozen: tuple[str, ...] = ()

    @property
    def trains_audio(self) -> bool:
        """Whether the stage trains the audio encoders (then its steps make the codes with
        gradients, switch AudioAttNet on at ``att_start`` and fit the mouth target)."""
        return any(AUDIO in g.modules for g in self.groups)


def default_stages(tcfg: TrainConfig) -> list[Stage]:
    """AD-NeRF's two stages for a schedule: the head with the audio encoders, then the torso
    under the frozen head."""
    return [
        Stage("head", "head", tcfg.head_iters, (ParamGroup(("head",), tcfg.lr), ParamGroup((AUDIO,), tcfg.lr_audio))),
        Stage("torso", "torso", tcfg.torso_iters, (ParamGroup(("torso",), tcfg.lr),), frozen=("head",)),
    ]


def group_parameters(model: TalkingHead, group: ParamGroup) -> list[nn.Parameter]:
    """The parameters of a group's modules, in the order they are named.

    Raises:
        ValueError: A module the model does not have.
    """
    params: list[nn.Parameter] = []
    for name in group.modules:
        if name == AUDIO:
            params += list(model.audio_net.parameters()) + list(model.att_net.parameters())
        elif name in model.layers:
            params += list(model.layers[name].parameters())
        else:
            raise ValueError(f"the model has no layer {name!r}; it has {', '.join(model.layers)} and {AUDIO!r}")
    return params


def check_frozen_trained(stage: Stage, stages: Sequence[Stage], steps: Mapping[str, int], before: Sequence[Stage] = ()) -> None:
    """Refuse ``stage`` while a stage of ``stages`` that trains a layer it draws frozen has not
    finished (``steps``: finished iterations by stage name); a stage in ``before`` runs first, so
    it does not count.

    Raises:
        RunError: Which stage waits for which, and the command that finishes it.
    """
    for k, other in enumerate(stages):
        done = steps.get(other.name, 0)
        if other.layer in stage.frozen and other not in before and done < other.iters:
            position = next((j for j, s in enumerate(stages) if s.name == stage.name), len(stages))
            raise RunError(
                f"stage {position + 1} ({stage.name}) needs a finished stage {k + 1} ({done}/{other.iters} {other.name} iterations); "
                f"run --stage {other.name} (with --resume) first"
            )
