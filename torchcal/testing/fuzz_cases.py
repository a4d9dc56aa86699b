"""Bad inputs a user can give the command line, each with the answer it must get.

Shipped with the package (like the contract suites) so that ``scripts/fuzz_count.py`` imports it
without path edits. Shared by ``tests/test_fuzz_cli.py`` (which runs them through ``torchcal.cli.main``) and
``scripts/fuzz_count.py`` (which runs them as processes against any checkout and counts the
outcomes). A case builds its inputs under a fresh folder from a small twin case and a fitted model
(:class:`Fixtures`) and says:

* ``rc``: the exit status (2: refused; 0: accepted with a warning);
* ``message``: text the one ``torchcal: error:`` line (or a ``torchcal: warning:`` line) holds;
* ``out`` / ``out_state``: an output path and what it must be afterwards: ``absent``,
  ``unchanged`` (as before the command, byte for byte) or ``whole`` (a verified model folder).
"""

from __future__ import annotations

import csv
import json
import math
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchcal.core.errors import TorchcalError
from torchcal.core.folder import seal, verify_folder, write_member, write_member_json
from torchcal.data.measurements import write_measurements_csv
from torchcal.kinematics.robot import load_robot, mdh_to_urdf
from torchcal.sim.twin import Twin, TwinConfig


@dataclass
class Fixtures:
    """A twin case (``case/robot.yaml``, ``train.csv``, ``test.csv``) and a model fitted to it."""

    root: Path
    case: Path
    model: Path

    @property
    def robot(self) -> Path:
        return self.case / "robot.yaml"

    @property
    def train(self) -> Path:
        return self.case / "train.csv"

    @property
    def test(self) -> Path:
        return self.case / "test.csv"


@dataclass
class Case:
    argv: list[str]
    rc: int
    message: str
    out: Path | None = None
    out_state: str = "absent"
    extra: dict = field(default_factory=dict)


FAST = ["residual=none", "gravity_compliance=none", "joint_harmonics=none"]


