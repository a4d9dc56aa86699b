"""torchcal compensate: a program's joint targets corrected offline by the export's compensator.

Truth: the twin's true robot. A corrected command puts the true TCP (where the model is right)
closer to the nominal target than the nominal command does; the written commands are the
compensator's own (the exported runtime's), also where they do not reach 1 um; such targets get a line.
"""

from __future__ import annotations

import contextlib
import json
import math
import warnings

import numpy as np
import pytest
import torch

from torchcal.cli import main
from torchcal.compensate.graphs import build_graphs, compensator_of
from torchcal.compensate.production_tcp import production_view, tcp_transform
from torchcal.compensate.program import compensate_program, sidecar_path
from torchcal.core.errors import TorchcalError
from torchcal.stages.store import load_model


def _program(path, q_rad: torch.Tensor, extra: str = "") -> None:
    n = q_rad.shape[1]
    rows = [",".join([f"q{j}" for j in range(1, n + 1)] + (["speed"] if extra else []))]
    rows += [",".join([repr(v) for v in row] + ([extra] if extra else [])) for row in torch.rad2deg(q_rad).tolist()]
    path.write_text("\n".join(rows) + "\n")


def _read(path) -> dict[str, np.ndarray]:
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    data = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    return {name: data[:, k] for k, name in enumerate(header)}


@pytest.fixture(scope="module")
def program(twin, model_dir, tmp_path_factory):
    folder = tmp_path_factory.mktemp("program")
    q = twin.robot.sample_joints(300, torch.Generator().manual_seed(21), margin=0.2)
    _program(folder / "targets.csv", q, extra="250")
    tool_mm = (load_model(model_dir).x[-6:-3] * 1e3).tolist()  # the fitted measured point: observable on the twin
    outcome = compensate_program(model_dir, folder / "targets.csv", folder / "corrected.csv", tcp_mm=tool_mm)
    return q, folder, outcome


def test_written_commands_are_the_compensators(program, model_dir):
    q, folder, outcome = program
    stored = load_model(model_dir)
    stored = production_view(stored, tcp_transform((stored.x[-6:-3] * 1e3).tolist(), None))
    with torch.no_grad():
        expected, residual = compensator_of(build_graphs(stored)).solve(q)
    out = _read(folder / "corrected.csv")
    got = torch.from_numpy(np.radians(np.stack([out[f"q{j}"] for j in range(1, q.shape[1] + 1)], 1)))
    ok = torch.from_numpy(out["corrected"]).bool()
    assert outcome.n_corrected == int(ok.sum()) >= 0.95 * len(q)
    assert torch.allclose(got, expected, atol=1e-12)  # every row, solved or not
    assert outcome.largest_correction_deg > 0.1  # the twin's errors need real corrections: the check can fail
    assert bool((residual[ok, 0] <= 1e-6).all()) and bool((residual[~ok, 0] > 1e-6).all())
    assert len(outcome.not_corrected) == int((~ok).sum())


def test_corrected_commands_bring_the_true_tcp_to_the_nominal_target(program, twin, model_dir):
    """The twin's true measured point under the corrected commands lands on the nominal target far better.

    Compared in the instrument frame (the base frame of a fit is defined only up to what row 1 and
    the instrument frame share; the flange only up to d6 / tool_z, so the TCP is the fitted measured
    point): the target is where the nominal robot puts that point, placed by the model's instrument frame.
    """
    q, folder, _ = program
    out = _read(folder / "corrected.csv")
    q_c = torch.from_numpy(np.radians(np.stack([out[f"q{j}"] for j in range(1, q.shape[1] + 1)], 1)))
    stored = load_model(model_dir)
    frame = stored.model.instrument_from_base(stored.x)
    nominal = twin.robot.flange_pose(q)
    target = nominal[:, :3, :3] @ stored.x[stored.model.layout.tool_slice][:3] + nominal[:, :3, 3]
    target = target @ frame[:3, :3].T + frame[:3, 3]
    before = (twin.true_positions(q) - target).norm(dim=-1)
    after = (twin.true_positions(q_c) - target).norm(dim=-1)
    assert float(after.square().mean().sqrt()) < 0.2 * float(before.square().mean().sqrt())


