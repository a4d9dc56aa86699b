"""The main job, ``torchcal run``: the tracker twin end to end (fit, held-out evaluation, report, export).

The CLI and the studies reach it as ``registry.default().run``; callable from Python and tests.
"""

from __future__ import annotations

import json
import time
from contextlib import ExitStack
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from torchcal.compensate.export import export_and_check
from torchcal.config import save_resolved_config
from torchcal.config.schema import RunConfig
from torchcal.config.workers import start_fit_workers
from torchcal.core.folder import (
    FolderError,
    check_output_folder,
    deferred_folder,
    overlapping,
    refuse_foreign_entries,
    staged_folder,
    write_member_json,
)
from torchcal.core.io import atomic_write_json
from torchcal.core.metrics import position_metrics
from torchcal.core.outputs import check_name
from torchcal.core.threads import fit_threads
from torchcal.core.workers import (
    import_in_workers,
    import_while_waiting,
    in_background,
    resolve_jobs,
)
from torchcal.data.measurements import Measurements, load_measurements
from torchcal.identify.calibrate import CalibrationResult
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.problem import CalibrationProblem
from torchcal.instruments.base import EvaluateRequest
from torchcal.instruments.registry import default
from torchcal.instruments.tracker.report import (
    REPORT_MODULES,
    ReportInputs,
    calibration_report,
    cross_validated_stage,
    model_name,
    score_pose_set,
)
from torchcal.instruments.tracker.twin_case import write_twin_case
from torchcal.kinematics.robot import load_robot
from torchcal.report.document import write_report
from torchcal.sim.twin import Twin
from torchcal.stages.geometry import NOMINAL_PROTOCOL, held_out_errors, nominal_errors
from torchcal.stages.pipeline import fit_model
from torchcal.stages.store import load_model


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


#: What the export imports on first use: the worker that exports imports it ahead (core.workers.warm_up).
EXPORT_MODULES = ("torchcal.compensate.export", "onnx", "onnxruntime", "torch.onnx")


def run(config: RunConfig, console=None) -> dict:
    """End to end on the twin; returns the summary also written to ``metrics.json``.

    Every step runs on :data:`~torchcal.core.threads.FIT_THREADS` torch threads (small solves,
    :mod:`torchcal.core.threads`).
    """
    with fit_threads():
        return _run(config, console)


#: What a run folder holds (``.torchcal-output`` aside): anything else is the user's, and a rerun is refused.
RUN_ENTRIES = ("case", "config.yaml", "figures", "metrics.json", "model", "report.html", "report.md")


def _run(config: RunConfig, console=None) -> dict:
    from rich.console import Console

    console = console or Console()
    final = Path(config.out) / check_name(config.name, "name=")
    within = ("study",)  # a study refits its best run inside its own folder
    exported = Path(config.export_dir) / config.name
    if config.export:
        if overlapping(final, exported):  # one would replace or swallow the other
            raise FolderError(f"{exported}: export_dir/name and out/name ({final}) are the same folder or one lies in the "
                              "other; give them separate places")
        check_output_folder(exported, "export_dir/name", purpose="export")
    elif (exported / "manifest.json").is_file():
        import warnings

        warnings.warn(f"{exported} holds the export of an earlier run of this name; this run (export=false) does not "
                      "replace it, so it no longer matches the run's model", stacklevel=2)
    refuse_foreign_entries(final, RUN_ENTRIES, sealed=("model",))
    # the run is built in a staging sibling and swapped in whole, and its export is moved into place only
    # after it: an interrupted run leaves the earlier run and the earlier export, a matching pair
    with ExitStack() as stack:
        pending, commit = (stack.enter_context(deferred_folder(exported, "export_dir/name", purpose="export"))
                           if config.export else (None, None))
        with staged_folder(final, "name=", purpose="run", sealed=False, within=within) as folder:
            summary = _run_into(folder, final, config, console, pending, exported)
        if commit is not None:
            commit()
        return summary


