"""A refitted discovery subset's Gauss–Newton model at its optimum (`LocalModel`), which the
discovery's bootstrap scores on each resample of the training segments (`cost`): the
linearisation at c = 0 misranks strong terms, a step from the subset's own optimum does
not."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True, eq=False)
class LocalModel:
    """The normal equations of a refitted subset at its optimum.

    - `gram` (S, P, P), `rhs` (S, P), `squares` (S,): J'J, J'r and r'r of each training
        segment's rows (the bootstrap reweights them);
    - `rest_gram` (P, P), `rest_rhs` (P,), `rest_squares`: the same for the rows every
        resample keeps (the priors);
    - `penalty`: the subset's criterion's k ln n + 2 ln C(P, |S|).
    """

    gram: np.ndarray
    rhs: np.ndarray
    squares: np.ndarray
    rest_gram: np.ndarray
    rest_rhs: np.ndarray
    rest_squares: float
    penalty: float

    @classmethod
    def at_optimum(cls, r, jac, segment_rows, n, penalty) -> LocalModel:
        """From the residuals `r` and Jacobian `jac` at the optimum: rows `segment_rows`
        per training segment, rows from `n` on the priors'."""
        rest = np.arange(n, r.shape[0])
        return cls(
            gram=np.stack([jac[rows].T @ jac[rows] for rows in segment_rows]),
            rhs=np.stack([jac[rows].T @ r[rows] for rows in segment_rows]),
            squares=np.asarray([r[rows] @ r[rows] for rows in segment_rows]),
            rest_gram=jac[rest].T @ jac[rest],
            rest_rhs=jac[rest].T @ r[rest],
            rest_squares=float(r[rest] @ r[rest]),
            penalty=float(penalty),
        )

    def cost(self, weights: np.ndarray) -> float:
        """The subset's cost Σr² on a resample (`weights` per segment): one Gauss–Newton
        step from its optimum on the reweighted normal equations."""
        gram = np.tensordot(weights, self.gram, 1) + self.rest_gram
        rhs = np.tensordot(weights, self.rhs, 1) + self.rest_rhs
        squares = float(weights @ self.squares) + self.rest_squares
        scale = np.sqrt(np.maximum(np.diag(gram), 1e-300))
        try:
            step = np.linalg.solve(gram / scale[:, None] / scale[None, :], rhs / scale)
        except np.linalg.LinAlgError:
            return squares
        return squares - float((rhs / scale) @ step)