def test_a_target_the_steps_do_not_solve_to_1um_keeps_the_compensators_better_command(twin, model_dir, tmp_path):
    """With one Newton step the model's TCP is not within 1 um of most targets, yet far closer than
    the nominal command leaves it: the compensator's command is written (as the runtime returns it),
    flagged, with its remaining error and the nominal one's, both recomputed here by forward kinematics."""
    q = twin.robot.sample_joints(20, torch.Generator().manual_seed(2), margin=0.3)
    _program(tmp_path / "t.csv", q)
    outcome = compensate_program(model_dir, tmp_path / "t.csv", tmp_path / "c.csv", iterations=1)
    out = _read(tmp_path / "c.csv")
    missed = np.flatnonzero(out["corrected"] == 0)
    assert len(missed) > 0 and len(outcome.not_corrected) == len(missed)
    assert outcome.not_corrected[0].startswith(f"{tmp_path / 't.csv'}: row {missed[0] + 2}: not solved to 0.001 mm")
    stored = production_view(load_model(model_dir), tcp_transform(None, None))
    with torch.no_grad():
        expected, _ = compensator_of(build_graphs(stored, iterations=1)).solve(q)
    written = torch.from_numpy(np.radians(np.stack([out[f"q{j}"] for j in range(1, 7)], 1)))
    assert torch.allclose(written, expected, atol=1e-12)
    model = stored.model

    def off_mm(joints: torch.Tensor) -> np.ndarray:  # the calibrated TCP's distance from the nominal target
        reached = (model.base_flange_pose(joints, stored.x) @ model.flange_from_tool(stored.x))[:, :3, 3]
        return ((reached - stored.robot.tcp_position(q)).norm(dim=-1) * 1e3).numpy()

    assert np.allclose(out["remaining_mm"], off_mm(written), rtol=1e-5, atol=1e-9)
    assert (out["remaining_mm"][missed] > 1e-3).all() and (off_mm(written)[missed] < 0.1 * off_mm(q)[missed]).all()


def test_never_overwrites_a_file_torchcal_did_not_write(program, model_dir, tmp_path):
    q, folder, _ = program
    theirs = tmp_path / "program.csv"
    theirs.write_text("q1\n1\n")
    with pytest.raises(TorchcalError, match="not a corrected program torchcal wrote"):
        compensate_program(model_dir, folder / "targets.csv", theirs)
    assert theirs.read_text() == "q1\n1\n"
    with pytest.raises(TorchcalError, match="is the targets file"):
        compensate_program(model_dir, folder / "targets.csv", folder / "targets.csv")
    with pytest.raises(TorchcalError, match="lies inside"):  # its record there would break the model's checksums
        compensate_program(model_dir, folder / "targets.csv", model_dir / "corrected.csv")
    assert not (model_dir / "corrected.csv").exists()
    # its own output, unchanged, may be rewritten; once edited, not any more
    out = tmp_path / "mine.csv"
    _program(folder / "few.csv", q[:3])
    compensate_program(model_dir, folder / "few.csv", out)
    assert json.loads(sidecar_path(out).read_text())["n_targets"] == 3
    compensate_program(model_dir, folder / "few.csv", out)
    out.write_text(out.read_text() + "\n")
    with pytest.raises(TorchcalError, match="was changed since"):
        compensate_program(model_dir, folder / "few.csv", out)


