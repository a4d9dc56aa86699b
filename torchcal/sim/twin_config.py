"""Settings of a twin case: plain values, importable without the numerical stack (a command reads
them before it starts its workers)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from torchcal.core.errors import TorchcalError
from torchcal.core.overrides import check_range

#: Largest ``margin_deg`` (exclusive): a margin kept from both limits of a joint eats twice its value
#: of the range, and industrial joints span 90 deg and more.
MAX_MARGIN_DEG = 45.0


@dataclass
class TwinConfig:
    """Settings of a twin case (report units: mm, deg).

    Attributes:
        robot: robot file (default: the embedded twin-kr6).
        seed: random seed of errors, poses and noise.
        n_train / n_test: poses written to train.csv / test.csv.
        length_error_mm / angle_error_deg: 1-sigma of MDH length and angle errors.
        tool_error_mm: 1-sigma of the tool offset error per axis.
        instrument_distance_mm: distance of the tracker from the robot base.
        tracker_sigma_mm / repeatability_mm: per-axis Gaussian noise.
        gravity: add gravity-induced joint compliance.
        gear: add periodic gear errors.
        gear_amplitude_deg: amplitude of the first gear harmonic.
        gear_orders: gear harmonics per joint (1 .. this order).
        compliance_cubic: relative change of the gravity deflection at a joint's largest torque
            (0: linear compliance).
        joint_stiffness_nm_per_rad: per-joint stiffness for the gravity compliance (a robot with
            more joints than values repeats the last value).
        link_masses_kg: point masses at the middle of links 2 and 3 and at the wrist.
        margin_deg: distance kept from joint limits when sampling poses, in ``[0, 45)`` deg
            (:data:`MAX_MARGIN_DEG`) and below half the narrowest limited joint range of the robot
            (:meth:`check_margin`): a larger margin leaves a joint no range to sample.
    """

    robot: str | None = None
    seed: int = 0
    n_train: int = 120
    n_test: int = 400
    length_error_mm: float = 0.3
    angle_error_deg: float = 0.03
    tool_error_mm: float = 0.5
    instrument_distance_mm: float = 2500.0
    tracker_sigma_mm: float = 0.012
    repeatability_mm: float = 0.008
    gravity: bool = False
    gear: bool = False
    gear_amplitude_deg: float = 0.01
    gear_orders: int = 2
    compliance_cubic: float = 0.0
    joint_stiffness_nm_per_rad: list[float] = field(default_factory=lambda: [4e5, 3e5, 2e5, 5e4, 4e4, 3e4])
    link_masses_kg: list[float] = field(default_factory=lambda: [25.0, 15.0, 10.0])
    margin_deg: float = 5.0

    def __post_init__(self) -> None:
        """Refuse counts below one and non-finite or negative sizes before anything is written."""
        for name in ("n_train", "n_test"):
            check_range(self, name, low=1, high=1_000_000)  # 10^6 poses: about 0.5 GB of float64 joints and Jacobians
        for name in ("length_error_mm", "angle_error_deg", "tool_error_mm", "tracker_sigma_mm", "repeatability_mm",
                     "gear_amplitude_deg"):
            _check_finite(self, name)
            check_range(self, name, low=0.0)
        _check_finite(self, "margin_deg")
        check_range(self, "margin_deg", low=0.0)
        if self.margin_deg >= MAX_MARGIN_DEG:
            raise TorchcalError(f"margin_deg must be in [0, {MAX_MARGIN_DEG:g}) deg, got {self.margin_deg!r}: it is kept "
                                "from both limits of every joint when sampling poses, so a larger one leaves no "
                                "range to sample")
        _check_finite(self, "instrument_distance_mm")
        check_range(self, "instrument_distance_mm", low=0.0, low_open=True)
        check_range(self, "gear_orders", low=1, high=20)
        check_range(self, "compliance_cubic", low=-0.9, high=10.0)
        # physics that cannot be: a negative mass, a zero or negative stiffness (a division by it writes NaN)
        if not self.link_masses_kg or any(not math.isfinite(m) or m < 0 for m in self.link_masses_kg):
            raise TorchcalError(f"link_masses_kg needs finite masses >= 0 (kg), got {list(self.link_masses_kg)}")
        if not self.joint_stiffness_nm_per_rad or any(not math.isfinite(k) or k <= 0
                                                      for k in self.joint_stiffness_nm_per_rad):
            raise TorchcalError(f"joint_stiffness_nm_per_rad needs finite values > 0 (N m/rad), got "
                                f"{list(self.joint_stiffness_nm_per_rad)}")

    def check_margin(self, joint_ranges_deg: list[float]) -> None:
        """Refuse a ``margin_deg`` not below half the narrowest of ``joint_ranges_deg`` (the spans,
        upper minus lower limit, of the robot's limited joints: a continuous joint keeps no margin)."""
        if joint_ranges_deg and 2.0 * self.margin_deg >= min(joint_ranges_deg):
            narrowest = min(joint_ranges_deg)
            raise TorchcalError(f"margin_deg must be below half the narrowest joint range of the robot "
                                f"({narrowest / 2:g} deg of {narrowest:g}), got {self.margin_deg!r}: it is kept from "
                                "both limits when sampling poses, so that joint would have no range to sample")

    @property
    def noise_floor_rms_mm(self) -> float:
        return math.sqrt(3.0 * (self.tracker_sigma_mm**2 + self.repeatability_mm**2))


def _check_finite(config: TwinConfig, name: str) -> None:
    """A size that is not a finite number: refused in plain words (the range check would print an
    ``inf`` bound beside an ``inf`` value)."""
    value = getattr(config, name)
    if isinstance(value, float) and not math.isfinite(value):
        raise TorchcalError(f"{name} must be a finite number, got {value!r}")
