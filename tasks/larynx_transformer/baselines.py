"""The baselines of ``task=larynx_transformer``: ridge regression on a causal window of psi, and the RMSE."""
from __future__ import annotations

import numpy as np

from data.pairs import LarynxSequence


def window_features(psi: np.ndarray, window: int) -> np.ndarray:
    """Causal window features [T, 55*window + 1]: psi[t-window+1..t] (first frame repeated before 0), then 1."""
    padded = np.concatenate([np.repeat(psi[:1], window - 1, axis=0), psi]).astype(np.float64)
    columns = [padded[k:k + len(psi)] for k in range(window)]
    return np.concatenate(columns + [np.ones((len(psi), 1))], axis=1)


def _gram(sequences: list[LarynxSequence], window: int) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Sums X^T X, X^T y, y^T y and the frame count over sequences."""
    gram, cross, yy, count = 0.0, 0.0, 0.0, 0
    for s in sequences:
        x, y = window_features(s.psi, window), s.tau.astype(np.float64)
        gram, cross, yy, count = gram + x.T @ x, cross + x.T @ y, yy + y @ y, count + len(y)
    return gram, cross, yy, count


def _solve_ridge(gram: np.ndarray, cross: np.ndarray, lam: float) -> np.ndarray:
    penalty = np.full(len(gram), lam)
    penalty[-1] = 0.0  # the intercept is not shrunk
    return np.linalg.solve(gram + np.diag(penalty), cross)


def ridge_groups(train: list[LarynxSequence]) -> list[str]:
    """What the ridge's lambda is cross-validated over, per sequence: its take where takes hold several
    sequences (clips of a recording, or several people's tau on one recording), else its subject, else the
    sequence itself."""
    takes, subjects = [s.take for s in train], [str(s.subject) for s in train]
    if len(set(takes)) < len(takes) and len(set(takes)) >= 2:
        return takes
    if len(set(subjects)) >= 2:
        return subjects
    return [s.name for s in train]


def fit_ridge(train: list[LarynxSequence], window: int, lambdas: list[float], folds: int = 5
              ) -> tuple[np.ndarray, float]:
    """Ridge weights [55*window+1] and the chosen lambda.

    lambda minimises the squared error of cross-validation over up to ``folds`` folds of the groups of
    :func:`ridge_groups` (takes, subjects or sequences: never frames of one recording on both sides); the
    weights are then refitted on everything.
    """
    groups = ridge_groups(train)
    names = sorted(set(groups))
    if len(names) < 2:
        gram, cross, _, _ = _gram(train, window)
        best = float(lambdas[len(lambdas) // 2])
        return _solve_ridge(gram, cross, best), best
    fold_of = {name: i % min(folds, len(names)) for i, name in enumerate(names)}
    parts = [_gram([s for s, g in zip(train, groups) if fold_of[g] == f], window)
             for f in range(min(folds, len(names)))]
    gram_all, cross_all = sum(p[0] for p in parts), sum(p[1] for p in parts)
    errors = np.zeros(len(lambdas))
    for gram, cross, yy, _ in parts:
        for j, lam in enumerate(lambdas):
            w = _solve_ridge(gram_all - gram, cross_all - cross, lam)
            errors[j] += w @ gram @ w - 2 * w @ cross + yy  # squared error on the held-out fold
    best = float(lambdas[int(np.argmin(errors))])
    return _solve_ridge(gram_all, cross_all, best), best


def rmse(predictions: list[np.ndarray], sequences: list[LarynxSequence]) -> float:
    """Root mean square tau error over all frames of all sequences (UV units)."""
    errors = np.concatenate([p - s.tau for p, s in zip(predictions, sequences)])
    return float(np.sqrt(np.mean(errors.astype(np.float64) ** 2)))
