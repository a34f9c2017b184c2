"""Ridge regression scored by blocked cross-validation: how well a linear map predicts a per-frame
series (a mouth opening) from per-frame inputs (feature windows) on frames it was not fitted on.

Frames in clip order share their neighbours' audio, so folds are contiguous blocks with a guard
of left-out frames on either side (:func:`blocked_folds`). Used by ``adnerf lip-signal``
(:mod:`adnerf.evaluation.lip_signal`) and by training, which asks the audio code to predict the
mouth only where the audio does (:mod:`adnerf.model.mouth_target`).
"""

from __future__ import annotations

import itertools

import numpy as np

__all__ = ["blocked_cv_corr", "blocked_folds", "pearson", "ridge_fit_predict"]


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two series; NaN when either is constant."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.std() == 0 or b.std() == 0:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


def ridge_fit_predict(x_fit: np.ndarray, y_fit: np.ndarray, x_pred: np.ndarray, strength: float = 0.1) -> np.ndarray:
    """Fit a ridge map ``x -> y`` and apply it.

    The columns of ``x`` are standardised on the fitted rows (a constant column is centred and
    left unscaled), ``y`` is centred, and the penalty is ``strength`` times the number of fitted
    rows, so the same strength suits clips of any length. Solved in the primal (``D x D``) or the
    dual (``n x n``) form, whichever is smaller; both give the same map.

    Args:
        x_fit: ``(n, D)`` inputs of the fitted rows.
        y_fit: ``(n,)`` targets.
        x_pred: ``(m, D)`` inputs to predict.
        strength: Penalty per fitted row (> 0).

    Returns:
        ``(m,)`` predictions, float64.
    """
    x_fit, x_pred = np.asarray(x_fit, np.float64), np.asarray(x_pred, np.float64)
    y_fit = np.asarray(y_fit, np.float64)
    if x_fit.ndim != 2 or x_pred.ndim != 2 or x_fit.shape[1] != x_pred.shape[1] or y_fit.shape != (x_fit.shape[0],):
        raise ValueError(f"ridge needs x_fit (n, D), y_fit (n,) and x_pred (m, D); got {x_fit.shape}, {y_fit.shape}, {x_pred.shape}")
    if not strength > 0:
        raise ValueError(f"the ridge strength must be positive; got {strength}")
    n, d = x_fit.shape
    mean, std = x_fit.mean(axis=0), x_fit.std(axis=0)
    std = np.where(std > 0, std, 1.0)
    a, b = (x_fit - mean) / std, (x_pred - mean) / std
    y0 = y_fit.mean()
    lam = strength * n
    if d <= n:
        w = np.linalg.solve(a.T @ a + lam * np.eye(d), a.T @ (y_fit - y0))
    else:
        w = a.T @ np.linalg.solve(a @ a.T + lam * np.eye(n), y_fit - y0)
    return b @ w + y0


def blocked_folds(n: int, blocks: int, guard: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Contiguous cross-validation folds over ``n`` frames in clip order.

    Returns ``blocks`` pairs ``(fit, test)``: the test blocks tile ``0 .. n-1`` (sizes differing by
    at most one), and each fit set is every frame more than ``guard`` frames away from its test
    block.

    Raises:
        ValueError: Fewer than 2 blocks, a negative guard, or too few frames to leave at least 8
            fitted frames and 4 tested frames per fold.
    """
    if blocks < 2 or guard < 0:
        raise ValueError(f"cross-validation needs >= 2 blocks and a guard >= 0; got {blocks}, {guard}")
    edges = np.linspace(0, n, blocks + 1).round().astype(int)
    frames = np.arange(n)
    folds = []
    for lo, hi in itertools.pairwise(edges):
        fit = frames[(frames < lo - guard) | (frames >= hi + guard)]
        test = frames[lo:hi]
        if len(test) < 4 or len(fit) < 8:
            raise ValueError(f"{n} frames are too few for {blocks} blocks with a guard of {guard} frames")
        folds.append((fit, test))
    return folds


def blocked_cv_corr(x: np.ndarray, y: np.ndarray, blocks: int = 6, guard: int = 8, strength: float = 0.1) -> list[float]:
    """The Pearson correlation of each block of :func:`blocked_folds` with the ridge map fitted on
    the frames outside it (:func:`ridge_fit_predict`), in clip order; ``nan`` for a block whose
    target never changes.

    Args:
        x: ``(N, D)`` inputs (or ``(N, ...)``, flattened per frame).
        y: ``(N,)`` targets.
        blocks: Cross-validation blocks.
        guard: Frames left out on either side of a tested block.
        strength: Ridge penalty per fitted row.
    """
    x = np.asarray(x, np.float64)
    x = x.reshape(x.shape[0], -1)
    y = np.asarray(y, np.float64)
    return [pearson(ridge_fit_predict(x[fit], y[fit], x[te], strength), y[te]) for fit, te in blocked_folds(len(y), blocks, guard)]
