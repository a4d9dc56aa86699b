"""Run a study: local workers take trials until the budget is met, then the best trial is refitted.

The budget is ``n_trials`` finished trials (complete or pruned) as the database counts them, over
every worker on every machine and every restart (:mod:`torchcal.studies.worker`). A killed trial is
failed once its heartbeat is stale, queued again and run by whichever worker is alive. The outcome
carries the counts of every state as the database has them, so the command's last line can say
when a study ends short of its budget.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from torchcal.compensate.export import export_model
from torchcal.config import save_resolved_config
from torchcal.core.errors import TorchcalError
from torchcal.core.folder import check_output_folder, overlapping
from torchcal.core.hashing import sha256_file
from torchcal.core.outputs import claim_folder, stamp_folder
from torchcal.core.shutdown import skip_collection_at_exit
from torchcal.data.measurements import load_measurements
from torchcal.instruments.base import EvaluateRequest
from torchcal.instruments.registry import default
from torchcal.kinematics.robot import load_robot
from torchcal.stages.geometry import with_tool
from torchcal.stages.pipeline import fit_model
from torchcal.studies.lock import StudyLock
from torchcal.studies.objective import (
    INTERRUPTED,
    RETRY_OF_INTERRUPTED,
    apply_values,
    check_case,
)
from torchcal.studies.report import write_study_report
from torchcal.studies.spec import StudyConfig, check_space, search_space
from torchcal.studies.storage import check_storage, open_study, shown_url, storage_url
from torchcal.studies.worker import counts as _counts
from torchcal.studies.worker import finished, work

#: Local worker processes one command starts at most: each is a process with its own copy of the
#: data and its own database connection, and more than the machine's cores only queue for them.
MAX_WORKERS = max(4, os.cpu_count() or 1)
#: Fit options that change how a trial runs, never its numbers (left out of the study's fingerprint).
UNSCORED_FIT_OPTIONS = ("progress", "jobs", "device")  # how a trial runs, not what it scores


def study_folder(base, study: StudyConfig) -> Path:
    return Path(base.out) / "studies" / study.name


def _enqueue_default(study, base, config: StudyConfig) -> None:
    """Queue the run configuration's own values as the first trial, so the study compares with it
    (only when they lie inside the search space, and only in a new study)."""
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


def _worker_process(base, config: StudyConfig, study_dir: str, threads: int) -> None:
    """A local worker process: a user-facing error is one line on stderr and exit status 1."""
    skip_collection_at_exit()
    try:
        work(base, config, study_dir, threads)
    except TorchcalError as exc:
        print(f"torchcal: error: {exc}", file=sys.stderr)
        sys.exit(1)


@dataclass
class StudyOutcome:
    """What a finished study produced; ``counts`` are the database's trials per state at the end."""

    study_dir: Path
    storage: str
    counts: dict[str, int]
    n_trials: int
    best_trial: int | None
    report: Path | None
    best_run: dict | None

    @property
    def short_by(self) -> int:
        """Finished trials still missing from the budget (0 when it is met)."""
        return max(0, self.n_trials - finished(self.counts))

    def summary(self, name: str) -> str:
        """One line: the trials per state as the database has them, and a warning when short."""
        c = self.counts
        line = (f"study {name}: {finished(c)} of {self.n_trials} trials finished ({c['COMPLETE']} complete, "
                f"{c['PRUNED']} pruned); {c['FAIL']} failed, {c['RUNNING']} running, {c['WAITING']} waiting in the "
                f"database; best trial {self.best_trial}; report {self.report}")
        if self.short_by:
            line += (f"; WARNING: {self.short_by} trial(s) short of the budget: run the same command again to "
                     "finish the study")
        return line


def _check_same_space(study, config: StudyConfig) -> None:
    """Refuse to resume a study under the same name with another search space or objectives (its
    trials would mix two questions); a new study records its own, in the storage, so every machine sees it."""
    space = json.dumps({"search_space": config.search_space, "objectives": list(config.objectives)},
                       sort_keys=True, default=str)
    stored = study.user_attrs.get("search_space")
    if stored is None:
        study.set_user_attr("search_space", space)
    elif stored != space:
        raise TorchcalError(f"study '{config.name}' already exists with another search space or objectives "
                            f"({stored[:120]}...); give another study.name, or the same study=... as before")


def fingerprint(base, config: StudyConfig) -> dict[str, Any]:
    """What the study's trials are scored on, besides their searched values: the twin's settings
    (or the SHA-256 of the measured data files) and the fit options the search space leaves fixed."""
    searched = set(config.search_space)
    out: dict[str, Any] = {}
    if config.train is None:
        out.update({f"twin.{k}": v for k, v in asdict(base.twin).items() if f"twin.{k}" not in searched})
    else:
        for name in ("robot", "train", "test", "holdout"):
            path = getattr(config, name)
            out[f"study.{name}"] = f"sha256:{sha256_file(path)}" if path is not None else None
        out["study.holdout_register"] = config.holdout_register
    out.update({f"fit.{k}": v for k, v in asdict(base.fit).items()
                if f"fit.{k}" not in searched and k not in UNSCORED_FIT_OPTIONS})
    return json.loads(json.dumps(out, default=str))


