"""``torchcal check``: does a model still hold for the robot? A handful of new poses decide.

The frame is always re-registered (the tracker stands wherever it was set up). Two pieces of
evidence, both from the model folder's own predicted uncertainty (``uncertainty.json``: each
pose's per-coordinate sigma ``s_i`` and 95 % radius):

* **per pose**: the registered error against the pose's predicted 95 % radius. How many poses lie
  beyond it is Binomial(n, 0.05) when the model holds; a tail probability below
  :data:`EXCEEDANCE_ALPHA` says it does not.
* **which group changed**: from the old model, refits freeing the instrument frame alone (the
  null) and the frame plus one group: the tool point (``tool``), one joint's zero offset
  (``theta<j>``), one link's geometry (``alpha<j>, a<j>, d<j>`` or ``beta<j>``) and, where the
  model has them, each joint-space term as a whole (``compliance``: the gravity compliance,
  named ``gravity_compliance``; ``harmonics``: the joint harmonics, named ``joint_harmonics``;
  one scale each, :mod:`torchcal.identify.term_scale`: a payload or balancer that changed the
  sag, a gearbox replaced). Residuals are
  whitened by ``s_i``, so ``chi2 = sum |r_i|^2 / s_i^2``; each group's evidence is the BIC
  difference ``dBIC = chi2_null - chi2_group - k ln(3n)`` (``k`` its parameters) and the
  likelihood-ratio p-value of ``chi2_null - chi2_group`` on ``k`` degrees of freedom. A group
  with ``dBIC >`` :data:`BIC_CHANGED` ("very strong" on Kass and Raftery's scale) is named.

Verdict: ``changed`` when either piece says so; ``changed`` lists the best group's names (or is
empty when only the per-pose test fired), ``valid`` otherwise. ``extrapolating`` instead of
``changed`` where at least :data:`EXTRAPOLATING_SHARE` of the poses lie further from every pose
the model was fitted on than a grouped cross-validation of those poses holds any out
(:func:`~torchcal.model_selection.leakage.far_from_training`): there a model misses by more than
it predicted because it extrapolates, whether or not the robot changed (``changed`` still names
the group the evidence points to, which ``update`` would free to extend the model). A learned residual head is not
tested: the check scores the geometric stage with its joint-space terms, and says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from scipy import stats

from torchcal.config.schema import UnitOptions
from torchcal.core.errors import ModelError
from torchcal.data.measurements import Measurements, load_measurements
from torchcal.identify.calibrate import register_instrument
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.problem import CalibrationProblem
from torchcal.identify.term_scale import TermScaleProblem
from torchcal.kinematics.error_model import ErrorModel
from torchcal.model_selection.leakage import far_from_training
from torchcal.report.document import Paragraph, Preformatted, Report, Section, Table
from torchcal.stages.foreign_data import refuse_foreign_file
from torchcal.stages.geometry import model_joints
from torchcal.stages.prediction_uncertainty import PosePrediction, stored_prediction
from torchcal.stages.store import StoredModel, load_model

#: Tail probability of the count of poses beyond their 95 % radius below which the model no longer holds.
EXCEEDANCE_ALPHA = 0.01
#: BIC difference above which a group counts as changed.
BIC_CHANGED = 10.0
#: Share of the poses further from every training pose than a grouped CV of those holds any out
#: (:func:`~torchcal.model_selection.leakage.far_from_training`) from which a model that misses them
#: is said to extrapolate rather than the robot to have changed.
EXTRAPOLATING_SHARE = 0.5
PROTOCOL = ("instrument frame re-registered to the new poses (rigid refit from the old model); per-pose error against "
            "the model's predicted 95 % radius; groups by BIC of refits from the old model, residuals whitened by "
            "each pose's predicted sigma")


@dataclass
class GroupEvidence:
    """One refit: the group freed besides the frame, its parameter count and its evidence."""

    group: str
    names: list[str]
    k: int
    chi2: float
    delta_bic: float
    p_value: float
    x: torch.Tensor = field(repr=False)

    def to_dict(self) -> dict:
        return {"group": self.group, "names": self.names, "k": self.k, "chi2": self.chi2,
                "delta_bic": self.delta_bic, "lr_p_value": self.p_value}


@dataclass
class CheckResult:
    """What ``check`` found (mm)."""

    verdict: str
    changed: list[str]
    n_poses: int
    errors_mm: np.ndarray
    p95_mm: np.ndarray
    lines_in_file: list[int]
    exceedances: int
    exceedance_p: float
    chi2_null: float
    groups: list[GroupEvidence]
    source: str
    n_far: int = 0
    far_radius_mm: float = float("nan")

    @property
    def best(self) -> GroupEvidence | None:
        return max(self.groups, key=lambda g: g.delta_bic) if self.groups else None

    def to_dict(self) -> dict:
        best = self.best
        return {
            "verdict": self.verdict,
            "changed": self.changed,
            "protocol": PROTOCOL,
            "data": {"file": self.source, "n_poses": self.n_poses},
            "rms_mm": float(np.sqrt(np.mean(self.errors_mm**2))),
            "beyond_95": {"count": self.exceedances, "expected": 0.05 * self.n_poses, "tail_p": self.exceedance_p,
                          "alpha": EXCEEDANCE_ALPHA},
            "groups": {"chi2_frame_only": self.chi2_null, "bic_changed_above": BIC_CHANGED,
                       "best": None if best is None else best.to_dict(),
                       "ranked": [g.to_dict() for g in sorted(self.groups, key=lambda g: -g.delta_bic)]},
            "poses": [{"row": r, "error_mm": float(e), "p95_mm": float(p), "beyond": bool(e > p)}
                      for r, e, p in zip(self.lines_in_file, self.errors_mm, self.p95_mm)],
            "not_tested": "a learned residual head (the geometric stage with its joint-space terms is scored)",
            "extrapolation": {"n_far": self.n_far,
                              "far_radius_mm": self.far_radius_mm if math.isfinite(self.far_radius_mm) else None,
                              "extrapolating_above_share": EXTRAPOLATING_SHARE},
        }

    def lines(self) -> list[str]:
        best = self.best
        out = [(f"{self.source}: {self.n_poses} poses, frame re-registered: RMS {float(np.sqrt(np.mean(self.errors_mm**2))):.3f} mm; "
               f"{self.exceedances} beyond their predicted 95 % radius (expected {0.05 * self.n_poses:.1f}, tail p "
               f"{self.exceedance_p:.2g})")]
        if best is not None:
            out.append(f"most likely change: {best.group} ({', '.join(best.names)}): dBIC {best.delta_bic:+.1f}, "
                       f"likelihood ratio p {best.p_value:.2g} (named above dBIC {BIC_CHANGED:g})")
        if self.n_far:
            out.append(f"{self.n_far} of the {self.n_poses} poses lie further than {self.far_radius_mm:.0f} mm (tool-point "
                       "motion) from every pose the model was fitted on, where it extrapolates")
        if self.verdict == "extrapolating":
            out.append(f"verdict: extrapolating: the model misses these poses, but most lie where it extrapolates, so a change "
                       f"of the robot cannot be told from the model's own extrapolation (the evidence points to "
                       f"{', '.join(self.changed) or 'no group'}); check with poses like the fitted ones, or update to "
                       "extend the model to these")
            return out
        out.append(f"verdict: {self.verdict}" + (f"; changed: {', '.join(self.changed)}" if self.changed else ""))
        return out


#: The joint-space term groups (``calibration.json`` key of the term, by group name).
TERM_GROUPS = {"compliance": "gravity_compliance", "harmonics": "joint_harmonics"}


def groups_of(model: ErrorModel, metadata: dict | None = None) -> dict[str, list[str]]:
    """The parameter groups a check tests, by name: tool, each joint offset, each link's geometry and,
    where the model folder's ``metadata`` holds them, each joint-space term as a whole (``compliance``
    named ``gravity_compliance``, ``harmonics`` named ``joint_harmonics``, as in ``calibration.json``)."""
    layout, active = model.layout, model.default_active()
    names = list(layout.names)
    groups = {"tool": ["tool_x", "tool_y", "tool_z"]}
    for j in range(1, model.robot.dof + 1):
        groups[f"theta{j}"] = [f"theta{j}"]
    for j in range(1, model.robot.dof + 1):
        link = [f"{p}{j}" for p in ("alpha", "a", "beta", "d") if active[names.index(f"{p}{j}")]]
        groups[f"link{j}"] = link
    for group, key in TERM_GROUPS.items():
        if (metadata or {}).get(key):
            groups[group] = [key]
    return groups


def term_deflections(stored: StoredModel, q: torch.Tensor) -> dict[str, torch.Tensor]:
    """Each stored joint-space term's deflection ``(n, N)`` rad at commanded joints ``q``, by its key."""
    terms = JointSpaceErrors.from_metadata(stored.metadata)
    out = {}
    if terms.compliance is not None:
        out[TERM_GROUPS["compliance"]] = terms.compliance.deflection(stored.robot, q)
    if terms.harmonics is not None:
        out[TERM_GROUPS["harmonics"]] = terms.harmonics.deflection(q)
    return out


