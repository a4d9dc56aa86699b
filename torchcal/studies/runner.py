"""Run a study: workers ask for trials until the budget is met, then the best trial is refitted.

The budget counts finished trials (complete or pruned) plus those running or queued, over every
worker on every machine, so two workers never overshoot by more than the trials they start at the
same instant. A worker started again after a crash resumes: finished trials are kept, the killed
trial (its heartbeat stale) is failed and queued again with the same parameters.
"""

from __future__ import annotations

import multiprocessing
import os
from dataclasses import dataclass
from pathlib import Path

from torchcal.core.errors import TorchcalError
from torchcal.studies.spec import StudyConfig

MAX_CONSECUTIVE_FAILURES = 3


def study_folder(base, study: StudyConfig) -> Path:
    return Path(base.out) / "studies" / study.name


def _counts(study) -> dict[str, int]:
    from optuna.trial import TrialState

    counts = {state.name: 0 for state in TrialState}
    for trial in study.get_trials(deepcopy=False):
        counts[trial.state.name] += 1
    return counts


def _budget_used(study) -> int:
    c = _counts(study)
    return c["COMPLETE"] + c["PRUNED"] + c["RUNNING"] + c["WAITING"]


def _enqueue_default(study, base, config: StudyConfig) -> None:
    """Queue the run configuration's own values as the first trial, so the study compares with it
    (only when they lie inside the search space)."""
    from torchcal.studies.spec import search_space

    if study.get_trials(deepcopy=False):
        return
    params = {}
    for dist in search_space(config):
        node = base
        for part in dist.key.split("."):
            node = getattr(node, part, None)
        if not dist.contains(node):
            return
        params[dist.key] = node
    study.enqueue_trial(params, user_attrs={"default_configuration": True}, skip_if_exists=True)


def work(base, config: StudyConfig, study_dir: str, threads: int = 1, worker: int = 0) -> int:
    """One worker: run trials of the shared study until its budget is met; returns trials run."""
    import optuna
    import torch

    from torchcal.studies.objective import StudyObjective
    from torchcal.studies.storage import open_study

    torch.set_num_threads(max(1, threads))
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = open_study(config, Path(study_dir), worker)
    objective = StudyObjective(base, config, Path(study_dir))
    ran, failures = 0, 0
    while True:
        optuna.storages.fail_stale_trials(study)
        if _budget_used(study) >= config.n_trials:
            return ran
        before = _counts(study)["FAIL"]
        study.optimize(objective, n_trials=1, catch=(TorchcalError, RuntimeError, ValueError))
        ran += 1
        failures = failures + 1 if _counts(study)["FAIL"] > before else 0
        if failures >= MAX_CONSECUTIVE_FAILURES:
            raise TorchcalError(f"study '{config.name}': {failures} trials in a row failed; see the failed trials' messages")


def _run_waiting(base, config: StudyConfig, study, study_dir: Path, threads: int) -> None:
    from optuna.trial import TrialState

    from torchcal.studies.objective import StudyObjective

    objective = None
    while study.get_trials(deepcopy=False, states=(TrialState.WAITING,)) and _budget_used(study) <= config.n_trials:
        objective = objective or StudyObjective(base, config, study_dir)
        study.optimize(objective, n_trials=1, catch=(TorchcalError, RuntimeError, ValueError))


@dataclass
class StudyOutcome:
    """What a finished study produced."""

    study_dir: Path
    storage: str
    counts: dict[str, int]
    best_trial: int | None
    report: Path | None
    best_run: dict | None