def _check_same_data(study, base, config: StudyConfig) -> None:
    """Refuse to resume a study whose trials were scored on other data or other fixed options (its
    trials would no longer compare); a new study records its fingerprint, and its cached twin cases
    are checked against the checksums its trials recorded."""
    mine = fingerprint(base, config)
    stored = study.user_attrs.get("fingerprint")
    if stored is None:
        study.set_user_attr("fingerprint", mine)
    else:
        changed = []
        # an option a later torchcal added is absent from an older study's record: at its default it
        # changes nothing the trials were scored on
        defaults = json.loads(json.dumps({**{f"fit.{k}": v for k, v in asdict(type(base.fit)()).items()},
                                          **{f"twin.{k}": v for k, v in asdict(type(base.twin)()).items()}}, default=str))
        for key in sorted(set(stored) | set(mine)):
            before, now = stored.get(key, "(unset)"), mine.get(key, "(unset)")
            if key not in stored and key in defaults and now == defaults[key]:
                continue
            if before != now:
                changed.append(f"{key} (file content differs)" if str(before).startswith("sha256:")
                               and str(now).startswith("sha256:") else f"{key}: {before} -> {now}")
        if changed:
            shown = "; ".join(changed[:4]) + (f"; and {len(changed) - 4} more" if len(changed) > 4 else "")
            raise TorchcalError(f"study '{config.name}' already exists with trials scored on other data or options "
                                f"({shown}); give another study.name, or the same data and options as before")
    cases = study_folder(base, config) / "cases"
    if cases.is_dir():
        for folder in sorted(p for p in cases.iterdir() if p.is_dir() and not p.name.startswith(".")):
            if f"case:{folder.name}" in study.user_attrs:
                check_case(study, folder)


def requeue_interrupted(study, max_retry: int = 1) -> list[int]:
    """Queue again, once, the parameters of trials a Ctrl-C (SIGINT) stopped (failed with the
    ``interrupted`` user attr), as the heartbeat queues a killed trial: the default configuration
    among them is then still compared. A chain of retries stops after ``max_retry`` (a trial the user
    stops again and again, because it hangs, does not come back on every resume). Returns the
    numbers queued again."""
    from optuna.trial import TrialState

    trials = study.get_trials(deepcopy=False)
    by_number = {t.number: t for t in trials}
    done = {t.user_attrs.get(RETRY_OF_INTERRUPTED) for t in trials}

    def retries(t) -> int:  # how many retries led to this trial
        n, origin = 0, t.user_attrs.get(RETRY_OF_INTERRUPTED)
        while origin is not None and origin in by_number and n <= max_retry:
            n, origin = n + 1, by_number[origin].user_attrs.get(RETRY_OF_INTERRUPTED)
        return n

    queued = []
    for t in trials:
        if t.state != TrialState.FAIL or not t.user_attrs.get(INTERRUPTED) or t.number in done:
            continue
        if retries(t) >= max_retry:
            continue
        params = {**t.system_attrs.get("fixed_params", {}), **t.params}
        attrs = {k: v for k, v in t.user_attrs.items() if k == "default_configuration"}
        study.enqueue_trial(params, user_attrs={**attrs, RETRY_OF_INTERRUPTED: t.number})
        queued.append(t.number)
    return queued


def _workers(workers: int, config: StudyConfig, finished_now: int | None, console) -> int:
    """``workers``, refused when below 1 or above ``MAX_WORKERS``, and capped at the trials left
    (``finished_now``: the trials already finished; ``None`` checks ``workers`` only)."""
    if workers < 1:
        raise TorchcalError(f"--workers must be at least 1, got {workers}")
    if workers > MAX_WORKERS:
        raise TorchcalError(f"--workers {workers}: at most {MAX_WORKERS} local workers (this machine's cores, at least "
                            "4): each is a process with its own data and database connection, and more only queue "
                            "for the cores; run more on other machines with a shared --storage")
    if finished_now is None:
        return workers
    left = max(1, config.n_trials - finished_now)
    if workers > left:
        if console is not None:
            console.log(f"study '{config.name}': {left} trial(s) left to run; starting {left} worker(s), not {workers} "
                        "(the others would only wait)")
        return left
    return workers


