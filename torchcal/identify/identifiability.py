"""Identifiability of the free parameters from the data at hand.

Columns of the identification Jacobian are scaled to unit length (so the analysis does not
depend on units), then:

* the singular values give the numerical rank, the condition number ``s_max / s_min`` and the
  observability index ``O1 = (s_1 ... s_L)^(1/L) / sqrt(m)`` (Borm & Menq);
* a base parameter set is chosen by Gram-Schmidt in a fixed order of preference (frame
  parameters first, then joints from the base outwards): a parameter whose scaled column has a
  residual below ``tolerance`` after projection on the kept ones is *not identifiable* with them;
  its column is expressed as a combination of kept columns and those partners are reported by
  name. Dropped parameters stay at their nominal value.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


@dataclass
class IdentifiabilityReport:
    """What the data can and cannot tell apart.

    Attributes:
        rank: numerical rank of the scaled Jacobian of all candidate parameters.
        condition_number: of the scaled Jacobian restricted to the base set.
        observability_index: O1 of the base set.
        singular_values: of the base-set scaled Jacobian.
        base_set: names of the identifiable parameters (kept).
        dependent: for each dropped parameter, the kept ones it is confounded with and the
            coefficient of each (scaled columns), largest first.
        weak: base-set parameters whose scaled column is nearly dependent (residual below
            ``weak_tolerance``): identifiable in principle, poorly in practice.
    """

    rank: int
    condition_number: float
    observability_index: float
    singular_values: list[float]
    base_set: list[str]
    dependent: dict[str, list[tuple[str, float]]] = field(default_factory=dict)
    weak: dict[str, float] = field(default_factory=dict)

    def to_metadata(self) -> dict:
        """What a model folder's ``calibration.json`` keeps of this report (JSON-ready)."""
        return {
            "rank": self.rank,
            "condition_number": self.condition_number,
            "observability_index": self.observability_index,
            "base_set": self.base_set,
            "not_identifiable": {k: [p for p, _ in v[:3]] for k, v in self.dependent.items()},
            "weak": self.weak,
        }

    def summary(self) -> str:
        lines = [
            (f"rank {self.rank}, condition number {self.condition_number:.3g}, "
             f"observability index {self.observability_index:.3g}"),
            f"identifiable ({len(self.base_set)}): {', '.join(self.base_set)}",
        ]
        for name, partners in self.dependent.items():
            with_ = ", ".join(f"{p} ({c:+.2f})" for p, c in partners[:3]) or "nothing: no effect on the TCP"
            lines.append(f"not identifiable: {name} - confounded with {with_}")
        for name, res in self.weak.items():
            lines.append(f"weakly identifiable: {name} (independent part {res:.2g} of its column)")
        return "\n".join(lines)


def preference_order(names: list[str]) -> list[int]:
    """Frame parameters first (they must stay free), then the joint rows in chain order."""
    frames = [i for i, n in enumerate(names) if n.startswith(("base_", "tool_"))]
    rest = [i for i, n in enumerate(names) if not n.startswith(("base_", "tool_"))]
    return frames + rest


def analyze(
    jacobian: torch.Tensor,
    names: list[str],
    *,
    tolerance: float = 1e-6,
    weak_tolerance: float = 1e-2,
) -> IdentifiabilityReport:
    """Analyze a ``(m, K)`` identification Jacobian whose columns are named ``names``."""
    norms = jacobian.norm(dim=0)
    scaled = jacobian / norms.clamp_min(1e-300)
    kept: list[int] = []
    basis = torch.zeros(jacobian.shape[0], 0, dtype=jacobian.dtype)
    dependent: dict[str, list[tuple[str, float]]] = {}
    weak: dict[str, float] = {}
    # A column at rounding level has no effect on the TCP; normalized it would look like a
    # random, independent direction, so it is judged on its raw size relative to the others.
    negligible = norms < 1e-10 * norms.max()
    for i in preference_order(names):
        if bool(negligible[i]):
            dependent[names[i]] = []
            continue
        col = scaled[:, i]
        resid = col - basis @ (basis.T @ col) if basis.shape[1] else col
        resid = resid - basis @ (basis.T @ resid) if basis.shape[1] else resid  # re-orthogonalize
        size = float(resid.norm())
        if size < tolerance:
            coeffs = torch.linalg.lstsq(scaled[:, kept], col.unsqueeze(-1)).solution.squeeze(-1)
            order = torch.argsort(coeffs.abs(), descending=True)
            dependent[names[i]] = [
                (names[kept[int(k)]], float(coeffs[k])) for k in order if abs(float(coeffs[k])) > 1e-3
            ]
            continue
        if size < weak_tolerance:
            weak[names[i]] = size
        kept.append(i)
        basis = torch.cat([basis, (resid / size).unsqueeze(-1)], 1)
    kept_sorted = sorted(kept)
    full_sv = torch.linalg.svdvals(scaled[:, ~negligible])
    rank = int((full_sv > tolerance * full_sv[0]).sum())
    sv = torch.linalg.svdvals(scaled[:, kept_sorted])
    m = jacobian.shape[0]
    o1 = float(torch.exp(torch.log(sv).mean()) / m**0.5)
    return IdentifiabilityReport(
        rank=rank,
        condition_number=float(sv[0] / sv[-1]),
        observability_index=o1,
        singular_values=sv.tolist(),
        base_set=[names[i] for i in kept_sorted],
        dependent=dependent,
        weak=weak,
    )
