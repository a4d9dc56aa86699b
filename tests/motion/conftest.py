import math

import numpy as np
import pytest
import torch
import yaml

from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import default_robot_path, load_robot

DEG = math.pi / 180.0


@pytest.fixture(scope="session")
def model() -> ErrorModel:
    return ErrorModel(load_robot(default_robot_path()))


@pytest.fixture(scope="session")
def x_nom(model) -> torch.Tensor:
    return model.nominal_vector()


@pytest.fixture(scope="session")
def mdh_fk():
    """An independent forward kinematics of the twin robot: Craig's modified DH product
    ``Rx(alpha) Tx(a) Rz(theta + q) Tz(d)`` in NumPy, read straight from the YAML file, times the
    tool translation. ``q (..., 6)`` rad -> ``T_base_tool (..., 4, 4)``, m."""
    doc = yaml.safe_load(default_robot_path().read_text())["kinematics"]
    rows = [(math.radians(j["alpha"]), j["a"] * 1e-3, math.radians(j["theta"]), j["d"] * 1e-3) for j in doc["joints"]]
    tool = np.eye(4)
    tool[:3, 3] = np.array(doc["tool"]) * 1e-3

    def fk(q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=np.float64)
        out = np.broadcast_to(np.eye(4), (*q.shape[:-1], 4, 4)).copy()
        for i, (alpha, a, theta, d) in enumerate(rows):
            ca, sa = math.cos(alpha), math.sin(alpha)
            ct, st = np.cos(theta + q[..., i]), np.sin(theta + q[..., i])
            link = np.zeros((*q.shape[:-1], 4, 4))
            link[..., 0, 0], link[..., 0, 1], link[..., 0, 3] = ct, -st, a
            link[..., 1, 0], link[..., 1, 1], link[..., 1, 2], link[..., 1, 3] = st * ca, ct * ca, -sa, -sa * d
            link[..., 2, 0], link[..., 2, 1], link[..., 2, 2], link[..., 2, 3] = st * sa, ct * sa, ca, ca * d
            link[..., 3, 3] = 1.0
            out = out @ link
        return out @ tool

    return fk
