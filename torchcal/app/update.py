"""``torchcal update``: a new model folder from an earlier one and a few new poses.

The robot's life after its calibration changes a part of it (a tool swapped, a joint re-mastered,
a link bent, the robot moved). ``update`` keeps what still holds and re-identifies the rest from a
handful of new poses (12-20 measured with the tracker wherever it now stands):

* **the instrument frame** is always re-registered (no prior: the tracker stands elsewhere);
* **what else is freed**: by default the group that :func:`torchcal.app.check.check_data` names
  (the same refits and the same BIC threshold, so ``check`` and ``update`` never disagree), kept
  only when the update's leave-one-out RMS with it is lower than with the frame alone (an update is
  never worse than the old model by the new poses' evidence); none when the check names none (the
  robot moved, or nothing changed). The other groups the check named are then added one at a time
  while the leave-one-out gain is above two standard errors (:func:`_add_named_groups`: one event
  can change two groups, a tool swapped and a joint re-mastered). ``free=`` overrides:
  ``frame`` (nothing else), ``tool``, ``offsets`` (every joint's zero offset), ``all`` (every
  parameter of the MDH table and the tool), or a comma list of check groups and parameter names
  (``free=tool,theta3``, ``free=link3``, ``free=a2,d4``);
* **the freed parameters** get the manufacturing-tolerance prior (:mod:`torchcal.identify.prior`)
  centred on the old model's values: the old model's posterior covariance says the opposite of
  the truth about a part that changed (it was pinned to the old value by hundreds of poses);
* **everything not freed stays fixed at the old model**, joint-space terms (gravity compliance,
  harmonics) included, and keeps the old covariance. A prior from that covariance would be the
  same in practice: the old fit saw 20 to 200 times more poses than the update, so its
  posterior sigmas are far below what the new poses could resolve; fixing keeps the fit as small
  as the new poses can carry (frame + freed group).

**Joint-space terms not freed are re-judged** on the new poses (:func:`_judge_terms`): dropped
when the leave-one-out errors are lower without the term by more than one standard error (a term
fitted on the old poses may not carry over: another probe mounting, another payload region).

**Prediction uncertainty** (``uncertainty.json``) is recalibrated on the new poses: each pose's
error predicted by a fit of the others (leave-one-out, frame and freed group refitted each time,
near twins left out together; with 12-20 poses every pose is its own region) gives the model discrepancy ``sigma_d`` as in
:mod:`torchcal.stages.prediction_uncertainty`. The *shape* of the 95 % region (the conformal
quantile of the normalised scores) is kept from the old model, calibrated on hundreds of
out-of-fold errors: 12-20 scores cannot place a 95th percentile (the split-conformal quantile of
12 is their largest), but they do estimate a scale (the variance from ``3n`` coordinates, about
+-20 % in sigma at ``n = 12``). A model without one takes both from the new poses and says so.

**A learned residual head** of the old model is kept only if it still helps on the new poses: the
update is made with and without the head's correction and the head is kept when the
leave-one-out RMS with it is lower; otherwise it is dropped with a line saying so. **Joint
stiffness** (a property of the joints, not measured by position poses) is kept as it was.

Provenance (``calibration.json`` ``update`` and the report): the parent folder and the SHA-256 of
its ``checksums.json`` (which pins every file of it), what was freed and why, the poses, the
check's evidence, the head decision and the uncertainty protocol.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from torchcal.app.check import (
    BIC_CHANGED,
    TERM_GROUPS,
    CheckResult,
    check_data,
    check_report,
    groups_of,
    refit,
    refit_whitening,
    refuse_other_robots,
    term_deflections,
)
from torchcal.config.schema import UnitOptions
from torchcal.core.errors import DataError, IdentifiabilityWarning, ModelError
from torchcal.core.folder import CHECKSUMS, write_member
from torchcal.core.hashing import sha256_file
from torchcal.core.metrics import repeated_groups
from torchcal.data.measurements import Measurements, load_measurements
from torchcal.identify.calibrate import CalibrationResult, calibrate
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.identify.prior import EarlierModel, PriorSpec, resolve_tolerances
from torchcal.report.document import Paragraph, Preformatted, Report, Section, Table, write_report
from torchcal.stages.base import ResidualStage
from torchcal.stages.geometry import model_joints
from torchcal.stages.prediction_uncertainty import (
    ErrorCalibration,
    calibrate_errors,
    load_uncertainty,
    point_jacobian,
    write_uncertainty,
)
from torchcal.stages.prior_options import prior_metadata
from torchcal.stages.residual_store import save_residual
from torchcal.stages.store import StoredModel, load_model, save_model

#: The keywords of ``free=`` besides group and parameter names.
FREE_KEYWORDS = ("auto", "frame", "tool", "offsets", "all")
#: Fewest new poses an update accepts (the frame takes 6 of their 3n coordinates, the LOO one more pose).
MIN_POSES = 6
#: Paired z (leave-one-out gain over its standard error) a second freed group must show: the rule by which
#: model selection admits a larger candidate (``torchcal.model_selection.compare``, ``z_min``); dropping a
#: term (a smaller model) needs one standard error.
ADD_GROUP_Z = 2.0
#: Poses whose joints all lie within this (deg) of each other are near twins: left out together in the leave-one-out.
NEAR_TWIN_DEG = 1.0
UNCERTAINTY_PROTOCOL = ("leave-one-out over the new poses (frame and freed parameters refitted without each pose and its "
                        "near twins): "
                        "discrepancy sigma from their errors; shape of the 95 % region (conformal quantile) {shape}")


@dataclass
class UpdateResult:
    """What an update found and fitted (SI inside; mm and deg in lines and metadata)."""

    stored: StoredModel
    data: Measurements
    freed: list[str]
    how: str
    check: CheckResult | None
    fit: CalibrationResult
    free: torch.Tensor
    covariance: torch.Tensor
    loo_errors_mm: np.ndarray
    uncertainty: ErrorCalibration
    head_kept: bool | None
    head_line: str | None
    parent_sha256: str
    notes: list[str] = field(default_factory=list)
    scales: dict[str, float] = field(default_factory=dict)
    used: StoredModel | None = None
    dropped_terms: list[str] = field(default_factory=list)

    @property
    def terms_of(self) -> StoredModel:
        """The parent with its joint-space terms as the update uses them (rescaled where freed)."""
        return self.used if self.used is not None else self.stored

    @property
    def fit_rms_mm(self) -> float:
        q = model_joints(self.terms_of, self.data.q)
        errors = self.data.position - self.fit.model.tcp_position(q, self.fit.x) - self._head_offset()
        return float(errors.norm(dim=-1).pow(2).mean().sqrt()) * 1e3

    @property
    def loo_rms_mm(self) -> float:
        return _loo_rms(self.loo_errors_mm)

    def _head_offset(self) -> torch.Tensor:
        if not self.head_kept or self.stored.residual is None:
            return torch.zeros_like(self.data.position)
        return _head_offset(self.stored, self.fit, self.data)

    def changes(self) -> list[dict]:
        """Per freed parameter: old and new value, change and new 1-sigma (mm or deg)."""
        layout = self.fit.model.layout
        scale = layout.unit_scale()
        angle = layout.is_angle()
        sigma = self.fit.covariance.diagonal().clamp_min(0).sqrt()
        position = {int(i): k for k, i in enumerate(self.fit.free.tolist())}
        rows = []
        for name in self.freed:
            if name in self.scales:
                s = self.scales[name]
                rows.append({"name": f"{name} scale", "unit": "", "old": 1.0, "new": 1.0 + s, "change": s, "sigma": math.nan})
                continue
            i = layout.index(name)
            old, new = float(self.stored.x[i] * scale[i]), float(self.fit.x[i] * scale[i])
            rows.append({"name": name, "unit": "deg" if bool(angle[i]) else "mm", "old": old, "new": new,
                         "change": new - old, "sigma": float(sigma[position[i]] * scale[i]) if i in position else 0.0})
        return rows

    def provenance(self) -> dict:
        """``calibration.json`` ``update``."""
        return {
            "parent": {"folder": str(self.stored.folder), "checksums_sha256": self.parent_sha256,
                       "data": (self.stored.metadata.get("data") or {})},
            "data": {"file": self.data.source, "sha256": self.data.sha256, "n_poses": len(self.data)},
            "frame": "re-registered (no prior)",
            "freed": self.freed,
            "freed_by": self.how,
            "prior_of_freed": "manufacturing tolerances centred on the parent's values",
            "kept": ("every other parameter, the joint-space terms not dropped included, fixed at the parent's values "
                     "with its covariance"),
            "joint_space_terms_dropped": self.dropped_terms,
            "joint_space_term_scales": {k: 1.0 + v for k, v in self.scales.items()},
            "changes": self.changes(),
            "fit_rms_mm": self.fit_rms_mm,
            "leave_one_out_rms_mm": self.loo_rms_mm,
            "evidence": None if self.check is None else self.check.to_dict(),
            "uncertainty": self.uncertainty.protocol,
            "residual_head": self.head_line,
            "notes": self.notes,
        }

    def lines(self) -> list[str]:
        out = [(f"parent model {self.stored.folder} (checksums SHA-256 {self.parent_sha256[:12]}...); "
                f"{len(self.data)} new poses from {self.data.source}; frame re-registered")]
        if self.check is not None:
            out += self.check.lines()
        out.append(f"freed: {', '.join(self.freed) if self.freed else 'nothing besides the frame'} ({self.how})")
        for c in self.changes():
            out.append(f"  {c['name']}: {c['old']:+.4f} -> {c['new']:+.4f} {c['unit']} (change {c['change']:+.4f}, "
                       f"1-sigma {c['sigma']:.4f})")
        out.append(f"updated model on its {len(self.data)} poses: RMS {self.fit_rms_mm:.3f} mm; leave-one-out "
                   f"(each pose predicted by a fit of the others) {self.loo_rms_mm:.3f} mm")
        out.append(f"prediction uncertainty recalibrated: discrepancy sigma {self.uncertainty.discrepancy_sigma_mm:.3f} mm "
                   f"per coordinate ({self.uncertainty.protocol})")
        if self.head_line:
            out.append(self.head_line)
        out += self.notes
        return out


def parent_sha256(folder: Path) -> str:
    """SHA-256 of a model folder's ``checksums.json`` (it lists every file's SHA-256: the folder's identity)."""
    return sha256_file(Path(folder) / CHECKSUMS)


