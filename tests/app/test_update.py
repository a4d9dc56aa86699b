"""torchcal update on a twin whose truth changed after calibration (or did not).

Truth: the twin's true parameters, changed by a known amount in one group (tool swapped, joint
re-mastered, link bent) or moved as a whole (only the frame changes). The update from 12 new
poses must free what changed, recover the change, and predict new poses of the changed robot as
well as the old model predicted the unchanged one.
"""

from __future__ import annotations

import dataclasses
import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import torch

from torchcal.app.update import near_twin_groups, update_data, write_update
from torchcal.cli import main
from torchcal.config.schema import FitConfig
from torchcal.core.folder import staged_folder
from torchcal.core.hashing import sha256_file
from torchcal.data.measurements import write_measurements_csv
from torchcal.kinematics.robot import load_robot
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import held_out_errors
from torchcal.stages.pipeline import fit_model
from torchcal.stages.prediction_uncertainty import stored_prediction
from torchcal.stages.store import load_model

MM, DEG = 1e-3, math.pi / 180


def _rms_mm(errors: torch.Tensor) -> float:
    return float(errors.norm(dim=-1).pow(2).mean().sqrt()) * 1e3


CASES = {
    "nothing": ({}, []),
    "robot moved": ({"base_x": 50 * MM, "base_y": -20 * MM, "base_rz": 1.0 * DEG}, []),
    "tool swapped": ({"tool_x": 1.0 * MM, "tool_y": -0.5 * MM, "tool_z": 2.0 * MM}, ["tool_x", "tool_y", "tool_z"]),
    "joint 3 re-mastered": ({"theta3": 0.05 * DEG}, ["theta3"]),
    "link 3 bent": ({"alpha3": 0.05 * DEG, "a3": 0.3 * MM}, ["alpha3", "a3"]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_update_recovers_the_change(calibrated, case, tmp_path):
    twin, stored = calibrated
    deltas, names = CASES[case]
    robot = twin.changed(**deltas)
    result = update_data(stored, robot.sample(12, torch.Generator().manual_seed(101)))
    assert set(names) <= set(result.freed) and (names or not result.freed)
    changes = {c["name"]: c for c in result.changes()}
    for name, delta in deltas.items():
        if name in changes:  # the change the update found, against the truth's (mm or deg), within 4 sigma
            unit = 1 / DEG if changes[name]["unit"] == "deg" else 1e3
            assert abs(changes[name]["change"] - delta * unit) < 4 * changes[name]["sigma"] + 1e-9
    with staged_folder(tmp_path / "new") as staging:
        write_update(staging, result)
    new = load_model(tmp_path / "new")
    test = robot.sample(300, torch.Generator().manual_seed(5))
    before = _rms_mm(held_out_errors(stored, twin.sample(300, torch.Generator().manual_seed(5)), register=True))
    own = held_out_errors(new, test)  # the updated model's own frame: what a user sees on new poses
    assert _rms_mm(own) < 1.3 * before
    inside = (own.norm(dim=-1) * 1e3 <= stored_prediction(new, test.q).p95_mm).double().mean()
    assert inside >= 0.85


def test_two_changed_groups_are_both_freed_and_an_unchanged_one_is_not(calibrated):
    """Truth: the tool swapped and joint 2 re-mastered at once. The check names one group (the
    stronger alone); the update adds the other, which the check also named, because the new poses'
    leave-one-out errors say so, recovers both changes within 4 sigma, and frees nothing the truth
    left alone."""
    twin, stored = calibrated
    deltas = {"tool_x": 1.0 * MM, "tool_y": -0.5 * MM, "tool_z": 2.0 * MM, "theta2": 0.05 * DEG}
    robot = twin.changed(**deltas)
    result = update_data(stored, robot.sample(16, torch.Generator().manual_seed(101)))
    assert set(result.freed) == set(deltas)
    assert any(line.startswith("group ") and ") added:" in line for line in result.notes)
    assert " added (the check named it" in result.how
    changes = {c["name"]: c for c in result.changes()}
    for name, delta in deltas.items():
        unit = 1 / DEG if changes[name]["unit"] == "deg" else 1e3
        assert abs(changes[name]["change"] - delta * unit) < 4 * changes[name]["sigma"]


def test_update_cli_writes_a_whole_folder_with_provenance(calibrated, tmp_path, capsys):
    twin, stored = calibrated
    data = twin.changed(theta3=0.05 * DEG).sample(12, torch.Generator().manual_seed(7))
    write_measurements_csv(tmp_path / "few.csv", data.q, data.position)
    out = tmp_path / "new"
    assert main(["update", "--model", str(stored.folder), "--data", str(tmp_path / "few.csv"), "--out", str(out)]) == 0
    meta = json.loads((out / "calibration.json").read_text())
    update = meta["update"]
    assert update["parent"]["checksums_sha256"] == sha256_file(stored.folder / "checksums.json")
    assert update["freed"] == ["theta3"] and update["data"]["n_poses"] == 12 and update["evidence"]["verdict"] == "changed"
    assert json.loads((out / "uncertainty.json").read_text())["n_poses"] == 12
    assert (out / "calibrated_robot.urdf").is_file() and (out / "report.html").is_file()
    assert "freed: theta3" in capsys.readouterr().out
    new = load_model(out)  # whole: checksums verified
    assert new.training_q is not None and len(new.training_q) == len(stored.training_q) + 12
    # free= overrides the evidence
    assert main(["update", "--model", str(stored.folder), "--data", str(tmp_path / "few.csv"), "--out",
                 str(tmp_path / "tool"), "free=tool"]) == 0
    assert json.loads((tmp_path / "tool" / "calibration.json").read_text())["update"]["freed"] == ["tool_x", "tool_y", "tool_z"]
    # an update of the update: the 95 % region's shape still comes from the first fit's out-of-fold errors, and
    # says so (it named the parent's 12 update poses); the export names which poses its training data are
    first = json.loads((stored.folder / "uncertainty.json").read_text())
    more = twin.changed(theta3=0.05 * DEG).sample(12, torch.Generator().manual_seed(8))
    write_measurements_csv(tmp_path / "more.csv", more.q, more.position)
    assert main(["update", "--model", str(out), "--data", str(tmp_path / "more.csv"), "--out", str(tmp_path / "again")]) == 0
    again = json.loads((tmp_path / "again" / "uncertainty.json").read_text())
    assert again["n_poses"] == 12 and again["shape_n_poses"] == first["n_poses"] == len(stored.training_q)
    assert again["conformal_q"] == first["conformal_q"] and f"calibrated on {first['n_poses']} out-of-fold" in again["protocol"]
    from torchcal.compensate.export import export_model

    manifest = export_model(tmp_path / "again", tmp_path / "export")
    assert manifest["training_data"]["n_poses"] == 12 and "update" in manifest["training_data"]["of"]
    assert manifest["training_data"]["n_poses_all_fits"] == len(stored.training_q) + 24


@pytest.mark.parametrize("argv, message", [
    (["free=wrist9"], "unknown 'wrist9'"),
    (["speed=3"], "unknown option 'speed=3'"),
])
def test_update_refuses_bad_options_in_one_line(calibrated, tmp_path, capsys, argv, message):
    twin, stored = calibrated
    data = twin.sample(12, torch.Generator().manual_seed(7))
    write_measurements_csv(tmp_path / "few.csv", data.q, data.position)
    code = main(["update", "--model", str(stored.folder), "--data", str(tmp_path / "few.csv"), "--out",
                 str(tmp_path / "new"), *argv])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "new").exists()


def test_update_never_writes_into_its_parent(calibrated, tmp_path, capsys):
    twin, stored = calibrated
    data = twin.sample(12, torch.Generator().manual_seed(7))
    write_measurements_csv(tmp_path / "few.csv", data.q, data.position)
    code = main(["update", "--model", str(stored.folder), "--data", str(tmp_path / "few.csv"), "--out", str(stored.folder)])
    assert code == 2 and "names the parent model" in capsys.readouterr().err


@pytest.mark.slow
def test_check_and_update_name_and_refit_a_changed_compliance(tmp_path):
    """A heavier payload at the wrist (10 -> 30 kg) changes the gravity sag, not the geometry."""
    twin = Twin.create(TwinConfig(seed=3, gravity=True))
    fit_model(tmp_path / "old", twin.robot, twin.sample(150, torch.Generator().manual_seed(11)),
              FitConfig(residual="none", progress=False))
    old = load_model(tmp_path / "old")
    assert old.metadata.get("gravity_compliance")
    heavy = dataclasses.replace(twin, config=dataclasses.replace(twin.config, link_masses_kg=[25.0, 15.0, 30.0]))
    result = update_data(old, heavy.sample(12, torch.Generator().manual_seed(300)))
    assert result.check is not None and result.check.changed == ["gravity_compliance"]
    assert result.freed == ["gravity_compliance"] and result.scales["gravity_compliance"] > 0.5  # the sag grew
    with staged_folder(tmp_path / "new") as staging:
        write_update(staging, result)
    new = load_model(tmp_path / "new")
    test = heavy.sample(300, torch.Generator().manual_seed(5))
    before = _rms_mm(held_out_errors(old, test, register=True))
    after = _rms_mm(held_out_errors(new, test))
    # one scale for the whole term takes most of the change (the true change is at one mass point only)
    assert after < 0.5 * before


def test_a_head_is_kept_while_it_helps_and_dropped_when_its_error_is_gone(tmp_path):
    """Truth: a twin with gear errors (which a head learns), and the same twin with the gearboxes replaced."""
    from torchcal.residual import HEADS
    from torchcal.residual.selection import fit_before_gate
    from torchcal.stages.geometry import model_joints
    from torchcal.stages.residual import make_features, residual_targets_mm
    from torchcal.stages.residual_store import StoredResidual, save_residual

    geared = Twin.create(TwinConfig(seed=3, gear=True, gear_amplitude_deg=0.05))
    replaced = Twin.create(TwinConfig(seed=3))
    assert torch.equal(geared.x_true, replaced.x_true)
    data = geared.sample(600, torch.Generator().manual_seed(11))
    config = FitConfig(residual="none", progress=False, gravity_compliance="none", joint_harmonics="none")
    fit_model(tmp_path / "old", geared.robot, data, config)
    stored = load_model(tmp_path / "old")
    head = HEADS["elm"].from_options(config)  # a head on every pose (the gate is the fit's business, not this test's)
    features = make_features(stored.robot, data)
    fit_before_gate(head, features(data.q, data.temperature),
                    residual_targets_mm(stored.model, stored.x, data, model_joints(stored, data.q)), seed=0)
    save_residual(tmp_path / "old", StoredResidual(head, features, {"decision": "fitted for this test"}))
    stored = load_model(tmp_path / "old")
    kept = update_data(stored, geared.sample(16, torch.Generator().manual_seed(300)), free="frame")
    dropped = update_data(stored, replaced.sample(16, torch.Generator().manual_seed(300)), free="frame")
    assert kept.head_kept is True and "kept" in (kept.head_line or "")
    assert dropped.head_kept is False and "dropped" in (dropped.head_line or "")
    with staged_folder(tmp_path / "new") as staging:
        write_update(staging, dropped)
    assert load_model(tmp_path / "new").residual is None
    with staged_folder(tmp_path / "new2") as staging:
        write_update(staging, kept)
    assert load_model(tmp_path / "new2").residual is not None


def test_update_of_a_urdf_robot_writes_the_users_urdf_with_the_updated_geometry(tmp_path):
    """A URDF robot: the updated folder's calibrated_robot.urdf is the user's file (every link kept) and
    reproduces the updated model's geometric stage (tool point in the base frame) to 1e-9 m."""
    fixture = Path(__file__).parents[1] / "kinematics" / "fixtures" / "arm6_offset.urdf"
    twin = Twin.create(TwinConfig(robot=str(fixture), seed=4))
    fit_model(tmp_path / "old", twin.robot, twin.sample(150, torch.Generator().manual_seed(11)),
              FitConfig(residual="none", progress=False))
    data = twin.changed(tool_x=1.0 * MM, tool_z=-2.0 * MM).sample(12, torch.Generator().manual_seed(3))
    write_measurements_csv(tmp_path / "few.csv", data.q, data.position)
    out = tmp_path / "new"
    assert main(["update", "--model", str(tmp_path / "old"), "--data", str(tmp_path / "few.csv"), "--out", str(out)]) == 0
    new, old = load_model(out), load_model(tmp_path / "old")
    assert new.metadata["update"]["freed"] == ["tool_x", "tool_y", "tool_z"]
    text = (out / "calibrated_robot.urdf").read_text()
    original = ET.fromstring(fixture.read_text())
    assert {link.get("name") for link in original.iter("link")} <= {link.get("name") for link in ET.fromstring(text).iter("link")}
    (tmp_path / "r.urdf").write_text(text)
    calibrated = load_robot(tmp_path / "r.urdf", base_link=twin.robot.base_link,
                            end_link=f"{twin.robot.end_link}_calibrated_tcp")
    q = twin.robot.sample_joints(50, torch.Generator().manual_seed(4))

    def in_base(stored):
        transform = stored.model.instrument_from_base(stored.x)
        return (stored.model.tcp_position(q, stored.x) - transform[:3, 3]) @ transform[:3, :3]

    assert torch.allclose(calibrated.tcp_position(q), in_base(new), atol=1e-9)
    # the file changed with the update: the tool moved by about the change made to the truth
    moved = (in_base(new) - in_base(old)).norm(dim=-1)
    assert bool(((moved > 1.5 * MM) & (moved < 3.0 * MM)).all())


def test_a_joint_space_term_is_kept_while_it_holds_and_dropped_when_it_is_gone(tmp_path):
    """Truth: a twin with gear errors (the fit's first harmonics model them), and the same twin with the
    gearboxes replaced (no periodic error left): the update keeps the harmonics on the first, drops them
    on the second, and the dropped model predicts new poses of the replaced robot better than the kept one."""
    geared = Twin.create(TwinConfig(seed=3, gear=True, gear_amplitude_deg=0.05, gear_orders=1))
    replaced = Twin.create(TwinConfig(seed=3))
    assert torch.equal(geared.x_true, replaced.x_true)
    config = FitConfig(residual="none", progress=False, gravity_compliance="none", joint_harmonics="first")
    fit_model(tmp_path / "old", geared.robot, geared.sample(300, torch.Generator().manual_seed(11)), config)
    stored = load_model(tmp_path / "old")
    assert stored.metadata.get("joint_harmonics")
    kept = update_data(stored, geared.sample(16, torch.Generator().manual_seed(300)), free="frame")
    dropped = update_data(stored, replaced.sample(16, torch.Generator().manual_seed(300)), free="frame")
    assert kept.dropped_terms == [] and any(n.startswith("joint_harmonics kept") for n in kept.notes)
    assert dropped.dropped_terms == ["joint_harmonics"]
    with staged_folder(tmp_path / "new") as staging:
        write_update(staging, dropped)
    new = load_model(tmp_path / "new")
    assert not new.metadata.get("joint_harmonics") and new.metadata["update"]["joint_space_terms_dropped"] == ["joint_harmonics"]
    test = replaced.sample(300, torch.Generator().manual_seed(5))
    assert _rms_mm(held_out_errors(new, test, register=True)) < 0.7 * _rms_mm(held_out_errors(stored, test, register=True))


def test_near_twins_are_left_out_together():
    """Poses whose joints all lie within 1 deg of each other form one group, linked transitively; 1.5 deg apart do not."""
    q = torch.zeros(5, 6, dtype=torch.float64)
    q[1, 2] = 0.8 * DEG  # a twin of pose 0
    q[2, 2] = 1.6 * DEG  # a twin of pose 1 (1.6 deg from pose 0): the same group
    q[3, 0] = 30 * DEG
    q[4, 0] = 31.5 * DEG  # 1.5 deg from pose 3 in joint 1: its own pose
    assert sorted(map(sorted, near_twin_groups(q))) == [[0, 1, 2], [3], [4]]


def test_an_update_of_a_parent_that_measured_orientations_says_its_compensator_orients_by_the_geometry(tmp_path):
    """An update measures positions only: where the parent's joint-space terms were fitted with measured
    orientations, the updated model's compensator no longer orients by them, and the update says so."""
    from torchcal.app.update import ORIENTATION_SOURCE_NOTE
    from torchcal.kinematics.error_model import ErrorModel

    twin = Twin.create(TwinConfig(seed=3, gravity=True))
    fit_model(tmp_path / "old", twin.robot, twin.sample(150, torch.Generator().manual_seed(11)),
              FitConfig(residual="none", progress=False))
    old = load_model(tmp_path / "old")
    assert old.metadata.get("gravity_compliance") and not old.model.with_orientation
    new_poses = twin.sample(12, torch.Generator().manual_seed(300))
    assert ORIENTATION_SOURCE_NOTE not in update_data(old, new_poses).notes
    model = old.model
    measured_orientations = dataclasses.replace(old, model=ErrorModel(
        model.robot, with_orientation=True, parallel_threshold_deg=model.parallel_threshold_deg,
        T_instrument_base=model.T_reference))
    assert ORIENTATION_SOURCE_NOTE in update_data(measured_orientations, new_poses).notes
