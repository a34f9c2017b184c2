"""The mouth target: the audio code is asked to predict the lip landmarks' opening and width."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from adnerf.model import train as train_module
from adnerf.formats.dataset import DatasetError, load_dataset
from adnerf.model.mouth_target import MouthProbe, mouth_targets, opening_signal
from adnerf.model.run_folder import RunError, stored_config
from adnerf.model.train import TrainConfig, Trainer, train
from adnerf.model.talking_head import ModelConfig, model_config
from adnerf.synth import SynthConfig, synthesize


def face(opening: np.ndarray, width: np.ndarray, eyes: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Landmarks ``(N, 68, 2)`` whose inner lips are ``opening`` apart, mouth corners ``width``
    apart and outer eye corners ``eyes`` apart (the other points anywhere)."""
    n = len(opening)
    lm = rng.uniform(0, 100, (n, 68, 2))
    centre = rng.uniform(40, 60, (n, 1, 2))
    for top, bottom, x in ((61, 67, -3.0), (62, 66, 0.0), (63, 65, 3.0)):
        lm[:, top] = centre[:, 0] + np.stack([np.full(n, x), -opening / 2], axis=1)
        lm[:, bottom] = centre[:, 0] + np.stack([np.full(n, x), opening / 2], axis=1)
    lm[:, 48] = centre[:, 0] - np.stack([width / 2, np.zeros(n)], axis=1)
    lm[:, 54] = centre[:, 0] + np.stack([width / 2, np.zeros(n)], axis=1)
    lm[:, 36] = centre[:, 0] + np.stack([-eyes / 2, np.full(n, -30.0)], axis=1)
    lm[:, 45] = centre[:, 0] + np.stack([eyes / 2, np.full(n, -30.0)], axis=1)
    return lm


def test_targets_are_the_opening_and_width_over_the_eye_distance_standardised_on_training_frames() -> None:
    rng = np.random.default_rng(0)
    n = 40
    opening, width, eyes = rng.uniform(0, 8, n), rng.uniform(20, 30, n), rng.uniform(40, 60, n)
    lm = face(opening, width, eyes, rng)
    train = list(range(30))
    targets, valid = mouth_targets(lm, train)
    assert targets.shape == (n, 2) and targets.dtype == np.float32 and valid.all()
    for column, raw in enumerate((opening / eyes, width / eyes)):
        mean, std = raw[train].mean(), raw[train].std()
        np.testing.assert_allclose(targets[:, column], (raw - mean) / std, atol=1e-5)
    # Scale-free: the same face twice as near the camera has the same targets.
    twice, _ = mouth_targets(2.0 * lm, train)
    np.testing.assert_allclose(twice, targets, atol=1e-5)
    # The mean and spread come from the training frames only: the held-out ones do not move them.
    moved = lm.copy()
    moved[30:] = face(opening[30:] + 50.0, width[30:], eyes[30:], rng)
    np.testing.assert_allclose(mouth_targets(moved, train)[0][:30], targets[:30], atol=1e-5)


def test_frames_without_finite_landmarks_are_left_out_and_bad_input_is_refused() -> None:
    rng = np.random.default_rng(1)
    n = 12
    lm = face(rng.uniform(0, 8, n), rng.uniform(20, 30, n), np.full(n, 50.0), rng)
    lm[3, 62] = np.nan
    lm[5, 45] = lm[5, 36]  # eye corners on each other: no scale
    targets, valid = mouth_targets(lm, range(n))
    assert valid.tolist() == [i not in (3, 5) for i in range(n)]
    assert np.isfinite(targets).all() and (targets[[3, 5]] == 0).all()
    kept = [i for i in range(n) if i not in (3, 5)]
    assert abs(targets[kept].mean(axis=0)).max() < 1e-5 and np.allclose(targets[kept].std(axis=0), 1.0, atol=1e-5)
    with pytest.raises(ValueError, match=r"\(N, 68, 2\)"):
        mouth_targets(lm[:, :67], range(n))
    with pytest.raises(ValueError, match="too few"):
        mouth_targets(lm, [3, 5])
    still = face(np.full(n, 4.0), rng.uniform(20, 30, n), np.full(n, 50.0), rng)
    with pytest.raises(ValueError, match="opening does not vary"):
        mouth_targets(still, range(n))


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small synthetic clip with landmarks whose opening follows the scene's true jaw."""
    data = synthesize(tmp_path_factory.mktemp("lips") / "data", SynthConfig(seconds=2.0, size=32, seed=5, blinks=False))
    jaw = np.load(data / "truth" / "jaw.npy")
    rng = np.random.default_rng(2)
    np.save(data / "landmarks.npy", face(2.0 + 6.0 * jaw, 24.0 + rng.normal(0, 1, len(jaw)), np.full(len(jaw), 50.0), rng))
    return data


