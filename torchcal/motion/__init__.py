"""Singularity-robust Cartesian motion: DLS inverse, closed-loop IK, paths, profiles, metrics."""

from torchcal.motion.clik import CLIKResult, follow
from torchcal.motion.config import KR6_SPEED_LIMITS_DEG_S, MotionConfig
from torchcal.motion.dls import (
    DLSInverse,
    adaptive_damping,
    damped_inverse,
    dls_inverse,
    pseudo_inverse,
)
from torchcal.motion.metrics import MotionMetrics, path_errors, summarize, velocity_steps
from torchcal.motion.path import ArcPath, CartesianLimits, CartesianTrajectory, LinePath, slerp
from torchcal.motion.profiles import SpeedProfile, make_profile, quintic, scurve, trapezoid
from torchcal.motion.trajectory import JointTrajectory, load_csv

__all__ = [
    "KR6_SPEED_LIMITS_DEG_S",
    "ArcPath",
    "CLIKResult",
    "CartesianLimits",
    "CartesianTrajectory",
    "DLSInverse",
    "JointTrajectory",
    "LinePath",
    "MotionConfig",
    "MotionMetrics",
    "SpeedProfile",
    "adaptive_damping",
    "damped_inverse",
    "dls_inverse",
    "follow",
    "load_csv",
    "make_profile",
    "path_errors",
    "pseudo_inverse",
    "quintic",
    "scurve",
    "slerp",
    "summarize",
    "trapezoid",
    "velocity_steps",
]
