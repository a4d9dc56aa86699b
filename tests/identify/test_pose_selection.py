"""The greedy design loop: each step is the exact best, closed-form optimum, groups, bad input."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from torchcal.identify.pose_selection import design_criterion, greedy_design


def _info(jac: torch.Tensor, idx, ridge: float) -> torch.Tensor:
    j = jac[list(idx)].reshape(-1, jac.shape[-1])
    return ridge * torch.eye(jac.shape[-1], dtype=jac.dtype) + j.T @ j


@pytest.mark.parametrize("criterion", ["D", "A", "worst"])
def test_every_step_is_the_best_single_addition(criterion):
    """Woodbury / determinant-lemma gains against direct inverses of every candidate's matrix."""
    gen = torch.Generator().manual_seed(5)
    jac = torch.randn(40, 2, 4, generator=gen, dtype=torch.float64) * torch.rand(40, 1, 1, generator=gen, dtype=torch.float64)
    groups = torch.arange(40) // 2  # pairs: at most one of each
    ridge = 1e-3
    chosen = greedy_design(jac, 8, criterion=criterion, groups=groups, ridge=ridge).tolist()
    assert len(set(groups[chosen].tolist())) == 8
    for step in range(1, 8):
        before = chosen[:step]
        used = set(groups[before].tolist())
        values = {
            c: design_criterion(_info(jac, before + [c], ridge), criterion)
            for c in range(40)
            if int(groups[c]) not in used
        }
        assert values[chosen[step]] == pytest.approx(min(values.values()), rel=1e-9, abs=1e-12)


def test_d_optimal_matches_brute_force_on_a_closed_form_case():
    """Candidates along the axes: the D-optimal triple is the longest vector on each axis."""
    lengths = {0: [1.0, 3.0, 2.0], 1: [0.5, 4.0], 2: [2.5, 1.5, 0.7]}
    rows = [(axis, a) for axis, values in lengths.items() for a in values]
    jac = torch.zeros(len(rows), 1, 3, dtype=torch.float64)
    for i, (axis, a) in enumerate(rows):
        jac[i, 0, axis] = a
    ridge = 1e-9
    best = min(itertools.combinations(range(len(rows)), 3), key=lambda s: design_criterion(_info(jac, s, ridge), "D"))
    chosen = greedy_design(jac, 3, criterion="D", ridge=ridge)
    assert sorted(chosen.tolist()) == sorted(best)
    # closed form: det = product of the squared longest lengths
    assert -design_criterion(_info(jac, chosen.tolist(), ridge), "D") == pytest.approx(math.log((3.0 * 4.0 * 2.5) ** 2), rel=1e-9)


def test_initial_candidates_come_first_and_count():
    jac = torch.randn(20, 3, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    chosen = greedy_design(jac, 5, criterion="A", initial=[7, 2])
    assert chosen[:2].tolist() == [7, 2] and len(set(chosen.tolist())) == 5


def test_bad_input_is_refused():
    jac = torch.randn(4, 2, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="criterion"):
        greedy_design(jac, 2, criterion="E")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="cannot select"):
        greedy_design(jac, 3, groups=torch.tensor([0, 0, 1, 1]))
    with pytest.raises(ValueError, match="rows, parameters"):
        greedy_design(jac[0], 1)
