"""``adnerf bench voices``: does a face learned from one voice follow another?

The synthetic scene's jaw follows the phonemes being spoken (:mod:`adnerf.audio.visemes`), so the same
sentences spoken by other espeak-ng voices, or faster, come with their own exact mouth truth.

1. **train**: one synthetic scene spoken by the training voice (``en``, 150 words/min), stored
   once per feature kind (``logmel``, ``phonemes``), and one run trained on each (the demo's
   schedule unless ``iterations`` is given). Datasets and runs are cached in the work folder.
2. **drive**: new sentences (none of them in the training speech), spoken by the training voice,
   the training voice faster, and two other voices, drive each run over the held-out poses.
3. **measure**: the rendered jaw opening is read off each frame by analysis by synthesis
   (:class:`JawReader`: the mouth crop matched against the scene rendered exactly at 21 openings
   under the same pose). Per driving voice and feature kind: the Pearson correlation over the
   frames between the read opening and the true jaw of that speech, the shift in frames (render
   late: > 0) that maximises it, and the mean absolute error; and, as the measure's own check, the
   reader's correlation on the scene rendered exactly with the true jaw (``reader_on_truth``).

The result is one dict; ``--json`` prints it, and ``WORK/bench_voices.png`` plots the tracks.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..evaluation.readers import JawReader, exact_frame

__all__ = ["DRIVE_SENTENCES", "DRIVING_VOICES", "TRAINING_VOICE", "JawReader", "Voice", "bench_voices", "format_voices_table", "mouth_follow"]

# None of these is among the training scene's sentences (adnerf.synth.SENTENCES).
DRIVE_SENTENCES = (
    "My father bought a map of the old harbour in March.",
    "Water boils faster when you put a lid on the pot.",
    "Bob and Pam will meet us by the big oak tree.",
    "How about a walk along the river after lunch?",
    "She opened the window and the cool air came in.",
    "Five purple balloons floated above the market.",
)


@dataclass(frozen=True)
class Voice:
    """An espeak-ng voice at a speaking rate.

    Attributes:
        label: How the tables name it.
        speaker: espeak-ng voice name (with a variant after ``+``).
        words_per_minute: Speaking rate.
    """

    label: str
    speaker: str
    words_per_minute: int


TRAINING_VOICE = Voice("A (training voice)", "en", 150)
DRIVING_VOICES = (
    Voice("A, new sentences", "en", 150),
    Voice("A, faster (210 wpm)", "en", 210),
    Voice("B, female (en+f3)", "en+f3", 150),
    Voice("C, US klatt (en-us+klatt)", "en-us+klatt", 150),
)


def mouth_follow(rendered: np.ndarray, truth: np.ndarray, max_shift: int = 5) -> dict:
    """How well a rendered mouth signal follows the truth: ``corr`` (Pearson, no shift),
    ``offset`` (frames; > 0: the render is late) and ``corr_at_offset`` (the best shift's)."""
    from ..evaluation.landmark_metrics import av_offset, pearson

    corr = pearson(rendered, truth)
    shift, best = av_offset(np.asarray(rendered, float), np.asarray(truth, float), max_shift)
    clean = lambda v: None if not math.isfinite(v) else round(float(v), 4)  # noqa: E731
    return {"corr": clean(corr), "offset": int(shift), "corr_at_offset": clean(best)}


def _scene(folder: Path, kind: str, seconds: float, size: int, seed: int, log: Callable[[str], None]) -> Path:
    from ..formats.dataset import DatasetFolder, read_meta
    from ..synth import SynthConfig, synthesize

    config = SynthConfig(seconds=seconds, size=size, seed=seed, voice="espeak", speaker=TRAINING_VOICE.speaker, words_per_minute=TRAINING_VOICE.words_per_minute, mouth="visemes", features=kind, test_fraction=0.1)
    if DatasetFolder(folder).is_dataset():
        meta = read_meta(folder)
        same = meta.n_frames == config.n_frames and meta.width == size and meta.feature_kind == kind
        if same and f"seed={seed} " in meta.source and f"speaker={TRAINING_VOICE.speaker} wpm={TRAINING_VOICE.words_per_minute} mouth=visemes" in meta.source:
            return folder
    log(f"synthesising the training scene ({kind} features) into {folder}")
    synthesize(folder, config, overwrite=folder.exists())
    return folder


def bench_voices(
    work: str | Path = "adnerf_bench_voices",
    *,
    kinds: Sequence[str] = ("logmel", "phonemes"),
    seconds: float = 30.0,
    drive_seconds: float = 8.0,
    size: int = 128,
    iterations: tuple[int, int] | None = None,
    seed: int = 0,
    device: str = "cpu",
    voices: Sequence[Voice] = DRIVING_VOICES,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict:
    """Train on one voice, drive with others, and measure how the mouth follows each.

    Args:
        work: Folder for the cached scenes, runs and the plot.
        kinds: Feature kinds to compare (each gets its own dataset and run).
        seconds: Length of the training scene.
        drive_seconds: Length of each driving clip.
        size: Frame size in pixels.
        iterations: ``(head, torso)`` training iterations (default: the demo's schedule).
        seed: Seed of the scene, the training and the driving sentences' order.
        device: ``"cpu"`` or ``"cuda"``.
        voices: The driving voices.
        progress: Progress bars.
        log: Where step messages go.

    Returns:
        ``{"rows": [...], ...}``: per driving voice its speaker and rate, ``reader_on_truth``, and
        per kind :func:`mouth_follow`'s figures and ``mean_abs_error``; plus the settings and the
        seconds of each step.
    """
    from ..audio.espeak import espeak_ready
    from ..audio.visemes import jaw_track
    from ..commands.demo import DEMO_TRAIN
    from ..commands.render_video import audio_frames, pingpong, render_frames
    from ..io import AudioTrack
    from ..formats.dataset import load_dataset
    from ..formats.run_folder import RunFolder
    from ..model.train import load_run, train
    from ..synth import SAMPLE_RATE, HeadModel, TorsoModel, espeak_speech

    if not espeak_ready():
        raise RuntimeError("bench voices needs espeak-ng (apt install espeak-ng): its speech and phoneme timings are the truth")
    if not kinds or any(k not in ("logmel", "phonemes") for k in kinds):
        raise ValueError(f"kinds must be logmel and/or phonemes; got {list(kinds)}")
    folder = Path(work)
    folder.mkdir(parents=True, exist_ok=True)
    seconds_spent: dict[str, float] = {}
    tcfg = replace(DEMO_TRAIN, seed=seed)
    if iterations is not None:
        tcfg = replace(tcfg, head_iters=iterations[0], torso_iters=iterations[1])
    runs, datasets = {}, {}
    t0 = time.perf_counter()
    for kind in kinds:
        data = _scene(folder / f"scene_{kind}", kind, seconds, size, seed, log)
        run_dir = folder / f"run_{kind}_{tcfg.head_iters}+{tcfg.torso_iters}_seed{seed}"
        if RunFolder(run_dir).is_run():
            train(data, run_dir, device=device, resume=True, progress=progress)
        else:
            log(f"training on {kind} features into {run_dir}")
            train(data, run_dir, config=tcfg, device=device, progress=progress)
        runs[kind], datasets[kind] = load_run(run_dir, device), load_dataset(data)
    seconds_spent["scenes_and_training"] = time.perf_counter() - t0

    ds0 = datasets[kinds[0]]
    fps = ds0.meta.fps
    plate = ds0.background.astype(np.float32) / 255.0
    t0 = time.perf_counter()
    test_poses = ds0.poses[list(ds0.meta.test)]
    reader = JawReader(ds0, test_poses)
    head, torso = HeadModel(ds0.meta.width), TorsoModel(ds0.meta.width)
    scene_plate = ds0.background.astype(np.float64) / 255.0
    seconds_spent["jaw_reader"] = time.perf_counter() - t0
    rows, tracks = [], []
    t0 = time.perf_counter()
    for voice in voices:
        speech = espeak_speech(drive_seconds, SAMPLE_RATE, seed + 1, speaker=voice.speaker, words_per_minute=voice.words_per_minute, sentences=DRIVE_SENTENCES)
        n = int(math.floor(drive_seconds * fps))
        times = np.arange(n) / fps
        jaw = jaw_track(speech.phonemes or (), times, end=drive_seconds)
        pose_index = pingpong(np.arange(len(test_poses)), n)
        poses = test_poses[pose_index]
        truth_crops = [exact_frame(head, torso, p, scene_plate, opening=o, box=reader.box(i)) for p, o, i in zip(poses, jaw, pose_index)]
        read_truth = reader.read_crops(truth_crops, pose_index)
        row: dict = {"voice": voice.label, "speaker": voice.speaker, "words_per_minute": voice.words_per_minute, "frames": n, "reader_on_truth": mouth_follow(read_truth, jaw)}
        track = {"voice": voice.label, "jaw": jaw}
        audio = AudioTrack(speech.samples, SAMPLE_RATE, 0.0)
        for kind in kinds:
            log(f"driving the {kind} run with {voice.label}")
            windows = audio_frames(audio, fps, kind, voice.label)[:n]
            clip = render_frames(runs[kind], windows, poses, plate)
            read = reader.read(clip.frames, pose_index)
            row[kind] = {**mouth_follow(read, jaw), "mean_abs_error": round(float(np.abs(read - jaw).mean()), 4)}
            track[kind] = read
        rows.append(row)
        tracks.append(track)
    seconds_spent["drive"] = time.perf_counter() - t0
    plot = _plot(folder / "bench_voices.png", tracks, kinds, fps)
    return {
        "rows": rows,
        "kinds": list(kinds),
        "training_voice": {"speaker": TRAINING_VOICE.speaker, "words_per_minute": TRAINING_VOICE.words_per_minute, "seconds": seconds},
        "drive_seconds": drive_seconds,
        "size": size,
        "head_iters": tcfg.head_iters,
        "torso_iters": tcfg.torso_iters,
        "device": device,
        "seconds": {k: round(v, 1) for k, v in seconds_spent.items()},
        "plot": str(plot),
    }


def format_voices_table(result: dict) -> str:
    """The result as a text table: per driving voice, the ceiling and each kind's correlation
    (and, where the best shift is not 0, that shift and its correlation)."""
    kinds = result["kinds"]

    def cell(f: dict) -> str:
        corr = "n/a" if f["corr"] is None else f"{f['corr']:.2f}"
        return corr if f["offset"] == 0 or f["corr_at_offset"] is None else f"{corr} ({f['corr_at_offset']:.2f} at {f['offset']:+d})"

    head = f"{'driving voice':<28}  {'reader':>7}  " + "  ".join(f"{k:>18}" for k in kinds)
    lines = [head, "-" * len(head)]
    for row in result["rows"]:
        lines.append(f"{row['voice']:<28}  {cell(row['reader_on_truth']):>7}  " + "  ".join(f"{cell(row[k]):>18}" for k in kinds))
    lines.append(
        "(correlation of the rendered jaw with the true jaw; in brackets: the best shift in frames, > 0 = render late; "
        f"reader: the same measure on exact renders; trained on {result['training_voice']['speaker']}, {result['head_iters']}+{result['torso_iters']} iterations)"
    )
    return "\n".join(lines)


def _plot(path: Path, tracks: list[dict], kinds: Sequence[str], fps: float) -> Path:
    """The true jaw and each kind's rendered jaw over time, one panel per driving voice."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(tracks), 1, figsize=(8, 1.9 * len(tracks)), sharex=True, squeeze=False)
    for ax, track in zip(axes[:, 0], tracks):
        t = np.arange(len(track["jaw"])) / fps
        ax.plot(t, track["jaw"], color="black", label="true jaw (visemes)")
        for kind, color in zip(kinds, ("tab:red", "tab:blue", "tab:green")):
            ax.plot(t, track[kind], color=color, label=f"render, {kind}", alpha=0.8)
        ax.set_title(track["voice"], fontsize=9)
        ax.set_ylabel("opening")
    axes[0, 0].legend(fontsize=7, ncol=3)
    axes[-1, 0].set_xlabel("seconds")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
