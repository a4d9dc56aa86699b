"""A laser-tracker twin case on disk: the shared :class:`~torchcal.sim.twin.Twin` measured as x, y, z points.

Files: ``robot.yaml`` (nominal), ``train.csv`` and ``test.csv`` (``q1..qN, x, y, z``: deg, mm, in
the twin's tracker frame ``instrument``) and ``truth.json`` (true robot, errors, noise).
"""

from __future__ import annotations

from pathlib import Path

import torch

from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.data.measurements import write_measurements_csv
from torchcal.kinematics.robot import robot_to_yaml
from torchcal.sim.twin import Twin, TwinConfig


def write_twin_case(out: str | Path, config: TwinConfig) -> dict[str, Path]:
    """Write ``robot.yaml``, ``train.csv``, ``test.csv`` and ``truth.json`` of a twin case."""
    out = Path(out)
    twin = Twin.create(config)
    gen = torch.Generator().manual_seed(config.seed + 7919)
    train = twin.sample(config.n_train, gen)
    test = twin.sample(config.n_test, gen)
    paths = {name: out / name for name in ("robot.yaml", "train.csv", "test.csv", "truth.json")}
    atomic_write_text(paths["robot.yaml"], robot_to_yaml(twin.robot))
    write_measurements_csv(paths["train.csv"], train.q, train.position)
    write_measurements_csv(paths["test.csv"], test.q, test.position)
    atomic_write_json(paths["truth.json"], twin.truth_dict())
    return paths