def _run_into(folder: Path, destination: Path, config: RunConfig, console, export_into: Path | None = None,
              exported_at: Path | None = None) -> dict:
    """The run's steps, writing into ``folder`` (staging); recorded paths name ``destination``, where it will be.

    ``export_into``: where the export is written (a pending folder, moved to ``exported_at`` after the run)."""
    started = time.perf_counter()
    save_resolved_config(folder / "config.yaml", config)
    start_fit_workers(config.fit)  # they start while the twin is simulated (kept where the CLI started them)
    import_while_waiting(*REPORT_MODULES)
    with console.status("[bold]simulating the twin") as status:
        case = write_twin_case(folder / "case", config.twin)
        robot = load_robot(case["robot.yaml"])
        train = replace(load_measurements(case["train.csv"], robot), source=str(destination / "case" / "train.csv"))
        test = replace(load_measurements(case["test.csv"], robot), source=str(destination / "case" / "test.csv"))
        console.log(f"twin: {len(train)} training and {len(test)} test poses, noise floor {config.twin.noise_floor_rms_mm:.4f} mm RMS")
        status.update("[bold]identifying geometry")
        twin = Twin.create(config.twin)
        truth: dict = {}

        def truth_projection(result: CalibrationResult) -> dict:
            console.log(
                f"geometry: {len(result.free)} parameters identified by {result.method} in {result.solve.iterations} "
                f"iterations; residual sigma {result.sigma_residual_m * 1e6:.1f} um"
            )
            truth["x"], truth["residual"] = projected_truth(twin, result)
            return {"twin_truth_projection_rms_mm": truth["residual"] * 1e3}

        model_dir = folder / "model"
        fitted = fit_model(model_dir, robot, train, config.fit, metadata=truth_projection, progress=status.update,
                           residual_progress=console.log)
        result, structure = fitted.result, fitted.structure
        truth_x, truth_residual = truth["x"], truth["residual"]
        if fitted.residual is not None:
            console.print(fitted.residual.table)
            console.log(fitted.residual.decision)
        if config.export:
            import_in_workers(EXPORT_MODULES)  # imported there while the held-out poses are scored
        status.update("[bold]evaluating on held-out poses")
        stored = load_model(model_dir)
        stages = {"nominal": nominal_errors(robot, test), "geometric": held_out_errors(stored, test, residual=False)}
        if stored.residual is not None:
            stages["geometric + residual"] = held_out_errors(stored, test)
        metrics = {stage: position_metrics(e) for stage, e in stages.items()}
    sigma = result.parameter_sigma()
    z = ((result.x - truth_x)[result.free] / sigma).abs()
    within = float((z <= 3.0).double().mean())
    summary: dict[str, Any] = {
        "name": config.name,
        "noise_floor_rms_mm": config.twin.noise_floor_rms_mm,
        "test": metrics,
        "final_stage": list(metrics)[-1],
        "nominal_protocol": NOMINAL_PROTOCOL,
        "truth_check": {
            "identifiable_parameters": len(result.free),
            "fraction_within_3_sigma": within,
            "projection_residual_rms_mm": truth_residual * 1e3,
            "z_scores": {n: float(v) for n, v in zip(result.free_names, z.tolist())},
        },
        "identifiability": result.identifiability.summary(),
        "residual": fitted.residual.to_dict() if fitted.residual is not None else None,
        "model": model_name(stored),
        "elapsed_s": None,
    }
    write_member_json(model_dir, "metrics.json", {"held_out_data": test.source, "stages": metrics, "final_stage": summary["final_stage"]})
    joint_truth = twin.gear_deviation if config.twin.gear else None
    if config.export:
        # the export and its checks in a worker while the report's figures are drawn here (core.workers)
        with in_background(export_and_check, model_dir, export_into, test,
                           twin.true_tcp_positions, jobs=resolve_jobs(config.fit.jobs)) as pending:

            def exported() -> dict:
                if "export" not in summary:
                    # written into a pending folder that moves to export_dir/name after the run: named as it will be
                    result = pending.result()
                    for key in ("out_dir", "summary"):
                        result[key] = result[key].replace(str(export_into), str(exported_at))
                    summary["export"] = result
                    console.log(summary["export"]["summary"])
                    if summary["export"].get("turned_tool_warning"):
                        console.log(f"warning: {summary['export']['turned_tool_warning']}")
                    _log_compensation_on_twin(summary["export"]["compensation_on_true_robot"], console)
                return summary["export"]

            report = _write_report(folder, stored, train, test, structure, summary, truth_x, case["test.csv"],
                                   joint_truth=joint_truth, exported=exported, jobs=resolve_jobs(config.fit.jobs))
            exported()
    else:
        report = _write_report(folder, stored, train, test, structure, summary, truth_x, case["test.csv"],
                               joint_truth=joint_truth)
    final = summary["test"][summary["final_stage"]]
    # the model as chosen (structure and head), not the stage key: "geometric" also holds joint-space terms
    console.log(f"report: {destination / report.relative_to(folder)}; final held-out RMS {final['position_rms_mm']:.4f} mm ({summary['model']})")
    summary["elapsed_s"] = time.perf_counter() - started
    atomic_write_json(folder / "metrics.json", summary)
    return summary


