"""SyncNet's LSE-D / LSE-C plumbing: checkpoint loading, crops, windows and the offset's sign.

No released weights are needed: a random SyncNet is built and saved, and the scoring is checked
end to end with a hand-made encoder pair whose embeddings are exact (a bright frame, a loud
audio frame), so a clip whose lips move a known number of frames after the sound must come out at
that offset with zero distance.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from adnerf.evaluation.syncnet import (
    CROP_SIZE,
    MAX_SHIFT,
    SyncNet,
    distance_curve,
    face_crops,
    load_syncnet,
    mfcc_16k,
    sync_scores,
)


def _random_syncnet(embedding: int = 1024) -> SyncNet:
    torch.manual_seed(0)
    net = SyncNet(embedding)
    for m in net.modules():  # non-trivial batch-norm statistics, so eval mode matters
        if isinstance(m, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d, torch.nn.BatchNorm3d)):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
    return net.eval()


def test_checkpoint_loads_bit_for_bit_in_every_layout(tmp_path: Path) -> None:
    net = _random_syncnet(256)
    aud, lip = torch.randn(2, 1, 13, 20), torch.randn(2, 3, 5, CROP_SIZE, CROP_SIZE)
    with torch.no_grad():
        want = (net.forward_aud(aud), net.forward_lip(lip))
    state = net.state_dict()
    layouts = {"plain": state, "prefixed": {f"__S__.{k}": v for k, v in state.items()}, "wrapped": {"state_dict": {f"module.{k}": v for k, v in state.items()}}}
    for name, obj in layouts.items():
        torch.save(obj, tmp_path / f"{name}.model")
        loaded = load_syncnet(tmp_path / f"{name}.model")
        assert not loaded.training
        with torch.no_grad():
            assert torch.equal(loaded.forward_aud(aud), want[0]), name
            assert torch.equal(loaded.forward_lip(lip), want[1]), name


def test_bad_checkpoints_are_refused_with_a_reason(tmp_path: Path) -> None:
    (tmp_path / "text.model").write_text("not a checkpoint")
    with pytest.raises(ValueError, match="could not be read"):
        load_syncnet(tmp_path / "text.model")
    torch.save({"lin0.model.1.weight": torch.zeros(1, 64, 1, 1)}, tmp_path / "lpips.pth")
    with pytest.raises(ValueError, match="missing"):
        load_syncnet(tmp_path / "lpips.pth")
    state = _random_syncnet().state_dict()
    state["netcnnlip.0.weight"] = torch.zeros(96, 1, 5, 7, 7)  # a grey-scale variant
    torch.save(state, tmp_path / "grey.model")
    with pytest.raises(ValueError, match="netcnnlip.0.weight"):
        load_syncnet(tmp_path / "grey.model")


def test_face_crop_geometry_and_channel_order() -> None:
    # Box (80, 60)-(120, 100): half-size 20, centre (100, 80). The crop spans rows 80 - 20 = 60
    # to 80 + 1.8 * 20 = 116 and columns 100 - 1.4 * 20 = 72 to 128: paint exactly that red.
    frame = np.zeros((200, 200, 3), np.uint8)
    frame[..., 2] = 255
    frame[60:116, 72:128] = (255, 0, 0)
    crops = face_crops(frame[None], np.array([[80.0, 60.0, 120.0, 100.0]]))
    assert crops.shape == (1, CROP_SIZE, CROP_SIZE, 3)
    inner = crops[0, 4:-4, 4:-4].astype(int)
    assert (inner[..., 2] == 255).all() and (inner[..., 0] == 0).all()  # BGR: red is the last channel
    # A box at the left edge, half-size 20 centred at u = 20: the crop's columns -8 .. 48 start 8
    # (of 56) columns outside the frame, which are the reference's grey 110: 32 of 224 pixels.
    edge = face_crops(frame[None], np.array([[0.0, 60.0, 40.0, 100.0]]))[0]
    assert (edge[:, :30] == 110).all() and not (edge[:, 34:] == 110).any()


def test_distance_curve_matches_the_reference_loop() -> None:
    g = torch.Generator().manual_seed(1)
    video, audio = torch.randn(9, 4, generator=g, dtype=torch.float64), torch.randn(9, 4, generator=g, dtype=torch.float64)
    s = 3
    curve = distance_curve(video, audio, s)
    padded = torch.cat([torch.zeros(s, 4, dtype=torch.float64), audio, torch.zeros(s, 4, dtype=torch.float64)])
    loop = torch.stack([torch.stack([torch.nn.functional.pairwise_distance(video[i : i + 1], padded[i + k : i + k + 1])[0] for k in range(2 * s + 1)]) for i in range(9)]).mean(0)
    torch.testing.assert_close(curve, loop, rtol=0, atol=1e-12)


class _Oracle(torch.nn.Module):
    """Exact embeddings: per window frame, "bright" (lips) and "loud" (audio) as 0 / 1."""

    def __init__(self) -> None:
        super().__init__()
        self.dummy = torch.nn.Parameter(torch.zeros(()))

    def forward_lip(self, x: torch.Tensor) -> torch.Tensor:  # (B, 3, 5, H, W)
        return (x.mean((1, 3, 4)) > 128).double()

    def forward_aud(self, x: torch.Tensor) -> torch.Tensor:  # (B, 1, 13, 20): c0 is the log energy
        return (x[:, 0, 0, ::4] > 10).double()  # each frame's first MFCC column lies inside it


@pytest.mark.parametrize("lag", [-3, 0, 2])
def test_lips_moving_after_the_sound_give_a_positive_offset(lag: int) -> None:
    fps, n = 25, 48
    rng = np.random.default_rng(4)
    loud = rng.random(n) < 0.4
    samples = np.zeros(n * 640, np.float32)
    for f in np.flatnonzero(loud):
        samples[f * 640 : f * 640 + 540] = 0.3 * rng.standard_normal(540)  # silent before the next frame's first MFCC window
    bright = np.roll(loud, lag)  # the lips show frame f's sound at frame f + lag
    crops = np.where(bright[:, None, None, None], 200, 20).astype(np.uint8) * np.ones((n, 8, 8, 3), np.uint8)
    scores = sync_scores(_Oracle(), crops, samples)
    assert scores.windows == n - 5
    assert scores.offset_frames == lag
    assert scores.lse_d < 0.5  # the wrapped-around frames of np.roll cost a little
    assert scores.lse_c > 1.0
    assert len(scores.curve) == 2 * MAX_SHIFT + 1 and fps == 25


def test_mfcc_columns_follow_the_audio_clock() -> None:
    samples = np.zeros(16000, np.float32)
    samples[8000:8640] = 0.5  # frame 12.5's worth of sound: 0.500 to 0.540 s
    cc = mfcc_16k(samples)
    assert cc.shape[0] == 13
    loud = np.flatnonzero(cc[0] > 0)
    assert loud.min() >= 48 and loud.max() <= 54  # 10 ms hops, 25 ms windows around 0.50-0.54 s


def test_sync_scores_refuse_a_clip_too_short() -> None:
    with pytest.raises(ValueError, match="at least 6 frames"):
        sync_scores(_Oracle(), np.zeros((5, 8, 8, 3), np.uint8), np.zeros(5 * 640, np.float32))
