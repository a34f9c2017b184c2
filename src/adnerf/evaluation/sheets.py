"""Contact sheets: grids of frames with titles, for looking at renders beside the truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["contact_sheet"]


def contact_sheet(path: Path, rows: list[np.ndarray], titles: list[str], row_labels: list[str]) -> Path:
    """A grid of images (rows of ``(k, H, W, 3)`` uint8 stacks) with column titles, saved as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_rows, n_cols = len(rows), len(titles)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(2.2 * n_cols, 2.2 * n_rows), squeeze=False)
    for r, stack in enumerate(rows):
        for c in range(n_cols):
            ax = axes[r][c]
            ax.imshow(stack[c])
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(titles[c], fontsize=9)
            if c == 0:
                ax.set_ylabel(row_labels[r], fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
