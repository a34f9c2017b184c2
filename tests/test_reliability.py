"""Reliability: no command deletes or replaces a user's file, mixes two runs, or ends in a traceback.

Each test reproduces a case that went wrong before (data loss, silently wrong results, crashes on
valid data, tracebacks), through the command line (``adnerf.cli.main``) where a user would meet it.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import stat
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from adnerf.cli import main
from adnerf.io import AudioTrack
from adnerf.formats.dataset import DatasetError, check_poses, load_dataset, write_wav
from adnerf.model.layers import RadianceLayer
from adnerf.model.train import TrainConfig, train
from adnerf.formats.outputs import (
    OutputError,
    check_file_output,
    check_folder_output,
    check_frames_folder,
)
from adnerf.synth import SynthConfig, synthesize

SMALL = SynthConfig(seconds=1.2, size=24, voice="formant", seed=5)
SYNTH_ARGS = ["--seconds", "1", "--size", "16", "--voice", "formant"]
CFG = {"head_iters": 8, "torso_iters": 4, "rays": 64, "lr": 0.005, "log_every": 2, "checkpoint_every": 4}


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("rel") / "data", SMALL)


@pytest.fixture(scope="module")
def run(scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return train(scene, tmp_path_factory.mktemp("relrun") / "run", config=TrainConfig(**CFG), progress=False)


def _fails(argv: list[str], message: str, capsys: pytest.CaptureFixture) -> None:
    """The command exits 2 with one line holding ``message`` and no traceback."""
    capsys.readouterr()  # drop what earlier commands printed
    assert main(argv) == 2, argv
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err, (argv, err)
    assert err.strip().count("\n") == 0 or "usage:" in err, err  # one line (argparse adds its usage)


def _tree(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` with its bytes: what 'changed nothing' compares."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------------ data loss


def test_overwrite_replaces_only_what_adnerf_made(tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    user = tmp_path / "userdir"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    _fails(["synth", "-o", str(user), "--overwrite", *SYNTH_ARGS], "is not an adnerf dataset", capsys)
    assert (user / "notes.txt").read_text() == "mine"

    # The folder holding the input video is never replaced, even when it is an adnerf dataset.
    me = tmp_path / "me"
    assert main(["synth", "-o", str(me), *SYNTH_ARGS]) == 0
    clip = me / "video.mp4"
    _fails(["preprocess", str(clip), "-o", str(me), "--overwrite"], "holds this command's input", capsys)
    assert clip.exists() and not list(tmp_path.glob(".me.*"))

    # The current folder and those above it are never replaced.
    inner = tmp_path / "a" / "b"
    inner.mkdir(parents=True)
    (inner / "keep.txt").write_text("x")
    monkeypatch.chdir(inner)
    _fails(["synth", "-o", "..", "--overwrite", *SYNTH_ARGS], "current folder", capsys)
    _fails(["synth", "-o", ".", "--overwrite", *SYNTH_ARGS], "current folder", capsys)
    assert (inner / "keep.txt").exists()

    # What --overwrite is for: replacing an adnerf dataset.
    before = (me / "meta.json").read_text()
    assert main(["synth", "-o", str(me), "--overwrite", "--seconds", "1.2", "--size", "16", "--voice", "formant"]) == 0
    assert (me / "meta.json").read_text() != before and not (me / "notes.txt").exists()
    # Without --overwrite an existing one is refused; an empty folder is filled.
    _fails(["synth", "-o", str(me), *SYNTH_ARGS], "already exists", capsys)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["synth", "-o", str(empty), *SYNTH_ARGS]) == 0 and (empty / "meta.json").exists()


def test_render_never_writes_over_inputs_or_existing_files(scene: Path, run: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    talk = tmp_path / "talk.wav"
    shutil.copy(scene / "audio.wav", talk)
    original = talk.read_bytes()
    base = ["render", str(run), "--audio", str(talk)]
    # The input itself, under its own name or through a link.
    video = tmp_path / "talk.mp4"
    shutil.copy(scene / "video.mp4", video)
    _fails(["render", str(run), "--audio", str(video), "-o", str(video)], "is also an input", capsys)
    link = tmp_path / "link.mp4"
    link.symlink_to(video)
    _fails(["render", str(run), "--audio", str(video), "-o", str(link)], "is also an input", capsys)
    assert talk.read_bytes() == original and video.read_bytes() == (scene / "video.mp4").read_bytes()

    out = tmp_path / "out.mp4"
    old_umask = os.umask(0o022)
    try:
        assert main([*base, "-o", str(out)]) == 0
    finally:
        os.umask(old_umask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o644  # a normal file, not mkstemp's 0600
    first = out.read_bytes()
    _fails([*base, "-o", str(out)], "--overwrite", capsys)
    assert out.read_bytes() == first
    out.chmod(0o640)
    assert main([*base, "-o", str(out), "--overwrite"]) == 0

    # --frames: never inside a dataset, never over existing frames without --overwrite.
    frames_before = _tree(scene / "frames")
    _fails([*base, "-o", str(tmp_path / "f1.mp4"), "--frames", str(scene / "frames")], "lies inside the adnerf dataset", capsys)
    assert _tree(scene / "frames") == frames_before and not (tmp_path / "f1.mp4").exists()
    pngs = tmp_path / "pngs"
    pngs.mkdir()
    (pngs / "000000.png").write_bytes(b"mine")
    _fails([*base, "-o", str(tmp_path / "f2.mp4"), "--frames", str(pngs)], "already holds 000000.png", capsys)
    assert (pngs / "000000.png").read_bytes() == b"mine" and not (tmp_path / "f2.mp4").exists()
    assert main([*base, "-o", str(tmp_path / "f3.mp4"), "--frames", str(pngs), "--overwrite"]) == 0
    assert cv2.imread(str(pngs / "000000.png")) is not None


def test_output_checks_directly(tmp_path: Path) -> None:
    a = tmp_path / "a.txt"
    a.write_text("x")
    with pytest.raises(OutputError, match="is also an input"):
        check_file_output(tmp_path / "." / "a.txt", inputs=[a], overwrite=True)
    with pytest.raises(OutputError, match="is a file"):
        check_folder_output(a, "dataset", overwrite=True)
    with pytest.raises(OutputError, match="is a file, not a folder"):
        check_folder_output(a / "sub", "run")  # its parent is a file: not writable
    with pytest.raises(OutputError, match="is a file"):
        check_frames_folder(a)
    check_file_output(tmp_path / "new.mp4", inputs=[a, None])  # fine: a new file


# -------------------------------------------------------------------------- silent wrong results


def test_resume_refuses_another_dataset_and_changes_nothing(scene: Path, run: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    other = synthesize(tmp_path / "other", SynthConfig(seconds=1.2, size=24, voice="formant", seed=6))  # same size and width, other content
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    before = _tree(copy)
    _fails(["train", str(other), "-o", str(copy), "--resume"], "trained on another dataset", capsys)
    assert _tree(copy) == before
    # The same content in another folder is the same dataset.
    moved = shutil.copytree(scene, tmp_path / "moved")
    assert main(["train", str(moved), "-o", str(copy), "--resume"]) == 0


def test_resume_continues_the_stored_config(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({k: v for k, v in CFG.items() if k not in ("head_iters", "torso_iters")}))
    out = tmp_path / "run"
    # The README's split-stage workflow.
    assert main(["train", str(scene), "-o", str(out), "--stage", "head", "--iters", "6", "--config", str(cfg)]) == 0
    assert main(["train", str(scene), "-o", str(out), "--stage", "torso", "--resume", "--iters", "2"]) == 0
    stored = json.loads((out / "run.json").read_text())["train"]
    assert (stored["rays"], stored["lr"], stored["head_iters"], stored["torso_iters"]) == (64, 0.005, 6, 2)
    ckpt = torch.load(out / "checkpoint.pt", weights_only=False)
    assert (ckpt["stages"]["head"]["step"], ckpt["stages"]["torso"]["step"]) == (6, 2)
    # More iterations is a change a resume may make; other settings are refused, changing nothing.
    assert main(["train", str(scene), "-o", str(out), "--stage", "torso", "--resume", "--iters", "3", "--amp", "off"]) == 0
    assert json.loads((out / "run.json").read_text())["train"]["rays"] == 64
    before = _tree(out)
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"rays": 1024}))
    _fails(["train", str(scene), "-o", str(out), "--resume", "--config", str(other)], "rays 64 -> 1024", capsys)
    assert _tree(out) == before


def test_scale_trains_the_schedule_in_fewer_larger_steps_and_only_for_a_new_run(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({k: v for k, v in CFG.items() if k not in ("head_iters", "torso_iters")}))
    out = tmp_path / "run"
    assert main(["train", str(scene), "-o", str(out), "--iters", "6", "--config", str(cfg), "--scale", "2"]) == 0
    stored = json.loads((out / "run.json").read_text())["train"]
    assert (stored["rays"], stored["frames"], stored["head_iters"], stored["torso_iters"]) == (128, 2, 3, 2)  # --iters 6: 6 + 3, then halved
    assert math.isclose(stored["lr"], 0.005 * math.sqrt(2))
    ckpt = torch.load(out / "checkpoint.pt", weights_only=False)
    assert (ckpt["stages"]["head"]["step"], ckpt["stages"]["torso"]["step"]) == (3, 2)
    before = _tree(out)
    _fails(["train", str(scene), "-o", str(out), "--resume", "--scale", "2"], "drop --scale", capsys)
    _fails(["train", str(scene), "-o", str(tmp_path / "r0"), "--scale", "0"], "must be >= 1", capsys)
    assert _tree(out) == before and not (tmp_path / "r0").exists()


def test_torso_stage_alone_is_refused_before_writing(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    _fails(["train", str(scene), "-o", str(tmp_path / "r"), "--stage", "torso"], "needs a finished stage 1", capsys)
    assert not (tmp_path / "r").exists()


def test_render_refuses_bad_poses_and_angles(scene: Path, run: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    n = int(np.floor(SMALL.seconds * SMALL.fps))
    good = np.load(scene / "poses.npy")[:n]
    cases = {"nan": good.copy(), "mirror": good.copy(), "shear": good.copy()}
    cases["nan"][3, 0, 3] = np.nan
    cases["mirror"][2, :3, 0] *= -1  # det R = -1
    cases["shear"][1, 0, 1] += 0.3
    messages = {"nan": "finite rigid", "mirror": "det -1", "shear": "not orthonormal"}
    for name, poses in cases.items():
        path = tmp_path / f"{name}.npy"
        np.save(path, poses)
        out = tmp_path / f"{name}.mp4"
        _fails(["render", str(run), "--audio", str(scene / "audio.wav"), "--poses", str(path), "-o", str(out)], messages[name], capsys)
        assert not out.exists()
    _fails(["render", str(run), "--audio", str(scene / "audio.wav"), "--yaw", "nan", "-o", str(tmp_path / "y.mp4")], "finite", capsys)
    with pytest.raises(DatasetError, match="det -1"):
        check_poses(cases["mirror"], "x")
    check_poses(good, "x")


def test_features_and_evaluate_refuse_what_they_used_to_accept(scene: Path, run: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    wav = scene / "audio.wav"
    _fails(["features", str(wav), "-o", str(tmp_path / "f.npy"), "--fps", "0"], "must be > 0", capsys)
    empty = tmp_path / "empty.wav"
    write_wav(empty, AudioTrack(np.zeros(0, dtype=np.float32), 16000))
    _fails(["features", str(empty), "-o", str(tmp_path / "e.npy"), "--kind", "logmel"], "holds no samples", capsys)
    assert not (tmp_path / "e.npy").exists()
    # Existing output: refused without --overwrite.
    assert main(["features", str(wav), "-o", str(tmp_path / "g.npy"), "--kind", "logmel", "--fps", "25"]) == 0
    _fails(["features", str(wav), "-o", str(tmp_path / "g.npy"), "--kind", "logmel"], "--overwrite", capsys)

    # Fewer precomputed windows than the audio has frames: a warning and a shorter clip.
    windows = np.load(scene / "features.npy")[:10]
    short = tmp_path / "short.npy"
    np.save(short, windows)
    with pytest.warns(UserWarning, match="10 feature windows but the audio gives 30 frames"):
        from adnerf.commands.render_video import render_audio_video
        from adnerf.model.train import load_run

        summary = render_audio_video(load_run(run), wav, tmp_path / "s.mp4", features=short)
    assert summary["frames"] == 10 and summary["audio_seconds"] == pytest.approx(10 / SMALL.fps, abs=1e-3)

    # A dataset of other intrinsics or fps than the run's.
    for key, value in (("intrinsics", [30.0, 30.0, 12.0, 12.0]), ("fps", 30.0)):
        other = shutil.copytree(scene, tmp_path / f"other_{key}")
        meta = json.loads((other / "meta.json").read_text())
        meta[key] = value
        (other / "meta.json").write_text(json.dumps(meta))
        _fails(["evaluate", str(run), str(other)], f"does not match the run's training data ({key}", capsys)


# ---------------------------------------------------------------------- crashes on valid data


def test_training_goes_through_frames_without_torso_and_fully_skipped_steps(scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data = shutil.copytree(scene, tmp_path / "data")
    ds = load_dataset(data)
    for i in ds.meta.train[::2]:  # half the training frames: no torso pixel (as preprocess writes for close crops)
        labels = ds.parsing[i].copy()
        labels[labels == 2] = 0
        cv2.imwrite(str(data / "parsing" / f"{i:06d}.png"), labels)
    cfg = TrainConfig(**{**CFG, "occupancy_start": 0.0, "occupancy_every": 1})
    calls = []

    def empty_grid(layer: RadianceLayer, cond: object, **kwargs: object) -> float:  # an estimate that marks every cell empty
        grid = layer.occupancy
        grid.density = torch.zeros_like(grid.density)
        grid.occupied = torch.zeros_like(grid.occupied)
        calls.append(layer.name)
        return 0.0

    monkeypatch.setattr(RadianceLayer, "update_occupancy", empty_grid)
    root = train(data, tmp_path / "run", config=cfg, progress=False)
    ckpt = torch.load(root / "checkpoint.pt", weights_only=False)
    assert (ckpt["stages"]["head"]["step"], ckpt["stages"]["torso"]["step"]) == (8, 4) and {"head", "torso"} <= set(calls)
    assert all(torch.isfinite(v).all() for v in ckpt["model"].values() if v.is_floating_point())


# --------------------------------------------------------------------- one line, not a traceback


def test_bad_configs_and_checkpoints_give_one_line_and_leave_nothing(scene: Path, run: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    configs = {
        "list": ([1, 2], "JSON object"),
        "type": ({"rays": "1024"}, "'rays' must be an integer"),
        "preset": ({"preset": "huge"}, "preset must be one of"),
        "nan": ({"lr": float("nan")}, "lr must be a finite number"),
    }
    for name, (doc, message) in configs.items():
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps(doc))
        _fails(["train", str(scene), "-o", str(tmp_path / f"run_{name}"), "--config", str(path)], message, capsys)
        assert not (tmp_path / f"run_{name}").exists()

    for content in (b"", b"not a checkpoint at all"):
        broken = shutil.copytree(run, tmp_path / f"broken{len(content)}")
        (broken / "checkpoint.pt").write_bytes(content)
        _fails(["train", str(scene), "-o", str(broken), "--resume"], "damaged or incomplete checkpoint", capsys)
        _fails(["render", str(broken), "--audio", str(scene / "audio.wav"), "-o", str(tmp_path / "x.mp4")], "damaged or incomplete checkpoint", capsys)
        _fails(["evaluate", str(broken), str(scene)], "damaged or incomplete checkpoint", capsys)
    (tmp_path / "bad_run").mkdir()
    (tmp_path / "bad_run" / "run.json").write_text("{oops")
    _fails(["evaluate", str(tmp_path / "bad_run"), str(scene)], "unreadable or damaged", capsys)


def test_unwritable_or_file_outputs_are_refused_before_work(scene: Path, run: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    blocked = a_file / "sub"  # below a file: cannot be created, for root too
    _fails(["synth", "-o", str(a_file), *SYNTH_ARGS], "is a file", capsys)
    _fails(["synth", "-o", str(blocked), *SYNTH_ARGS], "is a file, not a folder", capsys)
    _fails(["train", str(scene), "-o", str(a_file)], "is a file", capsys)
    _fails(["train", str(scene), "-o", str(blocked)], "is a file, not a folder", capsys)
    _fails(["demo", "-o", str(a_file)], "is a file", capsys)
    _fails(["preprocess", str(scene / "video.mp4"), "-o", str(a_file)], "is a file", capsys)
    _fails(["features", str(scene / "audio.wav"), "-o", str(blocked / "f.npy")], "is a file, not a folder", capsys)
    _fails(["render", str(run), "--audio", str(scene / "audio.wav"), "-o", str(blocked / "r.mp4")], "is a file, not a folder", capsys)
    assert a_file.read_text() == "x"
    # A run folder that holds other files is not taken over.
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    _fails(["train", str(scene), "-o", str(user)], "already exists and is not empty", capsys)
    assert sorted(p.name for p in user.iterdir()) == ["notes.txt"]


def test_resumed_log_holds_each_step_once(scene: Path, tmp_path: Path) -> None:
    cfg = TrainConfig(**{**CFG, "log_every": 1})
    out = tmp_path / "run"
    train(scene, out, config=cfg, progress=False, max_steps=6)  # "killed" after step 6; the checkpoint holds 4
    assert torch.load(out / "checkpoint.pt", weights_only=False)["stages"]["head"]["step"] == 4
    with open(out / "log.jsonl", "a") as f:
        f.write('{"stage": "head", "st')  # a line cut by the kill
    train(scene, out, progress=False, resume=True)
    rows = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    steps = [(r["stage"], r["step"]) for r in rows]
    assert steps == [("head", s) for s in range(1, 9)] + [("torso", s) for s in range(1, 5)]


def test_argument_ranges_are_checked_and_shown(capsys: pytest.CaptureFixture) -> None:
    for argv, message in (
        (["synth", "-o", "x", "--seconds", "nan"], "finite"),
        (["synth", "-o", "x", "--fps", "inf"], "finite"),
        (["synth", "-o", "x", "--size", "100000"], "must be <= 1024"),
        (["preprocess", "v.mp4", "-o", "x", "--test-fraction", "1.5"], "must be <= 0.9"),
        (["train", "d", "-o", "r", "--iters", "-3"], "must be >= 0"),
    ):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
    assert main(["synth", "--help"]) == 0
    out = capsys.readouterr().out
    assert "16 to 1024 (default: 128)" in " ".join(out.split()) and "(default: 18.0)" in out
    with pytest.raises(ValueError, match="would not fit in memory"):
        SynthConfig(seconds=600, size=1024).validate()


def test_a_clip_too_large_for_memory_is_refused_in_one_line_before_work(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    # A clip that would not fit is refused up front with what it needs and what there is, never
    # an out-of-memory kill part way through.
    import adnerf.memory
    from adnerf.io import read_video, write_video
    from adnerf.memory import MemoryNeedError, require

    n = load_dataset(scene).meta.n_frames
    need = n * SMALL.size * SMALL.size * 4  # uint8 frames (3 bytes a pixel) and labels (1)
    monkeypatch.setattr(adnerf.memory, "available_bytes", lambda: int(need / 0.9) + 1)
    load_dataset(scene)  # just fits
    monkeypatch.setattr(adnerf.memory, "available_bytes", lambda: int(need / 0.9) - 64)
    with pytest.raises(MemoryNeedError, match=rf"{n} frames of {SMALL.size}x{SMALL.size}"):
        load_dataset(scene)
    _fails(["train", str(scene), "-o", str(tmp_path / "run")], "available (use a shorter clip or a smaller frame size)", capsys)
    assert not (tmp_path / "run").exists()
    # Decoding a video is refused from the container's frame count, before any frame is decoded.
    video = write_video(tmp_path / "clip.mp4", np.zeros((10, 16, 16, 3), np.uint8), 25.0)
    monkeypatch.setattr(adnerf.memory, "available_bytes", lambda: 10 * 16 * 16 * 3)
    with pytest.raises(MemoryNeedError, match="10 frames of 16x16"):
        read_video(video)
    monkeypatch.setattr(adnerf.memory, "available_bytes", lambda: None)  # unknown: nothing is refused
    assert read_video(video).frames.shape == (10, 16, 16, 3)
    require(10**15, "anything", available=None)
    with pytest.raises(MemoryNeedError, match="the GPU"):
        require(10, "x", available=10, where="the GPU")


# ------------------------------------------------------------------------ one writer, interrupts


def _training_child(scene: Path, run_dir: Path, config: Path, *extra: str) -> "subprocess.Popen[str]":
    """``adnerf train`` of a run that would take very long, in a child process, once it has
    logged its first steps (so it holds the lock and has written a checkpoint)."""
    import subprocess
    import sys
    import time

    config.write_text(json.dumps({**CFG, "head_iters": 10**6, "checkpoint_every": 4}))
    child = subprocess.Popen([sys.executable, "-c", "import sys; from adnerf.cli import main; sys.exit(main(sys.argv[1:]))", "train", str(scene), "-o", str(run_dir), "--config", str(config), *extra], stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    deadline = time.time() + 120
    while not ((run_dir / "checkpoint.pt").exists() and (run_dir / "log.jsonl").exists()):
        assert child.poll() is None, child.stderr.read() if child.stderr else ""
        assert time.time() < deadline, "the training child did not start"
        time.sleep(0.2)
    return child


@pytest.mark.parametrize(("signum", "code"), [("SIGTERM", 143), ("SIGINT", 130)])
def test_a_second_writer_is_refused_and_a_signal_stops_training_with_its_checkpoint(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture, signum: str, code: int) -> None:
    import signal

    from adnerf.lock import lock_path

    run_dir = tmp_path / "run"
    child = _training_child(scene, run_dir, tmp_path / "cfg.json")
    try:
        # A second training of the same run (another terminal, a restarted job) is refused.
        _fails(["train", str(scene), "-o", str(run_dir), "--resume"], f"another adnerf writes this run: process {child.pid} on", capsys)
        with pytest.warns(UserWarning, match=r"is being trained \(process .*using its last checkpoint, head step \d+/1000000"):
            from adnerf.model.run_folder import load_run

            load_run(run_dir)  # a reader reads the last complete checkpoint, and says so
    finally:
        child.send_signal(getattr(signal, signum))
        _, err = child.communicate(timeout=120)
    # The signal finishes the step, writes a checkpoint and says where it stopped, in one line.
    assert child.returncode == code, err
    lines = [line for line in err.splitlines() if line.startswith("adnerf:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    step = int(lines[0].split("stopped at head step ")[1].split(" ")[0])
    assert lines[0].endswith(f"of 1000000 ({signum}); --resume continues")
    ckpt = torch.load(run_dir / "checkpoint.pt", weights_only=False)
    assert ckpt["stages"]["head"]["step"] == step
    logged = [json.loads(line)["step"] for line in (run_dir / "log.jsonl").read_text().splitlines()]
    assert logged == sorted(set(logged))  # each step once, in order
    assert not lock_path(run_dir).exists()  # released
    # The run resumes from there (now with an end in sight).
    (tmp_path / "more.json").write_text(json.dumps({"head_iters": step + 2}))
    assert main(["train", str(scene), "-o", str(run_dir), "--resume", "--config", str(tmp_path / "more.json"), "--stage", "head"]) == 0


def test_the_lock_of_a_killed_training_is_taken_over_with_a_warning(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    import signal

    from adnerf.lock import FolderBusyError, FolderLock, lock_owner, lock_path

    run_dir = tmp_path / "run"
    child = _training_child(scene, run_dir, tmp_path / "cfg.json")
    assert lock_owner(run_dir)["pid"] == child.pid
    child.send_signal(signal.SIGKILL)
    child.wait(timeout=60)
    assert lock_path(run_dir).exists() and lock_owner(run_dir) is None  # left behind, owner gone
    (tmp_path / "more.json").write_text(json.dumps({"head_iters": 1}))
    capsys.readouterr()
    assert main(["train", str(scene), "-o", str(run_dir), "--resume", "--config", str(tmp_path / "more.json"), "--stage", "head"]) == 0
    err = capsys.readouterr().err
    assert f"took over the lock of process {child.pid}" in err, err
    # A lock of another host cannot be checked: refused, with the file to remove.
    lock_path(tmp_path / "x").write_text(json.dumps({"pid": 1, "host": "elsewhere", "started": 0, "command": "adnerf train"}))
    with pytest.raises(FolderBusyError, match="process 1 on elsewhere .*remove .*x.adnerf-lock"):
        with FolderLock(tmp_path / "x"):
            pass
    # A half-written lock (a crash between create and write) holds nothing.
    lock_path(tmp_path / "y").write_text("{")
    with pytest.warns(UserWarning, match="took over"):
        with FolderLock(tmp_path / "y") as lock:
            assert lock.held and lock_owner(tmp_path / "y")["pid"] == os.getpid()
    assert not lock_path(tmp_path / "y").exists()


def test_dataset_writers_hold_the_lock_of_their_folder(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    import subprocess
    import sys

    from adnerf.lock import FolderLock

    # Another process holds the dataset folder's lock: synth, preprocess and import-adnerf refuse.
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from adnerf.lock import FolderLock\nwith FolderLock(sys.argv[1]):\n    print('held', flush=True); time.sleep(60)", str(tmp_path / "data")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        _fails(["synth", "-o", str(tmp_path / "data"), *SYNTH_ARGS], f"another adnerf writes this dataset: process {holder.pid}", capsys)
        video = tmp_path / "v.mp4"
        from adnerf.io import write_video

        write_video(video, np.zeros((4, 16, 16, 3), np.uint8), 25.0)
        _fails(["preprocess", str(video), "-o", str(tmp_path / "data")], f"process {holder.pid}", capsys)
        (tmp_path / "ad").mkdir()
        _fails(["import-adnerf", str(tmp_path / "ad"), "-o", str(tmp_path / "data")], f"process {holder.pid}", capsys)
    finally:
        holder.kill()
        holder.wait()
    assert not (tmp_path / "data").exists()
    with pytest.warns(UserWarning, match=f"took over the lock of process {holder.pid}"), FolderLock(tmp_path / "data"):
        pass  # this process can take it now (the killed holder is gone)


def test_sigterm_during_rendering_leaves_no_mp4_and_exits_143(run: Path, tmp_path: Path) -> None:
    import signal
    import subprocess
    import sys
    import time

    wav = tmp_path / "long.wav"
    write_wav(wav, AudioTrack((0.2 * np.sin(np.arange(16000 * 120) * 0.05)).astype(np.float32), 16000))  # 2 minutes: still rendering when the signal comes
    out = tmp_path / "out.mp4"
    child = subprocess.Popen([sys.executable, "-c", "import sys; from adnerf.cli import main; sys.exit(main(sys.argv[1:]))", "render", str(run), "--audio", str(wav), "-o", str(out)], stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    seen = ""
    deadline = time.time() + 120
    while "frame" not in seen:  # the progress bar has started: frames are being rendered
        assert child.poll() is None and time.time() < deadline, seen
        seen += child.stderr.read(1)
    child.send_signal(signal.SIGTERM)
    _, err = child.communicate(timeout=60)
    assert child.returncode == 143, seen + err
    assert "adnerf: interrupted" in err and "Traceback" not in err
    assert not out.exists() and not list(tmp_path.glob("*.mp4*"))  # nothing half-written under any name


def test_a_full_disk_keeps_the_previous_checkpoint_and_says_so_in_one_line(scene: Path, run: Path, tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    import errno

    import adnerf.model.run_folder as run_folder

    resumed = tmp_path / "run"
    shutil.copytree(run, resumed)
    before = (resumed / "checkpoint.pt").read_bytes()
    real = torch.save

    def full(obj: object, f: object, *a: object, **k: object) -> None:  # half the checkpoint, then no space
        real(obj, f, *a, **k)
        with open(f, "r+b") as h:  # type: ignore[arg-type]
            h.truncate(len(before) // 2)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(run_folder.torch, "save", full)
    (tmp_path / "more.json").write_text(json.dumps({"head_iters": CFG["head_iters"] + 4}))
    capsys.readouterr()
    assert main(["train", str(scene), "-o", str(resumed), "--resume", "--config", str(tmp_path / "more.json"), "--stage", "head"]) == 2
    err = capsys.readouterr().err  # after the training bar, closed first: one line of its own
    lines = [line for line in err.splitlines() if line.startswith("adnerf:")]
    assert len(lines) == 1 and "Traceback" not in err and lines[0].startswith(f"adnerf: error: {resumed}: the disk is full (") and "writing checkpoint.pt; the write had reached" in lines[0], err
    assert (resumed / "checkpoint.pt").read_bytes() == before  # the previous checkpoint, intact
    assert not [p.name for p in resumed.iterdir() if ".tmp" in p.name]  # no temporary left behind
    monkeypatch.setattr(run_folder.torch, "save", real)
    # The message gives the folder, the space free and how far the write got.
    from adnerf.atomic import atomic_path

    with pytest.raises(OSError, match=rf"{tmp_path}: the disk is full \(.* MiB free there\) writing x.bin; the write had reached 0.0 MiB"):
        with atomic_path(tmp_path / "x.bin") as tmp:
            tmp.write_bytes(b"12345")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert not (tmp_path / "x.bin").exists()
