"""How well can the audio encoder learn the jaw from a synthetic scene's training speech?

A probe, not part of the product: an :class:`adnerf.audio.AudioNet` plus one linear output is
trained to regress the scene's true mouth opening (``truth/jaw.npy``) from the training frames'
feature windows (standardised as :class:`adnerf.model.talking_head.TalkingHead` does), and its Pearson
correlation and RMS error are printed on the training and the held-out frames. The demo's scene
length was chosen with it (``docs/ARCHITECTURE.md``).

Run: ``python tools/jaw_probe.py DATASET [--iters 2000] [--seed 0]`` on a folder written by
``adnerf synth``.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from adnerf.audio import AudioNet
from adnerf.formats.dataset import load_dataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="a synthetic dataset (with truth/)")
    parser.add_argument("--iters", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    ds = load_dataset(args.dataset, truth=True)
    if ds.truth is None:
        raise SystemExit(f"{args.dataset} has no truth/ folder; the probe needs a synthetic scene")
    windows = torch.as_tensor(ds.features, dtype=torch.float32)
    jaw = torch.as_tensor(np.asarray(ds.truth.jaw), dtype=torch.float32)
    train, test = torch.as_tensor(list(ds.meta.train)), torch.as_tensor(list(ds.meta.test))
    flat = windows[train].reshape(-1, windows.shape[-1])
    x = (windows - flat.mean(0)) / flat.std(0).clamp_min(1e-6)

    torch.manual_seed(args.seed)
    net, out = AudioNet(windows.shape[-1]), torch.nn.Linear(64, 1)
    opt = torch.optim.Adam([*net.parameters(), *out.parameters()], lr=2e-3)
    for _ in range(args.iters):
        batch = train[torch.randint(len(train), (64,))]
        loss = (out(net(x[batch]))[:, 0] - jaw[batch]).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        pred = out(net(x))[:, 0]
    for name, idx in (("train", train), ("held-out", test)):
        corr = np.corrcoef(pred[idx].numpy(), jaw[idx].numpy())[0, 1]
        rmse = (pred[idx] - jaw[idx]).pow(2).mean().sqrt().item()
        print(f"{name:9s} frames {len(idx):4d}  jaw correlation {corr:.3f}  RMS error {rmse:.3f}")


if __name__ == "__main__":
    main()
