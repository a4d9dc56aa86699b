import math

import pytest
import torch

from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import default_robot_path, load_robot

DEG = math.pi / 180.0


@pytest.fixture(scope="session")
def model() -> ErrorModel:
    return ErrorModel(load_robot(default_robot_path()))


@pytest.fixture(scope="session")
def x_nom(model) -> torch.Tensor:
    return model.nominal_vector()