def make_fixtures(root: Path, run: Callable[[list[str]], int]) -> Fixtures:
    """Simulate a small twin case and fit a geometry-only model with ``run`` (a CLI entry point)."""
    case, model = root / "case", root / "model"
    assert run(["simulate", "--out", str(case), "n_train=40", "n_test=40"]) == 0
    assert run(["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "train.csv"), "--out", str(model), *FAST]) == 0
    return Fixtures(root, case, model)


# ----------------------------------------------------------------------------------------- helpers


def _rows(path: Path) -> tuple[list[str], list[list[str]]]:
    rows = list(csv.reader(path.read_text().splitlines()))
    return rows[0], rows[1:]


def _write_rows(path: Path, header: list[str], rows: list[list[str]]) -> Path:
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)
    return path


def _edit_csv(src: Path, dst: Path, edit: Callable[[list[str], int, list[str]], list[str]]) -> Path:
    header, rows = _rows(src)
    return _write_rows(dst, header, [edit(header, k, list(r)) for k, r in enumerate(rows)])


def _copy_model(fx: Fixtures, work: Path) -> Path:
    folder = work / "model"
    shutil.copytree(fx.model, folder)
    return folder


def _reseal(folder: Path) -> None:
    """Record the folder's current files as its own (a damaged file that its checksums vouch for)."""
    seal(folder)


def _fit(fx: Fixtures, data: Path, out: Path, *extra: str, robot: Path | None = None) -> list[str]:
    return ["fit", "--robot", str(robot or fx.robot), "--data", str(data), "--out", str(out), *FAST, *extra]


def _evaluate(model: Path, data: Path, *extra: str) -> list[str]:
    return ["evaluate", "--model", str(model), "--data", str(data), *extra]


# ------------------------------------------------------------------------------------------- cases


def csv_latin1(fx: Fixtures, w: Path) -> Case:
    data = w / "train.csv"
    lines = fx.train.read_bytes().split(b"\n")
    lines[3] += b"\xe9"
    data.write_bytes(b"\n".join(lines))
    return Case(_fit(fx, data, w / "out"), 2, "UTF-8", w / "out")


def csv_binary(fx: Fixtures, w: Path) -> Case:
    data = w / "train.csv"
    data.write_bytes(bytes((i * 7919 + 13) % 256 for i in range(4000)))
    return Case(_fit(fx, data, w / "out"), 2, "train.csv", w / "out")


def csv_nul(fx: Fixtures, w: Path) -> Case:
    data = w / "train.csv"
    data.write_bytes(fx.train.read_bytes().replace(b",", b",\x00", 1))
    return Case(_fit(fx, data, w / "out"), 2, "train.csv", w / "out")


def csv_huge_field(fx: Fixtures, w: Path) -> Case:
    data = _edit_csv(fx.train, w / "train.csv", lambda h, k, r: r if k != 2 else [*r[:-1], "7" * 200_000])
    return Case(_fit(fx, data, w / "out"), 2, "train.csv", w / "out")


def csv_metres(fx: Fixtures, w: Path) -> Case:
    def edit(h, k, r):
        for c in "xyz":
            r[h.index(c)] = repr(float(r[h.index(c)]) / 1000)
        return r
    return Case(_fit(fx, _edit_csv(fx.train, w / "train.csv", edit), w / "out"), 2, "length_unit=m", w / "out")


def csv_radians(fx: Fixtures, w: Path) -> Case:
    def edit(h, k, r):
        for i, c in enumerate(h):
            if c.startswith("q"):
                r[i] = repr(math.radians(float(r[i])))
        return r
    return Case(_fit(fx, _edit_csv(fx.train, w / "train.csv", edit), w / "out"), 2, "joint_unit=rad", w / "out")


def csv_1e300(fx: Fixtures, w: Path) -> Case:
    data = _edit_csv(fx.train, w / "train.csv", lambda h, k, r: r if k != 3 else [*r[: h.index("x")], "1e300", *r[h.index("x") + 1:]])
    return Case(_fit(fx, data, w / "out"), 2, "row 5, column 'x'", w / "out")


def csv_underscore(fx: Fixtures, w: Path) -> Case:
    data = _edit_csv(fx.train, w / "train.csv", lambda h, k, r: r if k != 0 else ["1_0", *r[1:]])
    return Case(_fit(fx, data, w / "out"), 2, "'1_0' is not a number", w / "out")


def csv_nan(fx: Fixtures, w: Path) -> Case:
    data = _edit_csv(fx.train, w / "train.csv", lambda h, k, r: r if k != 4 else [*r[:-1], "nan"])
    return Case(_fit(fx, data, w / "out"), 2, "row 6", w / "out")


def csv_duplicate(fx: Fixtures, w: Path) -> Case:
    header, rows = _rows(fx.train)
    data = _write_rows(w / "train.csv", header, [*rows, rows[0]])
    return Case(_fit(fx, data, w / "out"), 2, "duplicates row 2", w / "out")


def csv_missing_column(fx: Fixtures, w: Path) -> Case:
    header, rows = _rows(fx.train)
    i = header.index("q6")
    data = _write_rows(w / "train.csv", header[:i] + header[i + 1:], [r[:i] + r[i + 1:] for r in rows])
    return Case(_fit(fx, data, w / "out"), 2, "q1..q6", w / "out")


def csv_semicolon(fx: Fixtures, w: Path) -> Case:
    data = w / "train.csv"
    data.write_text("\n".join(line.replace(",", ";").replace(".", ",") for line in fx.train.read_text().splitlines()) + "\n")
    return Case(_fit(fx, data, w / "out"), 2, "separated by semicolons", w / "out")


def csv_wide_header(fx: Fixtures, w: Path) -> Case:
    header, rows = _rows(fx.train)
    extra = [f"c{i}" for i in range(200_000)]
    data = _write_rows(w / "train.csv", header + extra, [r + ["0"] * len(extra) for r in rows[:3]])
    return Case(_fit(fx, data, w / "out"), 2, "200009 columns", w / "out")


def csv_million_rows(fx: Fixtures, w: Path) -> Case:
    header, rows = _rows(fx.train)
    data = w / "train.csv"
    line = ",".join(rows[0]) + "\n"
    data.write_text(",".join(header) + "\n" + line * 600_000)
    return Case(_fit(fx, data, w / "out"), 2, "at most 500000 poses", w / "out")


def yaml_latin1(fx: Fixtures, w: Path) -> Case:
    robot = w / "robot.yaml"
    robot.write_bytes(fx.robot.read_bytes().replace(b"name: twin-kr6", b"name: twin-kr6-\xe9"))
    return Case(_fit(fx, fx.train, w / "out", robot=robot), 2, "UTF-8", w / "out")


def yaml_binary(fx: Fixtures, w: Path) -> Case:
    robot = w / "robot.yaml"
    robot.write_bytes(bytes((i * 104729 + 7) % 256 for i in range(3000)))
    return Case(_fit(fx, fx.train, w / "out", robot=robot), 2, "robot.yaml", w / "out")


def yaml_alias_bomb(fx: Fixtures, w: Path) -> Case:
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 10)]
    robot = w / "robot.yaml"
    robot.write_text("\n".join(lines) + "\nname: *a9\n" + fx.robot.read_text().split("\n", 1)[1])
    return Case(_fit(fx, fx.train, w / "out", robot=robot), 2, "aliases", w / "out")


