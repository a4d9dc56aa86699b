"""What the commands do: fit, evaluate, simulate and the end-to-end ``run``.

Kept apart from :mod:`torchcal.cli` so that the same steps are callable from Python and tests.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchcal.data.measurements import Measurements, load_measurements
from torchcal.errors import DataError
from torchcal.identify import IDENTIFIERS
from torchcal.identify.calibrate import CalibrationResult, calibrate
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.problem import CalibrationProblem
from torchcal.io import atomic_write_json
from torchcal.kinematics.robot import RobotModel, load_robot
from torchcal.kinematics.transforms import rigid_registration
from torchcal.metrics import position_metrics
from torchcal.model_store import StoredModel, load_model, save_model
from torchcal.sim.twin import Twin, TwinConfig, write_twin_case


@dataclass
class FitConfig:
    """Options of ``torchcal fit`` (and the fit stage of ``run``).

    Attributes:
        method: identifier: ``lm`` (default), ``gn`` or ``lasso``.
        parallel_threshold_deg: Hayati switch (see :mod:`torchcal.kinematics.error_model`).
        joint_unit / length_unit: units of the measurement file.
        residual: learned residual stage: ``auto`` (cross-validate every candidate head on top
            of the chosen structure, keep one only where it beats it beyond noise), ``none``, or
            head names joined by ``+``.
        split: how the cross-validation behind every choice forms its folds
            (:mod:`torchcal.model_selection.folds`): ``grouped`` (default; near-twin
            configurations in one fold), ``blocks`` (contiguous blocks of the file's row order,
            for data that drifts while measured) or ``random`` (rows; for comparison only).
        cv_folds: folds of that cross-validation.
        cv_groups: configuration regions (k-means clusters) of ``split=grouped``.
        harmonic_min_range_deg: first harmonics only on joints whose range in the data spans at
            least this (deg): over a shorter arc a harmonic is an offset and a slope that
            extrapolates wildly (:func:`~torchcal.identify.joint_fit.fit_joint_errors`).
        head_time_check: a head that passes the CV must pass again on contiguous blocks of the
            file's row order (measurement order), so that one that learned a drift is refused.
        device: ``cpu`` or a torch device string.
        seed: seed of the folds and of stochastic heads.
        tool_mm: nominal TCP in the flange frame (mm) replacing the robot file's (a URDF has none).
        residual_hidden: hidden units of ELM heads.
        mayfly_population / mayfly_iterations: MMA search of the ELM hidden layer.
        residual_margin: a head must lower the CV RMS by this fraction (and with a paired gain
            beyond chance over configuration groups) to be kept.
        progress: show progress of long steps.
        gravity_compliance: joint compliance under the arm's own weight, identified with the
            geometry (:mod:`torchcal.identify.compliance`): ``none``, ``wrist``, ``elbow+wrist``
            or ``auto`` (default: chosen by the cross-validation, with the harmonics).
        joint_harmonics: first-harmonic joint errors ``a_j sin q_j + b_j cos q_j`` (rad), every
            joint but the last, identified with the geometry (:mod:`torchcal.identify.harmonics`):
            ``none``, ``first`` or ``auto`` (default). With ``auto`` (here or in
            ``gravity_compliance``) the cross-validation compares the options and keeps the
            simplest within noise of the best (:mod:`torchcal.model_selection.compare`). The
            exported compensator carries both terms (:mod:`torchcal.compensate.joint_error_graph`).
    """

    method: str = "lm"
    parallel_threshold_deg: float = 2.0
    joint_unit: str = "deg"
    length_unit: str = "mm"
    residual: str = "auto"
    split: str = "grouped"
    cv_folds: int = 5
    cv_groups: int = 20
    head_time_check: bool = True
    harmonic_min_range_deg: float = 180.0
    device: str = "cpu"
    seed: int = 0
    tool_mm: list[float] | None = None
    residual_hidden: int = 80
    mayfly_population: int = 20
    mayfly_iterations: int = 50
    residual_margin: float = 0.05
    progress: bool = True
    gravity_compliance: str = "auto"
    joint_harmonics: str = "auto"


def registered_errors(predicted_base: torch.Tensor, measured: torch.Tensor) -> torch.Tensor:
    """Errors after the best rigid registration of ``predicted_base`` onto ``measured``."""
    transform = rigid_registration(predicted_base, measured)
    aligned = predicted_base @ transform[:3, :3].T + transform[:3, 3]
    return measured - aligned


def nominal_errors(robot: RobotModel, data: Measurements) -> torch.Tensor:
    """Nominal model errors after registering the instrument frame (the fair 'before')."""
    return registered_errors(robot.tcp_position(data.q), data.position)


def with_tool(robot: RobotModel, config: FitConfig) -> RobotModel:
    """``robot`` with the configured nominal tool, if one is configured."""
    if config.tool_mm is None:
        return robot
    if len(config.tool_mm) != 3:
        raise DataError(f"tool_mm needs 3 values (x, y, z in mm), got {list(config.tool_mm)}")
    from dataclasses import replace

    return replace(robot, tool=torch.tensor(config.tool_mm, dtype=torch.float64) * 1e-3)


def describe_structure(result: CalibrationResult) -> str:
    """``geometry``, ``geometry + gravity compliance + joint harmonics``, ... of a fit result."""
    terms = [t for t, present in (("gravity compliance", result.compliance is not None),
                                  ("joint harmonics", result.harmonics is not None)) if present]
    return "geometry" + "".join(f" + {t}" for t in terms)


def make_config_folds(robot: RobotModel, data: Measurements, config: FitConfig):
    """The folds every data-driven choice of this fit is judged on (``config.split``)."""
    from torchcal.model_selection.folds import make_folds

    order = np.asarray(data.line_numbers) if data.line_numbers else None
    return make_folds(config.split, robot, data.q, k=config.cv_folds, seed=config.seed, order=order,
                      groups=config.cv_groups)


def geometry_fitter(robot: RobotModel, config: FitConfig):
    def geometry(train: Measurements) -> CalibrationResult:
        return calibrate(robot, train, identifier=IDENTIFIERS[config.method](**_identifier_options(robot, config)),
                         parallel_threshold_deg=config.parallel_threshold_deg, device=config.device)

    return geometry


def _identifier_options(robot: RobotModel, config: FitConfig) -> dict:
    """LASSO's penalty is chosen by the same kind of folds as every other choice."""
    if config.method != "lasso":
        return {}
    return {"folds": config.cv_folds, "seed": config.seed, "split": config.split, "robot": robot}


