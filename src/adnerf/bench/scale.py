"""``adnerf bench scale VIDEO``: what a longer clip costs, in time and memory.

A user's clip may be ten seconds or five minutes. This benchmark makes clips of several lengths
from one clip (resized to ``size`` pixels, then looped, frames and audio together, or cut short:
:func:`looped_clip`) and, for each, measures in child processes of its own:

* **preprocess**: ``adnerf preprocess`` of the clip: wall time, each step's seconds and seconds per
  frame (from the dataset's report), the process's peak resident memory;
* **train**: ``adnerf train`` for ``steps`` head iterations and ``steps // 2`` torso iterations:
  seconds per step of each stage (the run's own clock, setup excluded), peak resident memory, and
  the bytes a frame of the clip holds in memory while training (its uint8 frame and labels).

Each length's row also holds the dataset's size on disk. ``growth`` compares the longest clip
with the shortest: each preprocessing step's seconds per frame, the training seconds per step and
the peak memory, as ratios (1.0: the cost per frame does not grow with the clip's length). A
length's dataset is reused when it exists (its preprocessing measurements are stored beside it);
the training run is made afresh.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

__all__ = ["bench_scale", "format_scale_table", "looped_clip"]

# The child runs the command, then writes its own peak resident memory (bytes) to the file its
# first argument names (the parent's getrusage would also count the pages a child shares with a
# large parent between fork and exec).
CHILD = (
    "import sys\n"
    "from adnerf.cli import main\n"
    "from adnerf.memory import peak_rss_bytes\n"
    "try:\n"
    "    code = main(sys.argv[2:])\n"
    "finally:\n"
    "    open(sys.argv[1], 'w').write(str(peak_rss_bytes() or ''))\n"
    "raise SystemExit(code)"
)


def looped_clip(video: str | Path, seconds: float, out: str | Path) -> tuple[Path, dict]:
    """``video`` looped (or cut short) to ``seconds``, frames and audio together, written to ``out``.

    Frame ``k`` of the result is frame ``k mod n`` of the clip's ``n`` frames; the audio of one
    pass is the clip's audio from its first frame's time, ``n / fps`` seconds of it (padded with
    silence where the track is shorter), so every pass starts on a frame and its sound. Frames are
    read once and written one at a time. An existing ``out`` is reused.

    Args:
        video: The clip (with or without audio).
        seconds: Length of the result; rounded to whole frames, at least one.
        out: The ``.mp4`` to write.

    Returns:
        The path and ``{"frames", "fps", "passes", "clip_frames"}``.
    """
    from ..io import AudioTrack, VideoWriter, read_video

    if not seconds > 0 or not math.isfinite(seconds):
        raise ValueError(f"a clip length must be a positive number of seconds; got {seconds}")
    clip = read_video(video)
    n, fps = len(clip.frames), clip.fps or len(clip.frames) / max(float(clip.timestamps[-1] - clip.timestamps[0]), 1e-9)
    count = max(1, round(seconds * fps))
    out = Path(out)
    info = {"frames": count, "fps": fps, "passes": count / n, "clip_frames": n}
    if out.exists():
        return out, info
    audio = None
    if clip.audio is not None:
        track = clip.audio.starting_at(float(clip.timestamps[0]))
        rate = track.sample_rate
        per_pass = round(n / fps * rate)
        one = np.zeros(per_pass, np.float32)
        one[: min(per_pass, len(track.samples))] = track.samples[:per_pass]
        total = round(count / fps * rate)
        audio = AudioTrack(np.resize(one, total), rate, 0.0)  # np.resize repeats the pass
    with VideoWriter(out, fps, audio) as writer:
        for k in range(count):
            writer.write(clip.frames[k % n])
    return out, info


def _child(argv: list[str], log_path: Path) -> tuple[float, float | None]:
    """Run ``adnerf ARGV`` in a child process; its wall seconds and peak resident memory (GiB;
    ``None`` where the system does not report a child's). Raises ``RuntimeError`` with the end of
    its output when it fails."""
    t0 = time.perf_counter()
    peak_file = log_path.with_suffix(".peak")
    peak_file.unlink(missing_ok=True)
    with open(log_path, "w") as logf:
        proc = subprocess.Popen([sys.executable, "-c", CHILD, str(peak_file), *argv], stdout=logf, stderr=subprocess.STDOUT)
        proc.wait()
    wall = time.perf_counter() - t0
    text = peak_file.read_text().strip() if peak_file.exists() else ""
    peak = int(text) / 2**30 if text else None
    if proc.returncode != 0:
        tail = log_path.read_text(errors="replace")[-2000:].replace("\r", "\n")
        raise RuntimeError(f"adnerf {' '.join(argv[:1])} failed (exit {proc.returncode}); the end of its output ({log_path}):\n{tail}")
    return wall, peak


def _disk_mib(folder: Path) -> float:
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file()) / 2**20


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b <= 0 else round(a / b, 3)


def bench_scale(
    video: str | Path,
    *,
    seconds: Sequence[float] = (10.0, 50.0, 300.0),
    size: int | None = 512,
    steps: int = 40,
    device: str = "cpu",
    work: str | Path = "adnerf_bench_scale",
    preprocess_args: Sequence[str] = (),
    log: Callable[[str], None] = print,
) -> dict:
    """Preprocess and train clips of several lengths made from one clip; time and memory of each.

    Args:
        video: The clip (one person, static camera, with audio).
        seconds: Lengths of the clips made from it (looped or cut), seconds.
        size: Longer side in pixels the clip is resized to first (``None``: as it is).
        steps: Head iterations of each timed training run (the torso gets half, at least one).
        device: ``"cpu"`` or ``"cuda"`` (training).
        work: Folder for the clips, datasets, runs and the children's logs.
        preprocess_args: Extra ``adnerf preprocess`` arguments (e.g. ``["--focal", "600"]``).
        log: Where step messages go.

    Returns:
        ``{"video", "size", "steps", "device", "rows": [...], "growth": {...}}``: a row per length
        (see the module docstring) and the longest clip's costs per frame over the shortest's.
    """
    from ..formats.dataset import DatasetFolder, frame_bytes, read_meta
    from ..formats.run_folder import RunFolder
    from .real import resized_video

    lengths = sorted({float(s) for s in seconds})
    if not lengths or not all(s > 0 and math.isfinite(s) for s in lengths):
        raise ValueError(f"clip lengths must be positive numbers of seconds; got {list(seconds)}")
    if steps < 1:
        raise ValueError(f"the timed training needs at least one step; got {steps}")
    if not Path(video).is_file():
        raise ValueError(f"{video}: no such video")
    folder = Path(work) / f"{Path(video).stem}_{size or 'native'}"
    folder.mkdir(parents=True, exist_ok=True)
    source, _ = resized_video(video, size, folder)
    rows = []
    for length in lengths:
        here = folder / f"{length:g}s"
        here.mkdir(exist_ok=True)
        log(f"{length:g} s: making the clip")
        clip, info = looped_clip(source, length, here / f"clip_{length:g}s.mp4")
        data, measured = here / "data", here / "preprocess_cost.json"
        if not (measured.exists() and DatasetFolder(data).is_dataset()):
            log(f"{length:g} s: preprocessing {info['frames']} frames")
            shutil.rmtree(data, ignore_errors=True)
            wall, peak = _child(["preprocess", str(clip), "-o", str(data), *preprocess_args], here / "preprocess.log")
            measured.write_text(json.dumps({"wall_s": wall, "peak_rss_gib": peak}))
        cost = json.loads(measured.read_text())
        report = json.loads(DatasetFolder(data).report.read_text())
        frames = int(report["frames"])
        timings = {k: float(v) for k, v in report["timings_s"].items()}
        run = here / "run"
        shutil.rmtree(run, ignore_errors=True)
        log(f"{length:g} s: training {steps} + {max(1, steps // 2)} steps")
        config = here / "train_config.json"
        config.write_text(json.dumps({"head_iters": steps, "torso_iters": max(1, steps // 2), "checkpoint_every": 10 * steps, "log_every": steps}))
        _, train_peak = _child(["train", str(data), "-o", str(run), "--config", str(config), "--device", device], here / "train.log")
        elapsed = RunFolder(run).elapsed()
        meta = read_meta(data)
        rows.append(
            {
                "seconds": length,
                "frames": frames,
                "width": meta.width,
                "height": meta.height,
                "fps": meta.fps,
                "passes": round(info["passes"], 3),
                "preprocess_s": round(cost["wall_s"], 1),
                "preprocess_steps_s": {k: round(v, 1) for k, v in timings.items()},
                "preprocess_ms_per_frame": {k: round(1e3 * v / frames, 2) for k, v in timings.items()},
                "preprocess_peak_rss_gib": None if cost["peak_rss_gib"] is None else round(cost["peak_rss_gib"], 2),
                "train_seconds_per_step": {"head": round(elapsed["head"] / steps, 4), "torso": round(elapsed["torso"] / max(1, steps // 2), 4)},
                "train_peak_rss_gib": None if train_peak is None else round(train_peak, 2),
                "data_bytes_per_frame": frame_bytes(meta),
                "dataset_disk_mib": round(_disk_mib(data), 1),
            }
        )
    first, last = rows[0], rows[-1]
    growth = {
        "from_seconds": first["seconds"],
        "to_seconds": last["seconds"],
        "preprocess_ms_per_frame": {k: _ratio(v, first["preprocess_ms_per_frame"].get(k)) for k, v in last["preprocess_ms_per_frame"].items()},
        "train_seconds_per_step": {k: _ratio(v, first["train_seconds_per_step"][k]) for k, v in last["train_seconds_per_step"].items()},
        "preprocess_peak_rss": _ratio(last["preprocess_peak_rss_gib"], first["preprocess_peak_rss_gib"]),
        "train_peak_rss": _ratio(last["train_peak_rss_gib"], first["train_peak_rss_gib"]),
    }
    return {"video": str(video), "size": size, "steps": steps, "device": device, "rows": rows, "growth": growth}


def format_scale_table(result: dict) -> str:
    """The rows as a text table: per length, preprocessing per step (ms a frame), memory, training."""
    rows = result["rows"]
    steps = list(rows[0]["preprocess_ms_per_frame"])
    head = f"{'clip':>7} {'frames':>6} {'prep s':>7} " + " ".join(f"{s:>8}" for s in steps) + f" {'prep GiB':>8} {'head s/it':>9} {'torso s/it':>10} {'train GiB':>9} {'KB/frame':>8} {'disk MiB':>8}"
    lines = [head, f"{'':>23}" + " ".join(f"{'ms/frame':>8}" for _ in steps)]

    def gib(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.2f}"

    for r in rows:
        per = " ".join(f"{r['preprocess_ms_per_frame'][s]:>8.1f}" for s in steps)
        lines.append(
            f"{r['seconds']:>6g}s {r['frames']:>6} {r['preprocess_s']:>7.0f} {per} {gib(r['preprocess_peak_rss_gib']):>8} "
            f"{r['train_seconds_per_step']['head']:>9.3f} {r['train_seconds_per_step']['torso']:>10.3f} {gib(r['train_peak_rss_gib']):>9} "
            f"{r['data_bytes_per_frame'] / 1e3:>8.0f} {r['dataset_disk_mib']:>8.0f}"
        )
    g = result["growth"]
    if len(rows) > 1:
        worst = max(((k, v) for k, v in g["preprocess_ms_per_frame"].items() if v is not None), key=lambda kv: kv[1], default=("-", None))
        lines.append(
            f"{g['to_seconds']:g} s against {g['from_seconds']:g} s: preprocessing per frame x{worst[1]} at most ({worst[0]}); "
            f"training per step head x{g['train_seconds_per_step']['head']}, torso x{g['train_seconds_per_step']['torso']}; "
            f"peak memory preprocessing x{g['preprocess_peak_rss']}, training x{g['train_peak_rss']}"
        )
    return "\n".join(lines)