def resolve_free(spec: str, stored: StoredModel, check: CheckResult | None) -> tuple[list[str], str]:
    """The parameter names ``free=spec`` frees besides the frame, and how they were chosen (one phrase)."""
    model = stored.model
    layout, active = model.layout, model.default_active()
    names = list(layout.names)
    tool = ["tool_x", "tool_y", "tool_z"]
    table = [n for i, n in enumerate(names) if layout.table_slice.start <= i < layout.table_slice.stop and bool(active[i])]
    text = str(spec).strip()
    if text == "auto":
        if check is None:
            raise ModelError("free=auto needs the check's evidence")
        best = check.best
        if check.changed and best is not None:
            if check.verdict == "extrapolating":  # an extension of the model to these poses, not a claim of a change
                return list(best.names), (f"chosen by the check's evidence on poses where the old model extrapolates "
                                          f"({check.n_far} of {check.n_poses}): group {best.group}, dBIC "
                                          f"{best.delta_bic:+.1f} > {BIC_CHANGED:g}; the model is extended to them, no "
                                          "change of the robot is claimed")
            return list(best.names), (f"chosen by the check's evidence: group {best.group}, dBIC {best.delta_bic:+.1f} "
                                      f"> {BIC_CHANGED:g}")
        return [], "chosen by the check's evidence: no group named (the robot moved or nothing changed)"
    if text == "frame":
        return [], "free=frame"
    if text == "tool":
        return tool, "free=tool"
    if text == "offsets":
        return [n for n in table if n.startswith("theta")], "free=offsets"
    if text == "all":
        return table + tool, "free=all"
    groups = groups_of(model, stored.metadata)
    chosen: list[str] = []
    for item in (t.strip() for t in text.split(",")):
        if item in groups:
            members = groups[item]
        elif (item in names and not item.startswith("base_")) or item in groups.get("compliance", []) + groups.get("harmonics", []):
            members = [item]
        else:
            raise DataError(f"free={spec}: unknown '{item}'; give auto, frame, tool, offsets, all, a group "
                            f"({', '.join(g for g, m in groups.items() if m)}) or parameter names")
        chosen += [m for m in members if m not in chosen]
    return chosen, f"free={text}"