def _structure_options(config: FitConfig) -> list[tuple[str, str]]:
    from torchcal.identify.compliance import POINT_SETS
    from torchcal.identify.harmonics import HARMONIC_SETS
    from torchcal.identify.joint_fit import joint_error_options

    sets = {"gravity_compliance": POINT_SETS, "joint_harmonics": HARMONIC_SETS}
    for key, allowed in sets.items():
        value = getattr(config, key)
        if value not in allowed and value != "auto":
            raise DataError(f"unknown {key} '{value}'; choose auto or one of {sorted(allowed)}")
    return joint_error_options(*(tuple(allowed) if getattr(config, key) == "auto" else (getattr(config, key),)
                                 for key, allowed in sets.items()))


def fit_with_selection(robot: RobotModel, data: Measurements, config: FitConfig, *, progress=None):
    """Identify the geometry and the joint-space terms the cross-validation supports.

    Returns ``(result, structure_cv)``. The cross-validation (folds of ``config.split``) runs
    when there is something to choose: several joint-space options (``auto``) or residual heads
    to judge later (``structure_cv`` carries the per-fold fits they learn on); otherwise
    ``structure_cv`` is ``None``. ``progress(text)`` is called before long steps.
    """
    from torchcal.identify.compliance import POINT_SETS
    from torchcal.identify.harmonics import HARMONIC_SETS
    from torchcal.identify.joint_fit import fit_joint_errors
    from torchcal.model_selection.structure import cross_validate_structures, structure_label

    if config.method not in IDENTIFIERS:
        raise DataError(f"unknown method '{config.method}'; choose one of {sorted(IDENTIFIERS)}")
    if config.residual != "none":
        from torchcal.residual_stage import head_names

        head_names(config.residual)  # an unknown head is refused before anything is fitted
    options = _structure_options(config)
    geometry = geometry_fitter(robot, config)
    structure = None
    gravity, harmonics = options[0]
    if len(options) > 1 or config.residual != "none":
        folds = make_config_folds(robot, data, config)
        structure = cross_validate_structures(robot, data, geometry, options, folds, progress=progress,
                                              harmonic_min_range_deg=config.harmonic_min_range_deg)
        gravity, harmonics = structure.chosen
    if progress is not None:
        progress("fitting the chosen structure on all poses")
    result = fit_joint_errors(robot, data, geometry(data), POINT_SETS[gravity], HARMONIC_SETS[harmonics],
                              config.harmonic_min_range_deg)
    if structure is not None and len(options) > 1:
        comparison = structure.comparison
        result.notes.append(f"structure chosen by {comparison.protocol}: "
                            + ", ".join(f"{r['name']} {r['cv_rms_mm']:.4f} mm" for r in comparison.rows)
                            + f" -> {structure_label(gravity, harmonics)} ({comparison.reason})")
    return result, structure


