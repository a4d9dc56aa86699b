"""The tracker's calibration report of a model folder on position measurements: what an engineer signs.

One builder, :func:`calibration_report`, serves ``torchcal fit`` (the training file, with the
cross-validated out-of-fold errors of the chosen structure), ``torchcal evaluate --report`` (a
held-out file) and ``torchcal run`` (the twin's training and held-out files, with its truth).
Every number is printed next to the protocol that produced it. Inputs are :class:`PoseSet`\\ s:
one measurement file scored by each model stage (:func:`score_pose_set`), the nominal robot with
its instrument frame and tool fitted first.

Units: mm and deg throughout; rows are the file's rows as its errors name them (the header is
row 1, blank lines count). The frames and parameter sections are the shared
:func:`~torchcal.report.parameters.parameter_sections`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchcal.core.metrics import iso9283_repeated, position_metrics
from torchcal.core.workers import import_in_workers
from torchcal.data.measurements import Measurements
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.model_selection.leakage import LeakageReport
from torchcal.report import plots
from torchcal.report.document import (
    Paragraph,
    PendingFigure,
    Preformatted,
    Report,
    Section,
    Table,
    draw_figures,
)
from torchcal.report.parameters import parameter_sections
from torchcal.stages.base import ModelStage
from torchcal.stages.geometry import (
    NOMINAL_PROTOCOL,
    held_out_errors,
    nominal_fit,
    predict_positions,
)
from torchcal.stages.orientation import (
    OrientationErrors,
    model_orientation_errors,
    nominal_orientation_errors,
)
from torchcal.stages.store import CALIBRATED_URDF, StoredModel, not_in_geometry

if TYPE_CHECKING:
    from torchcal.instruments.tracker.evaluate import Scored

#: Poses listed in the worst-poses table of each file.
WORST = 10
#: Repeated poses listed in the ISO 9283 table of each file (largest RP first).
ISO_ROWS = 20


@dataclass
class StageErrors:
    """Errors one model stage leaves on a file: ``measured - predicted`` ``(n, 3)``, instrument frame, m."""

    name: str
    errors_m: torch.Tensor
    protocol: str

    @property
    def mm(self) -> np.ndarray:
        return self.errors_m.detach().cpu().to(torch.float64).numpy() * 1e3


@dataclass
class PoseSet:
    """One measurement file scored by each model stage.

    Attributes:
        label: how the report names the file (``training file poses.csv``...).
        data: its measurements (joints, points, rows).
        stages: nominal first, the model as delivered last; extra stages (cross-validation) between.
        focus: index into ``stages`` of the errors the per-pose, per-joint and workspace figures show.
        points_base_mm: ``(n, 3)`` the TCP positions in the robot ``base`` frame, mm (workspace figures).
        orientation: where the file measures the tool's orientation, ``(name, errors)`` of the
            nominal robot and of the model (:mod:`torchcal.stages.orientation`).
    """

    label: str
    data: Measurements
    stages: list[StageErrors]
    points_base_mm: np.ndarray
    focus: int = -1
    orientation: list[tuple[str, OrientationErrors]] = field(default_factory=list)

    @property
    def delivered(self) -> StageErrors:
        return self.stages[-1]

    @property
    def focused(self) -> StageErrors:
        return self.stages[self.focus]

    @property
    def rows(self) -> np.ndarray:
        lines = self.data.line_numbers or tuple(range(2, len(self.data) + 2))
        return np.asarray(lines, dtype=np.int64)


@dataclass
class ReportInputs:
    """Everything besides the pose sets that a report shows; absent parts say so in their section.

    Attributes:
        selection: ``model_selection.json`` content (the cross-validated comparison), if any.
        compensator: ``metrics["compensator"]`` of the tracker evaluation of the delivered model.
        uncertainty: ``metrics["uncertainty"]`` (``coverage_95``, ``predicted_p95_mm``,
            ``observed_p95_mm``, ``per_pose_predicted_p95_mm``) on the last pose set, if the model
            predicts its own uncertainty.
        leakage: ``metrics["leakage"]`` of a held-out file.
        compensation_on_truth: the twin only: exported commands sent to the true robot (or a function
            giving them, called when the report reaches the compensator: the export may still run).
        truth_x: the twin only: the truth expressed in the fitted parameter set (SI).
        joint_truth: the twin only: its periodic (gear) joint errors, ``q (B, N) rad -> (B, N) rad``,
            drawn beside the learned per-joint curves.
        lines: what the command printed.
        context: paragraphs for the summary (the twin's noise floor...).
    """

    selection: dict | None = None
    compensator: dict | None = None
    uncertainty: dict | None = None
    leakage: dict | None = None
    compensation_on_truth: dict | Callable[[], dict] | None = None
    truth_x: torch.Tensor | None = None
    truth_note: str = ""
    joint_truth: Callable[[torch.Tensor], torch.Tensor] | None = None
    lines: list[str] = field(default_factory=list)
    context: list[str] = field(default_factory=list)


# ------------------------------------------------------------------------------------ scoring


def model_name(stored: StoredModel) -> str:
    """The stages of a model folder in words (``geometry + gravity compliance (elbow, tcp) + ...``):
    the chain first, then the terms each other stage adds to it, in the order they apply."""
    return _stage_names(stored.stages())


def structure_name(stored: StoredModel) -> str:
    """The model without its Cartesian stages (learned head, stiffness): what the geometry fit chose."""
    return _stage_names([s for s in stored.stages() if s.space != "tcp"])


def _stage_names(stages: Sequence[ModelStage]) -> str:
    ordered = sorted(stages, key=lambda s: s.space != "chain")  # stable: the chain first, the rest as they apply
    return " + ".join(title for title in (s.title() for s in ordered) if title)


def score_pose_set(stored: StoredModel, data: Measurements, *, held_out: bool, register: bool = False,
                   extra: Sequence[StageErrors] = (), focus_extra: bool = False, protocol: str | None = None,
                   scored: Scored | None = None) -> PoseSet:
    """Score ``data`` with the nominal robot and each stage of ``stored``.

    ``held_out``: the file was not fitted (else its numbers are marked optimistic). ``register``:
    the model's instrument frame is re-fitted to the file first (``evaluate --register``).
    ``extra`` stages (cross-validated errors of the same poses) go between the nominal and the
    model; ``focus_extra`` makes the first of them the one the per-pose figures show. ``protocol``
    replaces the default description of how the model's numbers on this file were obtained.
    ``scored``: :func:`~torchcal.instruments.tracker.evaluate.score` of the same model, file and
    ``register`` (``evaluate --report``): its errors are used instead of being computed again.
    """
    name = Path(data.source).name
    if protocol is not None:
        pass
    elif held_out:
        protocol = f"held-out file {name}, never fitted" + (
            "; instrument frame re-fitted to it first (--register)" if register else "")
    else:
        protocol = f"training poses of {name}, optimistic: the model was fitted to them"
    if scored is not None:
        nominal_errors, nominal_frame = scored.nominal_errors, scored.nominal_frame
    else:
        nominal_errors, nominal_frame, _ = nominal_fit(stored.robot, data)
    stages = [StageErrors("nominal", nominal_errors, f"{NOMINAL_PROTOCOL}; generous to the nominal")]
    stages += list(extra)
    structure = structure_name(stored)
    delivered = model_name(stored)
    if delivered != structure:
        stages.append(StageErrors(structure, held_out_errors(stored, data, register=register, residual=False), protocol))
    delivered_errors = scored.errors if scored is not None else held_out_errors(stored, data, register=register)
    stages.append(StageErrors(delivered, delivered_errors, protocol))
    with torch.no_grad():
        predicted = predict_positions(stored, data.q, data.temperature, data.wrench)
        transform = stored.model.instrument_from_base(stored.x)
        base = (predicted - transform[:3, 3]) @ transform[:3, :3]
    orientation = []
    if data.rotation is not None:
        known = scored.orientation if scored is not None else None
        model = known[0] if known is not None else model_orientation_errors(stored, data, register=register)
        if not held_out:  # as for the positions: the model was fitted to these poses
            model = replace(model, protocol=f"{model.protocol}; training poses, optimistic: the model was fitted to them")
        nominal = known[1] if known is not None else nominal_orientation_errors(stored.robot, data, nominal_frame)
        orientation = [("nominal", nominal), (structure, model)]
    return PoseSet(label=f"{'held-out' if held_out else 'training'} file {name}", data=data, stages=stages,
                   points_base_mm=base.detach().cpu().numpy() * 1e3, focus=1 if (focus_extra and extra) else -1,
                   orientation=orientation)


def cross_validated_stage(stored: StoredModel, structure) -> StageErrors | None:
    """The out-of-fold errors of the chosen structure from a fit's structure cross-validation, if it ran."""
    if structure is None:
        return None
    vectors = torch.as_tensor(structure.error_vectors_mm[structure.comparison.chosen], dtype=torch.float64) * 1e-3
    return StageErrors(f"{structure_name(stored)}, cross-validated", vectors,
                       f"held out: out-of-fold, {structure.folds.label}, each pose predicted by a fit that "
                       "never saw it")


# ---------------------------------------------------------------------------------- formatting


def _f(value: float, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{round(value, digits) + 0.0:.{digits}f}"  # + 0.0: no "-0.0000" for a rounded zero


def _g(value: float) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.3g}"


def _metric_row(pose_set: PoseSet, stage: StageErrors) -> list[str]:
    m = position_metrics(stage.errors_m)
    return [pose_set.label, stage.name, stage.protocol, str(m["n_poses"]), _f(m["position_rms_mm"]),
            _f(m["position_mean_mm"]), _f(m["position_p95_mm"]), _f(m["position_max_mm"])]


# ------------------------------------------------------------------------------------ sections


def _summary(stored: StoredModel, pose_sets: list[PoseSet], inputs: ReportInputs) -> Section:
    blocks: list = [Paragraph(f"Robot {stored.robot.name} ({stored.robot.dof} joints, nominal model "
                              f"{stored.metadata.get('robot_file', '')} of the model folder). "
                              f"Model as delivered: {model_name(stored)}.")]
    for pose_set in pose_sets:
        before = position_metrics(pose_set.stages[0].errors_m)["position_rms_mm"]
        after = position_metrics(pose_set.delivered.errors_m)["position_rms_mm"]
        blocks.append(Paragraph(
            f"{pose_set.label}: {before:.4f} mm RMS nominal ({pose_set.stages[0].protocol}) -> {after:.4f} mm RMS "
            f"with the model ({pose_set.delivered.protocol}); {len(pose_set.data)} poses."))
    comparison = (inputs.selection or {})
    if comparison.get("chosen"):
        row = next((r for r in comparison.get("candidates", []) if r.get("name") == comparison["chosen"]), None)
        if row is not None and math.isfinite(row.get("cv_rms_mm", math.nan)):
            blocks.append(Paragraph(f"At fit time, cross-validated on the fitted file (each pose held out, predicted by a "
                                    f"fit that never saw it): {row['cv_rms_mm']:.4f} mm RMS for {comparison['chosen']}, "
                                    f"{comparison.get('protocol', '')}."))
    blocks += [Paragraph(text) for text in inputs.context]
    return Section("Summary", blocks)


def _accuracy(pose_sets: list[PoseSet]) -> Section:
    rows = [_metric_row(p, s) for p in pose_sets for s in p.stages]
    blocks: list = [
        Paragraph("3-D distance between measured and predicted TCP positions (mm). The protocol column says how each "
                  "number was obtained: only numbers on poses a fit never saw (held out) estimate the accuracy on new "
                  "poses; numbers on the poses a model was fitted to are optimistic."),
        Table("accuracy", ["file", "model stage", "protocol", "poses", "RMS [mm]", "mean [mm]", "p95 [mm]", "max [mm]"], rows),
    ]
    oriented = [(p, name, o.metrics()) for p in pose_sets for name, o in p.orientation]
    if oriented:
        blocks += [
            Paragraph("Where a file measures the tool's orientation (rx, ry, rz): the angle between the measured and the "
                      "predicted orientation (deg): the orientation the model's compensator acts on. A learned residual "
                      "head corrects positions only; joint-space terms fitted to positions alone correct positions only "
                      "too, so such a model's row is its MDH chain at the commanded joints (with the terms where the fit "
                      "measured orientations)."),
            Table("orientation", ["file", "model stage", "protocol", "poses", "RMS [deg]", "mean [deg]", "p95 [deg]",
                                  "max [deg]"],
                  [[p.label, name, m["protocol"], str(m["n_poses"]), _f(m["orientation_rms_deg"]),
                    _f(m["orientation_mean_deg"]), _f(m["orientation_p95_deg"]), _f(m["orientation_max_deg"])]
                   for p, name, m in oriented]),
        ]
    for k, p in enumerate(pose_sets):
        blocks.append(PendingFigure(f"error_histogram_{k + 1}", plots.error_histogram, (
            {s.name: np.linalg.norm(s.mm, axis=1) for s in p.stages}, f"3-D error, {p.label}"),
            f"Distribution of the 3-D error per model stage, {p.label}."))
    return Section("Accuracy before and after", blocks)


def _selection(inputs: ReportInputs) -> Section | None:
    sel = inputs.selection
    if not sel:
        return None
    rows = []
    for r in sel.get("candidates", []):
        cv = r.get("cv_rms_mm", math.nan)
        rows.append([r.get("name", ""), _f(cv), _f(r.get("vs_best_pct", math.nan), 1), _f(r.get("se_pct", math.nan), 1),
                     "chosen" if r.get("name") == sel.get("chosen") else str(r.get("verdict", ""))])
    blocks: list = [
        Paragraph(f"Every choice of model structure and learned head was made by cross-validation on the fitted file: "
                  f"{sel.get('protocol', '')}. CV RMS is the RMS 3-D error of each pose predicted by the fit on the other "
                  "folds (held out, never fitted)."),
        Table("model_selection", ["candidate", "CV RMS [mm]", "vs best [%]", "1 SE [%]", "verdict"], rows),
        Paragraph(f"Chosen: {sel.get('chosen', '')} ({sel.get('reason', '')})."),
    ]
    if sel.get("residual_decision"):
        blocks.append(Paragraph(f"Residual head: {sel['residual_decision']}."))
    return Section("Model selection", blocks)


def _per_axis(pose_sets: list[PoseSet]) -> Section:
    rows = []
    for p in pose_sets:
        for s in p.stages:
            m = position_metrics(s.errors_m)
            rows.append([p.label, s.name, s.protocol] + [_f(m[f"{a}_{k}_mm"]) for a in "xyz" for k in ("mean", "rms")])
    blocks: list = [
        Paragraph("Signed error along each axis of the instrument frame (mm): a mean far from zero is a bias the model "
                  "leaves, an RMS much larger on one axis points at what the model misses in that direction."),
        Table("per_axis", ["file", "model stage", "protocol", "x mean", "x RMS", "y mean", "y RMS", "z mean", "z RMS"], rows),
    ]
    for k, p in enumerate(pose_sets):
        blocks.append(PendingFigure(f"axis_errors_{k + 1}", plots.axis_errors, (p.rows, p.focused.mm, p.focused.name,
                                                                                f"per-axis error, {p.label}"),
                             f"x, y, z error of every pose of {p.label} (instrument frame) under {p.focused.name} "
                             f"({p.focused.protocol}); the nominal's are in the table."))
    return Section("Errors per axis", blocks)


def _per_pose(pose_sets: list[PoseSet]) -> Section:
    blocks: list = []
    for k, p in enumerate(pose_sets):
        shown = {s.name: np.linalg.norm(s.mm, axis=1) for s in (p.stages[0], p.focused)}
        blocks.append(PendingFigure(f"per_pose_{k + 1}", plots.per_pose_errors, (p.rows, shown, f"3-D error per pose, {p.label}"),
                             f"3-D error of every pose against its row in {Path(p.data.source).name}: nominal and "
                             f"{p.focused.name} ({p.focused.protocol})."))
        e = p.focused.mm
        norm = np.linalg.norm(e, axis=1)
        worst = np.argsort(-norm)[:WORST]
        q_deg = np.degrees(p.data.q.detach().cpu().numpy())
        rows = [[str(int(p.rows[i])), _f(float(norm[i])), _f(float(e[i, 0])), _f(float(e[i, 1])), _f(float(e[i, 2])),
                 ", ".join(f"{v:.2f}" for v in q_deg[i])] for i in worst]
        blocks.append(Table(f"worst_poses_{k + 1}", ["row", "3-D [mm]", "x [mm]", "y [mm]", "z [mm]", "joints q1.. [deg]"], rows,
                            caption=f"The {len(worst)} worst poses of {p.label} under {p.focused.name} "
                                    f"({p.focused.protocol}); row = the row of the file (header = row 1), as torchcal's "
                                    "file errors name it."))
    return Section("Errors per pose and the worst poses", blocks)


def _joints_and_workspace(pose_sets: list[PoseSet]) -> list[Section]:
    joint_blocks: list = []
    space_blocks: list = []
    for k, p in enumerate(pose_sets):
        q_deg = np.degrees(p.data.q.detach().cpu().numpy())
        shown = np.linalg.norm(p.focused.mm, axis=1)
        joint_blocks.append(PendingFigure(f"error_vs_joints_{k + 1}", plots.error_vs_joints, (q_deg, shown, p.focused.name,
                                                                                              f"3-D error against each joint, {p.label}"),
                                   f"3-D error against each commanded joint angle, {p.label}, under {p.focused.name} "
                                   f"({p.focused.protocol}); line: median per tenth of the joint's range. A trend "
                                   "along one joint is an error of that joint the model does not carry."))
        norm = np.linalg.norm(p.focused.mm, axis=1)
        space_blocks.append(PendingFigure(f"workspace_{k + 1}", plots.workspace, (p.points_base_mm, norm, f"{p.focused.name}, {p.label}", "base"),
                                   f"TCP positions of {p.label} in the robot base frame, coloured by the 3-D error of "
                                   f"{p.focused.name} ({p.focused.protocol})."))
    return [Section("Error against the joint angles", joint_blocks),
            Section("Error across the workspace", space_blocks)]


def _iso9283(pose_sets: list[PoseSet]) -> Section:
    blocks: list = []
    for p in pose_sets:
        iso = iso9283_repeated(p.delivered.errors_m, p.data.q)
        if not iso["repeated_poses"]:
            blocks.append(Paragraph(f"{p.label}: {iso['instead']}."))
            continue
        shown = sorted(iso["poses"], key=lambda pose: -pose["RP_mm"])[:ISO_ROWS]
        rows = [[", ".join(str(int(p.rows[i])) for i in pose["index"]), str(pose["visits"]), _f(pose["AP_mm"]), _f(pose["RP_mm"])]
                for pose in shown]
        blocks += [
            Paragraph(f"{p.label}: {iso['repeated_poses']} commanded poses were visited more than once (joints equal within "
                      f"{iso['tolerance_deg']:g} deg), {iso['visits']} visits in all. AP: distance of the visits' barycentre "
                      f"from the {p.delivered.name} prediction; RP: mean distance of the visits from their barycentre + 3 "
                      f"standard deviations ({p.delivered.protocol}). Largest AP {iso['AP_max_mm']:.4f} mm, largest RP "
                      f"{iso['RP_max_mm']:.4f} mm. ISO 9283 asks for 30 visits per pose; fewer visits make RP uncertain."),
            Table(f"iso9283_{pose_sets.index(p) + 1}", ["rows", "visits", "AP [mm]", "RP [mm]"], rows,
                  caption=f"The {len(shown)} repeated poses with the largest RP (of {iso['repeated_poses']}); rows of the "
                          "file, header = row 1."),
        ]
    return Section("ISO 9283 pose accuracy and repeatability", blocks)


def _compensator(pose_sets: list[PoseSet], inputs: ReportInputs) -> Section:
    comp = inputs.compensator
    blocks: list = []
    last = pose_sets[-1]
    model = position_metrics(last.delivered.errors_m)
    if comp is None:
        blocks.append(Paragraph("The exported compensator was not evaluated for this report."))
    else:
        rows = [["model prediction of the TCP", last.delivered.protocol, _f(model["position_rms_mm"]),
                 _f(model["position_p95_mm"]), _f(model["position_max_mm"])]]
        if "delivered_rms_mm" in comp:
            rows.append(["compensated command (model error + what the compensator leaves unsolved, per pose)",
                         last.delivered.protocol + "; an upper bound by the triangle inequality",
                         _f(comp["delivered_rms_mm"]), _f(comp["delivered_p95_mm"]), _f(comp["delivered_max_mm"])])
        blocks += [
            Paragraph(f"The exported compensator solves each nominal command on the calibrated model ({comp['task']} task "
                      f"first, {comp['iterations']} Newton steps). On the poses of {last.label} it solves "
                      f"{100 * comp['solved_share']:.1f} % to 1 um by the model's own account (largest unsolved TCP "
                      f"{comp['unsolved_max_mm']:.2e} mm); the tool orientation deviates from the nominal target by "
                      f"{comp['orientation_deviation_median_rad']:.1e} rad (median), "
                      f"{comp['orientation_deviation_max_rad']:.1e} rad (max).{_corrections_sentence(comp)} The accuracy "
                      "it delivers is then the model's own accuracy plus that unsolved part:"),
            Table("compensator", ["what", "protocol", "RMS [mm]", "p95 [mm]", "max [mm]"], rows),
        ]
    truth = inputs.compensation_on_truth
    if callable(truth):  # the export's check, run beside the report: asked for only here
        truth = truth()
    if truth:
        rows = [[name, _f(truth[key]["position_rms_mm"]), _f(truth[key]["position_max_mm"])]
                for name, key in (("uncompensated", "uncompensated"), ("compensated, torch", "torch"),
                                  ("compensated, onnxruntime float64", "onnx_float64"),
                                  ("compensated, onnxruntime float32", "onnx_float32")) if truth.get(key)]
        blocks += [Paragraph(f"The twin only: the exported commands sent to the true robot, {truth['n_poses']} held-out "
                             "poses, error against the target (truth known):"),
                   Table("compensation_on_truth", ["command", "RMS [mm]", "max [mm]"], rows)]
    return Section("The exported compensator", blocks)


def _corrections_sentence(comp: dict) -> str:
    """The joint corrections and their 1-sigma, where the evaluation measured them."""
    c = comp.get("corrections")
    if not c or c["largest_joint_correction_sigma_deg"] is None:
        return ""
    sigmas = ", ".join(f"{v:.2g}" for v in c["median_joint_correction_sigma_deg"])
    return (f" Its joint corrections on the {c['n_poses']} of these poses not near a singularity: up to "
            f"{c['largest_joint_correction_deg']:.3g} deg (joint {c['joint']}; 1-sigma "
            f"{c['largest_joint_correction_sigma_deg']:.2g} deg from the calibration's uncertainty), median "
            f"{c['median_joint_correction_deg']:.3g} deg; each joint's median 1-sigma {sigmas} deg ({c['sigma_from']}).")


def _uncertainty(pose_sets: list[PoseSet], inputs: ReportInputs) -> Section:
    unc = inputs.uncertainty
    if not unc:
        return Section("Predicted and observed uncertainty", [Paragraph(
            "This model carries no prediction uncertainty: it gives no per-pose error radius to compare with the "
            "observed errors.")])
    last = pose_sets[-1]
    observed = np.linalg.norm(last.delivered.mm, axis=1)
    predicted = np.asarray(unc.get("per_pose_predicted_p95_mm") or [], dtype=np.float64)
    rows = [[last.label, last.delivered.protocol, f"{100 * unc['coverage_95']:.1f} %", _f(unc["predicted_p95_mm"]),
             _f(unc["observed_p95_mm"])]]
    blocks: list = [
        Paragraph("The model predicts for each pose the radius its 3-D error stays within with 95 % probability. On "
                  "poses it never saw about 95 % of the observed errors should fall inside; far fewer means the model is "
                  "overconfident, far more that it is too cautious."),
        Table("uncertainty", ["file", "protocol", "poses inside their 95 % radius", "predicted p95 [mm]",
                              "observed p95 [mm]"], rows),
    ]
    if len(predicted) == len(observed) and len(predicted):
        blocks.append(PendingFigure("uncertainty", plots.predicted_vs_observed, (predicted, observed, float(unc["coverage_95"])),
                             f"Observed 3-D error of each pose of {last.label} against its predicted 95 % radius."))
    else:
        blocks.append(Paragraph(f"No per-pose figure: {len(predicted)} predicted radii for {len(observed)} poses."))
    return Section("Predicted and observed uncertainty", blocks)


def _robot_files(stored: StoredModel) -> Section | None:
    """The calibrated robot files of the folder (YAML table, URDF) and what of the model they cannot hold."""
    if not (stored.folder / CALIBRATED_URDF).is_file():
        return None
    source = "the robot's own URDF with only the moving joints' origins changed" if stored.robot.urdf is not None \
        else "a URDF generated from the calibrated MDH table"
    return Section("Calibrated robot files", [Paragraph(
        f"calibrated_robot.yaml (the MDH table and tool, mm and deg) and {CALIBRATED_URDF} ({source}; the calibrated TCP "
        f"is the added link '{stored.robot.end_link}_calibrated_tcp') hold the geometric stage. "
        + " ".join(not_in_geometry(stored.metadata))
        + " The instrument-to-base transform of the measurement is in calibration.json (frames).")])


def _joint_terms(stored: StoredModel, pose_sets: list[PoseSet], joint_truth=None) -> Section | None:
    terms = JointSpaceErrors.from_metadata(stored.metadata)
    if terms.empty:
        return None
    q = pose_sets[0].data.q.to(torch.float64)
    rows: list[list[str]] = []
    for label, part in (("gravity compliance", JointSpaceErrors(terms.compliance, None)),
                        (terms.harmonics.label if terms.harmonics is not None else "", JointSpaceErrors(None, terms.harmonics))):
        if part.empty:
            continue
        dq = np.degrees((part.effective_joints(stored.robot, q) - q).detach().cpu().numpy()) * 1e3
        rows.extend([label, f"q{j + 1}", _f(float(np.sqrt(np.mean(dq[:, j] ** 2))), 2), _f(float(np.abs(dq[:, j]).max()), 2)]
                    for j in range(dq.shape[1]) if np.abs(dq[:, j]).max() > 0)
    blocks: list = [
        Paragraph(f"Joint errors the model adds to the commanded joints before the geometric chain, over the poses of "
                  f"{pose_sets[0].label} (millidegrees; coefficients in calibration.json)."),
        Table("joint_terms", ["term", "joint", "RMS [mdeg]", "max [mdeg]"], rows)]
    if terms.harmonics is not None:
        blocks += _joint_curves(stored, q, terms.harmonics, joint_truth)
    return Section("Joint-space terms", blocks)


def _joint_curves(stored: StoredModel, q: torch.Tensor, harmonics, joint_truth) -> list:
    """The learned periodic error of each joint as a function of its own angle over the poses' range
    (and the twin's truth): constants are left out, the joint zero offset ``theta_j`` carries them."""
    grid = torch.stack([torch.linspace(float(q[:, j].min()), float(q[:, j].max()), 361, dtype=torch.float64)
                        for j in range(q.shape[1])], 1)
    centred = lambda v: v - v.mean(0, keepdim=True)  # noqa: E731
    learned = np.degrees(centred(harmonics.deflection(grid)).numpy()) * 1e3
    truth = None if joint_truth is None else np.degrees(centred(joint_truth(grid)).detach().numpy()) * 1e3
    caption = (f"{harmonics.label}: the learned error of each joint against its own commanded angle, over the range "
               "of the poses, each curve less its mean (a constant is the joint zero offset's)")
    if truth is not None:
        miss = np.sqrt(np.mean((learned - truth) ** 2, axis=0))
        size = np.sqrt(np.mean(truth**2, axis=0))
        caption += ("; thick: the twin's gear error (truth). RMS of learned - truth per joint: "
                    + ", ".join(f"q{j + 1} {miss[j]:.2f} of {size[j]:.2f} mdeg" for j in range(len(miss))))
        caption += ". The last joint has none by design (identify.harmonics: it aliases with the tool lever)"
    return [PendingFigure("joint_curves", plots.joint_curves, (np.degrees(grid.numpy()), learned, truth,
                                                               "Learned periodic joint errors", "learned"), caption + ".")]


def _notes(stored: StoredModel, inputs: ReportInputs) -> Section:
    blocks: list = []
    ident = stored.metadata.get("identifiability") or {}
    if ident:
        dropped = ident.get("not_identifiable") or {}
        text = [(f"rank {ident.get('rank')}, condition number {_g(float(ident.get('condition_number', math.nan)))}, "
                f"observability index {_g(float(ident.get('observability_index', math.nan)))}"),
                f"identifiable ({len(ident.get('base_set', []))}): {', '.join(ident.get('base_set', []))}"]
        text += [f"not identifiable: {n} - confounded with {', '.join(p) or 'nothing'}" for n, p in dropped.items()]
        text += [f"weakly identifiable: {n} (independent part {_g(float(v))} of its column)" for n, v in (ident.get("weak") or {}).items()]
        blocks += [Paragraph("Identifiability of the geometric parameters from these poses (parameters that cannot be "
                             "identified stay at nominal; their effect is carried by the partners named):"),
                   Preformatted("\n".join(text))]
    notes = list(stored.metadata.get("notes") or [])
    if inputs.leakage:
        report = LeakageReport(**inputs.leakage)
        notes.append(f"{'warning: ' if report.warning else ''}{report.summary()}")
    if notes:
        blocks += [Paragraph("Notes and warnings of the fit and the evaluation:"), Preformatted("\n".join(notes))]
    if inputs.lines:
        blocks += [Paragraph("What the command printed:"), Preformatted("\n".join(inputs.lines))]
    return Section("Identifiability, notes and warnings", blocks)


def _convergence(stored: StoredModel) -> Section | None:
    solver = stored.metadata.get("solver") or {}
    history = solver.get("cost_history")
    if not history:
        return None
    return Section("Convergence", [
        Paragraph(f"{stored.metadata.get('method', '')}: {solver.get('iterations')} iterations, {solver.get('message')}."),
        PendingFigure("convergence", plots.convergence, (history,),
                      "Sum of squared residuals per accepted iteration of the geometric fit.")])


#: What a report imports in this process on first use (its figures; the ISO 9283 repeats' k-d tree):
#: a fit that will write one imports them while it waits for its worker (core.workers.import_while_waiting).
REPORT_MODULES = (*plots.IMPORTS, "scipy.spatial", "scipy.sparse.csgraph")


def calibration_report(title: str, stored: StoredModel, pose_sets: list[PoseSet], inputs: ReportInputs | None = None,
                       jobs: int = 1) -> Report:
    """The whole report (see the module docstring); ``pose_sets`` in the order shown, held-out last.

    ``jobs``: processes that draw the figures side by side (:func:`~torchcal.report.document.draw_figures`;
    the same bytes with one). In ``torchcal run`` the worker is exporting meanwhile: it takes the
    figures left when it is done.
    """
    inputs = inputs or ReportInputs()
    if jobs > 1:
        import_in_workers(plots.IMPORTS)  # imported there while the sections are built here
    before: list[Section | None] = [
        _summary(stored, pose_sets, inputs),
        _accuracy(pose_sets),
        _selection(inputs),
        _per_axis(pose_sets),
        _per_pose(pose_sets),
        *_joints_and_workspace(pose_sets),
        _iso9283(pose_sets),
    ]
    after: list[Section | None] = [
        _uncertainty(pose_sets, inputs),
        *parameter_sections(stored, inputs.truth_x, inputs.truth_note),
        _joint_terms(stored, pose_sets, inputs.joint_truth),
        _robot_files(stored),
        _notes(stored, inputs),
        _convergence(stored),
    ]
    shown_before = [s for s in before if s is not None]
    drawn = draw_figures(Report(title, [*shown_before, *(s for s in after if s is not None)]), jobs).sections
    # built last, shown in its place: on the twin it may wait for the export's check running beside
    compensator = _compensator(pose_sets, inputs)
    return Report(title, [*drawn[:len(shown_before)], compensator, *drawn[len(shown_before):]])
