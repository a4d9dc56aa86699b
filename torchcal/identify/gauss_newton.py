"""Gauss-Newton least squares with a backtracking line search (no damping)."""

from __future__ import annotations

import torch

from torchcal.identify.base import Identifier, SolveResult
from torchcal.identify.problem import LeastSquaresProblem


class GaussNewton(Identifier):
    """Undamped normal-equation steps solved by least squares (``torch.linalg.lstsq``).

    Converges quadratically near a zero-residual optimum; needs a start close enough and a
    full-rank Jacobian, which is why Levenberg-Marquardt is the default.
    """

    name = "gn"

    def __init__(self, max_iterations: int = 50, ftol: float = 1e-12) -> None:
        self.max_iterations = max_iterations
        self.ftol = ftol

    def solve(self, problem: LeastSquaresProblem, x0: torch.Tensor) -> SolveResult:
        x = x0.clone()
        free = problem.free
        r, jac = problem.jacobian(x)
        cost = 0.5 * float(r @ r)
        history = [cost]
        converged, message, iterations = False, "iteration limit", 0
        for iterations in range(1, self.max_iterations + 1):  # noqa: B007 (read after the loop)
            scale = jac.norm(dim=0).clamp_min(1e-300)
            step = torch.linalg.lstsq(jac / scale, -r.unsqueeze(-1)).solution.squeeze(-1) / scale
            t, accepted = 1.0, False
            while t > 1e-6:
                x_new = x.clone()
                x_new[free] = x[free] + t * step
                r_new = problem.residuals(x_new)
                cost_new = 0.5 * float(r_new @ r_new)
                if cost_new <= cost:
                    accepted = True
                    break
                t *= 0.5
            if not accepted:
                converged, message = True, "no decrease along the Gauss-Newton direction"
                break
            relative = (cost - cost_new) / max(cost, 1e-300)
            x, cost = x_new, cost_new
            history.append(cost)
            if relative < self.ftol:
                converged, message = True, "relative cost change below ftol"
                break
            r, jac = problem.jacobian(x)
        return SolveResult(
            x=x, free=free, cost=cost, iterations=iterations, converged=converged, history=history,
            selected=problem.names, message=message,
        )