def _effective(stored: StoredModel, data: Measurements) -> Measurements:
    """``data`` with the joints the geometric chain turns by (joint-space errors of the model applied)."""
    return replace(data, q=model_joints(stored, data.q))


def refit(stored: StoredModel, data: Measurements, names: list[str], sigma_m: torch.Tensor) -> tuple[float, torch.Tensor, ErrorModel]:
    """Refit the frame and ``names`` from the old model; returns ``(chi2, x, model)`` (whitened by ``sigma_m``)."""
    effective = _effective(stored, data)
    reference = register_instrument(stored.robot, effective, stored.model, stored.x)
    model = ErrorModel(stored.robot, with_orientation=False, parallel_threshold_deg=stored.model.parallel_threshold_deg,
                       T_instrument_base=reference)
    x0 = stored.x.detach().cpu().to(torch.float64).clone()
    x0[model.layout.base_slice] = 0.0
    layout = model.layout
    free = list(range(layout.base_slice.start, layout.base_slice.stop)) + [layout.index(n) for n in names
                                                                            if n in layout.names]
    terms = term_deflections(stored, data.q)
    scaled = [key for key in terms if key in names]
    if scaled:
        # a term as a whole refitted: one scale per term (identify.term_scale), the others as stored
        keys = list(terms)
        free += [layout.size + keys.index(key) for key in scaled]
        scaled_problem = TermScaleProblem(model, data, torch.stack([terms[k] for k in keys]), torch.tensor(free),
                                          [f"{k}_scale" for k in keys], weights=1.0 / sigma_m)
        x0 = torch.cat([x0, torch.zeros(len(keys), dtype=torch.float64)])
        solved = LevenbergMarquardt(max_iterations=100).solve(scaled_problem, x0)
        return 2.0 * float(solved.cost), solved.x, model
    whitening = torch.eye(3, dtype=torch.float64).expand(len(data), 3, 3) / sigma_m[:, None, None]
    problem = CalibrationProblem(model, effective, torch.tensor(free), whitening=whitening)
    solved = LevenbergMarquardt(max_iterations=100).solve(problem, x0)
    return 2.0 * float(solved.cost), solved.x, model


