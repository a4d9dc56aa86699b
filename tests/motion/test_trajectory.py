import numpy as np
import pytest
import torch

from torchcal.core.errors import DataError
from torchcal.motion.trajectory import JointTrajectory, load_csv


def _traj():
    g = torch.Generator().manual_seed(0)
    t = torch.arange(50, dtype=torch.float64) / 250.0
    return JointTrajectory(t=t, q=torch.randn(50, 6, generator=g, dtype=torch.float64), qdot=torch.randn(50, 6, generator=g, dtype=torch.float64), rate_hz=250.0)


@pytest.mark.parametrize("unit", ["deg", "rad"])
def test_csv_round_trip(tmp_path, unit):
    traj = _traj()
    path = traj.save_csv(tmp_path / "joints.csv", angle_unit=unit)
    back = load_csv(path, angle_unit=unit)
    torch.testing.assert_close(back.q, traj.q, rtol=1e-15, atol=1e-15)
    torch.testing.assert_close(back.qdot, traj.qdot, rtol=1e-15, atol=1e-15)
    torch.testing.assert_close(back.t, traj.t, rtol=0, atol=0)
    assert back.rate_hz == pytest.approx(250.0)
    assert path.read_text().splitlines()[0] == "t,q1,q2,q3,q4,q5,q6,qd1,qd2,qd3,qd4,qd5,qd6"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp file left


def test_npz_and_numpy(tmp_path):
    traj = _traj()
    data = np.load(traj.save_npz(tmp_path / "joints.npz"))
    np.testing.assert_array_equal(data["q"], traj.q.numpy())
    assert float(data["rate_hz"]) == 250.0
    assert traj.to_numpy()["qdot"].shape == (50, 6)


def test_bad_csv(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,q1,qd1\n0,1,2\n0.004,x,3\n")
    with pytest.raises(DataError, match="row 3, column 'q1'"):
        load_csv(bad)
    bad.write_text("t,q1,qd1\n0,1,2\n0,1,3\n")
    with pytest.raises(DataError, match="increase"):
        load_csv(bad)
    with pytest.raises(DataError):
        load_csv(tmp_path / "missing.csv")
