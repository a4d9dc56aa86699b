"""Shared fixtures: the embedded twin robot and small simulated data sets."""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import pytest
import torch

from torchcal.kinematics.robot import default_robot_path, load_robot

# Under pytest-xdist each worker gets its share of the cores: torch's default pool (every core) in
# every worker, and in the command-line processes the tests start, oversubscribes them.
if os.environ.get("PYTEST_XDIST_WORKER"):
    _share = max(1, (os.cpu_count() or 1) // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    os.environ.setdefault("OMP_NUM_THREADS", str(_share))
    torch.set_num_threads(_share)

# The suite's own workers (pytest-xdist) already use the cores: a fit's side-by-side worker processes
# (torchcal.core.workers) would only compete with them. Tests of those processes ask for them by name.
os.environ.setdefault("TORCHCAL_JOBS", "1")

# ../shared/data/real next to the checkout; TORCHCAL_REAL_DATA points elsewhere (e.g. from a worktree)
REAL_DATA = Path(os.environ.get("TORCHCAL_REAL_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))


@pytest.fixture(scope="session")
def robot():
    return load_robot(default_robot_path())


@pytest.fixture
def generator():
    return torch.Generator().manual_seed(1234)


@pytest.fixture(autouse=True)
def _quiet_identifiability():
    from torchcal.core.errors import IdentifiabilityWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        yield


def pytest_collection_modifyitems(config, items):
    if REAL_DATA.is_dir():
        return
    skip = pytest.mark.skip(reason=f"real-robot data folder {REAL_DATA} is absent")
    for item in items:
        if "real" in item.keywords:
            item.add_marker(skip)


def perturbed_vector(model, generator, length_mm=0.5, angle_deg=0.05):
    """A true parameter vector: nominal plus random errors on every active parameter."""
    x = model.nominal_vector()
    sigma = torch.where(model.layout.is_angle(), math.radians(angle_deg), length_mm * 1e-3)
    return x + torch.randn(x.shape, generator=generator, dtype=torch.float64) * sigma * model.default_active()
