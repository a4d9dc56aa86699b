"""Kill one of two workers of a shared study at a random moment, restart it at once; check the database.

Each repetition starts two ``torchcal study`` processes on one study in a database (as two machines
sharing a PostgreSQL server would), waits until a trial has finished, SIGKILLs one process group
after a random further delay, starts that command again at once, waits for both, and reads the
trials from the database. A repetition passes when the study holds exactly ``n_trials`` finished
trials, none WAITING or RUNNING, both commands exited 0, and no configuration was evaluated twice
(a trial that reuses a finished trial's result is marked ``repeat_of`` and is not counted).

    python scripts/study_fault_sweep.py --storage postgresql://postgres@127.0.0.1:55432/torchcal_test
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# the elm_mayfly parameters over a smaller range (quicker trials on a shared machine); a float
# margin makes an exact repeat of a configuration a sign of a repeated sampler stream, not chance
SMALL_SPACE = ("study.search_space={fit.residual_hidden: {type: int, low: 20, high: 60, step: 10}, "
               "fit.mayfly_population: {type: int, low: 6, high: 12, step: 2}, "
               "fit.residual_margin: {type: float, low: 0.03, high: 0.08}}")


def command(name: str, args) -> list[str]:
    return [sys.executable, "-m", "torchcal.cli", "study", "study=elm_mayfly", "measurement=twin_small",
            "experiment=quick", f"study.n_trials={args.n_trials}", f"study.name={name}", "study.refit_best=false",
            f"study.heartbeat_interval_s={args.heartbeat}", f"study.grace_period_s={args.grace}",
            f"fit.mayfly_iterations={args.iterations}", "--storage", args.storage] + ([] if args.full_space else [SMALL_SPACE])


def start(cmd: list[str], cwd: Path, log: Path) -> subprocess.Popen:
    env = {**os.environ, "TORCHCAL_CONFIG_DIR": str(REPO / "configs"), "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen(cmd, cwd=cwd, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT,
                            start_new_session=True)


_STORAGES: dict = {}


def trials(name: str, storage: str):
    """The study's trials now (one storage object per URL: opening one is not cheap)."""
    import optuna

    if storage not in _STORAGES:
        from torchcal.studies.spec import StudyConfig
        from torchcal.studies.storage import storage_url

        _STORAGES[storage] = optuna.storages.RDBStorage(storage_url(StudyConfig(storage=storage), Path(".")))
    try:
        return optuna.load_study(study_name=name, storage=_STORAGES[storage]).get_trials(deepcopy=False)
    except KeyError:
        return []


def repetition(i: int, args, rng: random.Random, root: Path) -> dict:
    from optuna.trial import TrialState

    from torchcal.studies.objective import same_configuration

    name = f"sweep-{uuid.uuid4().hex[:8]}"
    folders = [root / f"{name}-a", root / f"{name}-b"]
    for f in folders:
        f.mkdir(parents=True)
    began = time.monotonic()
    a = start(command(name, args), folders[0], folders[0] / "a.log")
    b = start(command(name, args), folders[1], folders[1] / "b.log")
    while not any(t.state.is_finished() for t in trials(name, args.storage)):
        if a.poll() is not None:
            break
        time.sleep(0.5)
    delay = rng.uniform(0.0, args.max_delay)
    time.sleep(delay)
    killed_running = [t.number for t in trials(name, args.storage) if t.state == TrialState.RUNNING
                      and t.user_attrs.get("worker_pid") == a.pid]
    alive = a.poll() is None
    if alive:
        os.killpg(a.pid, signal.SIGKILL)
    a.wait()
    restarted = start(command(name, args), folders[0], folders[0] / "a2.log")
    codes = [restarted.wait(timeout=args.timeout), b.wait(timeout=args.timeout)]
    done = trials(name, args.storage)
    count = {s.name: sum(t.state == s for t in done) for s in TrialState}
    evaluated = [t for t in done if t.state == TrialState.COMPLETE and "repeat_of" not in t.user_attrs]
    twice = sum(1 for k, t in enumerate(evaluated) if any(same_configuration(t, o) for o in evaluated[:k]))
    finished = count["COMPLETE"] + count["PRUNED"]
    ok = (finished == args.n_trials and count["WAITING"] == 0 and count["RUNNING"] == 0 and codes == [0, 0]
          and twice == 0)
    return {"rep": i + 1, "kill_s": delay, "killed": alive,
            "mid_trial": killed_running, "finished": finished, "fail": count["FAIL"], "waiting": count["WAITING"],
            "running": count["RUNNING"], "repeats": sum("repeat_of" in t.user_attrs for t in done),
            "evaluated_twice": twice, "exit": codes, "wall_s": time.monotonic() - began, "ok": ok}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--storage", required=True, help="database URL shared by the two workers")
    parser.add_argument("--reps", type=int, default=20)
    parser.add_argument("--n-trials", type=int, default=8)
    parser.add_argument("--heartbeat", type=int, default=1, help="study.heartbeat_interval_s")
    parser.add_argument("--grace", type=int, default=6, help="study.grace_period_s")
    parser.add_argument("--iterations", type=int, default=30, help="fit.mayfly_iterations")
    parser.add_argument("--max-delay", type=float, default=4.0, help="kill up to this long after the first finished trial (s)")
    parser.add_argument("--full-space", action="store_true", help="elm_mayfly's own search space")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timeout", type=float, default=600)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    rows = []
    print("| rep | kill after 1st finished (s) | killed | mid-trial | finished | failed | waiting | running | repeats "
          "reused | evaluated twice | exit codes | wall (s) | ok |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.reps):
            r = repetition(i, args, rng, Path(tmp))
            rows.append(r)
            print(f"| {r['rep']} | {r['kill_s']:.2f} | {'yes' if r['killed'] else 'no (had exited)'} | "
                  f"{r['mid_trial'] or '-'} | {r['finished']} | {r['fail']} | {r['waiting']} | {r['running']} | "
                  f"{r['repeats']} | {r['evaluated_twice']} | {r['exit']} | {r['wall_s']:.0f} | "
                  f"{'yes' if r['ok'] else 'NO'} |", flush=True)
    passed = sum(r["ok"] for r in rows)
    print(f"\n{passed} of {len(rows)} repetitions end with {args.n_trials} finished trials, none waiting or running, "
          f"both commands exit 0, no configuration evaluated twice")
    return 0 if passed == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
