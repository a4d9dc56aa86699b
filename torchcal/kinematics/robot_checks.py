"""Checks of a robot file that catch a typo or a wrong unit at load time, before a fit blames the data.

* :class:`StrictSafeLoader`: a ``yaml.SafeLoader`` that refuses a key given twice in one mapping
  (YAML keeps the last silently) and reads ``455e0`` / ``-1e9`` as numbers (YAML 1.1 reads an
  exponent without a dot, or without a sign after ``e``, as a string).
* :func:`check_keys`: unknown keys of a mapping, with the closest allowed one.
* :func:`joint_span_problem`, :func:`span_cause`: a joint limit beyond :data:`MAX_JOINT_BOUND_RAD`.
* :func:`check_reach`: a nominal reach outside :data:`MIN_REACH_M` .. :data:`MAX_REACH_M`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import torch
import yaml

from torchcal.core.errors import ModelError, did_you_mean

if TYPE_CHECKING:
    from torchcal.kinematics.robot import RobotModel

#: Largest revolute joint limit accepted (rad, about 1146 deg). Industrial wrists turn far: ABB axis 6
#: +-400 deg, FANUC J6 +-450 deg, UR joints +-360 deg (often written 6.28318530718, a hair over 2 pi),
#: some +-720 deg; a joint without limits is written ``continuous``. Beyond this it is a unit mix-up
#: (degrees in a URDF, whose limits are radians: +-170 reads as 170 rad) or not a joint range.
MAX_JOINT_BOUND_RAD = 20.0
#: Nominal reach (largest TCP distance from the base over the joint range, m) accepted: a desktop
#: arm reaches ~0.2 m, the largest industrial arms ~4 m and gantry-like chains ~10 m. A factor of
#: 1000 outside (mm read as m, or m as mm) lands far outside this window.
MIN_REACH_M = 0.05
MAX_REACH_M = 20.0
#: Joint samples over which the reach is taken (plus the zero pose); fixed seed, so loads repeat.
_REACH_SAMPLES = 256

# YAML 1.2 exponent floats that YAML 1.1 (PyYAML) leaves as strings: no dot (455e0, -1e9, 1E3) or
# no exponent sign (4.55e2). Plain scalars only: a quoted '455e0' stays a string.
_EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")


class DuplicateKeyError(yaml.YAMLError):
    """A key given twice in one YAML mapping; the message names the key and both lines."""


class StrictSafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses duplicate keys and reads exponent notation as numbers."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: dict[object, int] = {}  # key -> line of its first occurrence
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue  # '<<: *base' then 'key: x' overrides on purpose
                key = self.construct_object(key_node, deep=deep)
                line = key_node.start_mark.line + 1
                try:
                    first = seen.get(key)
                except TypeError:
                    continue  # unhashable: the SafeLoader's own error names it
                if first is None:
                    seen[key] = line
                else:
                    again = "" if first == line else f" (first on line {first})"
                    raise DuplicateKeyError(
                        f"line {line}: key {key!r} is given twice in one mapping{again}; YAML would keep only "
                        "the last value, so give each key once")
        return super().construct_mapping(node, deep=deep)


StrictSafeLoader.add_implicit_resolver("tag:yaml.org,2002:float", _EXPONENT_FLOAT, list("-+0123456789."))


def check_keys(mapping: Mapping, allowed: Iterable[str], path: Path, where: str) -> None:
    """Refuse keys of ``mapping`` not in ``allowed``: ``where`` names the mapping (``kinematics``,
    ``joint 3``); the message gives the closest allowed key (a misspelt key reads as absent)."""
    allowed = tuple(allowed)
    for key in mapping:
        if key in allowed:
            continue
        raise ModelError(f"{path}: {where} has unknown key {str(key)!r}{did_you_mean(key, allowed)}; "
                         f"allowed: {', '.join(allowed)}")


def joint_span_problem(lo: float, hi: float) -> bool:
    """Whether joint limits ``lo, hi`` (rad) are not a joint range: a bound beyond :data:`MAX_JOINT_BOUND_RAD`."""
    return max(abs(lo), abs(hi)) > MAX_JOINT_BOUND_RAD


def span_cause(lo: float, hi: float, angle_unit: str | None) -> str:
    """Why joint limits ``lo, hi`` (in ``angle_unit``; ``None`` for a URDF, radians) are refused."""
    turns = f"beyond +-{MAX_JOINT_BOUND_RAD:g} rad ({math.degrees(MAX_JOINT_BOUND_RAD):.0f} deg)"
    # read as degrees they would be a joint range (and not a tiny one): the likely mix-up
    as_degrees = not joint_span_problem(math.radians(lo), math.radians(hi)) and max(abs(lo), abs(hi)) >= 30.0
    if angle_unit is None:
        return f"{turns}: they look like degrees where URDF expects radians" if as_degrees else \
            f"{turns}: not a joint range (URDF limits are radians)"
    if angle_unit == "rad" and as_degrees:
        return f"{turns}: they look like degrees: set kinematics.angle_unit: deg"
    return f"{turns}: not a joint range; give the joint's travel, or 'continuous: true' for a joint without limits"


def nominal_reach(robot: RobotModel) -> float:
    """Largest nominal TCP distance from ``base`` (m) over the zero pose and sampled joints."""
    q = robot.sample_joints(_REACH_SAMPLES, torch.Generator().manual_seed(0))
    q = torch.cat([torch.zeros(1, robot.dof, dtype=q.dtype), q])
    return float(robot.tcp_position(q).norm(dim=-1).max())


def check_reach(robot: RobotModel, path: Path, length_unit: str | None, units: Mapping[str, float]) -> None:
    """Refuse a robot whose nominal reach is outside :data:`MIN_REACH_M` .. :data:`MAX_REACH_M`.

    Args:
        robot: the model as loaded (SI).
        path: its file, for the message.
        length_unit: the YAML's ``kinematics.length_unit``; ``None`` for a URDF (metres by definition).
        units: the YAML length units (metres per unit), to name the unit the values look like.
    """
    reach = nominal_reach(robot)
    if MIN_REACH_M <= reach <= MAX_REACH_M or not math.isfinite(reach):
        return
    side = "beyond" if reach > MAX_REACH_M else "below"
    head = (f"{path}: the nominal TCP reaches {reach:.3g} m from the base, {side} what an arm reaches "
            f"({MIN_REACH_M:g} to {MAX_REACH_M:g} m)")
    if length_unit is None:
        cause = ("the lengths look like millimetres where URDF expects metres (origin xyz)" if reach > MAX_REACH_M
                 else "URDF origin xyz are metres: the lengths look far too small for an arm")
        raise ModelError(f"{head}: {cause}")
    # the unit that brings the reach nearest ~1 m (log scale) is the one the values are in
    declared = units[length_unit]
    fits = {u: reach / declared * s for u, s in units.items() if MIN_REACH_M <= reach / declared * s <= MAX_REACH_M}
    if fits:
        guess = min(fits, key=lambda u: abs(math.log10(fits[u])))
        cause = (f"kinematics.length_unit is {length_unit!r} but the values (a, d, tool) look like {guess}: "
                 f"set length_unit: {guess}")
    else:
        cause = f"check the a, d and tool values (read as {length_unit}, kinematics.length_unit)"
    raise ModelError(f"{head}: {cause}")
