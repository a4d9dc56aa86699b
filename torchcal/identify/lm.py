"""Levenberg-Marquardt with Marquardt's parameter scaling and Nielsen's adaptive damping.

Scaling: the normal matrix is damped with ``lambda * diag(J^T J)`` (kept from the largest seen
diagonal, as in More's MINPACK), so metres and radians are treated on the scale of their effect
on the TCP. Damping: Nielsen (1999): after a step with gain ratio ``rho > 0``,
``lambda *= max(1/3, 1 - (2 rho - 1)^3)``; after a rejected step ``lambda *= nu, nu *= 2``.
"""

from __future__ import annotations

import torch

from torchcal.identify.base import Identifier, SolveResult
from torchcal.identify.problem import LeastSquaresProblem


class LevenbergMarquardt(Identifier):
    """Damped Gauss-Newton; the default identifier.

    Args:
        max_iterations: cap on accepted + rejected steps.
        ftol: stop when the relative cost decrease of an accepted step is below this.
        xtol: stop when the scaled step is below this relative to the scaled parameters.
        gtol: stop when the scaled gradient's infinity norm is below this.
        initial_damping: ``tau`` in ``lambda_0 = tau * max(diag(J^T J))``.
    """

    name = "lm"

    def __init__(
        self,
        max_iterations: int = 100,
        ftol: float = 1e-10,
        xtol: float = 1e-12,
        gtol: float = 1e-12,
        initial_damping: float = 1e-6,
    ) -> None:
        self.max_iterations = max_iterations
        self.ftol, self.xtol, self.gtol = ftol, xtol, gtol
        self.initial_damping = initial_damping

    def solve(self, problem: LeastSquaresProblem, x0: torch.Tensor) -> SolveResult:
        x = x0.clone()
        free = problem.free
        r, jac = problem.jacobian(x)
        cost = 0.5 * float(r @ r)
        history = [cost]
        jtj = jac.T @ jac
        diag = jtj.diagonal().clone().clamp_min(1e-300)
        lam = self.initial_damping * float(diag.max())
        nu = 2.0
        converged, message = False, "iteration limit"
        iterations = 0
        for iterations in range(1, self.max_iterations + 1):  # noqa: B007 (read after the loop)
            grad = jac.T @ r
            if float((grad.abs() / diag.sqrt()).max()) <= self.gtol * max(1.0, (2 * cost) ** 0.5):
                converged, message = True, "gradient below gtol"
                break
            step = torch.linalg.solve(jtj + lam * torch.diag(diag), -grad)
            predicted = -(float(step @ grad) + 0.5 * float(step @ (jtj @ step)))
            if 0.0 <= predicted < self.ftol * cost:
                # at the minimum already (a warm start): a step could only be rejected on rounding,
                # and the damping would double some 40 times before the loop gave up
                converged, message = True, "predicted decrease below ftol"
                break
            x_new = x.clone()
            x_new[free] = x[free] + step
            r_new = problem.residuals(x_new)
            cost_new = 0.5 * float(r_new @ r_new)
            rho = (cost - cost_new) / predicted if predicted > 0 else -1.0
            if rho > 0:
                x = x_new
                relative = (cost - cost_new) / max(cost, 1e-300)
                cost = cost_new
                history.append(cost)
                if relative < self.ftol:
                    converged, message = True, "relative cost change below ftol"
                    break
                r, jac = problem.jacobian(x)
                jtj = jac.T @ jac
                diag = torch.maximum(diag, jtj.diagonal())
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                scaled_step = float((step * diag.sqrt()).norm())
                scaled_x = float((x[free] * diag.sqrt()).norm())
                if scaled_step <= self.xtol * (scaled_x + self.xtol):
                    converged, message = True, "step below xtol"
                    break
            else:
                lam *= nu
                nu *= 2.0
                if lam > 1e300:
                    converged, message = True, "no further decrease possible"
                    break
        return SolveResult(
            x=x, free=free, cost=cost, iterations=iterations, converged=converged, history=history,
            selected=problem.names, message=message,
        )