def run_study(base, config: StudyConfig, *, workers: int = 1, console=None) -> StudyOutcome:
    """Create or resume the study, run ``workers`` local processes, refit the best, report."""
    config.validate()
    _workers(workers, config, None, console)
    check_space(base, config)
    study_dir = study_folder(base, config)
    if config.refit_best and base.export:
        # the best refit's run (study folder / best) and export must not coincide: found now, not after every trial
        export_at = (Path(base.export_dir) / "studies" / config.name / "best").resolve()
        if overlapping(study_dir / "best", export_at):
            raise TorchcalError(f"export_dir ({base.export_dir}) puts the best refit's export at {export_at}, its run "
                                "folder: give export_dir another place than out")
        # a file or a foreign folder where the export goes is found now, not after the trials
        check_output_folder(export_at, "export_dir/studies/<study>/best", purpose="export")
    check_storage(storage_url(config, study_dir), configured=bool(config.storage))
    claim_folder(study_dir, "study", "study.name")
    study_dir.mkdir(parents=True, exist_ok=True)
    stamp_folder(study_dir, "study")
    study = open_study(config, study_dir, checked=True)  # check_storage ran above, before anything was created
    _check_same_space(study, config)
    _check_same_data(study, base, config)
    save_resolved_config(study_dir / "config.yaml", base, study=config)
    url = storage_url(config, study_dir)
    with StudyLock(url, config.name, study_dir):
        _enqueue_default(study, base, config)
        requeued = requeue_interrupted(study, config.max_retry)
    if requeued and console is not None:
        console.log(f"study '{config.name}': trial(s) {requeued} were stopped by an interrupt; their parameters are "
                    "queued again")
    workers = _workers(workers, config, finished(_counts(study)), console)
    if console is not None:
        done = _counts(study)
        console.log(f"study '{config.name}' at {shown_url(url)}: {finished(done)} of {config.n_trials} trials "
                    f"finished; {workers} worker(s)")
    threads = max(1, (os.cpu_count() or 1) // max(1, workers))
    if workers <= 1:
        _with_progress(lambda: work(base, config, str(study_dir), threads), study, config, console)
    else:
        ctx = multiprocessing.get_context("spawn")
        procs = [ctx.Process(target=_worker_process, args=(base, config, str(study_dir), threads)) for _ in range(workers)]
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
    best_run = None
    best_number = _best_number(study)
    if config.refit_best and best_number is not None and len(config.objectives) == 1:
        best_run = refit_best(base, config, study, study_dir, console=console)
    report = write_study_report(study, config, study_dir, best_run=best_run)
    return StudyOutcome(study_dir, url, counts, config.n_trials, best_number, report, best_run)


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
    best = study.best_trial
    run_config = apply_values(base, dict(best.params))
    if config.train is not None:
        return _refit_best_on_files(run_config, config, best, study_dir, console)
    run_config.out = str(study_dir)
    run_config.name = "best"
    run_config.export_dir = str(Path(base.export_dir) / "studies" / config.name)
    summary = default().run(run_config, console=console)
    return {"trial": best.number, "params": dict(best.params), "run_folder": str(study_dir / "best"),
            "test": summary["test"], "final_stage": summary["final_stage"], "export": summary.get("export")}


def _refit_best_on_files(run_config, config: StudyConfig, best, study_dir: Path, console=None) -> dict:
    """The best trial on measured data: ``fit`` (geometry, gated residual), model folder, export."""
    fit_config = run_config.fit
    units = {"joint_unit": fit_config.joint_unit, "length_unit": fit_config.length_unit}
    robot_file, train_file = config.measured()
    robot = with_tool(load_robot(robot_file), fit_config)
    train = load_measurements(train_file, robot, **units)
    fitted = fit_model(study_dir / "best" / "model", robot, train, fit_config,
                       residual_progress=console.log if console is not None else None)
    folder = fitted.folder
    residual = fitted.residual.to_dict() if fitted.residual is not None else None
    out = {"trial": best.number, "params": dict(best.params), "run_folder": str(folder), "residual": residual}
    units_overrides = [f"{k}={v}" for k, v in units.items()]

    def evaluate(data: str, register: bool = False) -> dict:
        # the file scored as `torchcal evaluate` scores it, through the instrument's protocol
        return default().evaluate(EvaluateRequest(model=folder, data=Path(data), overrides=units_overrides,
                                                  register=register)).metrics

    if config.test:
        out.update({"test": {"model": evaluate(config.test)}, "final_stage": "model"})
    if config.holdout:
        out["holdout"] = evaluate(config.holdout, register=config.holdout_register)
    if run_config.export:
        manifest = export_model(folder, Path(run_config.export_dir) / "studies" / config.name / "best")
        out["export"] = manifest["files"]
    return out


def _with_progress(job, study, config: StudyConfig, console) -> None:
    """Run ``job`` (blocking) while a progress bar follows the study's finished trials."""
    import contextlib
    import threading

    from optuna.exceptions import StorageInternalError
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from sqlalchemy.exc import SQLAlchemyError

    if console is None:
        job()
        return
    stop = threading.Event()
    with Progress(TextColumn(f"study {config.name}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=True) as progress:
        task = progress.add_task("trials", total=config.n_trials)

        def follow() -> None:
            while not stop.wait(1.0):
                # the storage may be locked or out of reach for a moment; the next poll catches up
                with contextlib.suppress(SQLAlchemyError, StorageInternalError, OSError):
                    progress.update(task, completed=finished(_counts(study)))

        watcher = threading.Thread(target=follow, daemon=True)
        watcher.start()
        try:
            job()
        finally:
            stop.set()
            watcher.join()
