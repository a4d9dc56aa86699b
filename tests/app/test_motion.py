"""``torchcal motion`` end to end: files in, trajectory and report out, bad input as one line."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torchcal.cli import main
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import default_robot_path, load_robot
from torchcal.motion.waypoints import waypoints_csv

DEG = math.pi / 180.0
ROBOT = str(default_robot_path())
Q_START = [0.0, -70.0, 20.0, 10.0, 50.0, 0.0]


def _start_arg(q=Q_START) -> str:
    return "start=[" + ",".join(f"{v:g}" for v in q) + "]"


@pytest.fixture(scope="module")
def line_file(tmp_path_factory):
    """A 100 mm line from the pose of Q_START, constant orientation (nominal twin robot)."""
    model = ErrorModel(load_robot(default_robot_path()))
    first = model.tcp_pose(torch.tensor(Q_START, dtype=torch.float64) * DEG, model.nominal_vector())
    poses = first.expand(2, 4, 4).clone()
    poses[1, :3, 3] += torch.tensor([0.06, -0.08, 0.0], dtype=torch.float64)
    path = tmp_path_factory.mktemp("motion") / "path.csv"
    path.write_text(waypoints_csv(poses))
    return path, poses


def _read_trajectory(path):
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    return header, np.array([[float(v) for v in line.split(",")] for line in lines[1:]])


def test_motion_writes_trajectory_and_report(tmp_path, line_file, capsys):
    path, poses = line_file
    out = tmp_path / "TRAJ.csv"
    assert main(["motion", "--robot", ROBOT, "--path", str(path), "--out", str(out), _start_arg(), "dt=0.004"]) == 0
    printed = capsys.readouterr().out
    assert "path error: max" in printed and "joint speed: max" in printed and "report:" in printed
    header, data = _read_trajectory(out)
    assert header == ["t", "q1", "q2", "q3", "q4", "q5", "q6"]
    np.testing.assert_allclose(np.diff(data[:, 0]), 0.004, atol=1e-9)
    # a second forward kinematics (pytorch-kinematics on the URDF) of the written joints
    robot = load_robot(default_robot_path())
    flange = robot.pk_chain().forward_kinematics(torch.from_numpy(data[:, 1:] * DEG)).get_matrix()
    tcp = (flange[:, :3, :3] @ robot.tool + flange[:, :3, 3]).numpy()
    start, end = poses[0, :3, 3].numpy(), poses[1, :3, 3].numpy()
    u = end - start
    lam = np.clip((tcp - start) @ u / (u @ u), 0, 1)
    assert np.linalg.norm(tcp - (start + lam[:, None] * u), axis=-1).max() * 1e3 < 0.005
    assert np.linalg.norm(tcp[-1] - end) * 1e3 < 0.005
    report = tmp_path / "TRAJ_report"
    metrics = json.loads((report / "motion.json").read_text())
    assert metrics["within_tolerance"] and metrics["path_error_max_mm"] < 0.005
    assert metrics["duration_s"] == pytest.approx(data[-1, 0])
    for name in ("report.md", "report.html", "figures/path_error.png", "figures/joint_speed.png",
                 "figures/joint_accel.png", "figures/singularity.png"):
        assert (report / name).is_file()
    # joint speeds in the report are the finite differences of the file's joints
    speed = np.abs(np.diff(data[:, 1:], axis=0)).max(0) / 0.004
    np.testing.assert_allclose(metrics["joint_speed_max_deg_s"], speed, rtol=1e-6)


@pytest.mark.parametrize("body, expected", [
    ("x,y,z,rx,ry,rz\n1,2,3,4,5,6\n1,2,x3,4,5,6\n", "row 3, column 'z'"),
    ("x,y,z,rx,ry\n1,2,3,4,5\n", "missing column 'rz'"),
])
def test_bad_path_file_is_one_line(tmp_path, capsys, body, expected):
    path = tmp_path / "bad.csv"
    path.write_text(body)
    code = main(["motion", "--robot", ROBOT, "--path", str(path), "--out", str(tmp_path / "t.csv"), _start_arg()])
    err = capsys.readouterr().err
    assert code == 2 and expected in err and str(path) in err and err.count("\n") == 1
    assert not (tmp_path / "t.csv").exists()


@pytest.mark.parametrize("option, expected", [
    ([], "start=[q1,...,q6] (deg) is required"),
    (["start=[1,2,3]"], "start has 3 values"),
    ([_start_arg(), "speed=-5"], "speed must be a finite number in (0, inf), got -5.0"),
    ([_start_arg(), "joint_speed=[1,1,1,1,1,0]"], "joint_speed limits must be positive"),
    ([_start_arg(), "dampng=1"], "invalid override"),
    (["start=[0,-60,90,0,300,0]"], "start: q5 = 300 deg is outside joint 5's limits"),
])
def test_bad_options_are_one_line(tmp_path, line_file, capsys, option, expected):
    code = main(["motion", "--robot", ROBOT, "--path", str(line_file[0]), "--out", str(tmp_path / "t.csv"), *option])
    err = capsys.readouterr().err
    assert code == 2 and expected in err and err.count("\n") == 1
    assert not (tmp_path / "t_report").exists()  # refused before any work: no report either


def test_out_of_reach_writes_the_report_but_no_trajectory(tmp_path, capsys):
    path = tmp_path / "far.csv"
    path.write_text("x,y,z,rx,ry,rz\n600,0,700,0,90,0\n1400,0,700,0,90,0\n")  # 1.4 m: beyond the arm's reach
    out = tmp_path / "t.csv"
    model = ErrorModel(load_robot(default_robot_path()))
    from torchcal.kinematics import transforms as tf
    from torchcal.kinematics.ik import solve_ik

    target = tf.homogeneous(tf.euler_xyz_to_matrix(torch.tensor([0.0, 90 * DEG, 0.0], dtype=torch.float64)),
                            torch.tensor([0.6, 0.0, 0.7], dtype=torch.float64))
    q0 = solve_ik(model, model.nominal_vector(), target, torch.tensor([0, -30, 30, 0, 30, 0], dtype=torch.float64) * DEG).q
    code = main(["motion", "--robot", ROBOT, "--path", str(path), "--out", str(out), _start_arg((q0 / DEG).tolist())])
    err = capsys.readouterr().err
    assert code == 2 and "exceeds the tolerance" in err and "not written" in err
    assert not out.exists()
    metrics = json.loads((tmp_path / "t_report" / "motion.json").read_text())
    assert not metrics["within_tolerance"] and metrics["path_error_max_mm"] > 1.0


def test_out_names_a_folder(tmp_path, line_file, capsys):
    code = main(["motion", "--robot", ROBOT, "--path", str(line_file[0]), "--out", str(tmp_path), _start_arg()])
    assert code == 2 and "names an existing folder" in capsys.readouterr().err


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A twin with geometric errors, calibrated from 150 simulated tracker poses."""
    from torchcal.config.schema import FitConfig
    from torchcal.sim.twin import Twin, TwinConfig
    from torchcal.stages.geometry import fit, save_fit

    twin = Twin.create(TwinConfig(seed=3, gravity=False, gear=False))
    train = twin.sample(150, torch.Generator().manual_seed(11))
    result = fit(twin.robot, train, FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none"))
    return twin, save_fit(tmp_path_factory.mktemp("model") / "model", twin.robot, train, result, {})


def test_model_plans_the_real_robot(tmp_path, line_file, calibrated):
    """With --model the joints put the twin's true TCP on the path; the nominal joints miss it by about a mm."""
    from torchcal.stages.store import load_model

    twin, model_dir = calibrated
    path, poses = line_file
    runs = {}
    for name, extra in (("model", ["--model", str(model_dir)]), ("nominal", [])):
        out = tmp_path / f"{name}.csv"
        assert main(["motion", "--robot", ROBOT, "--path", str(path), "--out", str(out), _start_arg(), *extra]) == 0
        runs[name] = _read_trajectory(out)[1]
    stored = load_model(model_dir)
    # the path in the instrument frame, through the calibrated base frame; the twin's truth is there too
    frame = stored.model.instrument_from_base(stored.x)
    start, end = (frame[:3, :3] @ poses[:, :3, 3].T).T + frame[:3, 3]
    start, end = start.numpy(), end.numpy()
    errors = {}
    for name, data in runs.items():
        tcp = twin.model.tcp_pose(torch.from_numpy(data[:, 1:] * DEG), twin.x_true)[:, :3, 3].numpy()
        u = end - start
        lam = np.clip((tcp - start) @ u / (u @ u), 0, 1)
        errors[name] = np.linalg.norm(tcp - (start + lam[:, None] * u), axis=-1).max() * 1e3
    assert errors["model"] < 0.1
    assert errors["nominal"] > 5 * errors["model"]


def test_a_failed_run_keeps_the_earlier_trajectory_and_its_report(tmp_path, line_file, capsys):
    path, _ = line_file
    out = tmp_path / "TRAJ.csv"
    assert main(["motion", "--robot", ROBOT, "--path", str(path), "--out", str(out), _start_arg()]) == 0
    trajectory, report = out.read_text(), (tmp_path / "TRAJ_report" / "report.md").read_text()
    capsys.readouterr()
    # a path that leaves the arm's reach into the same --out: the run fails
    far = tmp_path / "far.csv"
    poses = line_file[1].clone()
    poses[1, :3, 3] = torch.tensor([1.8, 0.0, 0.7], dtype=torch.float64)  # 1.8 m: beyond the arm's reach
    far.write_text(waypoints_csv(poses))
    assert main(["motion", "--robot", ROBOT, "--path", str(far), "--out", str(out), _start_arg()]) == 2
    err = capsys.readouterr().err
    assert "kept from the earlier run" in err and "TRAJ_report_failed" in err
    assert out.read_text() == trajectory and (tmp_path / "TRAJ_report" / "report.md").read_text() == report
    assert "NOT written" in (tmp_path / "TRAJ_report_failed" / "report.md").read_text()


@pytest.mark.parametrize("columns, factor, expected", [
    ((0, 1, 2), 1e-3, "x, y, z look like metres"),
    ((3, 4, 5), DEG, "rx, ry, rz look like radians"),
])
def test_a_path_in_the_wrong_units_is_refused_naming_them(tmp_path, line_file, capsys, columns, factor, expected):
    lines = line_file[0].read_text().splitlines()
    rows = [[float(v) for v in line.split(",")] for line in lines[1:]]
    edited = [",".join(f"{v * factor:.9g}" if k in columns else f"{v:.9g}" for k, v in enumerate(row)) for row in rows]
    path = tmp_path / "wrong.csv"
    path.write_text("\n".join([lines[0], *edited]) + "\n")
    code = main(["motion", "--robot", ROBOT, "--path", str(path), "--out", str(tmp_path / "t.csv"), _start_arg()])
    err = capsys.readouterr().err
    assert code == 2 and expected in err and "wrong.csv" in err and err.count("\n") == 1
    assert not (tmp_path / "t_report").exists()


def test_a_model_with_another_robot_file_is_refused(tmp_path, line_file, calibrated, capsys):
    _, model_dir = calibrated
    other = tmp_path / "wide.yaml"
    other.write_text(Path(ROBOT).read_text().replace("min: -170", "min: -175", 1))  # same name, other limits
    assert "min: -175" in other.read_text()
    code = main(["motion", "--robot", str(other), "--path", str(line_file[0]), "--out", str(tmp_path / "t.csv"),
                 _start_arg(), "--model", str(model_dir)])
    err = capsys.readouterr().err
    assert code == 2 and "differ in their joint limits" in err


def test_the_models_robot_file_as_rewritten_to_nine_digits_is_its_robot(calibrated):
    from dataclasses import replace

    from torchcal.app.motion import kinematics_of
    from torchcal.core.errors import ModelError
    from torchcal.stages.store import load_model

    _, model_dir = calibrated
    robot = load_model(model_dir).robot
    kinematics_of(replace(robot, table=robot.table + 4e-9), model_dir)  # a rad/m file rewritten in deg/mm
    with pytest.raises(ModelError, match="kinematic table"):
        kinematics_of(replace(robot, table=robot.table + 1e-4), model_dir)


def test_a_waypoint_far_beyond_reach_or_a_grid_too_fine_is_one_line(tmp_path, line_file, capsys):
    path, _ = line_file
    far = tmp_path / "huge.csv"
    poses = line_file[1].clone()
    poses[1, :3, 3] = torch.tensor([1e9, 0.0, 0.0], dtype=torch.float64)  # 1e12 mm: no allocation of a grid that long
    far.write_text(waypoints_csv(poses))
    assert main(["motion", "--robot", ROBOT, "--path", str(far), "--out", str(tmp_path / "t.csv"), _start_arg()]) == 2
    assert "row 3: the waypoint is 1e+12 mm from the base, beyond the arm's nominal reach" in capsys.readouterr().err
    assert main(["motion", "--robot", ROBOT, "--path", str(path), "--out", str(tmp_path / "t.csv"), _start_arg(),
                 "step=1e-5", "gain=1"]) == 2  # 100 mm at 1e-5 mm: 1e7 grid points
    assert "grid points of step=1e-05 mm, more than 1000000; give a larger step" in capsys.readouterr().err
    assert not (tmp_path / "t.csv").exists()


def test_a_coarse_interpolation_period_is_judged_between_its_samples(tmp_path, line_file, capsys):
    """The samples lie on the line, but a controller interpolating the joints linearly between samples
    100 ms apart leaves it: measured halfway, by forward kinematics, and refused beyond the tolerance."""
    from torchcal.motion.planner import between_samples_error_mm

    path, _ = line_file
    out = tmp_path / "t.csv"
    assert main(["motion", "--robot", ROBOT, "--path", str(path), "--out", str(out), _start_arg()]) == 0
    fine = capsys.readouterr().out
    assert "halfway between them (joints interpolated linearly; tolerance 0.02 mm)" in fine
    assert main(["motion", "--robot", ROBOT, "--path", str(path), "--out", str(tmp_path / "c.csv"), _start_arg(),
                 "dt=0.2"]) == 2
    err = capsys.readouterr().err
    assert "halfway between the samples" in err and "beyond between_tolerance=0.02 mm: give dt=" in err
    # the measure itself, against a hand computation: two joint vectors whose midpoint's TCP is off the chord
    model = ErrorModel(load_robot(default_robot_path()))
    x = model.nominal_vector()

    class Kin:
        @staticmethod
        def pose(q):
            return model.tcp_pose(q, x)

    q = torch.tensor([Q_START, [v + 40.0 for v in Q_START]], dtype=torch.float64) * DEG
    ends = model.tcp_pose(q, x)
    mid = model.tcp_pose(q.mean(0, keepdim=True), x)[0, :3, 3]
    a, b = ends[0, :3, 3], ends[1, :3, 3]
    lam = float(torch.dot(mid - a, b - a) / torch.dot(b - a, b - a))
    expected = float((mid - (a + min(max(lam, 0.0), 1.0) * (b - a))).norm()) * 1e3
    got = between_samples_error_mm(Kin, q, ends)
    assert got.shape == (1,) and expected > 1.0 and abs(float(got[0]) - expected) < 1e-9
