"""Stage 1's audio jitter (``TrainConfig.audio_jitter``): the moved windows are the clip's audio
moved in time, later for a positive shift, and a stage-1 step reads the windows of one drawn
shift, for its rays and for the mouth target, while everything outside the stage reads them as
they are."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from adnerf.evaluation.landmark_metrics import INNER_PAIRS
from adnerf.formats.dataset import DatasetFolder, load_dataset
from adnerf.formats.run_folder import RunError
from adnerf.model.audio_jitter import MAX_AUDIO_JITTER, jittered_windows
from adnerf.model.talking_head import model_config
from adnerf.model.train import TrainConfig, Trainer, train
from adnerf.synth import SynthConfig, synthesize


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("aj") / "data", SynthConfig(seconds=1.6, size=32, voice="formant", seed=5))


def test_moved_windows_are_the_neighbouring_frames_audio(scene: Path) -> None:
    """At 25 fps a frame is two features long, so the windows moved by +2 (-2) features are the
    next (previous) frame's stored windows, up to the wav file's rounding; +1 moves each window's
    rows up by one. A shift of the wrong sign reads the other neighbour."""
    ds = load_dataset(scene)
    assert ds.meta.fps == 25.0
    stored = torch.as_tensor(ds.features)
    moved = jittered_windows(ds, 2)
    assert moved.shape == (5, *stored.shape) and moved.dtype == torch.float32
    torch.testing.assert_close(moved[2], stored.float(), rtol=0, atol=0)  # shift 0: the stored windows themselves

    def close(a: torch.Tensor, b: torch.Tensor) -> float:
        return float((a - b).abs().median())

    inner = slice(1, -1)  # frames whose neighbours exist
    assert close(moved[4][inner], stored[2:]) < 1e-3 and close(moved[0][inner], stored[:-2]) < 1e-3
    assert close(moved[4][inner], stored[:-2]) > 0.05  # what the wrong sign would read
    assert close(moved[3][:, :-1], stored[:, 1:]) < 1e-3 and close(moved[1][:, 1:], stored[:, :-1]) < 1e-3
    with pytest.raises(ValueError, match=f"1 to {MAX_AUDIO_JITTER}"):
        jittered_windows(ds, MAX_AUDIO_JITTER + 1)


def test_a_stage_one_step_reads_one_drawn_shift_and_the_rest_reads_the_stored_windows(scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data = tmp_path / "data"
    shutil.copytree(scene, data)
    jaw = load_dataset(data).truth.jaw
    landmarks = np.zeros((len(jaw), 68, 2))  # lips that open and widen with the jaw: the mouth target's
    landmarks[:, 45, 0] = 10.0
    landmarks[:, [b for _, b in INNER_PAIRS], 1] = 1.0 + 10.0 * jaw[:, None]
    landmarks[:, 54, 0] = 5.0 + jaw
    np.save(DatasetFolder(data).landmarks, landmarks)
    ds = load_dataset(data)
    root = tmp_path / "run"
    root.mkdir()
    tr = Trainer(root, ds, model_config(ds.meta), TrainConfig(rays=256, head_iters=12, torso_iters=2, log_every=6, audio_jitter=1, lip_min_signal=-1), "cpu", progress=False)
    assert tr.jittered is not None and tr.jittered.shape[0] == 3
    seen: list[tuple[str, int]] = []  # (stage, the shift of the windows read) of every code the model makes
    frame_codes = tr.model.frame_codes

    def recording(windows: torch.Tensor, frames: object = None, batch: int = 512) -> torch.Tensor:
        shifts = [k - 1 for k in range(3) if torch.equal(windows, tr.jittered[k])]
        assert len(shifts) == 1  # the windows of one shift, never a blend
        seen.append(("head" if tr.head_step < 12 else "torso", shifts[0]))
        return frame_codes(windows, frames, batch)

    monkeypatch.setattr(tr.model, "frame_codes", recording)
    tr.fit()
    head = [s for stage, s in seen if stage == "head"]
    assert {-1, 1} <= set(head)  # both moves drawn in 12 steps
    # Each step's codes come twice, its rays' and the mouth target's, from the same shift.
    assert tr.mouth_probe is not None and len(head) % 2 == 0 and all(a == b for a, b in zip(head[::2], head[1::2]))
    assert all(s == 0 for stage, s in seen if stage == "torso")  # the torso stage reads them as they are
    assert tr.step_windows is tr.windows


def test_audio_jitter_is_checked_and_refused_for_features_it_cannot_cut_again(scene: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="audio_jitter is a shift"):
        TrainConfig(audio_jitter=MAX_AUDIO_JITTER + 1).validate()
    with pytest.raises(ValueError, match="audio_jitter is a shift"):
        TrainConfig(audio_jitter=-1).validate()
    assert TrainConfig.from_stored({"head_iters": 10}).audio_jitter == 0  # runs stored before the key: none
    doc = json.loads((scene / "meta.json").read_text())
    imported = tmp_path / "imported"
    shutil.copytree(scene, imported)
    doc["feature_kind"] = "deepspeech"
    (imported / "meta.json").write_text(json.dumps(doc))
    with pytest.raises(RunError, match="audio_jitter cuts the windows again"):
        train(imported, tmp_path / "run", config=TrainConfig(head_iters=2, torso_iters=1, audio_jitter=1), progress=False)
    assert not (tmp_path / "run" / "checkpoint.pt").exists()
    np.testing.assert_array_equal(np.load(imported / "features.npy"), np.load(scene / "features.npy"))