def fit(robot: RobotModel, data: Measurements, config: FitConfig, *, progress=None) -> CalibrationResult:
    """Geometric identification plus the joint-space errors chosen by cross-validation (:func:`fit_with_selection`)."""
    return fit_with_selection(robot, data, config, progress=progress)[0]


def cross_validate_stored_structure(stored: StoredModel, data: Measurements, config: FitConfig):
    """The structure of a model folder alone, cross-validated on ``config``'s folds (for its heads)."""
    from torchcal.identify.compliance import POINT_SETS
    from torchcal.model_selection.structure import cross_validate_structures

    terms = JointSpaceErrors.from_metadata(stored.metadata)
    points = tuple(terms.compliance.points) if terms.compliance is not None else ()
    gravity = next(name for name, members in POINT_SETS.items() if members == points)
    harmonics = "first" if terms.harmonics is not None else "none"
    folds = make_config_folds(stored.robot, data, config)
    return cross_validate_structures(stored.robot, data, geometry_fitter(stored.robot, config), [(gravity, harmonics)],
                                     folds, harmonic_min_range_deg=config.harmonic_min_range_deg)


def save_fit(folder: Path, robot: RobotModel, data: Measurements, result: CalibrationResult, extra: dict) -> Path:
    ident = result.identifiability
    meta = {
        "method": result.method,
        "data": {"file": data.source, "sha256": data.sha256, "n_poses": len(data)},
        "identifiability": {
            "rank": ident.rank,
            "condition_number": ident.condition_number,
            "observability_index": ident.observability_index,
            "base_set": ident.base_set,
            "not_identifiable": {k: [p for p, _ in v[:3]] for k, v in ident.dependent.items()},
            "weak": ident.weak,
        },
        "residual_sigma_mm": result.sigma_residual_m * 1e3,
        "solver": {"iterations": result.solve.iterations, "message": result.solve.message, "cost_history": result.solve.history},
        "notes": result.notes,
        **extra,
    }
    meta.update(JointSpaceErrors.of(result).to_metadata())
    folder = Path(folder)
    # a new fit invalidates what an earlier fit into this folder learned on top of its geometry
    for stale in ("residual.safetensors", "residual.json", "model_selection.json"):
        (folder / stale).unlink(missing_ok=True)
    return save_model(folder, robot, result.model, result.x, result.free, result.covariance, meta, training_q=data.q)


def model_joints(stored: StoredModel, q: torch.Tensor) -> torch.Tensor:
    """Joints (rad) to put through the geometric chain: ``q`` plus every stored joint-space error."""
    return JointSpaceErrors.from_metadata(stored.metadata).effective_joints(stored.robot, q)


def predict_positions(
    stored: StoredModel, q: torch.Tensor, temperature: torch.Tensor | None = None, wrench: torch.Tensor | None = None
) -> torch.Tensor:
    """Model prediction of TCP positions (instrument frame, m), compliance and residual head included.

    With a ``wrench`` ``(n, 6)`` (N, N m at the TCP, tool frame) and a stiffness stage in the
    model, the deflection it predicts is added (the loaded TCP).
    """
    p = stored.model.tcp_position(model_joints(stored, q), stored.x)
    if stored.residual is not None:
        p = p + stored.residual.predict_base_error(q, temperature) @ stored.model.T_reference[:3, :3].T.to(p)
    if wrench is not None and stored.stiffness is not None:
        from torchcal.stiffness.vjm import deflection

        compliance = stored.stiffness.compliance.to(p)  # type: ignore[attr-defined]
        p = p + deflection(stored.model, q, stored.x, compliance, wrench.to(p), wrench_frame="tool")[..., :3]
    return p