def run_study(base, config: StudyConfig, *, workers: int = 1, console=None) -> StudyOutcome:
    """Create or resume the study, run ``workers`` local processes, refit the best, report."""
    from torchcal.config import save_resolved_config
    from torchcal.studies.report import write_study_report
    from torchcal.studies.storage import open_study, storage_url

    config.validate()
    study_dir = study_folder(base, config)
    study_dir.mkdir(parents=True, exist_ok=True)
    save_resolved_config(study_dir / "config.yaml", base, study=config)
    study = open_study(config, study_dir)
    _enqueue_default(study, base, config)
    if console is not None:
        done = _counts(study)
        console.log(f"study '{config.name}' at {storage_url(config, study_dir).split('@')[-1]}: "
                    f"{done['COMPLETE'] + done['PRUNED']} of {config.n_trials} trials finished; {workers} worker(s)")
    threads = max(1, (os.cpu_count() or 1) // max(1, workers))
    if workers > 1 and storage_url(config, study_dir).startswith("sqlite"):
        # SQLite has no row locks: two processes could both take the same queued trial (the
        # default configuration, a retry). Queued trials run here first; workers then only ask
        # for new ones, which the storage numbers atomically.
        _run_waiting(base, config, study, study_dir, threads)
    if workers <= 1:
        _with_progress(lambda: work(base, config, str(study_dir), threads), study, config, console)
    else:
        ctx = multiprocessing.get_context("spawn")
        procs = [ctx.Process(target=work, args=(base, config, str(study_dir), threads, k)) for k in range(workers)]
        for p in procs:
            p.start()
        def join_all() -> None:
            for p in procs:
                p.join()

        _with_progress(join_all, study, config, console)
        bad = [p.exitcode for p in procs if p.exitcode != 0]
        if bad:
            raise TorchcalError(f"study '{config.name}': {len(bad)} worker(s) exited with status {bad}")
    counts = _counts(study)
    unfinished = counts["RUNNING"] + counts["WAITING"]
    if unfinished and console is not None:
        console.log(f"{unfinished} trial(s) still running elsewhere or killed less than {config.grace_period_s} s ago; "
                    "run the study again later to finish them")
    best_run = None
    best_number = _best_number(study)
    if config.refit_best and best_number is not None and len(config.objectives) == 1:
        best_run = refit_best(base, config, study, study_dir, console=console)
    report = write_study_report(study, config, study_dir, best_run=best_run)
    return StudyOutcome(study_dir, storage_url(config, study_dir), counts, best_number, report, best_run)


def _best_number(study) -> int | None:
    from optuna.trial import TrialState

    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    if not complete:
        return None
    if len(study.directions) > 1:
        return None
    return study.best_trial.number


def refit_best(base, config: StudyConfig, study, study_dir: Path, console=None) -> dict:
    """Refit the best trial as a full run (report, held-out test, export) under the study folder."""
    from torchcal.app.pipeline import run
    from torchcal.studies.objective import apply_values

    best = study.best_trial
    run_config = apply_values(base, dict(best.params))
    if config.train is not None:
        return _refit_best_on_files(run_config, config, best, study_dir, console)
    run_config.out = str(study_dir)
    run_config.name = "best"
    run_config.export_dir = str(Path(base.export_dir) / "studies" / config.name)
    summary = run(run_config, console=console)
    return {"trial": best.number, "params": dict(best.params), "run_folder": str(study_dir / "best"),
            "test": summary["test"], "final_stage": summary["final_stage"], "export": summary.get("export")}


def _refit_best_on_files(run_config, config: StudyConfig, best, study_dir: Path, console=None) -> dict:
    """The best trial on measured data: ``fit`` (geometry, gated residual), model folder, export."""
    from torchcal.compensate.export import export_model
    from torchcal.config import save_resolved_config
    from torchcal.data.measurements import load_measurements
    from torchcal.instruments.tracker.evaluate import evaluate
    from torchcal.kinematics.robot import load_robot
    from torchcal.stages.geometry import fit_with_selection, save_fit, with_tool
    from torchcal.stages.residual import fit_residual_stage

    fit_config = run_config.fit
    units = {"joint_unit": fit_config.joint_unit, "length_unit": fit_config.length_unit}
    assert config.robot is not None and config.train is not None  # called with measured data; validated together
    robot = with_tool(load_robot(config.robot), fit_config)
    train = load_measurements(config.train, robot, **units)
    result, structure = fit_with_selection(robot, train, fit_config)
    folder = save_fit(study_dir / "best" / "model", robot, train, result, {})
    save_resolved_config(folder / "config.yaml", fit_config)
    residual = fit_residual_stage(folder, train, fit_config, progress=console.log if console is not None else None, structure=structure) if fit_config.residual != "none" else None
    out = {"trial": best.number, "params": dict(best.params), "run_folder": str(folder), "residual": residual}
    if config.test:
        metrics = evaluate(folder, config.test, config=fit_config)
        out.update({"test": {"model": metrics}, "final_stage": "model"})
    if run_config.export:
        manifest = export_model(folder, Path(run_config.export_dir) / "studies" / config.name / "best")
        out["export"] = manifest["files"]
    return out


def _with_progress(job, study, config: StudyConfig, console) -> None:
    """Run ``job`` (blocking) while a progress bar follows the study's finished trials."""
    import threading

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    if console is None:
        job()
        return
    stop = threading.Event()
    with Progress(TextColumn(f"study {config.name}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=True) as progress:
        task = progress.add_task("trials", total=config.n_trials)

        def follow() -> None:
            while not stop.wait(1.0):
                try:
                    c = _counts(study)
                    progress.update(task, completed=c["COMPLETE"] + c["PRUNED"])
                except Exception:  # noqa: BLE001 (the storage may be locked for a moment; the next poll catches up)
                    pass

        watcher = threading.Thread(target=follow, daemon=True)
        watcher.start()
        try:
            job()
        finally:
            stop.set()
            watcher.join()