#: An update measures positions only: its model's compensator orients the tool by the geometry, also where the
#: parent's joint-space terms were fitted with measured orientations (``stages.orientation.orientation_source_of``).
ORIENTATION_SOURCE_NOTE = ("the parent measured the tool's orientation and this update positions only: the updated model's "
                           "compensator orients the tool by its geometry, not by the joint-space terms (docs/prior.md); "
                           "measure orientations again (rx, ry, rz) and refit to orient by them")


def _fit(stored: StoredModel, data: Measurements, names: list[str]) -> CalibrationResult:
    """MAP fit of the frame and ``names`` from the old model, every other parameter fixed at its old value.

    ``data``'s joints are the commanded ones: the old model's joint-space terms are applied here.
    """
    effective = replace(data, q=model_joints(stored, data.q))
    layout = stored.model.layout
    fixed = tuple(n for n in layout.names if not n.startswith("base_") and n not in names)
    empty = torch.zeros(0, dtype=torch.long)
    earlier = EarlierModel(x=stored.x.detach().cpu().to(torch.float64), indices=empty,
                           covariance=torch.zeros(0, 0, dtype=torch.float64), label=str(stored.folder))
    spec = PriorSpec(tolerances=resolve_tolerances(stored.robot.source), scale=1.0, earlier=earlier)
    with warnings.catch_warnings():
        # the rank diagnostic of a group fit is a note of the result; every freed name has its prior
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        return calibrate(stored.robot, effective, use_orientation=False, fixed=fixed, prior=spec,
                         parallel_threshold_deg=stored.model.parallel_threshold_deg)


