"""Bad inputs through the command line: one line and exit status 2 (or a warning), never a traceback.

Each case of :mod:`torchcal.testing.fuzz_cases` runs through ``torchcal.cli.main`` in this process, so an
exception that escapes ``main`` (a traceback for a user) fails the test. Checked: the exit
status, that stderr holds exactly one ``torchcal: error:`` line with the expected text (or the
expected warning), and the state of the output path (absent, unchanged or a whole model folder).
Ctrl-C runs as a process: exit 130 and the earlier model folder left as it was.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest

from torchcal.cli import main
from torchcal.testing.fuzz_cases import (
    CASES,
    Fixtures,
    file_size_limit,
    make_fixtures,
    out_state_problem,
    snapshot,
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory) -> Fixtures:
    return make_fixtures(tmp_path_factory.mktemp("fuzz"), main)


@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input_gets_one_line(name, fixtures, tmp_path, capfd):
    case = CASES[name](fixtures, tmp_path)
    before = snapshot(case.out)
    capfd.readouterr()
    with warnings.catch_warnings(record=True) as caught, file_size_limit(case.extra.get("file_limit")):
        warnings.simplefilter("always")  # pytest takes warnings before the CLI prints them
        rc = main(case.argv)
    err = capfd.readouterr().err + "".join(f"torchcal: warning: {w.message}\n" for w in caught)
    assert "Traceback" not in err
    assert rc == case.rc, err
    if case.rc == 2:
        errors = [line for line in err.splitlines() if line.startswith("torchcal: error:")]
        assert len(errors) == 1, err
        assert case.message in errors[0], errors[0]
    else:
        warned = [line for line in err.splitlines() if line.startswith("torchcal: warning:")]
        assert any(case.message in line for line in warned), err
    assert out_state_problem(case, before) == ""


def test_whole_folder_records_warning(fixtures, tmp_path, capfd):
    """A fit accepted with a warning says so in the model folder too (calibration.json)."""
    import json

    case = CASES["joint_never_moves"](fixtures, tmp_path)
    assert main(case.argv) == 0
    meta = json.loads((case.out / "calibration.json").read_text())
    assert any("spans only 0.000 deg" in line for line in meta["joints_not_moved"])


def _cli_process(argv: list[str]) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    return subprocess.Popen([sys.executable, "-m", "torchcal.cli", *argv], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env,
                            # SIGINT as a terminal delivers it, even where the tests run with it ignored
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


@pytest.mark.parametrize("sig, status, word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")])
def test_ctrl_c_or_sigterm_leaves_the_earlier_model(fixtures, tmp_path, sig, status, word):
    import shutil

    out = tmp_path / "model"
    shutil.copytree(fixtures.model, out)
    before = snapshot(out)
    proc = _cli_process(["fit", "--robot", str(fixtures.robot), "--data", str(fixtures.train), "--out", str(out)])
    deadline = time.monotonic() + 120
    while not any(p.name.startswith(".model.staging-") for p in tmp_path.iterdir()):  # the fit has begun writing
        assert proc.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == status, err
    assert "Traceback" not in err and word in err
    assert snapshot(out) == before
    assert not any(p.name.startswith(".model.staging-") for p in tmp_path.iterdir())


def _children(pid: int) -> set[int]:
    """Processes whose parent is ``pid`` (Linux /proc)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended while read
            continue
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from /proc")
def test_ctrl_c_during_a_fit_in_two_processes_stops_its_workers(fixtures, tmp_path):
    """Ctrl-C while the heads are fitted side by side: one line, status 130, and no worker left running."""
    proc = _cli_process(["fit", "--robot", str(fixtures.robot), "--data", str(fixtures.train), "--out",
                         str(tmp_path / "model"), "jobs=2"])
    deadline = time.monotonic() + 120
    # the geometry and structure are saved in the staging folder: the heads' cross-validation follows at once
    while not list(tmp_path.glob(".model.staging-*/calibration.json")):
        assert proc.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    time.sleep(0.5)
    workers = _children(proc.pid)
    assert workers, "the fit runs in one process"
    proc.send_signal(signal.SIGINT)
    # a worker left behind keeps the command's output pipes open until it gives up waiting (a minute)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "interrupted" in err
    deadline = time.monotonic() + 10
    while any(Path(f"/proc/{pid}").exists() and "Z" not in Path(f"/proc/{pid}/stat").read_text().split()[2:3]
              for pid in workers):
        assert time.monotonic() < deadline, f"worker processes {workers} still run after the command ended"
        time.sleep(0.1)


def test_kill_9_leaves_a_whole_folder(fixtures, tmp_path):
    """kill -9 while a refit is writing: the earlier folder or the new one, whole (scripts/kill_sweep.py sweeps)."""
    import shutil

    from torchcal.core.folder import verify_folder
    from torchcal.stages.store import load_model

    out = tmp_path / "model"
    shutil.copytree(fixtures.model, out)
    before = snapshot(out)
    proc = _cli_process(["fit", "--robot", str(fixtures.robot), "--data", str(fixtures.test), "--out", str(out),
                         "residual=none", "gravity_compliance=none", "joint_harmonics=none"])
    deadline = time.monotonic() + 120
    while not any(p.name.startswith(".model.staging-") for p in tmp_path.iterdir()):
        assert proc.poll() is None and time.monotonic() < deadline
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate()
    verify_folder(out)
    load_model(out)
    assert snapshot(out) == before or (out / "checksums.json").read_bytes() != before["checksums.json"]


def test_profile_fit_into_a_model_folder_keeps_the_model(fixtures, tmp_path):
    """A sensor fitted into a calibrated model folder is added to the model, which stays whole."""
    import shutil

    from torchcal.core.folder import verify_folder
    from torchcal.stages.store import load_model

    case, out = tmp_path / "profile", tmp_path / "model"
    shutil.copytree(fixtures.model, out)
    assert main(["simulate", "instrument=profile", "--out", str(case), "seed=7"]) == 0
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "profile.csv"), "--out", str(out)]) == 0
    assert (out / "sensor.json").is_file()
    verify_folder(out)
    assert load_model(out).x.equal(load_model(fixtures.model).x)


def test_every_classed_case_exists():
    """The counts by class (scripts/fuzz_count.py) name only cases that exist."""
    from torchcal.testing.fuzz_cases import _BY_CLASS, CLASSES

    assert all(name in CASES for names in _BY_CLASS.values() for name in names)
    assert set(CLASSES) == set(CASES)