def test_the_loss_reads_each_drawn_frames_own_code_and_target(scene: Path) -> None:
    ds = load_dataset(scene)
    tcfg = TrainConfig(head_iters=4, torso_iters=0, lip_weight=0.5, lip_frames=16, lip_min_signal=-1.0)
    trainer = Trainer(Path("unused"), ds, model_config(ds.meta), tcfg, "cpu", False)
    targets, _ = mouth_targets(ds.landmarks, ds.meta.train)
    state = trainer.generator.get_state()
    loss, weight, opt = trainer.mouth_loss()
    # The same draw, made again, and the read-out's error computed from scratch.
    frames = torch.as_tensor(ds.meta.train)[torch.randint(len(ds.meta.train), (16,), generator=torch.Generator().set_state(state))]
    codes = trainer.model.frame_codes(trainer.windows, frames)
    expected = (trainer.mouth_probe(codes) - torch.as_tensor(targets)[frames]).square().mean()
    torch.testing.assert_close(loss, expected)
    assert weight == 0.5 and opt is trainer.opt_probe
    # Without landmarks, or at weight 0, there is no read-out and no draw.
    ds.landmarks = None
    bare = Trainer(Path("unused"), ds, model_config(ds.meta), tcfg, "cpu", False)
    before = bare.generator.get_state()
    assert bare.mouth_probe is None and bare.mouth_loss() is None
    assert torch.equal(bare.generator.get_state(), before)