def yaml_python_tag(fx: Fixtures, w: Path) -> Case:
    robot = w / "robot.yaml"
    robot.write_text(fx.robot.read_text().replace("name: twin-kr6", "name: !!python/object/apply:os.system ['true']"))
    return Case(_fit(fx, fx.train, w / "out", robot=robot), 2, "not valid YAML", w / "out")


def yaml_wrong_sign(fx: Fixtures, w: Path) -> Case:
    robot = w / "robot.yaml"
    robot.write_text(fx.robot.read_text().replace("a: 455", "a: -455"))
    return Case(_fit(fx, fx.train, w / "out", robot=robot), 2, "still misses the measured points", w / "out")


def _urdf(fx: Fixtures) -> str:
    return mdh_to_urdf(load_robot(fx.robot))


def urdf_nan_origin(fx: Fixtures, w: Path) -> Case:
    text = _urdf(fx)
    i = text.index('xyz="', text.index("<joint"))
    robot = w / "robot.urdf"
    robot.write_text(text[:i] + 'xyz="nan 0 0" data-x="' + text[i + 5:])
    return Case(_fit(fx, fx.train, w / "out", robot=robot), 2, "finite", w / "out")


def _urdf_with(fx: Fixtures, w: Path, opening: str, value: str) -> Path:
    """The twin's robot as URDF with the first attribute that ``opening`` starts (``'<axis xyz="'``) set to ``value``."""
    text = _urdf(fx)
    i = text.index(opening)
    j = text.index('"', i + len(opening))
    robot = w / "robot.urdf"
    robot.write_text(text[:i] + opening + value + text[j:])
    return robot


def urdf_zero_axis(fx: Fixtures, w: Path) -> Case:
    robot = _urdf_with(fx, w, '<axis xyz="', "0 0 0")
    return Case(_fit(fx, fx.train, w / "out", robot=robot), 2, "axis", w / "out")


def urdf_nan_limit(fx: Fixtures, w: Path) -> Case:
    robot = _urdf_with(fx, w, '<limit lower="', "nan")
    return Case(_fit(fx, fx.train, w / "out", robot=robot), 2, "must be finite numbers", w / "out")


def _yaml_last_joint(fx: Fixtures, w: Path, entries: str) -> Path:
    """The twin's robot YAML with the last joint's limits (``min: .., max: ..``) replaced by ``entries``."""
    import re

    lines = fx.robot.read_text().splitlines()
    last = max(i for i, line in enumerate(lines) if "min:" in line)
    lines[last] = re.sub(r"min: [^,}]+, max: [^,}]+", entries, lines[last])
    robot = w / "robot.yaml"
    robot.write_text("\n".join(lines) + "\n")
    return robot


def yaml_continuous_with_limits(fx: Fixtures, w: Path) -> Case:
    robot = _yaml_last_joint(fx, w, "continuous: true, min: -170, max: 170")
    return Case(_fit(fx, fx.train, w / "out", robot=robot), 2, "continuous and has min/max", w / "out")


def yaml_continuous_not_boolean(fx: Fixtures, w: Path) -> Case:
    robot = _yaml_last_joint(fx, w, "continuous: 1")
    return Case(_fit(fx, fx.train, w / "out", robot=robot), 2, "'continuous' must be true or false", w / "out")


def yaml_deeply_nested(fx: Fixtures, w: Path) -> Case:
    robot = w / "robot.yaml"
    robot.write_text("name: " + "[" * 20000 + "]" * 20000 + "\n" + fx.robot.read_text().split("\n", 1)[1])
    return Case(_fit(fx, fx.train, w / "out", robot=robot), 2, "robot.yaml", w / "out")