def held_out_errors(stored: StoredModel, data: Measurements, *, register: bool = False, residual: bool = True) -> torch.Tensor:
    """``measured - predicted`` (instrument frame, m) of a stored model on ``data``.

    ``register``: first re-fit only the rigid instrument frame (Kabsch, its exact least-squares
    optimum), for data measured with the instrument elsewhere. ``residual=False`` scores the
    model without its learned head.
    """
    if residual:
        predicted = predict_positions(stored, data.q, data.temperature, data.wrench)
    else:
        predicted = stored.model.tcp_position(model_joints(stored, data.q), stored.x)
    return registered_errors(predicted, data.position) if register else data.position - predicted


def evaluate(model_dir: str | Path, data_path: str | Path, *, register: bool = False, config: FitConfig | None = None) -> dict:
    """Score a model folder on a measurement file (see the command-line contract)."""
    config = config or FitConfig()
    stored = load_model(model_dir)
    data = load_measurements(data_path, stored.robot, joint_unit=config.joint_unit, length_unit=config.length_unit)
    metrics = position_metrics(held_out_errors(stored, data, register=register))
    metrics.update({"model": str(model_dir), "data": str(data_path), "registered": register})
    if stored.training_q is not None:
        from torchcal.model_selection.leakage import leakage_report

        metrics["leakage"] = leakage_report(stored.robot, stored.training_q, data.q).to_dict()
    metrics["compensator"] = compensator_summary(stored, data.q)
    return metrics


def compensator_summary(stored: StoredModel, q: torch.Tensor) -> dict:
    """What the default exported compensator (position first) leaves at the joints ``q``, by the model's own account.

    For each pose its command is solved as the exported graph does (no load), and the graph's
    ``residual`` output gives the remaining TCP position error and the tool's orientation
    deviation from the nominal target. Returns the share of poses solved to 1 um (mm and rad
    values below).
    """
    from torchcal.compensate.compensator import CompensatorGraph

    graph = CompensatorGraph.from_stored(stored)
    with torch.no_grad():
        _, residual = graph.solve(q.to(torch.float64))
    position_mm, turn = residual[:, 0] * 1e3, residual[:, 1]
    return {
        "task": graph.task,
        "iterations": graph.iterations,
        "solved_share": float((position_mm <= 1e-3).double().mean()),
        "unsolved_max_mm": float(position_mm.max()),
        "orientation_deviation_median_rad": float(turn.median()),
        "orientation_deviation_p99_rad": float(turn.quantile(0.99)),
        "orientation_deviation_max_rad": float(turn.max()),
    }


def projected_truth(twin: Twin, result: CalibrationResult, n: int = 2000) -> tuple[torch.Tensor, float]:
    """The twin's geometric truth expressed in the fitted base parameter set.

    The non-identifiable parameters are fixed at nominal in the fit, so the raw truth is not
    comparable parameter by parameter; the equivalent truth is the reduced model fitted to the
    true robot's noise-free geometric positions. Returns it and its RMS fit residual (m), which
    is ~0 when the dropped parameters are exactly absorbed.
    """
    gen = torch.Generator().manual_seed(12345)
    q = twin.robot.sample_joints(n, gen)
    clean = Measurements(q=q, position=twin.model.tcp_position(q, twin.x_true))
    problem = CalibrationProblem(result.model, clean, result.free)
    sol = LevenbergMarquardt(max_iterations=50).solve(problem, result.x)
    r = problem.residuals(sol.x)
    return sol.x, float(r.pow(2).mean().sqrt())


@dataclass
class RunConfig:
    """The main job: simulate the default twin, fit, evaluate on held-out poses, report, export."""

    name: str = "twin-default"
    out: str = "runs"
    twin: TwinConfig = field(default_factory=lambda: TwinConfig(gravity=True, gear=True, n_train=1500, n_test=600))
    fit: FitConfig = field(default_factory=FitConfig)
    export: bool = True
    export_dir: str = "exported_models"