def _rescaled(stored: StoredModel, scales: dict[str, float]) -> StoredModel:
    """``stored`` with each joint-space term in ``scales`` (by its ``calibration.json`` key) multiplied by ``1 + s``."""
    terms = JointSpaceErrors.from_metadata(stored.metadata)
    compliance, harmonics = terms.compliance, terms.harmonics
    if compliance is not None and TERM_GROUPS["compliance"] in scales:
        compliance = replace(compliance, coefficients=compliance.coefficients * (1.0 + scales[TERM_GROUPS["compliance"]]))
    if harmonics is not None and TERM_GROUPS["harmonics"] in scales:
        factor = 1.0 + scales[TERM_GROUPS["harmonics"]]
        harmonics = replace(harmonics, coefficients=harmonics.coefficients * factor,
                            sigma=None if harmonics.sigma is None else harmonics.sigma * abs(factor))
    return replace(stored, metadata={**stored.metadata, **JointSpaceErrors(compliance, harmonics).to_metadata()})


def _fit_all(stored: StoredModel, data: Measurements, names: list[str]) -> tuple[StoredModel, CalibrationResult, dict]:
    """The update's fit: freed joint-space terms first (each as a whole, one scale, with the frame and the
    freed geometry, by least squares: :func:`torchcal.app.check.refit`), then the MAP fit of the frame and
    the freed geometry on the joints of the rescaled terms. Returns ``(terms model, fit, scales)``."""
    keys = [n for n in names if n in TERM_GROUPS.values()]
    geometry = [n for n in names if n not in keys]
    if not keys:
        return stored, _fit(stored, data, geometry), {}
    _, x, model = refit(stored, data, names, torch.ones(len(data), dtype=torch.float64))
    present = list(term_deflections(stored, data.q))
    scales = {k: float(x[model.layout.size + present.index(k)]) for k in keys}
    used = _rescaled(stored, scales)
    return used, _fit(used, data, geometry), scales


def near_twin_groups(q: torch.Tensor, within_deg: float = NEAR_TWIN_DEG) -> list[list[int]]:
    """Poses linked (transitively) by every joint within ``within_deg`` of each other: left out together
    (:func:`torchcal.core.metrics.repeated_groups`, each other pose a group of its own)."""
    twins = [group.tolist() for group in repeated_groups(q, within_deg)]
    linked = {i for group in twins for i in group}
    return twins + [[i] for i in range(len(q)) if i not in linked]


def _loo_errors(stored: StoredModel, data: Measurements, names: list[str]) -> np.ndarray:
    """``(n, 3)`` mm: each pose's error predicted by the update fitted to the other poses (near twins,
    :func:`near_twin_groups`, left out with it: a twin in the fit would predict its sibling)."""
    n = len(data)
    out = np.zeros((n, 3))
    for group in near_twin_groups(data.q):
        rest = [k for k in range(n) if k not in group]
        used, fit, _ = _fit_all(stored, data.subset(rest), names)
        q = model_joints(used, data.q[group])
        out[group] = ((data.position[group] - fit.model.tcp_position(q, fit.x)) * 1e3).numpy()
    return out


def _loo_rms(errors: np.ndarray) -> float:
    """RMS of ``(n, 3)`` errors (mm) over the poses."""
    return float(np.sqrt(np.mean(np.sum(errors**2, axis=-1))))


def _without(stored: StoredModel, keys: list[str]) -> StoredModel:
    """``stored`` without the joint-space terms ``keys`` (``calibration.json`` keys)."""
    return replace(stored, metadata={k: v for k, v in stored.metadata.items() if k not in keys})


