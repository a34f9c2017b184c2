"""Where the background moves: a screen, a window onto a street, a flag in a draught.

The background plate is one picture for the whole clip and the renderer draws it behind the person
unchanged, so any part of the background that moves while the clip is filmed comes out frozen (the
plate holds its median) and the fields may try to learn it instead. :func:`moving_regions` finds
background pixels that often differ from their own median over the clip, away from the person's
outline (where parsing errors would look like motion), and names the parts of the frame where they
gather ("top right", "middle left", ...), for the report's warning.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..formats.dataset import LABEL_BACKGROUND

__all__ = ["moving_regions"]

ROWS, COLS = ("top", "middle", "bottom"), ("left", "centre", "right")


def moving_regions(
    frames: np.ndarray,
    labels: np.ndarray,
    *,
    samples: int = 48,
    level: float = 20.0,
    often: float = 0.25,
    share: float = 0.03,
    margin: int = 7,
) -> list[dict]:
    """The parts of the frame where the background moves.

    Args:
        frames: uint8 RGB frames ``(N, H, W, 3)``.
        labels: Parsing ``(N, H, W)`` (background 0).
        samples: Frames looked at, spread over the clip.
        level: Grey-level difference from the pixel's median that counts as a change.
        often: Share of a pixel's background frames that must change for it to count as moving.
        share: Share of a part's steady background pixels that must move for the part to be named.
        margin: Pixels kept away from the person's outline in each frame.

    Returns:
        One dict per part of a 3 x 3 grid where the background moves, largest share first:
        ``{"region": "top right", "share": float, "box": [x0, y0, x1, y1]}``.
    """
    n, H, W = labels.shape
    pick = np.unique(np.linspace(0, n - 1, min(samples, n)).round().astype(int))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
    grey = np.empty((len(pick), H, W), np.float32)
    seen = np.empty((len(pick), H, W), bool)
    for k, i in enumerate(pick):
        grey[k] = cv2.cvtColor(frames[i], cv2.COLOR_RGB2GRAY)
        seen[k] = cv2.erode((labels[i] == LABEL_BACKGROUND).astype(np.uint8), kernel) > 0
    count = seen.sum(0)
    steady = count >= max(2, len(pick) // 4)  # background in enough of the frames to judge
    if not steady.any():
        return []
    # Each pixel's median over the frames that show it as background (the lower middle value):
    # the other frames sort to the end, and pixels seen too rarely are left out (steady).
    ranked = np.sort(np.where(seen, grey, np.float32(np.inf)), axis=0)
    middle = np.clip((count - 1) // 2, 0, len(pick) - 1)
    median = np.where(steady, np.take_along_axis(ranked, middle[None], axis=0)[0], 0.0).astype(np.float32)
    changed = (np.abs(grey - median[None]) > level) & seen
    moving = steady & (changed.sum(0) >= often * np.maximum(count, 1))
    out = []
    for r, row in enumerate(ROWS):
        for c, col in enumerate(COLS):
            y0, y1, x0, x1 = r * H // 3, (r + 1) * H // 3, c * W // 3, (c + 1) * W // 3
            base = int(steady[y0:y1, x0:x1].sum())
            if base < 0.05 * (y1 - y0) * (x1 - x0):
                continue  # mostly person: nothing to judge
            frac = float(moving[y0:y1, x0:x1].sum()) / base
            if frac >= share:
                out.append({"region": f"{row} {col}", "share": round(frac, 3), "box": [x0, y0, x1, y1]})
    return sorted(out, key=lambda d: -d["share"])