def run(config: RunConfig, console=None) -> dict:
    """End to end on the twin; returns the summary also written to ``metrics.json``."""
    from rich.console import Console

    from torchcal.report.runreport import write_run_report

    console = console or Console()
    from torchcal.config import save_resolved_config

    folder = Path(config.out) / config.name
    started = time.perf_counter()
    save_resolved_config(folder / "config.yaml", config)
    with console.status("[bold]simulating the twin") as status:
        case = write_twin_case(folder / "case", config.twin)
        robot = load_robot(case["robot.yaml"])
        train = load_measurements(case["train.csv"], robot)
        test = load_measurements(case["test.csv"], robot)
        console.log(f"twin: {len(train)} training and {len(test)} test poses, noise floor {config.twin.noise_floor_rms_mm:.4f} mm RMS")
        status.update("[bold]identifying geometry")
        result, structure = fit_with_selection(robot, train, config.fit, progress=status.update)
        console.log(
            f"geometry: {len(result.free)} parameters identified by {result.method} in {result.solve.iterations} iterations; "
            f"residual sigma {result.sigma_residual_m * 1e6:.1f} um"
        )
        twin = Twin.create(config.twin)
        truth_x, truth_residual = projected_truth(twin, result)
        model_dir = folder / "model"
        save_fit(model_dir, robot, train, result, {"twin_truth_projection_rms_mm": truth_residual * 1e3})
        residual_summary = None
        if config.fit.residual != "none":
            status.update("[bold]learning the residual")
            from torchcal.residual_stage import fit_residual_stage

            residual_summary = fit_residual_stage(model_dir, train, config.fit, console=console, structure=structure)
        status.update("[bold]evaluating on held-out poses")
        stored = load_model(model_dir)
        err_nominal = nominal_errors(robot, test)
        err_geometric = test.position - stored.model.tcp_position(model_joints(stored, test.q), stored.x)
        stages = {"nominal (registered)": err_nominal, "geometric": err_geometric}
        if stored.residual is not None:
            stages["geometric + residual"] = test.position - predict_positions(stored, test.q, test.temperature)
        metrics = {stage: position_metrics(e) for stage, e in stages.items()}
    sigma = result.parameter_sigma()
    z = ((result.x - truth_x)[result.free] / sigma).abs()
    within = float((z <= 3.0).double().mean())
    summary = {
        "name": config.name,
        "noise_floor_rms_mm": config.twin.noise_floor_rms_mm,
        "test": metrics,
        "final_stage": list(metrics)[-1],
        "truth_check": {
            "identifiable_parameters": len(result.free),
            "fraction_within_3_sigma": within,
            "projection_residual_rms_mm": truth_residual * 1e3,
            "z_scores": {n: float(v) for n, v in zip(result.free_names, z.tolist())},
        },
        "identifiability": result.identifiability.summary(),
        "residual": residual_summary,
        "model": describe_structure(result) + (f" + {residual_summary['kept']} head"
                                               if residual_summary and residual_summary["kept"] else ""),
        "elapsed_s": None,
    }
    write_run_report(folder, robot, result, stages, summary, truth_x, console=console)
    atomic_write_json(model_dir / "metrics.json", {"held_out_data": test.source, "stages": metrics, "final_stage": summary["final_stage"]})
    if config.export:
        from torchcal.compensate.export import export_and_check

        export_dir = Path(config.export_dir) / config.name
        summary["export"] = export_and_check(model_dir, export_dir, test, console=console, true_positions=twin.true_positions)
        _log_compensation_on_twin(summary["export"]["compensation_on_true_robot"], console)
    summary["elapsed_s"] = time.perf_counter() - started
    atomic_write_json(folder / "metrics.json", summary)
    return summary


def _log_compensation_on_twin(result: dict, console) -> None:
    """One line on the exported compensator's commands sent to the true twin, one on the poses it left unsolved."""
    console.log(
        "compensated on the true twin ({n} test poses, RMS): uncompensated {u:.4f} mm, torch {t:.4f} mm, "
        "onnxruntime float64 {o:.4f} mm ({r64:.4f}x torch), float32 {o32:.4f} mm ({r32:.4f}x)".format(
            n=result["n_poses"], u=result["uncompensated"]["position_rms_mm"], t=result["torch"]["position_rms_mm"],
            o=result["onnx_float64"]["position_rms_mm"], r64=result["onnx_float64_over_torch"],
            o32=result["onnx_float32"]["position_rms_mm"], r32=result["onnx_float32_over_torch"])
    )
    if result["torch_on_unsolved"] is not None and result["torch_on_solved"] is not None:
        console.log(
            f"  {100 * result['solved_share']:.1f} % of the test poses solved to 1 um: RMS {result['torch_on_solved']['position_rms_mm']:.4f} mm "
            f"there; the rest lie near a singularity (RMS {result['torch_on_unsolved']['position_rms_mm']:.4f} mm, partial correction)"
        )


def simulate(out: str | Path, config: TwinConfig) -> dict[str, Path]:
    return write_twin_case(out, config)
