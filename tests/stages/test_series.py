"""Several series of one robot fitted together (stages.series): the twin knows both frames and the geometry."""

from __future__ import annotations

import warnings

import pytest
import torch

from torchcal.config.schema import FitConfig
from torchcal.core.errors import DataError, IdentifiabilityWarning
from torchcal.identify.joint_fit import predicted_positions
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit_with_selection, registered_errors
from torchcal.stages.series import fit_series

CONFIG = FitConfig(residual="none", uncertainty="none", gravity_compliance="none", joint_harmonics="none",
                   progress=False)


def _rms_mm(errors: torch.Tensor) -> float:
    return float(errors.norm(dim=-1).pow(2).mean().sqrt()) * 1e3


@pytest.fixture(scope="module")
def two_setups():
    """One twin measured from two tracker placements (60 poses each), optionally with a re-mounted probe."""
    twin = Twin.create(TwinConfig(seed=3))
    moved = twin.changed(base_x=0.8, base_y=-1.2, base_rz=0.7, base_rx=0.05)
    gen = torch.Generator().manual_seed(5)
    first, second = twin.sample(60, gen), moved.sample(60, gen)
    test_q = twin.robot.sample_joints(500, torch.Generator().manual_seed(9))
    return twin, moved, first, second, test_q


def _geometry_error_mm(twin, result, q) -> float:
    """The fitted robot against the true one on new poses, after the best rigid frame (mm RMS)."""
    return _rms_mm(registered_errors(predicted_positions(result, q), twin.true_positions(q)))


def test_two_setups_together_beat_either_alone(two_setups):
    twin, moved, first, second, test_q = two_setups
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        alone = [fit_with_selection(twin.robot, d, CONFIG)[0] for d in (first, second)]
        both = fit_series(twin.robot, [first, second], CONFIG)
    errors = [_geometry_error_mm(twin, r, test_q) for r in alone]
    together = _geometry_error_mm(twin, both.result, test_q)
    assert together < min(errors), (together, errors)
    # both frames: the fit predicts each tracker's points on new poses without any registration (the
    # first tracker's frame alone is not separable from the robot's base parameters: compared jointly)
    in_first = _rms_mm(twin.true_positions(test_q) - predicted_positions(both.result, test_q))
    t = both.frames[1].transform
    in_second = _rms_mm(moved.true_positions(test_q) - (predicted_positions(both.result, test_q) @ t[:3, :3].T + t[:3, 3]))
    assert in_first < _rms_mm(twin.true_positions(test_q) - predicted_positions(alone[0], test_q))
    assert in_second < _rms_mm(moved.true_positions(test_q) - predicted_positions(alone[1], test_q))
    # the registration is exact: mapping again moves nothing
    assert both.last_move_mm < 1e-6


def test_per_series_tool_recovers_a_remounted_probe(two_setups):
    twin, _, first, _, _ = two_setups
    shift = torch.tensor([0.004, -0.003, 0.035], dtype=torch.float64)  # the probe re-mounted 35 mm further out
    remounted = twin.changed(base_x=0.8, base_y=-1.2, base_rz=0.7, tool_x=float(shift[0]), tool_y=float(shift[1]),
                             tool_z=float(shift[2]))
    second = remounted.sample(60, torch.Generator().manual_seed(6))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        fit = fit_series(twin.robot, [first, second], FitConfig(**{**CONFIG.__dict__, "series_tool": "per_series"}))
        # one tool for both mounts cannot explain the points: refused, nothing written
        with pytest.raises(DataError, match="still misses"):
            fit_series(twin.robot, [first, second], FitConfig(**{**CONFIG.__dict__, "series_tool": "shared"}))
        # auto: the nominal fits' tools are 35 mm apart, so a tool each, and a frame each with it
        auto = fit_series(twin.robot, [first, second], CONFIG)
    assert auto.tool == "per_series" and any("series_tool=per_series" in n for n in auto.result.notes)
    # the offset is in the TCP frame (the flange's axes for a point tool)
    assert torch.allclose(fit.frames[1].tool_offset, shift, atol=1e-4), fit.frames[1].tool_offset
    assert fit.last_move_mm < 1e-3


def test_one_series_is_refused(two_setups):
    twin, _, first, _, _ = two_setups
    with pytest.raises(DataError, match="at least two"):
        fit_series(twin.robot, [first], CONFIG)


def test_one_tracker_placement_is_one_frame(two_setups):
    twin, _, first, _, test_q = two_setups
    again = twin.sample(60, torch.Generator().manual_seed(8))  # the same placement, another 60 poses
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        shared = fit_series(twin.robot, [first, again], FitConfig(**{**CONFIG.__dict__, "series_frame": "shared"}))
        with pytest.raises(DataError, match="one tool"):
            fit_series(twin.robot, [first, again], FitConfig(**{**CONFIG.__dict__, "series_frame": "shared",
                                                                  "series_tool": "per_series"}))
        alone = fit_with_selection(twin.robot, first, CONFIG)[0]
    assert shared.pooled.series is None and len(shared.pooled) == 120
    # auto finds the one placement: the frames fitted with the nominal robot agree within millimetres
    from torchcal.stages.series import resolve_set_ups

    assert resolve_set_ups(twin.robot, [first, again], CONFIG)[:2] == ("shared", "shared")
    assert all(torch.equal(f.transform, torch.eye(4, dtype=torch.float64)) for f in shared.frames)
    in_frame = _rms_mm(twin.true_positions(test_q) - predicted_positions(shared.result, test_q))
    assert in_frame < _rms_mm(twin.true_positions(test_q) - predicted_positions(alone, test_q))
