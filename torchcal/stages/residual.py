"""The learned-residual stage of ``fit``: candidate heads judged by grouped cross-validation.

Targets are the poses' position errors left by the chosen structure (geometry, with its
joint-space terms), rotated into the ``base`` frame (so a head is independent of where the
tracker stood) and scaled to mm. Every candidate head is cross-validated on the folds of
:mod:`torchcal.model_selection` (configuration groups by default, never a random row split): on
each fold it learns the errors of that fold's structure fit and predicts the held-out poses. A
head is kept only where it beats the structure by ``residual_margin`` in CV RMS with a paired
gain beyond chance over configuration groups; the kept head is then fitted on all poses. The
comparison table (structures and heads) is written to ``model_selection.json``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from torchcal.core.folder import write_member_json
from torchcal.core.workers import resolve_jobs
from torchcal.data.folds import make_folds
from torchcal.data.measurements import Measurements
from torchcal.identify.joint_fit import CV_TOLERANCE
from torchcal.model_selection.compare import Comparison, compare_candidates
from torchcal.model_selection.heads import cross_validate_heads, make_features
from torchcal.model_selection.structure import StructureCV, cross_validate_structures
from torchcal.residual import HEADS, ResidualHead, head_names
from torchcal.residual.selection import fit_before_gate
from torchcal.stages.geometry import cross_validate_stored_structure, geometry_fitter, model_joints
from torchcal.stages.prediction_uncertainty import (
    calibrate_errors,
    point_jacobian,
    write_uncertainty,
)
from torchcal.stages.residual_store import StoredResidual, save_residual
from torchcal.stages.store import load_model

SELECTION_FILE = "model_selection.json"


@dataclass
class ResidualOutcome:
    """What the residual stage decided.

    ``comparison``: the final table (structures and heads, the chosen row and why); ``kept``: the
    head fitted and written into the model folder (``None``: none passed); ``decision``: one line.
    """

    decision: str
    kept: str | None
    comparison: Comparison

    @property
    def table(self) -> str:
        """The comparison as a printable table."""
        return self.comparison.format_table()

    def to_dict(self) -> dict:
        """``decision``, ``kept``, ``comparison`` (its dict) and ``table``: what ``metrics.json`` records."""
        return {"decision": self.decision, "kept": self.kept, "comparison": self.comparison.to_dict(), "table": self.table}


def head_modules(config) -> list[str]:
    """The modules the heads of ``config`` import when they fit (a worker imports them ahead)."""
    return list(dict.fromkeys(m for h in _candidates(config) for m in (type(h).__module__, *h.imports)))


def _candidates(config) -> list[ResidualHead]:
    """The heads of ``config.residual``, each built by its own :meth:`ResidualHead.from_options`."""
    return [HEADS[name].from_options(config) for name in head_names(config.residual)]


def residual_targets_mm(model, x, data: Measurements, joints: torch.Tensor | None = None) -> torch.Tensor:
    """Geometric residuals of ``data`` in the ``base`` frame, mm ``(n, 3)``.

    ``joints``: what the chain is evaluated at (default ``data.q``; ``q`` plus the joint-space
    errors when the model has any), while the head's features stay the commanded joints.
    """
    error = data.position - model.tcp_position(data.q if joints is None else joints, x)
    return error @ model.T_reference[:3, :3].to(error) * 1e3


def select_with_heads(robot, data: Measurements, structure: StructureCV, config, progress=None) -> Comparison:
    """The final comparison: the structures of ``structure`` and every head on the chosen one.

    A head that passes on ``structure``'s folds must pass again on contiguous blocks of row
    (measurement) order when ``config.head_time_check`` is on and the folds were not blocks
    already: a head can learn what drifts while a series is measured (tracker, temperature),
    which configuration folds cannot tell from a robot property when neighbouring
    configurations were measured minutes apart. Requiring both is never less strict than either.
    """
    assert structure.comparison is not None
    parent = structure.comparison.chosen
    heads = cross_validate_heads(robot, data, structure, parent, lambda: _candidates(config),
                                 margin=config.residual_margin, seed=config.seed, progress=progress,
                                 jobs=resolve_jobs(config.jobs))
    candidates = structure.candidates + heads.candidates
    units, protocol = structure.folds.units(), structure.folds.description
    head_rows = {c.name for c in heads.candidates}
    later: list[dict] = []
    excluded: dict[str, str] = {}  # heads that failed the check on time blocks, with why
    timed_protocol = None
    timed: dict = {}  # the structure's fits on the time blocks, made once for every head checked
    while True:  # the best head still in the running, checked on time blocks; the next one if it fails
        comparison = _decided(candidates, units, protocol, parent, structure, head_rows, excluded)
        head = comparison.chosen_head
        if head is None or not config.head_time_check or structure.folds.kind == "blocks":
            break
        timed_protocol, rows, passed = _check_on_time_blocks(robot, data, structure, head, config, progress, timed)
        seen = {row["name"] for row in later}
        later += [row for row in rows if row["name"] not in seen]  # the structure's rows once
        if passed:
            break
        excluded[comparison.chosen] = f"rejected: passed on configuration regions, not on {timed_protocol}"
    if timed_protocol is not None:
        checked = "a kept head" if comparison.chosen_head is not None else "each head that passed"
        comparison.protocol = f"{protocol}; {checked} also checked by {timed_protocol}"
    if excluded:
        failed = ", ".join(f"'{comparison.heads.get(name, name)}'" for name in excluded)
        comparison.reason = (f"{comparison.reason}; head {failed} passed on configuration regions but not on blocks of "
                             "measurement order: it learned what changed while the series was measured, not the robot")
    for name, why in heads.stopped.items():
        comparison.rows.append(_stopped_row(f"{parent}+{name}", why))
        comparison.heads[f"{parent}+{name}"] = name
    for row in later:
        comparison.rows.append(row)
        if row.get("head") is not None:
            comparison.heads[row["name"]] = row.pop("head")
        row.pop("head", None)
    return comparison


def _decided(candidates, units, protocol: str, parent: str, structure: StructureCV, head_rows: set[str],
             excluded: dict[str, str]) -> Comparison:
    """The comparison of the structures and heads with ``excluded`` heads ruled out: a head is chosen
    where it wins; otherwise the structure ``parent``, chosen before the heads, with its own reason."""
    assert structure.comparison is not None
    comparison = compare_candidates(candidates, units, protocol, tolerance=structure_tolerance(), excluded=excluded)
    if comparison.chosen not in head_rows and comparison.chosen != parent:
        # the structures were decided without heads; heads only add rows on top of that choice. The
        # table is restated against the structures, so that its verdicts and the decision agree.
        comparison = _restated(candidates, units, protocol, parent, structure, {**excluded, **{
            name: f"not kept: {comparison.chosen} is within noise of it, and the structure ({parent}) was chosen "
                  "before the heads" for name in head_rows if name not in excluded and _eligible(comparison, name)}})
    elif comparison.chosen == parent:
        # the structure's own reason (a learned joint model's check on time blocks included)
        comparison.reason = structure.comparison.reason
    return comparison


def _eligible(comparison: Comparison, name: str) -> bool:
    row = next(r for r in comparison.rows if r["name"] == name)
    return not row["verdict"].startswith(("rejected", "not kept"))


def _restated(candidates, units, protocol: str, parent: str, structure: StructureCV,
              excluded: dict[str, str]) -> Comparison:
    """The comparison of ``candidates`` again with ``excluded`` ruled out: the structure ``parent`` chosen, every
    verdict relative to the best candidate still in the running."""
    assert structure.comparison is not None
    restated = compare_candidates(candidates, units, protocol, tolerance=structure_tolerance(), excluded=excluded)
    restated.chosen, restated.reason = parent, structure.comparison.reason
    return restated


def _stopped_row(name: str, why: str) -> dict:
    nan = float("nan")
    return {"name": name, "cv_rms_mm": nan, "vs_best_pct": nan, "se_pct": nan, "verdict": why, "detail": ""}


def _check_on_time_blocks(robot, data: Measurements, structure: StructureCV, head_name: str,
                          config, progress, cache: dict | None = None) -> tuple[str, list[dict], bool]:
    """Repeat the chosen head's CV on blocks of row order.

    Returns the blocks' protocol, the rows of that check (named ``... [time blocks]``, each with
    its ``head`` or ``None``) and whether the head is kept there too. ``cache``: where the
    structure's own fits on the blocks are kept between the heads checked (they do not depend on the head).
    """
    assert structure.comparison is not None
    parent = structure.comparison.chosen
    cache = {} if cache is None else cache
    if "timed" not in cache:
        order = torch.as_tensor(data.line_numbers).numpy() if data.line_numbers else None
        cache["blocks"] = make_folds("blocks", robot, data.q, k=config.cv_folds, order=order, series=data.series)
        cache["timed"] = cross_validate_structures(
            robot, data, geometry_fitter(robot, config, structure.prior, start=structure.prior_start), [structure.chosen],
            cache["blocks"], harmonic_min_range_deg=config.harmonic_min_range_deg, progress=progress,
            jobs=resolve_jobs(config.jobs))
    blocks, timed = cache["blocks"], cache["timed"]
    heads = cross_validate_heads(robot, data, timed, parent,
                                 lambda: [h for h in _candidates(config) if h.name == head_name],
                                 margin=config.residual_margin, seed=config.seed, progress=progress)
    check = compare_candidates(timed.candidates + heads.candidates, blocks.units(), blocks.description)
    rows = [{**row, "name": f"{row['name']} [time blocks]", "head": check.heads.get(row["name"])} for row in check.rows]
    rows += [{**_stopped_row(f"{parent}+{name} [time blocks]", why), "head": name} for name, why in heads.stopped.items()]
    passed = check.chosen_head == head_name
    return blocks.description, rows, passed


def structure_tolerance() -> float:
    return CV_TOLERANCE


def fit_residual_stage(
    model_dir, data: Measurements, config, progress: Callable[[str], None] | None = None, structure: StructureCV | None = None
) -> ResidualOutcome:
    """Cross-validate the heads on top of a saved model's structure; fit and write the kept one.

    ``structure``: the structure CV of the fit that wrote ``model_dir`` (its folds and fold
    fits); without it the stored structure is cross-validated alone on ``config``'s folds.
    ``progress`` is called with a line per step (when ``config.progress``). Nothing is printed here.
    """
    stored = load_model(model_dir)
    if structure is None:
        structure = cross_validate_stored_structure(stored, data, config)
    progress = progress if config.progress else None
    comparison = select_with_heads(stored.robot, data, structure, config, progress=progress)
    kept = comparison.chosen_head
    if kept is not None:
        head = next(h for h in _candidates(config) if h.name == kept)
        features = make_features(stored.robot, data)
        targets = residual_targets_mm(stored.model, stored.x, data, model_joints(stored, data.q))
        fit_before_gate(head, features(data.q, data.temperature), targets, seed=config.seed)
        row = next(r for r in comparison.rows if r["name"] == comparison.chosen)
        decision = (f"residual head '{kept}' kept: {comparison.reason}; CV RMS {row['cv_rms_mm']:.4f} mm; "
                    "fitted on all training poses")
        save_residual(model_dir, StoredResidual(head, features, {"decision": decision, "cv_rms_mm": row["cv_rms_mm"],
                                                                 "protocol": comparison.protocol}))
        if config.uncertainty != "none":  # the head's out-of-fold errors replace the structure's
            jac = point_jacobian(stored.model, stored.x, stored.free, model_joints(stored, data.q))
            write_uncertainty(model_dir, calibrate_errors(jac, stored.covariance, comparison.errors_mm[comparison.chosen],
                                                          comparison.protocol, config.uncertainty))
    else:
        rejected = [r for r in comparison.rows if r["name"] in comparison.heads]
        why = "; ".join(f"{r['name']}: {r['verdict']}" for r in rejected) or "no head candidates"
        decision = f"no residual head kept ({why})"
    write_selection(model_dir, comparison, decision)
    return ResidualOutcome(decision, kept, comparison)


def write_selection(model_dir, comparison: Comparison, decision: str) -> None:
    """``model_selection.json``: the comparison table and the residual decision."""
    write_member_json(Path(model_dir), SELECTION_FILE, {**comparison.to_dict(), "residual_decision": decision,
                                                        "table": comparison.format_table()})
