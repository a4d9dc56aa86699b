"""The command-line contract: simulate, fit, evaluate (with and without --register)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from torchcal.cli import main


@pytest.fixture(scope="module")
def twin_fit(tmp_path_factory):
    """A simulated twin case and ``fit``'s default model of it (the structure cross-validated): the
    tests that only read the model folder (``evaluate`` writes nothing there) share the one fit."""
    case, model = tmp_path_factory.mktemp("case"), tmp_path_factory.mktemp("fit") / "model"
    assert main(["simulate", "--out", str(case), "n_train=150", "n_test=100", "seed=5"]) == 0
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "train.csv"), "--out", str(model), "residual=none"]) == 0
    return case, model


@pytest.mark.slow
def test_simulate_fit_evaluate(tmp_path, capsys, twin_fit):
    case, model = twin_fit
    for name in ("calibration.safetensors", "calibration.json", "calibrated_robot.yaml", "robot.yaml"):
        assert (model / name).is_file()
    out = tmp_path / "m.json"
    assert main(["evaluate", "--model", str(model), "--data", str(case / "test.csv"), "--json", str(out)]) == 0
    metrics = json.loads(out.read_text())
    for key in ("n_poses", "position_rms_mm", "position_mean_mm", "position_max_mm", "position_p95_mm"):
        assert key in metrics
    truth = json.loads((case / "truth.json").read_text())
    assert metrics["n_poses"] == 100
    assert metrics["position_rms_mm"] < 1.2 * truth["noise_floor_rms_mm"]
    # new poses: no twins of the training poses, no leakage warning
    assert metrics["leakage"]["twin_share"] == 0.0 and not metrics["leakage"]["warning"]
    # what the exported compensator leaves at the scored poses (position first: solved, orientation reported)
    comp = metrics["compensator"]
    assert comp["task"] == "position" and comp["solved_share"] > 0.9
    assert 0.0 <= comp["orientation_deviation_median_rad"] <= comp["orientation_deviation_max_rad"] < 0.5
    selection = json.loads((model / "model_selection.json").read_text())
    assert selection["chosen"].startswith("geometry") and "configuration regions" in selection["protocol"]
    # scoring the training file itself: every pose is its own twin, and evaluate says so
    capsys.readouterr()
    assert main(["evaluate", "--model", str(model), "--data", str(case / "train.csv"), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["leakage"]["twin_share"] == 1.0
    assert "warning:" in capsys.readouterr().err


@pytest.mark.slow
def test_evaluate_register_refits_only_the_frame(tmp_path, capsys, twin_fit):
    case, model = twin_fit
    # the tracker was moved: shift and rotate the test file's points
    lines = (case / "test.csv").read_text().splitlines()
    arr = np.array([[float(v) for v in l.split(",")] for l in lines[1:]])
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    arr[:, 6:9] = arr[:, 6:9] @ rot.T + np.array([120.0, -40.0, 15.0])
    moved = tmp_path / "moved.csv"
    moved.write_text("\n".join([lines[0]] + [",".join(f"{v:.10f}" for v in row) for row in arr]) + "\n")
    plain, registered = tmp_path / "a.json", tmp_path / "b.json"
    # scored in the fit's frame the points are missed by centimetres: refused, naming --register
    assert main(["evaluate", "--model", str(model), "--data", str(moved), "--json", str(plain)]) == 2
    assert "add --register" in capsys.readouterr().err and not plain.exists()
    assert main(["evaluate", "--model", str(model), "--data", str(moved), "--json", str(registered), "--register"]) == 0
    b = json.loads(registered.read_text())
    assert b["position_rms_mm"] < 0.04


def test_unknown_override_is_one_clear_line(tmp_path, capsys):
    assert main(["simulate", "--out", str(tmp_path), "n_trian=3"]) == 2
    err = capsys.readouterr().err
    assert "n_trian" in err and "Traceback" not in err


@pytest.mark.slow
def test_yaml_and_urdf_variants_give_the_same_calibration(tmp_path):
    from torchcal.kinematics.robot import load_robot, mdh_to_urdf

    case = tmp_path / "case"
    main(["simulate", "--out", str(case), "n_train=120", "n_test=80", "seed=8"])
    (case / "robot.urdf").write_text(mdh_to_urdf(load_robot(case / "robot.yaml")))
    results = []
    # the twin's structure is given and no uncertainty calibrated, so nothing is cross-validated (what
    # the robot file is read into is tested, not the structure choice or the prediction uncertainty)
    structure = ["residual=none", "gravity_compliance=elbow+wrist", "joint_harmonics=first", "uncertainty=none"]
    for robot_file, extra in (("robot.yaml", []), ("robot.urdf", []), ("robot.urdf", ["tool_mm=[0,0,100]"])):
        model = tmp_path / f"m{len(results)}"
        assert main(["fit", "--robot", str(case / robot_file), "--data", str(case / "train.csv"), "--out", str(model), *structure, *extra]) == 0
        out = tmp_path / f"e{len(results)}.json"
        main(["evaluate", "--model", str(model), "--data", str(case / "test.csv"), "--json", str(out)])
        results.append(json.loads(out.read_text())["position_rms_mm"])
    # the same robot and tool from either file: the same calibration
    assert abs(results[0] - results[2]) < 1e-6
    # a URDF without its tool: the prior's tool (the flange) is 100 mm off, named in a warning; the fit
    # still finds the tool, a little worse where the 100 mm leak into d6 through the prior
    assert results[1] < 1.02 * results[0]


@pytest.mark.slow
def test_tracer_simulate_fit_evaluate_register(tmp_path):
    """Lengths alone calibrate the robot to the noise floor of the held-out tracker check."""
    case = tmp_path / "tracer"
    assert main(["simulate", "--out", str(case), "instrument=tracer", "seed=3", "n_test=150", "loss_probability=0.05"]) == 0
    truth = json.loads((case / "truth.json").read_text())
    for method in ("joint", "two_step"):
        model = tmp_path / method
        assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "lengths.csv"), "--out", str(model),
                     f"tracer_method={method}", "residual=none"]) == 0
        meta = json.loads((model / "calibration.json").read_text())
        assert meta["tracer"]["method"] == method and len(meta["tracer"]["stations_mm"]) == 4
        err = np.array(meta["tracer"]["stations_mm"]) - np.array(truth["stations_mm"])
        assert np.abs(err).max() < 2.0  # mm: the base frame as the nominal row 1 realizes it
        out = tmp_path / f"{method}.json"
        assert main(["evaluate", "--model", str(model), "--data", str(case / "test.csv"), "--register", "--json", str(out)]) == 0
        metrics = json.loads(out.read_text())
        assert metrics["n_poses"] == 150
        assert metrics["position_rms_mm"] < 1.25 * truth["noise_floor_rms_mm"], (method, metrics["position_rms_mm"])
    assert main(["export", "--model", str(tmp_path / "joint"), "--out", str(tmp_path / "onnx")]) == 0
    # the tracer fit keeps its poses' joints: the export judges its corrections over them
    manifest = json.loads((tmp_path / "onnx" / "manifest.json").read_text())
    assert manifest["corrections"]["extent"]["training poses"]["n_poses"] > 0


@pytest.mark.slow
def test_a_reader_that_closes_the_pipe_gets_no_traceback(twin_fit):
    """`torchcal evaluate ... | head`: the reader stops early; no BrokenPipe traceback."""
    import subprocess
    import sys

    case, model = twin_fit
    # `true` exits without reading: the pipe is closed long before evaluate writes its result
    command = f"{sys.executable} -m torchcal.cli evaluate --model {model} --data {case / 'test.csv'} | true"
    done = subprocess.run(["bash", "-o", "pipefail", "-c", command], capture_output=True, text=True, timeout=300)
    assert "Traceback" not in done.stderr and "BrokenPipe" not in done.stderr, done.stderr[-2000:]
    assert done.returncode == 0


def test_each_warning_once_per_command(tmp_path):
    """A LASSO fit repeats the identifiability analysis in its refit: the warning is shown once."""
    import warnings

    case = tmp_path / "case"
    assert main(["simulate", "--out", str(case), "n_train=60", "n_test=20", "seed=1"]) == 0
    lines = (case / "train.csv").read_text().splitlines()
    # joint 6 held at one angle: its offset cannot be identified, which the analysis warns about
    fixed = [lines[0]] + [",".join(row.split(",")[:5] + ["12.5"] + row.split(",")[6:]) for row in lines[1:]]
    data = tmp_path / "fixed.csv"
    data.write_text("\n".join(fixed) + "\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")  # shown every time unless the command itself says each once
        assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(data), "--out", str(tmp_path / "m"),
                     "method=lasso", "residual=none", "gravity_compliance=none", "joint_harmonics=none"]) == 0
    texts = [str(w.message) for w in caught]
    assert any("cannot be identified" in t for t in texts)
    assert len(texts) == len(set(texts)), texts


def test_fit_takes_two_series_each_in_its_own_frame(tmp_path, capsys):
    case = tmp_path / "case"
    main(["simulate", "--out", str(case), "n_train=120", "n_test=200", "seed=7"])
    lines = (case / "test.csv").read_text().splitlines()
    arr = np.array([[float(v) for v in l.split(",")] for l in lines[1:]])
    c, s = np.cos(0.4), np.sin(0.4)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    second, scored = tmp_path / "second.csv", tmp_path / "scored.csv"
    # the second series: the first 100 test poses, measured from a tracker moved 0.3 m and turned 23 deg
    moved = arr[:100].copy()
    moved[:, 6:9] = moved[:, 6:9] @ rot.T + np.array([300.0, -80.0, 25.0])
    second.write_text("\n".join([lines[0]] + [",".join(f"{v:.10f}" for v in row) for row in moved]) + "\n")
    scored.write_text("\n".join([lines[0]] + lines[101:]) + "\n")
    model = tmp_path / "model"
    # the twin's structure is given (the series' frames are tested, not the structure choice): the
    # cross-validation still runs over the pooled series, for the one structure's uncertainty
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "train.csv"), "--data", str(second),
                 "--out", str(model), "residual=none", "gravity_compliance=elbow+wrist", "joint_harmonics=first"]) == 0
    meta = json.loads((model / "calibration.json").read_text())
    files = meta["series"]["files"]
    assert [f["n_poses"] for f in files] == [120, 100] and meta["series"]["tool"] == "shared"
    assert all(len(f["sha256"]) == 64 for f in files)
    # the second frame found: the moved tracker's rotation about z (0.4 rad) and its shift
    frame = np.array(files[1]["T_series_reference"])
    assert abs(np.arctan2(frame[1, 0], frame[0, 0]) - 0.4) < 1e-4
    assert np.allclose(frame[:3, 3], rot @ np.zeros(3) + np.array([0.300, -0.080, 0.025]), atol=1e-4)
    truth = json.loads((case / "truth.json").read_text())
    out = tmp_path / "e.json"
    assert main(["evaluate", "--model", str(model), "--data", str(scored), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["position_rms_mm"] < 1.2 * truth["noise_floor_rms_mm"]
    # an instrument without series refuses a second file in one line
    capsys.readouterr()
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "train.csv"), "--data",
                 str(tmp_path / "nothere.csv"), "--out", str(tmp_path / "m2")]) == 2
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.slow
def test_evaluate_scores_the_tool_orientation_where_the_file_measures_it(tmp_path, twin_fit):
    """A file with rx, ry, rz: the position-only model's flange orientation against the nominal robot's."""
    import torch

    from torchcal.data.measurements import load_measurements, write_measurements_csv
    from torchcal.kinematics import transforms as tf
    from torchcal.sim.twin import Twin, TwinConfig

    case, model = twin_fit
    twin = Twin.create(TwinConfig(n_train=150, n_test=100, seed=5))
    written = load_measurements(case / "test.csv", twin.robot)  # it is the twin `simulate seed=5` wrote: noise apart
    assert float((written.position - twin.true_positions(written.q)).norm(dim=-1).max()) < 2e-4
    generator = torch.Generator().manual_seed(11)
    q = twin.robot.sample_joints(80, generator)
    flange = twin.T_instrument_base() @ twin.model.base_flange_pose(q + twin.joint_deviation(q), twin.x_true)
    probe = tf.so3_exp(torch.tensor([0.4, 0.1, -2.0], dtype=torch.float64))  # mounted at an angle the fit never saw
    angles = tf.matrix_to_euler_xyz(flange[..., :3, :3] @ probe) * (180.0 / np.pi)
    path, out, report = tmp_path / "six_d.csv", tmp_path / "m.json", tmp_path / "report"
    write_measurements_csv(path, q, twin.measure(q, generator), extra={"rx": angles[:, 0], "ry": angles[:, 1],
                                                                        "rz": angles[:, 2]})
    assert main(["evaluate", "--model", str(model), "--data", str(path), "--json", str(out), "--report", str(report)]) == 0
    metrics = json.loads(out.read_text())
    assert metrics["position_rms_mm"] < 0.1  # the fitted twin's robot: a guard that the file is of it
    orientation = metrics["orientation"]
    assert "probe rotation on the flange fitted to these orientations" in orientation["protocol"]
    assert orientation["n_poses"] == 80 and orientation["nominal"]["n_poses"] == 80
    # the model's flange orientation, known from positions alone, is closer than the nominal robot's
    assert orientation["orientation_rms_deg"] < 0.6 * orientation["nominal"]["orientation_rms_deg"]
    assert metrics["orientation_rms_deg"] == orientation["orientation_rms_deg"]
    text = (report / "report.md").read_text()
    assert "RMS [deg]" in text and f"{orientation['orientation_rms_deg']:.4f}" in text
    # the compensator's joint corrections on these poses, with their uncertainty, in the metrics and the report
    corrections = metrics["compensator"]["corrections"]
    assert corrections["largest_joint_correction_sigma_deg"] > 0 and len(corrections["median_joint_correction_sigma_deg"]) == 6
    assert f"{corrections['largest_joint_correction_deg']:.3g} deg (joint {corrections['joint']}; 1-sigma" in text
    assert not any("worse than the nominal robot" in w for w in metrics.get("warnings", []))
    # a file whose orientations follow the nominal robot (the arm turned as its drawing says): the model's are worse,
    # and the user is told that its compensator turns the tool by them
    nominal = twin.T_instrument_base() @ twin.robot.flange_pose(q)
    angles = tf.matrix_to_euler_xyz(nominal[..., :3, :3] @ probe) * (180.0 / np.pi)
    write_measurements_csv(path, q, twin.measure(q, generator), extra={"rx": angles[:, 0], "ry": angles[:, 1],
                                                                        "rz": angles[:, 2]})
    assert main(["evaluate", "--model", str(model), "--data", str(path), "--json", str(out)]) == 0
    assert any("worse than the nominal robot" in w for w in json.loads(out.read_text())["warnings"])


def test_a_path_too_long_is_one_line(tmp_path, capsys):
    out = tmp_path / ("a" * 300)  # one name over the file system's 255 bytes
    assert main(["simulate", "--out", str(out), "n_train=20", "n_test=10"]) == 2
    err = capsys.readouterr().err
    assert "path too long for the file system" in err and err.count("\n") == 1 and "Traceback" not in err
