"""LASSO identification on the standardized Jacobian, as in the laser-tracer calibration patent.

1. Linearize at the start: ``r ~ J dx``.
2. Frame parameters (instrument and tool) are never penalized: their columns are projected out
   of the kinematic columns and of ``r`` (their least-squares effect removed first).
3. The kinematic columns are standardized (mean 0, unit length) and ``r`` is centred, so the L1
   bound treats a degree and a millimetre alike by their effect on the TCP.
4. The L1 bound (equivalently the penalty ``alpha`` on the same path) is chosen by K-fold
   cross-validation over poses (scikit-learn's ``LassoCV``; all rows of a pose stay in one fold),
   the folds of :mod:`torchcal.data.folds`: configuration groups by default, so that a
   near-twin of a held-out pose never sits in the training part and favours a weak penalty.
5. The selected support plus the frame parameters is refitted without penalty by
   Levenberg-Marquardt, which removes the shrinkage bias of the L1 estimate.
"""

from __future__ import annotations

import numpy as np
import torch

from torchcal.data.folds import make_folds
from torchcal.identify.base import Identifier, SolveResult
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.problem import CalibrationProblem

FRAME_PREFIXES = ("base_", "tool_")


class LassoIdentifier(Identifier):
    """Sparse selection of kinematic error parameters, then an unbiased refit.

    Args:
        folds: cross-validation folds over poses.
        n_alphas: points on the regularization path.
        seed: fold assignment seed.
        selection_threshold: a standardized coefficient counts as selected above this.
        split: ``grouped`` (configuration groups of the problem's nominal robot), ``blocks``
            (row order) or ``random`` (:func:`~torchcal.data.folds.make_folds`).
        robot: nominal robot for grouped folds (default: the problem's).
    """

    name = "lasso"

    def __init__(self, folds: int = 5, n_alphas: int = 60, seed: int = 0, selection_threshold: float = 1e-12,
                 split: str = "grouped", robot=None) -> None:
        self.folds = folds
        self.split, self.robot = split, robot
        self.n_alphas = n_alphas
        self.seed = seed
        self.selection_threshold = selection_threshold
        self.alpha_: float | None = None

    def solve(self, problem: CalibrationProblem, x0: torch.Tensor) -> SolveResult:
        from sklearn.linear_model import LassoCV

        names = problem.names
        frame_mask = np.array([n.startswith(FRAME_PREFIXES) for n in names])
        r, jac = problem.jacobian(x0)
        a = (-jac).numpy()  # predicted change per parameter: r ~ a @ dx
        y = r.numpy()
        frame_cols, kin_cols = a[:, frame_mask], a[:, ~frame_mask]
        if frame_cols.shape[1]:
            q_frame, _ = np.linalg.qr(frame_cols)
            kin_cols = kin_cols - q_frame @ (q_frame.T @ kin_cols)
            y = y - q_frame @ (q_frame.T @ y)
        centred = kin_cols - kin_cols.mean(0)
        norms = np.linalg.norm(centred, axis=0)
        keep_cols = norms > 1e-12 * max(1.0, float(norms.max(initial=0.0)))
        standardized = centred[:, keep_cols] / norms[keep_cols]
        y = y - y.mean()
        rows = problem.rows_per_pose
        n_poses = len(y) // rows
        robot = self.robot if self.robot is not None else problem.model.robot
        fold_of_pose = make_folds(self.split, robot, problem.data.q[:n_poses].cpu(), k=self.folds, seed=self.seed).fold
        fold_of_row = np.repeat(fold_of_pose, rows)
        splits = [(np.flatnonzero(fold_of_row != k), np.flatnonzero(fold_of_row == k)) for k in range(self.folds)]
        model = LassoCV(alphas=self.n_alphas, cv=splits, fit_intercept=False, max_iter=20000, tol=1e-8)
        model.fit(standardized, y)
        self.alpha_ = float(model.alpha_)
        coef = np.zeros(kin_cols.shape[1])
        coef[keep_cols] = model.coef_
        kin_names = [n for n, f in zip(names, frame_mask) if not f]
        chosen = {n for n, c in zip(kin_names, coef) if abs(c) > self.selection_threshold}
        support = [i for i, n in zip(problem.free.tolist(), names) if n.startswith(FRAME_PREFIXES) or n in chosen]
        refit = LevenbergMarquardt().solve(problem.with_free(torch.tensor(support, dtype=torch.long)), x0)
        refit.selected = [problem.model.layout.names[i] for i in support]
        refit.message = f"LASSO kept {len(chosen)} of {len(kin_names)} kinematic parameters (alpha={self.alpha_:.3g}); {refit.message}"
        return refit
