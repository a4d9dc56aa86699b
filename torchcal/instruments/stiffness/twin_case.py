"""``torchcal simulate instrument=stiffness``: a loading-rig twin case written as contract files.

Writes ``robot.yaml`` (the nominal robot), ``stiffness_train.csv``, ``stiffness_test.csv`` and
``stiffness_truth.json`` (see :mod:`torchcal.instruments.stiffness.twin` for the physics).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import torch

from torchcal.core.errors import TorchcalError
from torchcal.core.io import atomic_write_text
from torchcal.instruments.stiffness.twin import StiffnessTwinConfig, write_stiffness_case
from torchcal.kinematics.robot import default_robot_path, load_robot, robot_to_yaml
from torchcal.stiffness.vjm import classic_compliance


@dataclass
class StiffnessCaseConfig(StiffnessTwinConfig):
    """``key=value`` settings of a stiffness twin case (contract units: mm, deg, N, N m).

    Attributes:
        robot: robot YAML or URDF (default: the embedded twin-kr6).
        n_train / n_test: loaded poses in ``stiffness_train.csv`` / ``stiffness_test.csv``.
        joint_stiffness_nm_per_rad: true stiffness about each joint axis, N m/rad (default:
            sampled per ``seed``, 1e5..5e5 for axes 1-3 and 1e4..5e4 for the wrist).
        plan: ``optimal`` (default: the training poses and rig-limit wrenches of an A-optimal
            loading plan designed at the middle of those ranges) or ``random`` (random poses and
            wrenches: the files of earlier versions, unchanged).
        plan_candidates: random candidate poses the plan chooses from (default ``2 n_train``).
        off_axis: off-axis compliance of every joint as a fraction of its on-axis compliance
            (default 0: the joints yield only about their axes; see
            :func:`~torchcal.instruments.stiffness.twin.with_off_axis`).
        The rig's settings are inherited from :class:`~torchcal.instruments.stiffness.twin.StiffnessTwinConfig`.
    """

    robot: str | None = None
    n_train: int = 120
    n_test: int = 200
    joint_stiffness_nm_per_rad: list[float] | None = None
    plan: str = "optimal"
    plan_candidates: int | None = None

    def twin_config(self) -> StiffnessTwinConfig:
        """The rig settings alone, as the twin configuration."""
        names = {f.name for f in fields(StiffnessTwinConfig)}
        return StiffnessTwinConfig(**{k: getattr(self, k) for k in names})


def write_stiffness_twin_case(out: str | Path, config: StiffnessCaseConfig) -> dict[str, Path]:
    """Write ``robot.yaml`` and the stiffness case files of ``config`` to ``out``."""
    if config.n_train < 1 or config.n_test < 1:
        raise TorchcalError(f"n_train and n_test must be positive, got {config.n_train} and {config.n_test}")
    if config.plan not in ("optimal", "random"):
        raise TorchcalError(f"plan must be 'optimal' or 'random', got {config.plan!r}")
    if config.off_axis < 0:
        raise TorchcalError(f"off_axis must be >= 0 (a fraction of the on-axis compliance), got {config.off_axis}")
    if config.plan_candidates is not None and config.plan_candidates < config.n_train:
        raise TorchcalError(f"plan_candidates ({config.plan_candidates}) must be at least n_train ({config.n_train})")
    out = Path(out)
    robot = load_robot(config.robot or default_robot_path())
    compliance = None
    if config.joint_stiffness_nm_per_rad is not None:
        k = torch.tensor(list(config.joint_stiffness_nm_per_rad), dtype=torch.float64)
        if k.shape != (robot.dof,) or not bool((k > 0).all()):
            raise TorchcalError(
                f"joint_stiffness_nm_per_rad needs {robot.dof} positive values (N m/rad), got {list(config.joint_stiffness_nm_per_rad)}"
            )
        compliance = classic_compliance(k)
    robot_path = out / "robot.yaml"
    atomic_write_text(robot_path, robot_to_yaml(robot))
    paths = write_stiffness_case(
        out,
        config.twin_config(),
        n_train=config.n_train,
        n_test=config.n_test,
        robot=robot,
        compliance=compliance,
        plan=config.plan,
        plan_candidates=config.plan_candidates,
    )
    return {"robot.yaml": robot_path, **paths}
