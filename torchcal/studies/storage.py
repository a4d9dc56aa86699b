"""Where a study lives: SQLite in its folder by default, any RDB URL for workers on many machines.

Heartbeats make a study survive a killed worker: every running trial records a heartbeat each
``heartbeat_interval_s``; before a worker asks for a new trial, Optuna fails any running trial
whose heartbeat is older than ``grace_period_s`` and the retry callback queues it again with the
same parameters. Finished trials are rows in the database and are never touched again.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from torchcal.core.errors import TorchcalError
from torchcal.studies.spec import StudyConfig

CREATE_ATTEMPTS = 5


def storage_url(config: StudyConfig, study_dir: Path) -> str:
    """The study's storage URL: the configured one, or ``sqlite:///<study_dir>/study.db``."""
    if config.storage:
        return config.storage
    return f"sqlite:///{(study_dir / 'study.db').resolve()}"


def open_storage(config: StudyConfig, study_dir: Path):
    """An Optuna RDB storage with heartbeats and retry of stale trials."""
    import warnings

    import optuna
    from sqlalchemy.exc import IntegrityError, ProgrammingError, SQLAlchemyError

    # Heartbeats are the documented way to recover killed trials; their "experimental" notice is noise.
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    url = storage_url(config, study_dir)
    if url.startswith("sqlite"):
        study_dir.mkdir(parents=True, exist_ok=True)
        # Several local workers share the file; wait for its lock instead of failing at once.
        engine_kwargs: dict[str, Any] = {"connect_args": {"timeout": 60}}
    else:
        engine_kwargs = {"pool_pre_ping": True}
    # Workers on several machines may start together on an empty database: all of them try to
    # create Optuna's tables and all but one fail on the catalog's unique index. The tables then
    # exist, so opening again succeeds.
    error: Exception
    for attempt in range(CREATE_ATTEMPTS):
        try:
            return optuna.storages.RDBStorage(
                url,
                engine_kwargs=engine_kwargs,
                heartbeat_interval=config.heartbeat_interval_s,
                grace_period=config.grace_period_s,
                heartbeat_stale_trial_callback=optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=config.max_retry),
            )
        except (IntegrityError, ProgrammingError) as exc:
            if attempt == CREATE_ATTEMPTS - 1:
                error = exc
                break
            time.sleep(0.5 * (attempt + 1))
        except (SQLAlchemyError, ImportError, ValueError) as exc:
            error = exc
            break
    shown = url.split("@")[-1] if "@" in url else url
    raise TorchcalError(f"cannot open study storage '{shown}': {str(error).splitlines()[0]}") from None


def sampler_seed(config: StudyConfig, study_dir: Path, worker: int = 0) -> int:
    """The seed of one worker's sampler.

    Workers with the same seed would propose the same parameters one after the other, so local
    worker ``k`` uses ``seed + k``. Processes on several machines sharing a database server cannot
    be told apart by an index, and their trial order is not reproducible anyway: their seed also
    takes the process id.
    """
    import os

    seed = config.seed + worker
    if not storage_url(config, study_dir).startswith("sqlite"):
        seed += 7919 * os.getpid()
    return seed % (2**31)


def open_study(config: StudyConfig, study_dir: Path, worker: int = 0):
    """Create the study or load it when it exists (this is what makes a restart resume)."""
    import optuna

    storage = open_storage(config, study_dir)
    seed = sampler_seed(config, study_dir, worker)
    sampler: optuna.samplers.BaseSampler
    if config.sampler == "tpe":
        sampler = optuna.samplers.TPESampler(seed=seed, n_startup_trials=min(8, max(2, config.n_trials // 3)))
    else:
        sampler = optuna.samplers.RandomSampler(seed=seed)
    pruner = (
        optuna.pruners.MedianPruner(n_startup_trials=3, n_warmup_steps=config.pruner_warmup_steps)
        if config.pruner == "median" and len(config.objectives) == 1
        else optuna.pruners.NopPruner()
    )
    try:
        return optuna.create_study(
            storage=storage,
            study_name=config.name,
            sampler=sampler,
            pruner=pruner,
            directions=config.directions,
            load_if_exists=True,
        )
    except ValueError as exc:  # e.g. an existing study with other directions
        raise TorchcalError(f"study '{config.name}': {exc}") from None