def refit_whitening(stored: StoredModel, data: Measurements) -> tuple[PosePrediction, torch.Tensor]:
    """The model's predicted uncertainty at ``data``'s poses and the per-pose sigma ``(n,)`` (m) that
    whitens :func:`refit`'s residuals; a model without a predicted uncertainty is refused."""
    prediction = stored_prediction(stored, data.q)
    if prediction is None:
        raise ModelError(f"{stored.folder}: the model has no predicted uncertainty (uncertainty.json); "
                         "check needs it: fit it again with uncertainty=conformal or gaussian")
    return prediction, prediction.sigma_mm.detach().cpu().to(torch.float64) * 1e-3


def refuse_other_robots(stored: StoredModel, data: Measurements, refused: str) -> None:
    """Refuse ``data`` the model misses by centimetres even with the instrument frame and the tool
    point re-fitted (another robot or set-up, or swapped columns): a check or an update of it would
    only name some group as changed (:func:`~torchcal.stages.foreign_data.refuse_foreign_file`). A
    new tool of any length is what ``check`` names and ``update free=tool`` fits: not refused."""
    refuse_foreign_file(frame_and_tool_errors(stored, data), stored, data, True, refused,
                        refitted="the instrument frame and the tool point")


def frame_and_tool_errors(stored: StoredModel, data: Measurements) -> torch.Tensor:
    """``measured - predicted`` ``(n, 3)`` (m) of the model with its instrument frame and tool point
    re-fitted to ``data`` (:func:`refit` of the tool point, unweighted; the MDH table and joint-space
    terms as stored)."""
    _, x, model = refit(stored, data, ["tool_x", "tool_y", "tool_z"], torch.ones(len(data), dtype=torch.float64))
    effective = _effective(stored, data)
    return effective.position - model.tcp_position(effective.q, x)