def _write_report(folder: Path, stored, train: Measurements, test: Measurements, structure, summary: dict,
                  truth_x: torch.Tensor, test_file: Path, joint_truth=None, exported=None, jobs: int = 1) -> Path:
    """The run's report (the one report builder of ``fit`` and ``evaluate``): training and held-out file, truth.

    ``exported()``: the export's summary, asked for only when the report reaches the compensator.
    ``jobs``: processes that draw the figures (a worker exporting meanwhile takes its first figure
    when the export is done, :func:`~torchcal.core.workers.side_by_side`).
    """
    cv = cross_validated_stage(stored, structure)
    extra = [cv] if cv is not None else []
    pose_sets = [score_pose_set(stored, train, held_out=False, extra=extra, focus_extra=bool(extra)),
                 score_pose_set(stored, test, held_out=True)]
    # the held-out file scored as `torchcal evaluate` scores it: leakage, uncertainty, compensator
    scored = default().evaluate(EvaluateRequest(model=stored.folder, data=Path(test_file)))
    floor = summary["noise_floor_rms_mm"]
    final = summary["test"][summary["final_stage"]]["position_rms_mm"]
    ratio = final / floor
    context = [f"The twin's measurement noise floor is {floor:.4f} mm RMS: the model leaves {final:.4f} mm on the "
               f"held-out poses, {ratio:.2f}x the floor"
               + (": what is above it is what the model cannot express." if ratio > 1.2 else ": nothing systematic is left.")]
    tc = summary["truth_check"]
    truth_note = (f"{tc['fraction_within_3_sigma'] * 100:.1f} % of the {tc['identifiable_parameters']} identified parameters "
                  f"lie within 3 sigma of the twin's truth (projected onto the identified set; projection residual "
                  f"{tc['projection_residual_rms_mm']:.2e} mm).")
    inputs = ReportInputs(selection=_selection(stored.folder), compensator=scored.metrics["compensator"],
                          uncertainty=scored.metrics.get("uncertainty"), leakage=scored.metrics.get("leakage"),
                          compensation_on_truth=(lambda: exported()["compensation_on_true_robot"]) if exported else None,
                          truth_x=truth_x, truth_note=truth_note, joint_truth=joint_truth, context=context)
    report = calibration_report(f"torchcal report: {stored.robot.name} ({summary['name']})", stored, pose_sets, inputs,
                                jobs=jobs)
    return write_report(folder, report)["report.md"]


def _selection(model_dir: Path) -> dict | None:
    path = Path(model_dir) / "model_selection.json"
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None


def _log_compensation_on_twin(result: dict, console, tcp: str = "the flange") -> None:
    """One line on the exported compensator's commands sent to the true twin, one on the poses it left unsolved."""
    console.log(
        "compensated on the true twin at the exported TCP ({tcp}; {n} test poses, RMS): uncompensated {u:.4f} mm, "
        "torch {t:.4f} mm (the model's own error there {m:.4f} mm), "
        "onnxruntime float64 {o:.4f} mm ({r64:.4f}x torch), float32 {o32:.4f} mm ({r32:.4f}x)".format(
            tcp=tcp, m=result["model_own_error"]["position_rms_mm"],
            n=result["n_poses"], u=result["uncompensated"]["position_rms_mm"], t=result["torch"]["position_rms_mm"],
            o=result["onnx_float64"]["position_rms_mm"], r64=result["onnx_float64_over_torch"],
            o32=result["onnx_float32"]["position_rms_mm"], r32=result["onnx_float32_over_torch"])
    )
    if result["torch_on_unsolved"] is not None and result["torch_on_solved"] is not None:
        console.log(
            f"  {100 * result['solved_share']:.1f} % of the test poses solved to 1 um: RMS {result['torch_on_solved']['position_rms_mm']:.4f} mm "
            f"there; the rest lie near a singularity (RMS {result['torch_on_unsolved']['position_rms_mm']:.4f} mm, partial correction)"
        )