def _clearly_better(base: np.ndarray, other: np.ndarray, z: float = 1.0) -> tuple[bool, float, float]:
    """Whether ``other``'s leave-one-out errors beat ``base``'s by more than ``z`` standard errors of the
    per-pose difference of squared errors (``z = 1``, the one-standard-error rule, for a simpler model:
    with 12-20 poses a smaller RMS alone is often noise; :data:`ADD_GROUP_Z` for a larger one).
    Returns ``(better, mean gain, its standard error)`` in mm^2."""
    gain = np.sum(base**2, axis=-1) - np.sum(other**2, axis=-1)
    se = float(np.std(gain, ddof=1) / math.sqrt(len(gain))) if len(gain) > 1 else math.inf
    return float(gain.mean()) > z * se, float(gain.mean()), se


def _judge_terms(stored: StoredModel, data: Measurements, names: list[str],
                 loo: np.ndarray) -> tuple[StoredModel, np.ndarray, list[str], list[str]]:
    """Each joint-space term not freed, re-judged on the new poses: dropped when the update's
    leave-one-out errors are clearly lower without it (:func:`_clearly_better`; greedy: the largest
    gain first, then the others again without it).

    A term fitted on the old poses may not carry over (another probe mounting, another payload
    region: docs/validation.md, UR10 A -> D); dropping it fits nothing more, so the two
    leave-one-out errors compare like for like; the term was chosen on hundreds of poses, so it
    goes only when the new poses show more than noise. Returns ``(base model, its LOO errors,
    dropped keys, lines)``.
    """
    candidates = [k for k in TERM_GROUPS.values() if stored.metadata.get(k) and k not in names]
    dropped: list[str] = []
    lines: list[str] = []
    base = stored
    while candidates:
        trials = {k: _loo_errors(_without(base, [k]), data, names) for k in candidates}
        key = min(trials, key=lambda k: _loo_rms(trials[k]))
        better, gain, se = _clearly_better(loo, trials[key])
        already = f" ({', '.join(dropped)} dropped)" if dropped else ""
        lines.append(f"{key} {'dropped' if better else 'kept'}{already}: leave-one-out RMS {_loo_rms(trials[key]):.3f} mm "
                     f"without it, {_loo_rms(loo):.3f} mm with it (gain {gain:+.4f} mm^2 per pose, one standard "
                     f"error {se:.4f}: dropped above one)")
        if not better:
            break
        base, loo = _without(base, [key]), trials[key]
        dropped.append(key)
        candidates.remove(key)
    return base, loo, dropped, lines


def _add_named_groups(stored: StoredModel, data: Measurements, check: CheckResult, names: list[str],
                      loo: np.ndarray) -> tuple[list[str], np.ndarray, list[str], list[str]]:
    """The other groups the check named (each above :data:`BIC_CHANGED` on its own), added one at a time
    while the update's leave-one-out errors are lower with it by more than :data:`ADD_GROUP_Z`
    standard errors (:func:`_clearly_better`; greedy: the lowest leave-one-out RMS first, then the
    others again with it).

    One event (a crash, a changed probe mounting) can change more than one group; the check ranks
    each group alone, so a second group whose evidence was partly the first one's is tried only
    when its dBIC given the groups freed already is still above :data:`BIC_CHANGED` (one refit
    each), and added only when the new poses, each predicted by a fit of the others, show more
    than noise. Returns
    ``(names, their LOO errors, the groups added, lines)``.
    """
    added: list[str] = []
    present = set(stored.model.layout.names) | {k for k in TERM_GROUPS.values() if stored.metadata.get(k)}
    # a joint-space term the update dropped is not brought back
    candidates = [g for g in check.groups if g.delta_bic > BIC_CHANGED and not set(g.names) <= set(names)
                  and set(g.names) <= present]
    lines: list[str] = []
    _, sigma_m = refit_whitening(stored, data)  # the check ran on this model, so it has an uncertainty
    while candidates and len(names) + 6 < 3 * (len(data) - 1):
        extended = {g.group: names + [n for n in g.names if n not in names] for g in candidates}
        # the check's own test, given what is freed already: one refit per group before any leave-one-out
        # (n refits each); a group whose evidence the freed ones explain is not tried further
        chi2_now = refit(stored, data, names, sigma_m)[0]
        conditional = {g.group: chi2_now - refit(stored, data, extended[g.group], sigma_m)[0]
                       - (len(extended[g.group]) - len(names)) * math.log(3 * len(data)) for g in candidates}
        lines.extend(f"group {g.group} (dBIC {g.delta_bic:+.1f}) not added: dBIC {conditional[g.group]:+.1f} "
                     f"given {', '.join(names)} (tried above {BIC_CHANGED:g})"
                     for g in candidates if conditional[g.group] <= BIC_CHANGED)
        candidates = [g for g in candidates if conditional[g.group] > BIC_CHANGED]
        if not candidates:
            break
        trials = {g.group: _loo_errors(stored, data, extended[g.group]) for g in candidates}
        group = min(candidates, key=lambda g: _loo_rms(trials[g.group]))
        better, gain, se = _clearly_better(loo, trials[group.group], ADD_GROUP_Z)
        lines.append(f"group {group.group} (dBIC {group.delta_bic:+.1f}) {'added' if better else 'not added'}: leave-one-out "
                     f"RMS {_loo_rms(trials[group.group]):.3f} mm with it, {_loo_rms(loo):.3f} mm without (gain "
                     f"{gain:+.4f} mm^2 per pose, one standard error {se:.4f}: added above {ADD_GROUP_Z:g} of them)")
        if not better:
            break
        names, loo = extended[group.group], trials[group.group]
        added.append(group.group)
        candidates.remove(group)
    return names, loo, added, lines