def check_data(stored: StoredModel, data: Measurements) -> CheckResult:
    """The check of ``stored`` against ``data`` (see the module docstring)."""
    refuse_other_robots(stored, data, "nothing was checked")
    prediction, sigma_m = refit_whitening(stored, data)
    n = len(data)
    if n < 4:
        raise ModelError(f"{data.source}: {n} poses; check needs at least 4 (the frame takes 6 of their 3n coordinates)")
    chi2_null, x_null, model = refit(stored, data, [], sigma_m)
    residual = data.position - model.tcp_position(_effective(stored, data).q, x_null)
    # the frame's 6 parameters absorb part of the error: scale back to what a new pose would show
    inflate = math.sqrt(3 * n / max(3 * n - 6, 1))
    errors = residual.norm(dim=-1).numpy() * 1e3 * inflate
    p95 = prediction.p95_mm.detach().cpu().numpy()
    beyond = int((errors > p95).sum())
    tail = float(stats.binom.sf(beyond - 1, n, 0.05)) if beyond > 0 else 1.0
    log_n = math.log(3 * n)
    groups = []
    for group, names in groups_of(stored.model, stored.metadata).items():
        if not names or len(names) + 6 >= 3 * n:
            continue
        chi2, x, _ = refit(stored, data, names, sigma_m)
        gain = max(chi2_null - chi2, 0.0)
        groups.append(GroupEvidence(group, names, len(names), chi2, gain - len(names) * log_n,
                                    float(stats.chi2.sf(gain, len(names))), x))
    best = max(groups, key=lambda g: g.delta_bic) if groups else None
    named = best is not None and best.delta_bic > BIC_CHANGED
    changed = best.names if named and best is not None else []
    if named and best is not None and best.group == "tool":
        changed = ["tool"]
    verdict = "changed" if named or tail < EXCEEDANCE_ALPHA else "valid"
    n_far, far_radius = 0, float("nan")  # no radius (a handful of fitted configurations): nothing is called far
    if stored.training_q is not None:
        far, far_radius = far_from_training(stored.robot, stored.training_q, data.q)
        n_far = int(far.sum())
        if verdict == "changed" and n_far >= EXTRAPOLATING_SHARE * n:
            verdict = "extrapolating"
    return CheckResult(verdict=verdict, changed=changed, n_poses=n, errors_mm=errors, p95_mm=p95,
                       lines_in_file=list(data.line_numbers) or list(range(2, n + 2)), exceedances=beyond,
                       exceedance_p=tail, chi2_null=chi2_null, groups=groups, source=data.source, n_far=n_far,
                       far_radius_mm=far_radius)


def check_model(model_dir: str | Path, data_file: str | Path, units: UnitOptions | None = None) -> CheckResult:
    """Load the model folder and the position file (in ``units``: deg and mm by default) and check one against the other."""
    units = units or UnitOptions()
    stored = load_model(model_dir)
    data = load_measurements(data_file, stored.robot, joint_unit=units.joint_unit, length_unit=units.length_unit)
    return check_data(stored, data)


def check_report(result: CheckResult, model_dir: str | Path) -> Report:
    """The report of a check: verdict, evidence per group, per-pose errors against their 95 % radius."""
    doc = result.to_dict()
    groups = Table("groups", ["group", "parameters", "k", "chi2", "dBIC", "likelihood ratio p"],
                   [[g["group"], ", ".join(g["names"]), str(g["k"]), f"{g['chi2']:.1f}", f"{g['delta_bic']:+.1f}",
                     f"{g['lr_p_value']:.2g}"] for g in doc["groups"]["ranked"]],
                   caption=f"refits from the old model freeing the frame and one group; frame only: chi2 "
                           f"{result.chi2_null:.1f}; a group is named above dBIC {BIC_CHANGED:g}")
    poses = Table("poses", ["row", "error, mm", "predicted 95 % radius, mm", "beyond"],
                  [[str(p["row"]), f"{p['error_mm']:.3f}", f"{p['p95_mm']:.3f}", "yes" if p["beyond"] else ""]
                   for p in doc["poses"]])
    return Report(f"Check of {Path(model_dir).name} on {Path(result.source).name}", [
        Section("Verdict", [Paragraph(f"{result.verdict}" + (f": changed {', '.join(result.changed)}" if result.changed else "")),
                            Preformatted("\n".join(result.lines())), Paragraph(f"Protocol: {PROTOCOL}."),
                            Paragraph(f"Not tested: {doc['not_tested']}.")]),
        Section("Which group changed", [groups]),
        Section("Per pose", [poses]),
    ])
