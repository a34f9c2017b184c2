"""The training schedule of a run: what ``adnerf train --config`` takes and ``run.json`` stores.

Its own module so that the run folder (:mod:`adnerf.model.run_folder`), rendering and evaluation read a
run's schedule without importing the trainer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

from ..fields import check_config_keys
from .audio_jitter import MAX_AUDIO_JITTER
from .lip_patch import MIN_PATCH
from .talking_head import AMP_MODES

__all__ = ["PRESETS", "TrainConfig"]


@dataclass
class TrainConfig:
    """Training schedule.

    Attributes:
        head_iters: Stage-1 iterations.
        torso_iters: Stage-2 iterations (the torso gains more per second of training than the head;
            ``docs/decisions.md``, *The torso stage's share of the schedule*).
        rays: Rays per iteration (an eye batch adds ``eye_rays * rays``).
        frames: Training frames each iteration (of either stage) draws its rays from,
            ``rays // frames`` each, every frame under its own audio code and pose (1: the paper's
            one frame a step).
        lr: Initial learning rate of the fields (Adam).
        lr_audio: Initial learning rate of the audio encoders.
        lr_final: Final learning rate as a fraction of the initial one (exponential decay).
        att_start: Fraction of stage 1 after which AudioAttNet smooths the audio codes.
        mouth_rays: Fraction of each stage-1 batch drawn around the mouth (the dataset's mouth point
            projected with the frame's pose, a square of side ``MOUTH_CROP`` units); the rest is
            drawn from the whole head box.
        eye_rays: For heads that read the eye openness (datasets with eye points, clips that
            blink): each stage-1 iteration also renders ``eye_rays * rays`` rays around the eyes
            (squares of side ``EYE_CROP`` units) of a second frame, so the eyes are taught without
            taking rays or frames from the rest of the head.
        blink_frames: Fraction of those eye batches whose frame is drawn among the blinking
            training frames (openness below 0.75), which are few (a blink is about 5 frames every
            2-6 s) and the only ones that teach the eye condition; the others among all frames.
            (``docs/decisions.md``, *Half the eye batches at blinks*.)
        lip_weight: Weight of the mouth-target loss in stage 1 (:mod:`adnerf.model.mouth_target`):
            a linear read-out of the audio code predicts the lip landmarks' standardised opening
            and width, on ``lip_frames`` training frames a step. 0, or a dataset without
            ``landmarks.npy``, trains the audio code from the photometric loss alone (AD-NeRF's).
        lip_frames: Training frames whose audio codes the mouth-target loss reads each step.
        lip_min_signal: The mouth target is used only when the clip's audio predicts the opening
            of its training frames at least this well (cross-validated correlation,
            :func:`~adnerf.model.mouth_target.opening_signal`); -1 uses it always.
        lip_patch: Side, in rays, of a square patch about the mouth that each stage-1 frame's
            rays end with, in place of as many of its random mouth rays, scored by its
            structural similarity to the frame beside the squared error
            (:mod:`adnerf.model.lip_patch`); 0 (the default): none. At least
            ``lip_patch.MIN_PATCH``, and its square at most the mouth's share of a frame's rays.
        lip_patch_weight: Weight of the patch's ``1 - SSIM`` in stage 1's loss.
        audio_jitter: Largest shift, in 20 ms speech features, of the audio a stage-1 step's
            codes read: each step draws a shift in ``[-audio_jitter, audio_jitter]`` and every
            frame of the step (its rays', its eye batch's and the mouth target's) reads its
            feature window moved that far in time (:mod:`adnerf.model.audio_jitter`); the torso
            stage, the pose refits and renders read the windows as they are. A mouth does not
            follow its sound to the 20 ms, so the encoder learns codes that a slightly earlier or
            later window also gives. 0 (the default): none. Needs features adnerf computes from
            the dataset's audio (``logmel``, ``phonemes``, ``logmel+phonemes``).
        mouth_input: 1: where the mouth target is used, the head also reads the mouth's opening and
            width (each training frame's own; when rendering, the read-out of the audio code;
            :attr:`ModelConfig.mouth_dim <adnerf.model.talking_head.ModelConfig.mouth_dim>`); 0 (the
            default: ``docs/decisions.md``, *The head does not read the mouth by default*): the head
            reads the audio code alone.
        torso_person_rays: Fraction of each stage-2 batch drawn among the frame's torso pixels
            (the rest uniformly in the torso box, which is mostly background).
        mask_weight: Weight of the opacity loss against the parsing (stage 1: head pixels opaque,
            others clear; stage 2: torso pixels). Without it a static plate lets a layer stay
            half transparent and mix in the plate's colour, which a new background exposes.
        occupancy_start: Fraction of each stage after which the layer's occupancy grid is
            estimated and empty space skipped (the field needs a rough shape first).
        occupancy_every: Iterations between updates of the occupancy grid (each update
            evaluates both fields once per cell under the current frame's condition).
        checkpoint_every: Iterations between checkpoints.
        log_every: Iterations between log lines.
        amp: Mixed precision of the field evaluations: ``"auto"`` (bfloat16 on CUDA, off on
            CPU), ``"bf16"`` or ``"off"``; the compositor and the losses stay in float32.
        seed: Seed of the initialisation and of the ray sampling.
        preset: Field preset (``"fast"`` or ``"paper"``; see :func:`~adnerf.model.talking_head.model_config`).
        head_samples: Samples per ray of each pass of the head layer (coarse, and as many again
            for the fine pass), in training and in every render of the run; 0: the preset's
            (fast 16 + 16, paper 64 + 128).
        torso_samples: The same for the torso layer.
        head_grid: Finest plane resolution of the head's fine tri-plane field (fast preset), in
            cells a side; 0: the preset's (256). Finer planes than a frame has pixels across
            cannot be taught cell by cell, and each one costs time in every step.
        head_width: Width of the head's fine field's MLP (fast preset); 0: the preset's (64).
        head_gate: Width of the head fields' gated condition (:attr:`FieldConfig.cond_gate
            <adnerf.fields.FieldConfig.cond_gate>`): a projection of the audio code that each
            point scales by a gate of its own position, so the code can act at the mouth alone;
            0: the code shifts every point of the head's first layer alike (AD-NeRF).
        head_planes: Residual plane sets of the head's fine field around the mouth, blended by a
            linear map of the condition and added to its finest features there
            (:attr:`FieldConfig.cond_planes <adnerf.fields.FieldConfig.cond_planes>`; fast
            preset); 0: the head's features do not depend on the audio code.
        torso_motion: 1: where the dataset has the torso's motion (``torso.npy``), the torso layer
            follows it (:attr:`ModelConfig.torso_motion <adnerf.model.talking_head.ModelConfig.torso_motion>`;
            ``docs/decisions.md``, *The torso follows its own motion*); 0: the torso's place is
            what its field makes of the head pose and audio code (AD-NeRF).
        pose_lr: Learning rate (Adam) of each training frame's head-pose correction
            (:mod:`adnerf.model.pose_refine`), learnt in stage 1 with the head and used from then
            on (the torso stage, renders of the training frames); 0: the tracked poses as they are
            (``docs/decisions.md``, *The head poses are fitted to the pixels*).
        pose_refit: Passes over the training frames that fit each pose correction again with the
            field frozen (:func:`~adnerf.model.pose_refine.fit_corrections`, ``REFIT_STEPS`` Adam
            steps of ``REFIT_RAYS`` rays a frame of :mod:`adnerf.model.train`, from the learnt
            correction on), at ``i / pose_refit`` of stage 1 for ``i = 1 .. pose_refit`` (the
            last at its end, before the torso stage). Each takes minutes: on the 50 s real clip
            (1284 training frames) two took about as long as a 256 px, 4345-iteration head
            stage (``docs/decisions.md``, *Refitting the training frames' poses*). 0 (the
            default): none. Needs ``pose_lr`` > 0.
        pose_start: Fraction of stage 1 after which the pose corrections learn (the head needs a
            shape to be aligned to first).
    """

    head_iters: int = 3600
    torso_iters: int = 3000
    rays: int = 1024
    frames: int = 1
    lr: float = 1e-2
    lr_audio: float = 2e-3
    lr_final: float = 0.1
    att_start: float = 0.6
    mouth_rays: float = 0.25
    eye_rays: float = 0.25
    blink_frames: float = 0.5
    lip_weight: float = 0.01
    lip_frames: int = 64
    lip_min_signal: float = 0.2
    lip_patch: int = 0
    lip_patch_weight: float = 0.03
    audio_jitter: int = 0
    mouth_input: int = 0
    torso_motion: int = 1
    torso_person_rays: float = 0.5
    mask_weight: float = 0.1
    occupancy_start: float = 0.1
    occupancy_every: int = 16
    checkpoint_every: int = 250
    log_every: int = 25
    amp: str = "auto"
    seed: int = 0
    preset: str = "fast"
    head_samples: int = 0
    torso_samples: int = 0
    head_grid: int = 0
    head_width: int = 0
    head_gate: int = 0
    head_planes: int = 0
    pose_lr: float = 3e-4
    pose_refit: int = 0
    pose_start: float = 0.3

    def scaled(self, k: int) -> "TrainConfig":
        """The same schedule in ``k`` times fewer, ``k`` times larger steps: ``k`` times the rays,
        drawn from ``k`` times the frames (so each frame is drawn as often and with as many rays
        as before), and the learning rates times ``sqrt(k)``.

        The iteration counts and the per-iteration periods (occupancy updates, checkpoints, log
        lines) are divided by ``k`` (rounded, at least 1; a stage of 0 iterations stays 0), so
        the run draws as many rays, updates its occupancy grid, checkpoints and logs after as
        many rays as before; fractions of a stage are kept.

        This is the schedule for a GPU, where a step costs nearly the same for 1024 rays as for
        8192 and a step's frames are rendered in one call; the defaults stay unscaled on every
        device (``adnerf train --scale K``; ``docs/decisions.md``, *Larger steps on a GPU are opt-in*).

        Raises:
            ValueError: ``k`` is not a positive integer.
        """
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(f"the scale of a schedule is a positive integer; got {k!r}")

        def fewer(n: int) -> int:
            return 0 if n == 0 else max(1, round(n / k))

        return replace(
            self,
            rays=self.rays * k,
            frames=self.frames * k,
            lr=self.lr * math.sqrt(k),
            lr_audio=self.lr_audio * math.sqrt(k),
            head_iters=fewer(self.head_iters),
            torso_iters=fewer(self.torso_iters),
            occupancy_every=fewer(self.occupancy_every),
            checkpoint_every=fewer(self.checkpoint_every),
            log_every=fewer(self.log_every),
        )

    def validate(self) -> None:
        """Raise ``ValueError`` on impossible settings."""
        for name, kind in _FIELD_TYPES.items():
            value = getattr(self, name)
            if kind is float and not math.isfinite(value):
                raise ValueError(f"{name} must be a finite number; got {value!r}")
        if self.head_iters < 0 or self.torso_iters < 0:
            raise ValueError("iteration counts must be >= 0")
        if self.rays < 1 or self.checkpoint_every < 1 or self.log_every < 1 or self.occupancy_every < 1:
            raise ValueError("rays, checkpoint_every, log_every and occupancy_every must be >= 1")
        if not (self.lr > 0 and self.lr_audio > 0 and 0 < self.lr_final <= 1):
            raise ValueError("learning rates must be positive and lr_final in (0, 1]")
        if not (0 <= self.att_start <= 1 and 0 <= self.occupancy_start <= 1 and 0 <= self.pose_start <= 1):
            raise ValueError("att_start, occupancy_start and pose_start must lie in [0, 1]")
        if self.pose_lr < 0:
            raise ValueError(f"pose_lr must be >= 0 (0: the tracked poses); got {self.pose_lr}")
        if self.pose_refit < 0 or (self.pose_refit and self.pose_lr == 0):
            raise ValueError(f"pose_refit is a number of passes, >= 0, and refits learnt corrections (pose_lr > 0); got {self.pose_refit} with pose_lr {self.pose_lr}")
        if self.frames < 1 or self.rays % self.frames:
            raise ValueError(f"frames must be >= 1 and divide rays ({self.rays}); got {self.frames}")
        if self.amp not in AMP_MODES:
            raise ValueError(f"amp must be one of {AMP_MODES}; got {self.amp!r}")
        if self.mask_weight < 0 or self.lip_weight < 0:
            raise ValueError("mask_weight and lip_weight must be >= 0")
        if self.lip_frames < 1:
            raise ValueError(f"lip_frames must be >= 1; got {self.lip_frames}")
        if self.lip_patch_weight < 0:
            raise ValueError(f"lip_patch_weight must be >= 0; got {self.lip_patch_weight}")
        mouth = int(round(self.mouth_rays * (self.rays // self.frames)))
        if self.lip_patch and (self.lip_patch < MIN_PATCH or self.lip_patch**2 > mouth):
            raise ValueError(f"lip_patch is 0 or a side of at least {MIN_PATCH} rays whose square fits the {mouth} mouth rays of a frame (mouth_rays x rays / frames); got {self.lip_patch}")
        if not 0 <= self.audio_jitter <= MAX_AUDIO_JITTER:
            raise ValueError(f"audio_jitter is a shift in speech features, 0 to {MAX_AUDIO_JITTER} (half a window); got {self.audio_jitter}")
        if self.mouth_input not in (0, 1):
            raise ValueError(f"mouth_input is 0 or 1; got {self.mouth_input}")
        if self.head_planes < 0 or (self.head_planes and self.preset != "fast"):
            raise ValueError(f"head_planes is a number of residual plane sets (>= 0; 0: none) of the fast preset's head; got {self.head_planes} with preset {self.preset!r}")
        if self.head_gate < 0:
            raise ValueError(f"head_gate is a width, >= 0 (0: no gated condition); got {self.head_gate}")
        if self.torso_motion not in (0, 1):
            raise ValueError(f"torso_motion is 0 or 1; got {self.torso_motion}")
        if not -1 <= self.lip_min_signal <= 1:
            raise ValueError(f"lip_min_signal is a correlation, in [-1, 1]; got {self.lip_min_signal}")
        if not (0 <= self.mouth_rays <= 1 and 0 <= self.torso_person_rays <= 1 and 0 <= self.eye_rays <= 1 and 0 <= self.blink_frames <= 1):
            raise ValueError("mouth_rays, eye_rays, blink_frames and torso_person_rays must lie in [0, 1]")
        for key in ("head_samples", "torso_samples"):
            if getattr(self, key) != 0 and getattr(self, key) < 2:
                raise ValueError(f"{key} is 0 (the preset's) or at least 2 a pass; got {getattr(self, key)}")
        if self.head_grid != 0 and self.head_grid < 16:
            raise ValueError(f"head_grid is 0 (the preset's) or at least the planes' base resolution, 16; got {self.head_grid}")
        if self.head_grid and self.preset != "fast":
            raise ValueError(f"head_grid sets the fast preset's tri-plane; the {self.preset!r} preset has none")
        if self.head_width < 0 or (self.head_width and self.preset != "fast"):
            raise ValueError(f"head_width is 0 (the preset's) or a width of the fast preset's head MLP; got {self.head_width} with preset {self.preset!r}")
        if self.preset not in PRESETS:
            raise ValueError(f"preset must be one of {PRESETS}; got {self.preset!r}")

    @staticmethod
    def from_stored(d: dict) -> "TrainConfig":
        """The schedule a run folder stored (``run.json``'s ``"train"``): as :meth:`from_dict`, but
        a key added after the run was written takes the value that run trained with
        (:data:`LATER_KEYS`), not today's default."""
        return TrainConfig.from_dict({**LATER_KEYS, **d} if isinstance(d, dict) else d)

    @staticmethod
    def from_dict(d: object, base: "TrainConfig | None" = None) -> "TrainConfig":
        """From a dict (a ``--config`` JSON file) whose keys replace those of ``base`` (default: the
        defaults). Unknown keys, a non-object and a value of the wrong type (named by its key) are
        ``TypeError`` / ``ValueError``."""
        if not isinstance(d, dict):
            raise TypeError(f"a training config is a JSON object of TrainConfig fields; got a {type(d).__name__}")
        check_config_keys(d, TrainConfig, "training config")
        for key, value in d.items():
            kind = _FIELD_TYPES[key]
            ok = isinstance(value, str) if kind is str else isinstance(value, kind if kind is int else (int, float)) and not isinstance(value, bool)
            if not ok:
                raise TypeError(f"training config key {key!r} must be {_TYPE_WORDS[kind]}; got {value!r}")
        return replace(base or TrainConfig(), **{k: float(v) if _FIELD_TYPES[k] is float else v for k, v in d.items()})


PRESETS = ("fast", "paper")
LATER_KEYS: dict[str, object] = {"lip_weight": 0.0, "mouth_input": 0, "torso_motion": 0, "pose_lr": 0.0}
"""Keys added to the schedule after runs were written without them, with the value those runs
trained with (the audio code from the photometric loss alone, the torso from the pose and the
code, the tracked poses as they were)."""
_FIELD_TYPES: dict[str, type] = {f.name: {"int": int, "float": float, "str": str}[f.type] for f in fields(TrainConfig)}  # type: ignore[index]
_TYPE_WORDS = {int: "an integer", float: "a number", str: "a string"}