def _head_offset(stored: StoredModel, fit: CalibrationResult, data: Measurements) -> torch.Tensor:
    """The old head's correction at ``data``'s poses in the instrument frame of ``fit`` (m)."""
    assert stored.residual is not None
    stage = ResidualStage(stored.residual, fit.model.T_reference[:3, :3])
    offset = stage.tcp_offset(data.q, temperature=data.temperature)
    return torch.zeros_like(data.position) if offset is None else offset.to(data.position)


def _union(stored: StoredModel, fit: CalibrationResult, joints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The new folder's estimated indices and joint covariance (the fit's and the parent's, linked).

    The fit estimated ``f`` (frame and freed group) with the kept parameters ``k`` fixed at the
    parent's values; their error ``dk`` (covariance ``S_k``, the parent's) is partly absorbed by
    ``f``: to first order ``df = e_f - A dk`` with ``A`` the least-squares map of the kept
    parameters' effect at the new poses (``joints``) onto ``f``'s and ``e_f`` the fit's own error
    (covariance ``S_f``). So ``Cov(f) = S_f + A S_k A^T``, ``Cov(f, k) = -A S_k``: a point's
    predicted error ``J_f e_f + (J_k - J_f A) dk`` keeps only what the refit cannot absorb (row 1
    of an arm, which the frame takes over entirely, adds nothing).
    """
    new = fit.free.tolist()
    fitted = set(new)
    old = stored.free.tolist()
    kept = [k for k, i in enumerate(old) if i not in fitted]
    free = new + [old[k] for k in kept]
    jac = point_jacobian(fit.model, fit.x, torch.tensor(free, dtype=torch.long), joints).reshape(-1, len(free))
    nf = len(new)
    s_f = fit.covariance.detach().cpu().to(torch.float64)
    take = torch.tensor(kept, dtype=torch.long)
    s_k = stored.covariance.detach().cpu().to(torch.float64)[take][:, take]
    a = torch.linalg.lstsq(jac[:, :nf], jac[:, nf:], driver="gelsd").solution if kept else torch.zeros(nf, 0, dtype=torch.float64)
    cov = torch.zeros(len(free), len(free), dtype=torch.float64)
    cov[:nf, :nf] = s_f + a @ s_k @ a.T
    cov[:nf, nf:] = -a @ s_k
    cov[nf:, :nf] = cov[:nf, nf:].T
    cov[nf:, nf:] = s_k
    order = torch.argsort(torch.tensor(free))
    return torch.tensor(free, dtype=torch.long)[order], cov[order][:, order]


def _uncertainty(stored: StoredModel, data: Measurements, fit: CalibrationResult, free: torch.Tensor,
                 cov: torch.Tensor, loo_mm: np.ndarray) -> ErrorCalibration:
    """Recalibrated prediction uncertainty (module docstring)."""
    old = load_uncertainty(stored.folder)
    joints = model_joints(stored, data.q)
    jac = point_jacobian(fit.model, fit.x, free, joints)
    norms = np.linalg.norm(loo_mm, axis=-1)
    method = old.method if old is not None else "conformal"
    if old is None:
        return calibrate_errors(jac, cov, norms, UNCERTAINTY_PROTOCOL.format(
            shape=f"from these {len(norms)} poses too (the parent has no uncertainty.json): coarse"), method)
    fresh = calibrate_errors(jac, cov, norms, "", method)
    shape_n = old.shape_n_poses  # an updated parent kept it from its own; None: an earlier version did not say
    origin = (f"calibrated on {shape_n} out-of-fold errors" if shape_n is not None else
              "calibrated on an earlier fit's out-of-fold errors, how many the parent's file does not record")
    return ErrorCalibration(method, fresh.discrepancy_sigma_mm, old.conformal_q, old.score_quantiles, fresh.cv_rms_mm,
                            len(norms), UNCERTAINTY_PROTOCOL.format(shape=f"kept from the parent ({origin})"),
                            shape_n_poses=shape_n)


def update_data(stored: StoredModel, data: Measurements, free: str = "auto") -> UpdateResult:
    """The update of ``stored`` from ``data`` (see the module docstring); nothing is written."""
    n = len(data)
    if n < MIN_POSES:
        raise DataError(f"{n} poses; update needs at least {MIN_POSES} (12-20 advisable)", path=data.source)
    spec = str(free).strip()
    if not spec:
        raise DataError("free= is empty; give auto, frame, tool, offsets, all or names")
    refuse_other_robots(stored, data, "no model was written")
    check = check_data(stored, data) if spec == "auto" or load_has_uncertainty(stored) else None
    names, how = resolve_free(spec, stored, check)
    if 3 * (n - 1) <= 6:
        raise DataError(f"{n} poses are too few for the frame", path=data.source)
    notes: list[str] = []
    work = data
    head_kept: bool | None = None
    head_line = None
    loo = _loo_errors(stored, work, names)
    base, loo, dropped, term_lines = _judge_terms(stored, work, names, loo)
    notes += term_lines
    if spec == "auto" and names:
        # the named group must beat the old model (frame only) on the new poses, else it is not freed
        frame_only = _loo_errors(base, work, [])
        if _loo_rms(frame_only) <= _loo_rms(loo):
            how += (f"; not freed: leave-one-out RMS {_loo_rms(loo):.3f} mm with it, {_loo_rms(frame_only):.3f} mm "
                    "with the frame alone")
            names, loo = [], frame_only
        else:
            how += f"; leave-one-out RMS {_loo_rms(loo):.3f} mm, {_loo_rms(frame_only):.3f} mm with the frame alone"
            assert check is not None
            names, loo, added, lines = _add_named_groups(base, work, check, names, loo)
            notes += lines
            if added:
                how += f"; then {', '.join(added)} added (the check named it; leave-one-out RMS {_loo_rms(loo):.3f} mm)"
    used, fit, scales = _fit_all(base, work, names)
    if stored.residual is not None:
        corrected = replace(data, position=data.position - _head_offset(stored, fit, data))
        used_h, fit_h, scales_h = _fit_all(base, corrected, names)
        loo_h = _loo_errors(base, corrected, names)
        without, with_head = _loo_rms(loo), _loo_rms(loo_h)
        head_kept = with_head < without
        if head_kept:
            used, fit, scales, loo = used_h, fit_h, scales_h, loo_h
            head_line = (f"residual head ({stored.residual.head.name}) kept: leave-one-out RMS "
                         f"{with_head:.3f} mm with it, {without:.3f} mm without")
        else:
            head_line = (f"residual head ({stored.residual.head.name}) dropped: leave-one-out RMS "
                         f"{with_head:.3f} mm with it, {without:.3f} mm without (it no longer helps on this robot)")
    if stored.stiffness is not None:
        notes.append("joint stiffness kept from the parent (position poses do not measure it)")
    union_free, cov = _union(stored, fit, model_joints(used, data.q))
    uncertainty = _uncertainty(used, data, fit, union_free, cov, loo)
    for key, scale in scales.items():
        notes.append(f"{key} refitted as a whole: scaled by {1.0 + scale:.3f} (with the frame and the freed geometry)")
    if stored.model.with_orientation and not JointSpaceErrors.from_metadata(used.metadata).empty:
        notes.append(ORIENTATION_SOURCE_NOTE)
    return UpdateResult(stored=stored, data=data, freed=names, how=how, check=check, fit=fit, free=union_free,
                        covariance=cov, loo_errors_mm=loo, uncertainty=uncertainty, head_kept=head_kept,
                        head_line=head_line, parent_sha256=parent_sha256(stored.folder), notes=notes, scales=scales,
                        used=used, dropped_terms=dropped)


def load_has_uncertainty(stored: StoredModel) -> bool:
    """Whether the folder has a prediction uncertainty (the check's evidence needs one)."""
    return load_uncertainty(stored.folder) is not None


def write_update(folder: Path, result: UpdateResult) -> Path:
    """Write the updated model folder into ``folder`` (a staging folder: the caller swaps it in)."""
    stored, fit, data = result.stored, result.fit, result.data
    meta = {
        "method": "update",
        "data": {"file": data.source, "sha256": data.sha256, "n_poses": len(data)},
        "identifiability": fit.identifiability.to_metadata(),
        "residual_sigma_mm": fit.sigma_residual_m * 1e3,
        "solver": {"iterations": fit.solve.iterations, "message": fit.solve.message, "cost_history": fit.solve.history},
        "notes": [*fit.notes, *result.notes] + ([result.head_line] if result.head_line else []),
        "prior": prior_metadata(fit),
        "update": result.provenance(),
        **JointSpaceErrors.from_metadata(result.terms_of.metadata).to_metadata(),
    }
    training = data.q if stored.training_q is None else torch.cat([stored.training_q.to(data.q), data.q])
    save_model(folder, stored.robot, fit.model, fit.x, result.free, result.covariance, meta, training_q=training)
    write_uncertainty(folder, result.uncertainty)
    if result.head_kept and stored.residual is not None:
        save_residual(folder, stored.residual)
    for name in ("stiffness.safetensors", "stiffness.json"):
        if stored.stiffness is not None and (stored.folder / name).is_file():
            write_member(folder, name, (stored.folder / name).read_bytes())
    write_report(folder, update_report(result), member=True)
    return folder


def update_report(result: UpdateResult) -> Report:
    """The report of an update: provenance, what changed, the evidence, the recalibrated uncertainty."""
    changes = Table("changes", ["parameter", "parent", "updated", "change", "1-sigma", "unit"],
                    [[c["name"], f"{c['old']:+.4f}", f"{c['new']:+.4f}", f"{c['change']:+.4f}", f"{c['sigma']:.4f}", c["unit"]]
                     for c in result.changes()], caption="freed parameters (all others kept at the parent's values)")
    sections = [
        Section("Update", [Paragraph(f"Parent model: {result.stored.folder} (SHA-256 of its checksums.json "
                                     f"{result.parent_sha256}). New poses: {result.data.source} ({len(result.data)})."),
                           Preformatted("\n".join(result.lines()))]),
        Section("What changed", [changes, Paragraph(
            "Frame re-registered without a prior. Freed parameters: manufacturing-tolerance prior centred on the "
            "parent's values. Everything else, joint-space terms included, fixed at the parent's values with its covariance"
            + (f"; dropped (they no longer hold on the new poses; the lines above say by how much): {', '.join(result.dropped_terms)}."
               if result.dropped_terms else "."))]),
        Section("Prediction uncertainty", [Paragraph(
            f"{result.uncertainty.protocol}: leave-one-out RMS {result.loo_rms_mm:.3f} mm, discrepancy sigma "
            f"{result.uncertainty.discrepancy_sigma_mm:.3f} mm per coordinate. With {len(result.data)} poses the scale is "
            f"known to about +-{100 / math.sqrt(2 * 3 * len(result.data)):.0f} % (1 sigma).")]),
    ]
    if result.check is not None:
        sections += check_report(result.check, result.stored.folder).sections[1:2]
    return Report(f"Update of {Path(result.stored.folder).name} from {Path(result.data.source).name}", sections)


def update_model(model_dir: str | Path, data_file: str | Path, out: str | Path, free: str = "auto",
                 units: UnitOptions | None = None) -> UpdateResult:
    """Load, update and write ``out`` whole (staged: an interrupted update leaves what was there).

    ``units``: of the new poses' file (deg and mm by default)."""
    from torchcal.core.folder import check_output_folder, staged_folder

    out = Path(out)
    if out.resolve() == Path(model_dir).resolve():
        raise DataError(f"{out}: --out names the parent model; an update writes a new folder")
    check_output_folder(out, "--out", purpose="model")
    units = units or UnitOptions()
    stored = load_model(model_dir)
    data = load_measurements(data_file, stored.robot, joint_unit=units.joint_unit, length_unit=units.length_unit)
    result = update_data(stored, data, free)
    with staged_folder(out, "--out", purpose="model") as staging:
        write_update(staging, result)
    return result
