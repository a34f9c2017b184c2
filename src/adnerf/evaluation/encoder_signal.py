"""How well the audio encoder itself, trained on nothing but the mouth, predicts a held-out opening.

The ridge figures of :mod:`adnerf.evaluation.lip_signal` bound what a *linear* map of the
feature windows tells about the mouth. Training's audio encoder is not linear: stage 1 reads each
window with :class:`~adnerf.audio.nets.AudioNet`. This module trains that network (a fresh one,
with a linear read-out on its code) on the training frames to predict their inner-lip opening and
nothing else, and scores its predictions on the held-out frames: the lip sync that training's own
encoder reaches when the whole of its capacity and every gradient go to the mouth. A radiance field
driven by the encoder's code draws the mouth at best as well as that code carries it, so this is
the ceiling of the held-out ``mouth_open_corr`` of a run on the clip, measured in seconds instead
of a training run.

Protocol: windows standardised per feature on the training frames; the opening standardised on
the training frames; ``seeds`` networks, each trained for ``epochs`` passes over the training
frames in shuffled batches of ``batch`` with Adam at ``lr`` on the squared error; the held-out
prediction is the mean of the networks' predictions (an ensemble), whose Pearson correlation with
the true opening is reported beside the mean of the single networks' correlations. Nothing of the
held-out frames is seen before they are scored, and the epoch count is fixed in advance (never
chosen on the held-out frames).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..audio.nets import AudioNet
from ..ridge import pearson

__all__ = ["EncoderSignal", "encoder_signal"]


@dataclass(frozen=True)
class EncoderSignal:
    """The held-out correlation of :func:`encoder_signal`.

    Attributes:
        ensemble_corr: Pearson correlation of the mean prediction of the networks with the true
            held-out opening.
        single_corr: Mean over the networks of each one's correlation.
        seeds: Networks trained.
        epochs: Passes over the training frames each.
    """

    ensemble_corr: float
    single_corr: float
    seeds: int
    epochs: int


def encoder_signal(
    windows: np.ndarray,
    opening: np.ndarray,
    train: Sequence[int],
    test: Sequence[int],
    *,
    epochs: int = 50,
    seeds: int = 3,
    batch: int = 64,
    lr: float = 5e-4,
    moved: np.ndarray | None = None,
    progress: Callable[[int], None] | None = None,
) -> EncoderSignal:
    """Train AudioNet + a linear read-out on the training frames' opening; score the held-out ones.

    Args:
        windows: ``(N, 16, D)`` feature windows, one per frame (what training's encoder reads).
        opening: ``(N,)`` true inner-lip opening per frame (any scale).
        train: Frames to train on (at least two, with an opening that varies).
        test: Held-out frames to score (at least two).
        epochs: Passes over the training frames per network (> 0).
        seeds: Networks trained, seeded ``0 .. seeds - 1`` (> 0).
        batch: Frames per step.
        lr: Adam's learning rate.
        moved: ``(S, N, 16, D)`` the windows moved in time by ``S`` shifts
            (:func:`~adnerf.model.audio_jitter.moved_windows`, the jitter training can apply):
            each training sample reads the windows of a shift drawn for it; the held-out
            frames are scored on ``windows``. ``None``: no jitter.
        progress: Called with 1 after each finished epoch of each network.

    Returns:
        The ensemble's and the single networks' held-out correlations.

    Raises:
        ValueError: Windows not ``(N, 16, D)``, an opening of another length, non-finite values,
            too few frames, an opening constant over the training frames, a non-positive count,
            or ``moved`` not ``(S, N, 16, D)`` of ``windows``' frames and width.
    """
    x = np.asarray(windows, np.float64)
    y = np.asarray(opening, np.float64)
    if x.ndim != 3 or x.shape[1] != 16:
        raise ValueError(f"the encoder reads windows (N, 16, D); got {x.shape}")
    if y.shape != (x.shape[0],):
        raise ValueError(f"one opening per window: {x.shape[0]} windows, openings of shape {y.shape}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("feature windows and openings must be finite")
    if epochs < 1 or seeds < 1 or batch < 1:
        raise ValueError(f"epochs, seeds and batch must be positive; got {epochs}, {seeds}, {batch}")
    if moved is not None and (moved.ndim != 4 or moved.shape[1:] != x.shape or not np.isfinite(moved).all()):
        raise ValueError(f"moved windows must be finite, (S, {', '.join(map(str, x.shape))}); got {moved.shape}")
    tr, te = np.asarray(train, np.int64), np.asarray(test, np.int64)
    if len(tr) < 2 or len(te) < 2:
        raise ValueError(f"the encoder needs at least two training and two held-out frames; got {len(tr)} and {len(te)}")
    y_sd = y[tr].std()
    if not y_sd > 0:
        raise ValueError("the opening does not vary over the training frames: nothing to learn")
    mean, sd = x[tr].mean(axis=(0, 1)), x[tr].std(axis=(0, 1))
    sd = np.where(sd > 0, sd, 1.0)  # a constant feature is centred, not scaled
    xs = torch.from_numpy(((x - mean) / sd).astype(np.float32))
    ys = torch.from_numpy(((y - y[tr].mean()) / y_sd).astype(np.float32))
    # The training frames' inputs, one row a shift: (S, n_train, 16, D); S = 1 without jitter.
    x_tr = xs[tr][None] if moved is None else torch.from_numpy(((np.asarray(moved, np.float64)[:, tr] - mean) / sd).astype(np.float32))
    y_tr, x_te = ys[tr], xs[te]
    preds = []
    for seed in range(seeds):
        g = torch.Generator().manual_seed(seed)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)  # the layers' initialisation
            net, head = AudioNet(x.shape[2]), torch.nn.Linear(64, 1)
        opt = torch.optim.Adam([*net.parameters(), *head.parameters()], lr=lr)
        for _ in range(epochs):
            order = torch.randperm(len(tr), generator=g)
            for b in range(0, len(order), batch):
                pick = order[b : b + batch]
                shift = torch.randint(len(x_tr), (len(pick),), generator=g) if len(x_tr) > 1 else torch.zeros(len(pick), dtype=torch.int64)
                loss = (head(net(x_tr[shift, pick]))[:, 0] - y_tr[pick]).square().mean()
                opt.zero_grad()
                loss.backward()
                opt.step()
            if progress is not None:
                progress(1)
        with torch.no_grad():
            preds.append(head(net(x_te))[:, 0].double().numpy())
    truth = y[te]
    return EncoderSignal(pearson(np.mean(preds, axis=0), truth), float(np.mean([pearson(p, truth) for p in preds])), seeds, epochs)
