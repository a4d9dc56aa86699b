"""Joint stiffness: virtual joint method, identification, loading plan, deformed kinematics, compensation.

Frames: spring deformations live in each MDH joint frame; deflections, Jacobians and wrenches
handed to :func:`deflection` are in the ``instrument`` frame (the ``base`` frame when no
instrument is registered), wrenches from a file in the ``tool`` frame.
"""

from torchcal.stiffness.compensate import (
    DeflectionCompensation,
    DeflectionCompensator,
    compensate_deflection,
)
from torchcal.stiffness.deformed import (
    deformed_joint_poses,
    deformed_tcp_pose,
    loaded_tcp_pose,
    rederive_parameters,
)
from torchcal.stiffness.identify import (
    StiffnessEstimate,
    deflection_metrics,
    identify_stiffness,
    instrument_model,
)
from torchcal.stiffness.plan import LoadingPlan, plan_loading, rig_wrenches
from torchcal.stiffness.vjm import (
    SPRING_COMPONENTS,
    cartesian_compliance,
    classic_compliance,
    compliance_from_stiffness,
    deflection,
    joint_deformations,
    spring_names,
    virtual_joint_jacobian,
)

__all__ = [
    "SPRING_COMPONENTS",
    "DeflectionCompensation",
    "DeflectionCompensator",
    "LoadingPlan",
    "StiffnessEstimate",
    "cartesian_compliance",
    "classic_compliance",
    "compensate_deflection",
    "compliance_from_stiffness",
    "deflection",
    "deflection_metrics",
    "deformed_joint_poses",
    "deformed_tcp_pose",
    "identify_stiffness",
    "instrument_model",
    "joint_deformations",
    "loaded_tcp_pose",
    "plan_loading",
    "rederive_parameters",
    "rig_wrenches",
    "spring_names",
    "virtual_joint_jacobian",
]