@pytest.mark.parametrize("text, where", [
    ("q1,q2,q3,q4,q5,q6\n0,0,0,0,abc,0\n", "row 2, column 'q5'"),
    ("q1,q2,q3,q4,q5\n0,0,0,0,0\n", "row 1"),
    ("q1,q2,q3,q4,q5,q6\n0,0,0,0,0,720\n", "row 2, column 'q6'"),
])
def test_bad_targets_are_one_line_naming_file_row_column(model_dir, tmp_path, capsys, text, where):
    (tmp_path / "bad.csv").write_text(text)
    code = main(["compensate", "--model", str(model_dir), "--targets", str(tmp_path / "bad.csv"),
                 "--out", str(tmp_path / "o.csv")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "bad.csv" in err and where in err
    assert not (tmp_path / "o.csv").exists()


def test_cli_prints_the_summary(program, model_dir, tmp_path, capsys):
    _, folder, _ = program
    code = main(["compensate", "--model", str(model_dir), "--targets", str(folder / "targets.csv"),
                 "--out", str(tmp_path / "c.csv"), "--tcp-mm", "0", "0", "0"])
    out = capsys.readouterr().out
    assert code == 0 and "targets corrected" in out and "largest joint correction" in out


def _poses(path, pose: torch.Tensor, oriented: bool) -> None:
    header = "x,y,z,rx,ry,rz" if oriented else "x,y,z"
    from torchcal.kinematics.transforms import matrix_to_euler_xyz

    cells = torch.cat([pose[:, :3, 3] * 1e3] + ([torch.rad2deg(matrix_to_euler_xyz(pose[:, :3, :3]))] if oriented else []), 1)
    path.write_text("\n".join([header] + [",".join(repr(v) for v in row) for row in cells.tolist()]) + "\n")


@pytest.mark.parametrize("oriented", [True, False])
def test_tcp_poses_with_a_start_give_the_joint_programs_result(twin, model_dir, tmp_path, oriented):
    """A path of TCP poses (the nominal robot's at known joints, small steps) equals that joint program."""
    from torchcal.kinematics.error_model import ErrorModel

    stored = production_view(load_model(model_dir), tcp_transform([0.0, 0.0, 0.0], None))
    start = twin.robot.sample_joints(1, torch.Generator().manual_seed(5), margin=0.4)[0]
    steps = torch.linspace(0, 1, 25, dtype=torch.float64)[:, None] * torch.deg2rad(torch.tensor([20.0, -10, 15, 30, -20, 40]))
    q = start + steps
    nominal = ErrorModel(stored.robot, T_instrument_base=torch.eye(4, dtype=torch.float64))
    _poses(tmp_path / "poses.csv", nominal.tcp_pose(q, nominal.nominal_vector()), oriented)
    _program(tmp_path / "joints.csv", q)
    by_joints = compensate_program(model_dir, tmp_path / "joints.csv", tmp_path / "a.csv")
    by_poses = compensate_program(model_dir, tmp_path / "poses.csv", tmp_path / "b.csv",
                                  start_deg=torch.rad2deg(start).tolist())
    a, b = _read(tmp_path / "a.csv"), _read(tmp_path / "b.csv")
    assert by_poses.n_corrected == by_joints.n_corrected == len(q)
    if oriented:  # the pose fixes the joints: the same program
        for j in range(1, 7):
            assert np.allclose(a[f"q{j}"], b[f"q{j}"], atol=1e-6)
    # the TCP position of the corrected command, on the model, is the target's either way: the file's
    # own account, and the calibrated model's forward kinematics at the corrected joints
    assert np.allclose(b["remaining_mm"], 0.0, atol=1e-3)
    q_c = torch.deg2rad(torch.tensor(np.stack([b[f"q{j}"] for j in range(1, 7)], 1), dtype=torch.float64))
    reached = (stored.model.base_flange_pose(q_c, stored.x) @ stored.model.flange_from_tool(stored.x))[:, :3, 3]
    target = nominal.tcp_pose(q, nominal.nominal_vector())[:, :3, 3]
    assert float((reached - target).norm(dim=-1).max()) < 1e-6  # m


def test_tcp_poses_need_a_start_and_name_an_unreachable_row(model_dir, tmp_path, capsys):
    stored = production_view(load_model(model_dir), tcp_transform(None, None))
    near = torch.deg2rad(torch.tensor([[5.0, -65.0, 95.0, 5.0, 35.0, 5.0]], dtype=torch.float64))  # near the start below
    x, y, z = (stored.robot.tcp_position(near)[0] * 1e3).tolist()
    (tmp_path / "poses.csv").write_text(f"x,y,z\n{x},{y},{z}\n9000,0,0\n")
    assert main(["compensate", "--model", str(model_dir), "--targets", str(tmp_path / "poses.csv"),
                 "--out", str(tmp_path / "o.csv")]) == 2
    assert "--start" in capsys.readouterr().err
    assert main(["compensate", "--model", str(model_dir), "--targets", str(tmp_path / "poses.csv"),
                 "--out", str(tmp_path / "o.csv"), "--start", "0", "-60", "90", "0", "30", "0"]) == 2
    err = capsys.readouterr().err
    assert "row 3" in err and "not reachable" in err and len(err.strip().splitlines()) == 1
    # a pose whose inverse kinematics from the start ends outside a joint's range at every whole turn
    (tmp_path / "far.csv").write_text("x,y,z\n500,0,600\n")
    assert main(["compensate", "--model", str(model_dir), "--targets", str(tmp_path / "far.csv"),
                 "--out", str(tmp_path / "o.csv"), "--start", "0", "-60", "90", "0", "30", "0"]) == 2
    err = capsys.readouterr().err
    assert "row 2" in err and "outside its limits" in err and "give a start nearer" in err


def test_a_programs_other_columns_reach_the_corrected_file_as_written(program):
    _, folder, _ = program
    lines = (folder / "corrected.csv").read_text().splitlines()
    assert lines[0].split(",")[-1] == "speed" and all(line.split(",")[-1] == "250" for line in lines[1:])


def test_a_program_in_the_wrong_units_or_a_tool_out_of_reach_is_refused(program, model_dir, tmp_path, capsys):
    q, folder, _ = program

    def refused(targets, *extra) -> str:
        code = main(["compensate", "--model", str(model_dir), "--targets", str(targets), "--out", str(tmp_path / "o.csv"),
                     *extra])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1 and not (tmp_path / "o.csv").exists()
        return err

    radians = tmp_path / "rad.csv"
    radians.write_text("q1,q2,q3,q4,q5,q6\n" + "".join(",".join(repr(v) for v in row) + "\n" for row in q[:20].tolist()))
    assert "the joints look like radians; a program file's joints are in degrees" in refused(radians)
    metres = tmp_path / "m.csv"
    metres.write_text("x,y,z\n0.8,0,0.9\n0.81,0,0.9\n")
    assert "the targets look like metres" in refused(metres, "--start", "0", "-60", "90", "0", "30", "0")
    assert "tools reach at most" in refused(folder / "targets.csv", "--tcp-mm", "0", "0", "1e6")
    clash = tmp_path / "clash.csv"
    clash.write_text("q1,q2,q3,q4,q5,q6,corrected\n0,-60,90,0,30,0,1\n")
    assert "column 'corrected'" in refused(clash)


def test_tcp_pose_joints_take_the_turn_nearest_the_previous_target_within_the_limits(tmp_path):
    import math

    from torchcal.compensate.program import nearest_turn_within_limits
    from torchcal.core.errors import DataError

    deg = math.pi / 180
    limits = torch.tensor([[-185.0, 185.0], [-350.0, 350.0], [-170.0, 170.0], [-math.inf, math.inf]], dtype=torch.float64) * deg
    previous = torch.tensor([20.0, 30.0, 0.0, 10.0], dtype=torch.float64) * deg
    solved = torch.tensor([470.0, -330.0, 100.0, 725.0], dtype=torch.float64) * deg  # 110, 30, 100, 5 deg a turn away
    got = nearest_turn_within_limits(solved, previous, limits, tmp_path / "p.csv", 7) / deg
    assert torch.allclose(got, torch.tensor([110.0, 30.0, 100.0, 5.0], dtype=torch.float64), atol=1e-9)
    with pytest.raises(DataError, match=r"row 7.*joint 3 at 175 deg, outside its limits \[-170, 170\] deg at every whole turn"):
        nearest_turn_within_limits(torch.tensor([0.0, 0.0, 175.0, 0.0], dtype=torch.float64) * deg, previous, limits, tmp_path / "p.csv", 7)


def test_a_tcp_program_with_part_of_an_orientation_is_refused(model_dir, tmp_path):
    (tmp_path / "poses.csv").write_text("x,y,z,rx,ry\n500,0,600,0,90\n")
    with pytest.raises(TorchcalError, match="rx, ry given without rz"):
        compensate_program(model_dir, tmp_path / "poses.csv", tmp_path / "o.csv", start_deg=[0.0, -90.0, 90.0, 0.0, 30.0, 0.0])


def test_a_jump_between_targets_is_named_as_a_possible_change_of_configuration():
    """The program keeps one arm configuration from --start: a joint turning by more than 90 deg between
    targets (a wrist flip: q4 + 180, q5 -> -q5, q6 + 180 reaches the same flange pose) is named."""
    import math

    from torchcal.compensate.program import configuration_jumps

    deg = math.pi / 180
    start = torch.tensor([0.0, -60.0, 90.0, -40.0, 40.0, 30.0], dtype=torch.float64) * deg
    q = torch.tensor([[2.0, -61.0, 91.0, -39.0, 41.0, 31.0],      # a small step: nothing
                      [2.0, -61.0, 91.0, 141.0, -41.0, 211.0],    # the same pose, the wrist flipped
                      [3.0, -62.0, 92.0, 142.0, -42.0, 212.0]], dtype=torch.float64) * deg
    lines = configuration_jumps(q, start, [2, 3, 4])
    assert len(lines) == 1 and lines[0].startswith("row 3: joint 4 turns 180.0 deg from row 2")
    first = configuration_jumps(q[1:], start, [3, 4])
    assert len(first) == 1 and "from --start" in first[0]


def test_tcp_pose_angles_that_look_like_radians_are_warned_about(twin, model_dir, tmp_path):
    from torchcal.kinematics.error_model import ErrorModel

    stored = production_view(load_model(model_dir), tcp_transform(None, None))
    start = twin.robot.sample_joints(1, torch.Generator().manual_seed(5), margin=0.4)[0]
    q = start + torch.linspace(0, 1, 5, dtype=torch.float64)[:, None] * torch.deg2rad(torch.tensor([5.0, -5, 5, 5, -5, 5]))
    nominal = ErrorModel(stored.robot, T_instrument_base=torch.eye(4, dtype=torch.float64))
    poses = nominal.tcp_pose(q, nominal.nominal_vector())
    _poses(tmp_path / "deg.csv", poses, True)
    start_deg = torch.rad2deg(start).tolist()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # degrees: no warning
        compensate_program(model_dir, tmp_path / "deg.csv", tmp_path / "a.csv", start_deg=start_deg)
    lines = (tmp_path / "deg.csv").read_text().splitlines()
    header = lines[0].split(",")
    cols = [header.index(c) for c in ("rx", "ry", "rz")]
    rows = []
    for line in lines[1:]:
        cells = line.split(",")
        for c in cols:
            cells[c] = repr(math.radians(float(cells[c])))
        rows.append(",".join(cells))
    (tmp_path / "rad.csv").write_text("\n".join([lines[0], *rows]) + "\n")
    # the radians may also be unreachable: the warning comes first
    with pytest.warns(UserWarning, match="if they are radians, give them in degrees"), contextlib.suppress(TorchcalError):
        compensate_program(model_dir, tmp_path / "rad.csv", tmp_path / "b.csv", start_deg=start_deg)


def test_compensate_names_itself_when_it_refuses_large_corrections():
    from torchcal.compensate.production_tcp import check_corrections

    large = {"median_joint_correction_deg": 5.0, "largest_joint_correction_deg": 37.0, "joint": 3,
             "median_tool_rotation_deg": 0.1, "largest_tool_rotation_deg": 1.0}
    with pytest.raises(TorchcalError, match=r"^compensate refused"):
        check_corrections({"training poses": large}, allow=False, command="compensate")
    with pytest.raises(TorchcalError, match=r"^export refused"):
        check_corrections({"training poses": large}, allow=False)