def test_a_step_adds_the_weighted_mouth_loss_to_the_audio_encoders_gradient(scene: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ds = load_dataset(scene)
    trainer = Trainer(Path("unused"), ds, model_config(ds.meta), TrainConfig(lip_weight=0.25, lip_frames=8, lip_min_signal=-1.0), "cpu", False)
    audio = list(trainer.model.audio_net.parameters())
    frames = torch.tensor(ds.meta.train[:8])
    codes_of = lambda: trainer.model.frame_codes(trainer.windows, frames)  # noqa: E731
    lip = lambda: trainer.mouth_probe.loss(codes_of(), trainer.mouth[frames])  # noqa: E731
    photometric = lambda: codes_of().square().mean()  # noqa: E731  (a stand-in with a gradient at the audio net)

    def grads(loss: torch.Tensor) -> list[torch.Tensor]:
        return [g.clone() for g in torch.autograd.grad(loss, audio)]

    expected = [a + 0.25 * b for a, b in zip(grads(photometric()), grads(lip()))]
    seen: list[list[torch.Tensor]] = []
    real_step = torch.optim.Adam.step

    def spy(self, *a, **kw):  # noqa: ANN001, ANN002, ANN003, ANN202
        if self is trainer.opt_head:
            seen.append([p.grad.clone() for p in audio])
        return real_step(self, *a, **kw)

    monkeypatch.setattr(torch.optim.Adam, "step", spy)
    probe_before = [p.detach().clone() for p in trainer.mouth_probe.parameters()]

    # A render whose fine colours' MSE against black is the stand-in (the coarse ones add 0).
    value = photometric().sqrt().reshape(1, 1).expand(1, 3)
    out = SimpleNamespace(final=SimpleNamespace(rgb=value), coarse=SimpleNamespace(rgb=torch.zeros(1, 3)))
    train_module._optimise([(out, torch.zeros(1, 3), torch.zeros(1, dtype=torch.bool), None)], 0.0, trainer.opt_head, extra=(lip(), 0.25, trainer.opt_probe))
    assert len(seen) == 1
    for got, want in zip(seen[0], expected):
        torch.testing.assert_close(got, want)
    # The read-out learnt too (its own optimizer stepped).
    assert any(not torch.equal(a, b) for a, b in zip(probe_before, trainer.mouth_probe.parameters()))


def test_training_fits_the_read_out_and_a_resume_restores_it(scene: Path, tmp_path: Path) -> None:
    cfg = TrainConfig(head_iters=40, torso_iters=0, lip_weight=1.0, lip_min_signal=-1.0, checkpoint_every=20, log_every=10)
    whole = train(scene, tmp_path / "whole", config=cfg, progress=False)
    split = tmp_path / "split"
    train(scene, split, config=cfg, progress=False, max_steps=20)
    train(scene, split, resume=True, progress=False)
    a = torch.load(whole / "checkpoint.pt", weights_only=False)
    b = torch.load(split / "checkpoint.pt", weights_only=False)
    for key, value in a["mouth_probe"]["model"].items():
        torch.testing.assert_close(b["mouth_probe"]["model"][key], value)
    for key, value in a["model"].items():  # the audio encoders were taught the same way
        if key.startswith("audio_net"):
            torch.testing.assert_close(b["model"][key], value)
    # The log carries the read-out's error, which falls as the codes learn the mouth.
    lips = [json.loads(line)["lip"] for line in (whole / "log.jsonl").read_text().splitlines() if json.loads(line)["stage"] == "head"]
    assert len(lips) == 4 and lips == sorted(lips, reverse=True) and lips[-1] < 0.6 * lips[0]
    # The read-out of the trained codes follows the true jaw on the training frames.
    ds = load_dataset(scene)
    trainer = Trainer(tmp_path / "whole", ds, ModelConfig.from_dict(json.loads((whole / "run.json").read_text())["model"]), cfg, "cpu", False)
    trainer.load(a)
    with torch.no_grad():
        pred = trainer.mouth_probe(trainer.model.frame_codes(trainer.windows, torch.tensor(ds.meta.train)))[:, 0].numpy()
    assert np.corrcoef(pred, ds.truth.jaw[ds.meta.train])[0, 1] > 0.8


def test_runs_stored_without_the_key_resume_without_the_mouth_target(scene: Path, tmp_path: Path) -> None:
    run = train(scene, tmp_path / "old", config=TrainConfig(head_iters=2, torso_iters=0, lip_weight=0.0), progress=False)
    doc = json.loads((run / "run.json").read_text())
    del doc["train"]["lip_weight"], doc["train"]["lip_frames"]  # as a run written before the key
    (run / "run.json").write_text(json.dumps(doc))
    assert stored_config(run).lip_weight == 0.0
    assert TrainConfig.from_dict({}).lip_weight == TrainConfig().lip_weight > 0  # a new config gets the default
    train(scene, run, config=TrainConfig(head_iters=4, torso_iters=0, lip_weight=0.0), resume=True, progress=False)
    assert "mouth_probe" not in torch.load(run / "checkpoint.pt", weights_only=False)


def test_landmarks_of_another_length_or_a_still_mouth_are_refused_with_the_way_out(scene: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad"
    shutil.copytree(scene, bad)
    np.save(bad / "landmarks.npy", np.zeros((3, 68, 2)))
    with pytest.raises(DatasetError, match="landmarks.npy has shape"):
        load_dataset(bad)
    n = len(np.load(scene / "landmarks.npy"))
    np.save(bad / "landmarks.npy", face(np.full(n, 3.0), np.full(n, 24.0), np.full(n, 50.0), np.random.default_rng(0)))
    with pytest.raises(RunError, match=r"does not vary.*lip_weight"):
        train(bad, tmp_path / "run", config=TrainConfig(head_iters=1, torso_iters=0, lip_min_signal=-1.0), progress=False)
    train(bad, tmp_path / "run", config=TrainConfig(head_iters=1, torso_iters=0, lip_weight=0.0), progress=False)


def test_probe_maps_codes_to_the_two_targets() -> None:
    probe = MouthProbe(8)
    assert probe(torch.zeros(5, 8)).shape == (5, 2)


def test_the_target_is_used_only_where_the_audio_predicts_the_opening(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A longer clip whose opening is the loudness of its feature windows' centre (a linear function
    of what the audio encoder reads) is taught the target; the same clip with openings drawn at
    random, which no audio predicts, is not, and run.json and the console say why."""
    data = synthesize(tmp_path / "long", SynthConfig(seconds=8.0, size=32, seed=6, blinks=False))
    windows = np.load(data / "features.npy")
    n = len(windows)
    rng = np.random.default_rng(3)
    loud = windows[:, 8].mean(axis=1)
    heard = face(2.0 + 6.0 * (loud - loud.min()) / np.ptp(loud), np.full(n, 24.0) + rng.normal(0, 0.5, n), np.full(n, 50.0), rng)
    np.save(data / "landmarks.npy", heard)
    cfg = TrainConfig(head_iters=1, torso_iters=0)
    ds = load_dataset(data)
    targets, valid = mouth_targets(ds.landmarks, ds.meta.train)
    assert opening_signal(ds.features, targets, valid, ds.meta.train) > 0.9
    run = train(data, tmp_path / "heard", config=cfg, progress=False)
    doc = json.loads((run / "run.json").read_text())["mouth_target"]
    assert doc["used"] and doc["signal"] > 0.9 and doc["min_signal"] == 0.2 and "mouth_probe" in torch.load(run / "checkpoint.pt", weights_only=False)
    np.save(data / "landmarks.npy", face(rng.uniform(0, 8, n), np.full(n, 24.0) + rng.normal(0, 0.5, n), np.full(n, 50.0), rng))
    ds = load_dataset(data)
    targets, valid = mouth_targets(ds.landmarks, ds.meta.train)
    assert abs(opening_signal(ds.features, targets, valid, ds.meta.train)) < 0.2
    trainer = Trainer(tmp_path / "unheard", ds, model_config(ds.meta), cfg, "cpu", True)
    assert trainer.mouth_probe is None and trainer.mouth_loss() is None
    assert not trainer.mouth_doc["used"] and "under lip_min_signal 0.2" in trainer.mouth_doc["why"] and trainer.mouth_doc["why"] in capsys.readouterr().err
    # Too few training frames to cross-validate: no target, and the reason given.
    ds.meta.train = ds.meta.train[:20]
    short = Trainer(tmp_path / "short", ds, model_config(ds.meta), cfg, "cpu", False)
    assert short.mouth_probe is None and short.mouth_doc["signal"] is None and "cannot be cross-validated" in short.mouth_doc["why"]
    # -1 uses the target whatever the audio predicts.
    assert Trainer(tmp_path / "forced", ds, model_config(ds.meta), TrainConfig(lip_min_signal=-1.0), "cpu", False).mouth_probe is not None
    with pytest.raises(ValueError, match="lip_min_signal"):
        TrainConfig(lip_min_signal=1.5).validate()


def test_the_mouth_code_is_zero_for_the_mean_mouth_and_tells_openings_apart() -> None:
    from adnerf.model.conditions import SIGNAL_WIDTHS, mouth_code

    assert torch.equal(mouth_code(torch.zeros(2)), torch.zeros(SIGNAL_WIDTHS["mouth"]))
    v = torch.linspace(-4.0, 4.0, 81, dtype=torch.float64)
    codes = mouth_code(torch.stack([v, torch.zeros_like(v)], -1))
    assert torch.all(torch.diff(codes[:, 0]) > 0)  # the lowest frequency orders the openings
    assert torch.equal(codes[:, 6:], torch.zeros_like(codes[:, 6:]))  # the width's half reads the width alone
    gaps = torch.cdist(codes, codes) + torch.eye(len(v), dtype=torch.float64)
    assert gaps.min() > 0.01  # every opening 0.1 apart has a code of its own


def test_a_head_that_reads_the_mouth_is_given_each_frames_own_when_training_and_the_read_out_when_rendering(scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Training conditions a frame on its landmarks' mouth (and an eye batch on the mouth of the
    frame whose speech it borrows); rendering on the model's read-out of the code; a run trained
    with mouth_input 0 reads no mouth."""
    from adnerf.model.run_folder import load_run
    from adnerf.model.talking_head import TalkingHead

    cfg = TrainConfig(head_iters=6, torso_iters=2, lip_weight=1.0, lip_min_signal=-1.0, mouth_input=1, checkpoint_every=6, log_every=2)
    run_dir = train(scene, tmp_path / "mouth", config=cfg, progress=False)
    doc = json.loads((run_dir / "run.json").read_text())
    assert doc["model"]["mouth_dim"] == 12
    run = load_run(run_dir)
    assert run.model.reads_mouth and run.model.layers["head"].conditions[-1] == "mouth" and not any("mouth" in c for c in run.model.layers["torso"].conditions)
    ds = load_dataset(scene)
    trainer = Trainer(run_dir, ds, run.model.config, cfg, "cpu", False)
    targets, _ = mouth_targets(ds.landmarks, ds.meta.train)
    code = torch.zeros(run.model.config.audio_dim)
    pose = ds.head_pose(3)
    torch.testing.assert_close(trainer.condition(3, code, pose).extra["mouth"], torch.as_tensor(targets[3]))
    torch.testing.assert_close(trainer.condition(3, code, pose, speech=7).extra["mouth"], torch.as_tensor(targets[7]))
    with torch.no_grad():
        codes = run.model.frame_codes(torch.as_tensor(ds.features), [0, 5])
        rendered = run.model.condition(codes[1], pose).extra["mouth"]
        torch.testing.assert_close(rendered, run.model.mouth_from_codes(codes[1]))
    assert not torch.equal(rendered, torch.as_tensor(targets[5]))  # the read-out, not the landmarks
    # The probe the trainer fits is the model's own (saved with the weights rendering loads).
    assert trainer.mouth_probe is trainer.model.mouth_probe
    # mouth_input 0: the mouth target alone, as before.
    plain = train(scene, tmp_path / "plain", config=TrainConfig(head_iters=2, torso_iters=0, lip_weight=1.0, lip_min_signal=-1.0, mouth_input=0), progress=False)
    assert json.loads((plain / "run.json").read_text())["model"]["mouth_dim"] == 0
    assert not load_run(plain).model.reads_mouth
    with pytest.raises(ValueError, match="does not read the mouth"):
        TalkingHead(model_config(ds.meta)).mouth_from_codes(code)