def model_json_truncated(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    path = model / "calibration.json"
    path.write_text(path.read_text()[:200])
    return Case(_evaluate(model, fx.test), 2, "calibration.json", model, "unchanged")


def model_json_invalid_sealed(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    (model / "calibration.json").write_text('{"format": "torchcal-model/1", "robot_file": ')
    _reseal(model)
    return Case(_evaluate(model, fx.test), 2, "invalid JSON", model, "unchanged")


def model_json_missing_key_sealed(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    meta = json.loads((model / "calibration.json").read_text())
    del meta["parameter_names"]
    (model / "calibration.json").write_text(json.dumps(meta))
    _reseal(model)
    return Case(_evaluate(model, fx.test), 2, "parameter_names", model, "unchanged")


def safetensors_bitflip(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    path = model / "calibration.safetensors"
    data = bytearray(path.read_bytes())
    data[-20] ^= 0x10
    path.write_bytes(bytes(data))
    return Case(_evaluate(model, fx.test), 2, "calibration.safetensors", model, "unchanged")


def safetensors_bad_header_sealed(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    (model / "calibration.safetensors").write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json}xxxxxx")
    _reseal(model)
    return Case(_evaluate(model, fx.test), 2, "calibration.safetensors", model, "unchanged")


def safetensors_nan_sealed(fx: Fixtures, w: Path) -> Case:
    from safetensors.torch import load_file, save_file

    model = _copy_model(fx, w)
    path = model / "calibration.safetensors"
    tensors = load_file(str(path))
    tensors["x"][7] = float("nan")
    save_file(tensors, str(path))
    _reseal(model)
    return Case(_evaluate(model, fx.test), 2, "NaN", model, "unchanged")


def safetensors_foreign_sealed(fx: Fixtures, w: Path) -> Case:
    import torch
    from safetensors.torch import save_file

    model = _copy_model(fx, w)
    save_file({"x": torch.zeros(5, dtype=torch.float64), "T_reference": torch.eye(4, dtype=torch.float64),
               "free": torch.arange(3), "covariance": torch.eye(3, dtype=torch.float64)},
              str(model / "calibration.safetensors"))
    _reseal(model)
    return Case(_evaluate(model, fx.test), 2, "calibration.safetensors", model, "unchanged")


def model_stale_residual(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    (model / "residual.json").write_text('{"head": "elm", "settings": {}, "uses_temperature": false}')
    (model / "residual.safetensors").write_bytes(b"\x00" * 16)
    return Case(_evaluate(model, fx.test), 2, "residual.", model, "unchanged")


def model_no_checksums(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    (model / "checksums.json").unlink(missing_ok=True)
    return Case(_evaluate(model, fx.test), 2, "checksums.json", model, "unchanged")


def _robot_file(fx: Fixtures, w: Path, value: str) -> Path:
    model = _copy_model(fx, w)
    meta = json.loads((model / "calibration.json").read_text())
    meta["robot_file"] = value
    (model / "calibration.json").write_text(json.dumps(meta))
    _reseal(model)
    return model


def robot_file_of_another_model_sealed(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    path = model / "robot.yaml"
    path.write_text(path.read_text().replace("a: 455", "a: 480"))
    _reseal(model)
    return Case(_evaluate(model, fx.test), 2, "not the robot file this model was fitted with", model, "unchanged")


def robot_file_absolute(fx: Fixtures, w: Path) -> Case:
    model = _robot_file(fx, w, "/etc/passwd")
    return Case(_evaluate(model, fx.test), 2, "inside the model folder", model, "unchanged")


def robot_file_parent(fx: Fixtures, w: Path) -> Case:
    model = _robot_file(fx, w, "../../case/robot.yaml")
    shutil.copytree(fx.case, w / "case")
    return Case(_evaluate(model, fx.test), 2, "inside the model folder", model, "unchanged")


def fit_out_is_file(fx: Fixtures, w: Path) -> Case:
    out = w / "out"
    out.write_text("keep me\n")
    return Case(_fit(fx, fx.train, out), 2, "existing file", out, "unchanged")


def fit_out_foreign_folder(fx: Fixtures, w: Path) -> Case:
    out = w / "out"
    out.mkdir()
    (out / "notes.txt").write_text("keep me\n")
    return Case(_fit(fx, fx.train, out), 2, "other files", out, "unchanged")


def fit_out_holds_data(fx: Fixtures, w: Path) -> Case:
    out = _copy_model(fx, w)
    shutil.copy(fx.train, out / "train.csv")
    return Case(_fit(fx, out / "train.csv", out), 2, "--data", out, "unchanged")


def evaluate_json_is_folder(fx: Fixtures, w: Path) -> Case:
    out = w / "metrics.json"
    out.mkdir()
    (out / "keep.txt").write_text("keep me\n")
    return Case(_evaluate(fx.model, fx.test, "--json", str(out)), 2, "existing folder", out, "unchanged")


def export_out_is_file(fx: Fixtures, w: Path) -> Case:
    out = w / "export"
    out.write_text("keep me\n")
    return Case(["export", "--model", str(fx.model), "--out", str(out)], 2, "existing file", out, "unchanged")


def export_out_is_model(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    return Case(["export", "--model", str(model), "--out", str(model)], 2, "outside the model folder", model, "unchanged")


def simulate_zero(fx: Fixtures, w: Path) -> Case:
    return Case(["simulate", "--out", str(w / "sim"), "n_train=0"], 2, "n_train", w / "sim")


def simulate_negative(fx: Fixtures, w: Path) -> Case:
    return Case(["simulate", "--out", str(w / "sim"), "n_train=-5"], 2, "n_train", w / "sim")


def threshold_negative(fx: Fixtures, w: Path) -> Case:
    return Case(_fit(fx, fx.train, w / "out", "parallel_threshold_deg=-5"), 2, "parallel_threshold_deg", w / "out")


def threshold_nan(fx: Fixtures, w: Path) -> Case:
    return Case(_fit(fx, fx.train, w / "out", "parallel_threshold_deg=nan"), 2, "parallel_threshold_deg", w / "out")


def residual_unknown(fx: Fixtures, w: Path) -> Case:
    argv = ["fit", "--robot", str(fx.robot), "--data", str(fx.train), "--out", str(w / "out"), "residual=bananas"]
    return Case(argv, 2, "bananas", w / "out")


def unknown_option(fx: Fixtures, w: Path) -> Case:
    return Case(_fit(fx, fx.train, w / "out", "bananas=1"), 2, "bananas", w / "out")


def register_three_poses(fx: Fixtures, w: Path) -> Case:
    header, rows = _rows(fx.test)
    data = _write_rows(w / "test.csv", header, rows[:3])
    return Case(_evaluate(fx.model, data, "--register"), 2, "--register", None)


def evaluate_metres(fx: Fixtures, w: Path) -> Case:
    def edit(h, k, r):
        for c in "xyz":
            r[h.index(c)] = repr(float(r[h.index(c)]) / 1000)
        return r
    return Case(_evaluate(fx.model, _edit_csv(fx.test, w / "test.csv", edit)), 2, "length_unit=m", None)


def few_poses(fx: Fixtures, w: Path) -> Case:
    header, rows = _rows(fx.train)
    data = _write_rows(w / "train.csv", header, rows[:20])
    return Case(_fit(fx, data, w / "out"), 0, "per parameter", w / "out", "whole")


def _points_of_other_poses(src: Path, dst: Path) -> Path:
    """The file with each row's x, y, z taken from another row (joints and points of different poses)."""
    header, rows = _rows(src)
    cols = [header.index(c) for c in "xyz"]
    shifted = rows[7:] + rows[:7]
    return _write_rows(dst, header, [[(shifted[k][i] if i in cols else v) for i, v in enumerate(r)]
                                     for k, r in enumerate(rows)])


def fit_points_of_other_poses(fx: Fixtures, w: Path) -> Case:
    data = _points_of_other_poses(fx.train, w / "train.csv")
    return Case(_fit(fx, data, w / "out"), 2, "still misses the measured points", w / "out")


def evaluate_points_of_other_poses(fx: Fixtures, w: Path) -> Case:
    data = _points_of_other_poses(fx.test, w / "test.csv")
    return Case(_evaluate(fx.model, data, "--json", str(w / "m.json")), 2, "another robot", w / "m.json")


def evaluate_instrument_moved(fx: Fixtures, w: Path) -> Case:
    def edit(h, k, r):
        r[h.index("x")] = repr(float(r[h.index("x")]) + 400.0)
        return r
    return Case(_evaluate(fx.model, _edit_csv(fx.test, w / "test.csv", edit)), 2, "add --register", None)


def rows_with_mistyped_angle(fx: Fixtures, w: Path) -> Case:
    def edit(h, k, r):
        if k in (5, 23):  # two of forty rows: a joint angle typed with a slipped digit
            r[h.index("q2")] = repr(float(r[h.index("q2")]) + 9.0)
        return r
    return Case(_fit(fx, _edit_csv(fx.train, w / "train.csv", edit), w / "out"), 0, "line 7", w / "out", "whole")


def joint_never_moves(fx: Fixtures, w: Path) -> Case:
    twin = Twin.create(TwinConfig(n_train=60))
    q = twin.robot.sample_joints(60, torch.Generator().manual_seed(5))
    q[:, 2] = 0.3  # joint 3 held still while the others move
    data = w / "train.csv"
    write_measurements_csv(data, q, twin.model.tcp_position(q, twin.x_true))
    return Case(_fit(fx, data, w / "out"), 0, "spans only 0.000 deg", w / "out", "whole")


def orientation_garbage(fx: Fixtures, w: Path) -> Case:
    header, rows = _rows(fx.train)
    angles = [[f"{(k * 37 + 11 * c) % 360 - 180:.1f}" for c in range(3)] for k in range(len(rows))]
    data = _write_rows(w / "train.csv", [*header, "rx", "ry", "rz"], [r + a for r, a in zip(rows, angles)])
    return Case(_fit(fx, data, w / "out"), 2, "contradict the positions", w / "out")


def evaluate_orientation_garbage(fx: Fixtures, w: Path) -> Case:
    header, rows = _rows(fx.test)
    angles = [[f"{(k * 37 + 11 * c) % 360 - 180:.1f}" for c in range(3)] for k in range(len(rows))]
    data = _write_rows(w / "test.csv", [*header, "rx", "ry", "rz"], [r + a for r, a in zip(rows, angles)])
    return Case(_evaluate(fx.model, data, "--json", str(w / "m.json")), 2, "convention", w / "m.json")


def rows_in_metres(fx: Fixtures, w: Path) -> Case:
    def edit(h, k, r):
        if k < 12:  # twelve of forty rows in metres: the file mixes units
            for c in "xyz":
                r[h.index(c)] = repr(float(r[h.index(c)]) / 1000)
        return r
    return Case(_fit(fx, _edit_csv(fx.train, w / "train.csv", edit), w / "out"), 2, "a typo or a wrong value",
                w / "out")


# ------------------------------------------------ round 2: outputs, write failures, names, options


def _export_folder(work: Path) -> Path:
    """A sealed export folder (its manifest and a graph file), as ``torchcal export`` leaves one."""
    folder = work / "export"
    write_member_json(folder, "manifest.json", {"format": "torchcal-export/1", "files": {"compensator": "c.onnx"}})
    write_member(folder, "c.onnx", b"onnx graph bytes")
    return folder


def fit_out_is_export(fx: Fixtures, w: Path) -> Case:
    out = _export_folder(w)
    return Case(_fit(fx, fx.train, out), 2, "names an export folder", out, "unchanged")


def export_out_is_other_model(fx: Fixtures, w: Path) -> Case:
    other = _copy_model(fx, w)
    return Case(["export", "--model", str(fx.model), "--out", str(other)], 2, "names a model folder", other, "unchanged")


def simulate_out_is_model(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    return Case(["simulate", "--out", str(model), "n_train=20"], 2, "names a model folder", model, "unchanged")


def simulate_out_is_export(fx: Fixtures, w: Path) -> Case:
    out = _export_folder(w)
    return Case(["simulate", "--out", str(out), "n_train=20"], 2, "names an export folder", out, "unchanged")


def json_into_model(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    return Case(_evaluate(fx.model, fx.test, "--json", str(model / "metrics.json")), 2, "inside a model folder",
                model, "unchanged")


def json_onto_checksums(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    return Case(_evaluate(fx.model, fx.test, "--json", str(model / "checksums.json")), 2, "inside a model folder",
                model, "unchanged")


def json_onto_user_file(fx: Fixtures, w: Path) -> Case:
    mine = w / "results.json"
    mine.write_text('{"my": "notes"}\n')
    return Case(_evaluate(fx.model, fx.test, "--json", str(mine)), 2, "not a metrics file", mine, "unchanged")


def report_into_model(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    return Case(_evaluate(fx.model, fx.test, "--report", str(model / "report")), 2, "inside a model folder",
                model, "unchanged")


def report_onto_export(fx: Fixtures, w: Path) -> Case:
    out = _export_folder(w)
    return Case(_evaluate(fx.model, fx.test, "--report", str(out)), 2, "names an export folder", out, "unchanged")


def report_onto_user_folder(fx: Fixtures, w: Path) -> Case:
    out = w / "docs"
    out.mkdir()
    (out / "thesis.md").write_text("keep me\n")
    return Case(_evaluate(fx.model, fx.test, "--report", str(out)), 2, "not a torchcal output", out, "unchanged")


def refit_over_user_file(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    (model / "notes.txt").write_text("measured on a Tuesday\n")
    return Case(_fit(fx, fx.train, model), 2, "notes.txt", model, "unchanged")


def export_out_inside_model(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    return Case(["export", "--model", str(fx.model), "--out", str(model / "onnx")], 2, "inside a model folder",
                model, "unchanged")


def fit_file_too_large(fx: Fixtures, w: Path) -> Case:
    model = _copy_model(fx, w)
    case = Case(_fit(fx, fx.train, model), 2, "ulimit -f", model, "unchanged")
    case.extra["file_limit"] = 40_000  # bytes: the report's figures do not fit
    return case


def export_file_too_large(fx: Fixtures, w: Path) -> Case:
    case = Case(["export", "--model", str(fx.model), "--out", str(w / "export")], 2, "ulimit -f", w / "export")
    case.extra["file_limit"] = 40_000
    return case


def run_name_parent(fx: Fixtures, w: Path) -> Case:
    return Case(["run", f"out={w / 'runs'}", "name=../escaped", "twin.n_train=20"], 2, "one folder name", w / "escaped")


def run_name_slash(fx: Fixtures, w: Path) -> Case:
    return Case(["run", f"out={w / 'runs'}", "name=a/b", "twin.n_train=20"], 2, "one folder name", w / "runs")


def run_name_huge(fx: Fixtures, w: Path) -> Case:
    return Case(["run", f"out={w / 'runs'}", "name=" + "9" * 5000, "twin.n_train=20"], 2, "a value of 5000 characters", w / "runs")


def study_name_parent(fx: Fixtures, w: Path) -> Case:
    return Case(["study", f"out={w / 'runs'}", "study.name=../../escaped", "study.n_trials=1"], 2, "one folder name",
                w / "escaped")


def simulate_negative_mass(fx: Fixtures, w: Path) -> Case:
    return Case(["simulate", "--out", str(w / "sim"), "gravity=true", "link_masses_kg=[25,-15,10]"], 2,
                "link_masses_kg", w / "sim")


def simulate_zero_stiffness(fx: Fixtures, w: Path) -> Case:
    return Case(["simulate", "--out", str(w / "sim"), "gravity=true", "joint_stiffness_nm_per_rad=[0]"], 2,
                "joint_stiffness_nm_per_rad", w / "sim")


def seed_beyond_32_bits(fx: Fixtures, w: Path) -> Case:
    return Case(_fit(fx, fx.train, w / "out", "seed=4294967296"), 2, "seed must be an integer", w / "out")


def seed_negative(fx: Fixtures, w: Path) -> Case:
    return Case(_fit(fx, fx.train, w / "out", "seed=-3"), 2, "seed must be an integer", w / "out")


def device_meta(fx: Fixtures, w: Path) -> Case:
    return Case(_fit(fx, fx.train, w / "out", "device=meta"), 2, "not meta", w / "out")


def device_unknown(fx: Fixtures, w: Path) -> Case:
    return Case(_fit(fx, fx.train, w / "out", "device=gpu0"), 2, "not a torch device", w / "out")


def boolean_given_number(fx: Fixtures, w: Path) -> Case:
    return Case(_fit(fx, fx.train, w / "out", "head_time_check=2"), 2, "true or false", w / "out")


def evaluate_interpolation(fx: Fixtures, w: Path) -> Case:
    return Case(_evaluate(fx.model, fx.test, "joint_unit=${oc.env:HOME}"), 2, "interpolation", None)


def evaluate_fit_option(fx: Fixtures, w: Path) -> Case:
    return Case(_evaluate(fx.model, fx.test, "--json", str(w / "m.json"), "residual=mlp"), 2,
                "residual is an option of fit, not of evaluate", w / "m.json")


def simulate_interpolation(fx: Fixtures, w: Path) -> Case:
    return Case(["simulate", "--out", str(w / "sim"), "n_train=${n_test}"], 2, "interpolation", w / "sim")


def study_workers_zero(fx: Fixtures, w: Path) -> Case:
    return Case(["study", f"out={w / 'runs'}", "--workers", "0"], 2, "--workers", w / "runs")


def study_trials_zero(fx: Fixtures, w: Path) -> Case:
    return Case(["study", f"out={w / 'runs'}", "--n-trials", "0"], 2, "--n-trials", w / "runs")


def export_iterations_huge(fx: Fixtures, w: Path) -> Case:
    return Case(["export", "--model", str(fx.model), "--out", str(w / "export"), "--iterations", "100000"], 2,
                "--iterations", w / "export")


def hidden_units_huge(fx: Fixtures, w: Path) -> Case:
    return Case(_fit(fx, fx.train, w / "out", "residual_hidden=50000000"), 2, "residual_hidden", w / "out")


def simulate_huge(fx: Fixtures, w: Path) -> Case:
    return Case(["simulate", "--out", str(w / "sim"), "n_train=300000000"], 2, "n_train", w / "sim")


CASES: dict[str, Callable[[Fixtures, Path], Case]] = {f.__name__: f for f in (
    csv_latin1, csv_binary, csv_nul, csv_huge_field, csv_metres, csv_radians, csv_1e300, csv_underscore, csv_nan,
    csv_duplicate, csv_missing_column, csv_semicolon, csv_wide_header, csv_million_rows,
    yaml_latin1, yaml_binary, yaml_alias_bomb, yaml_python_tag, yaml_wrong_sign, urdf_nan_origin, urdf_zero_axis,
    urdf_nan_limit, yaml_deeply_nested, yaml_continuous_with_limits, yaml_continuous_not_boolean,
    model_json_truncated, model_json_invalid_sealed, model_json_missing_key_sealed, safetensors_bitflip,
    safetensors_bad_header_sealed, safetensors_nan_sealed, safetensors_foreign_sealed, model_stale_residual,
    model_no_checksums, robot_file_absolute, robot_file_parent, robot_file_of_another_model_sealed,
    fit_out_is_file, fit_out_foreign_folder, fit_out_holds_data, evaluate_json_is_folder, export_out_is_file,
    export_out_is_model, simulate_zero, simulate_negative, threshold_negative, threshold_nan, residual_unknown,
    unknown_option, register_three_poses, evaluate_metres, few_poses,
    fit_out_is_export, export_out_is_other_model, simulate_out_is_model, simulate_out_is_export, json_into_model,
    json_onto_checksums, json_onto_user_file, report_into_model, report_onto_export, report_onto_user_folder,
    refit_over_user_file, export_out_inside_model, fit_file_too_large, export_file_too_large, run_name_parent,
    run_name_slash, run_name_huge, study_name_parent, seed_beyond_32_bits, seed_negative, device_meta,
    device_unknown, boolean_given_number, evaluate_interpolation, evaluate_fit_option, simulate_interpolation, study_workers_zero,
    study_trials_zero, export_iterations_huge, hidden_units_huge, simulate_huge, fit_points_of_other_poses,
    evaluate_points_of_other_poses, evaluate_instrument_moved, rows_with_mistyped_angle, rows_in_metres,
    joint_never_moves, orientation_garbage, evaluate_orientation_garbage, simulate_negative_mass, simulate_zero_stiffness,
)}

#: Cases by class (the reliability rounds' classes); every other case is a bad input file.
_BY_CLASS: dict[str, tuple[str, ...]] = {
    "outputs on other outputs": (
        "fit_out_is_file", "fit_out_foreign_folder", "fit_out_holds_data", "evaluate_json_is_folder",
        "export_out_is_file", "export_out_is_model", "fit_out_is_export", "export_out_is_other_model",
        "simulate_out_is_model", "simulate_out_is_export", "json_into_model", "json_onto_checksums",
        "json_onto_user_file", "report_into_model", "report_onto_export", "report_onto_user_folder",
        "refit_over_user_file", "export_out_inside_model"),
    "write failures": ("fit_file_too_large", "export_file_too_large"),
    "names that escape": ("run_name_parent", "run_name_slash", "run_name_huge", "study_name_parent"),
    "sealed but inconsistent folders": (
        "model_json_invalid_sealed", "model_json_missing_key_sealed", "safetensors_bad_header_sealed",
        "safetensors_nan_sealed", "safetensors_foreign_sealed", "robot_file_absolute", "robot_file_parent",
        "robot_file_of_another_model_sealed"),
    "options that crash deep": (
        "seed_beyond_32_bits", "seed_negative", "device_meta", "device_unknown", "boolean_given_number",
        "evaluate_interpolation", "evaluate_fit_option", "simulate_interpolation", "study_workers_zero", "study_trials_zero",
        "threshold_negative", "threshold_nan", "residual_unknown", "unknown_option", "simulate_zero",
        "simulate_negative"),
    "bad rows and contradictory inputs": ("rows_with_mistyped_angle", "rows_in_metres", "csv_semicolon",
                                          "joint_never_moves", "orientation_garbage", "evaluate_orientation_garbage", "urdf_nan_limit", "yaml_deeply_nested", "yaml_continuous_with_limits",
                                          "yaml_continuous_not_boolean", "simulate_negative_mass",
                                          "simulate_zero_stiffness"),
    "a file of another robot or set-up": ("yaml_wrong_sign", "fit_points_of_other_poses", "evaluate_points_of_other_poses",
                                          "evaluate_instrument_moved"),
    "hangs and unbounded memory": ("export_iterations_huge", "hidden_units_huge", "simulate_huge", "csv_huge_field",
                                   "csv_wide_header", "csv_million_rows"),
}

#: The class of each case, for counts by class.
CLASSES: dict[str, str] = {name: next((c for c, names in _BY_CLASS.items() if name in names), "bad input files")
                           for name in CASES}


@contextmanager
def file_size_limit(limit: int | None) -> Iterator[None]:
    """The process's file-size limit (``ulimit -f``) lowered to ``limit`` bytes for the block (``None``: unchanged).

    Python ignores SIGXFSZ, so a write beyond the limit raises ``OSError(EFBIG)`` as on a full disk.
    """
    if limit is None:
        yield
        return
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))


def snapshot(path: Path | None) -> object:
    """What ``path`` holds (file bytes, or each file of a folder), to compare before and after a command."""
    if path is None or not path.exists():
        return None
    if path.is_file():
        return path.read_bytes()
    return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def out_state_problem(case: Case, before: object) -> str:
    """``""`` when ``case.out`` is in the state the case requires, else what is wrong."""
    if case.out is None:
        return ""
    if case.out_state == "absent":
        return "" if not case.out.exists() else f"{case.out} was written"
    if case.out_state == "unchanged":
        return "" if snapshot(case.out) == before else f"{case.out} was changed"
    try:
        verify_folder(case.out)
    except TorchcalError as exc:
        return f"{case.out} is not whole: {exc}"
    return ""
