"""The study report: optimization history, parameter importances, best configuration (Markdown + PNG)."""

from __future__ import annotations

from pathlib import Path

from torchcal.core.io import atomic_write_bytes, atomic_write_text
from torchcal.studies.spec import StudyConfig


def _plot_history(trials, config: StudyConfig, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from optuna.trial import TrialState

    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    done = [t for t in trials if t.state == TrialState.COMPLETE]
    pruned = [t for t in trials if t.state == TrialState.PRUNED and t.intermediate_values]
    ax.scatter([t.number for t in done], [t.values[0] for t in done], s=18, label="complete")
    if pruned:
        ax.scatter([t.number for t in pruned], [t.intermediate_values[max(t.intermediate_values)] for t in pruned],
                   s=18, marker="x", color="grey", label="pruned (last reported)")
    if done and len(config.objectives) == 1:
        best, xs, ys = float("inf"), [], []
        for t in sorted(done, key=lambda t: t.number):
            best = min(best, t.values[0])
            xs.append(t.number)
            ys.append(best)
        ax.step(xs, ys, where="post", color="C3", label="best so far")
    ax.set_xlabel("trial")
    ax.set_ylabel(f"{config.objectives[0]}")
    ax.set_title(f"study {config.name}: optimization history")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, path)


def _plot_importances(importances: dict[str, float], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 0.6 + 0.45 * len(importances)))
    names = list(importances)[::-1]
    ax.barh(names, [importances[n] for n in names])
    ax.set_xlabel("importance (fANOVA, share of objective variance)")
    ax.set_title("parameter importances")
    fig.tight_layout()
    _save(fig, path)


def _plot_pareto(trials, config: StudyConfig, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from optuna.trial import TrialState

    done = [t for t in trials if t.state == TrialState.COMPLETE]
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    ax.scatter([t.values[1] for t in done], [t.values[0] for t in done], s=18)
    ax.set_xlabel(config.objectives[1])
    ax.set_ylabel(config.objectives[0])
    ax.set_title("trade-off")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(fig, path)


def _save(fig, path: Path) -> None:
    import io

    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())


def _mm(value) -> str:
    return "n/a" if value is None else f"{value:.4f} mm"


def write_study_report(study, config: StudyConfig, study_dir: Path, best_run: dict | None = None) -> Path:
    """Write ``report.md`` and its figures into ``study_dir``; returns the report path."""
    import optuna
    from optuna.trial import TrialState

    trials = study.get_trials(deepcopy=False)
    figures = study_dir / "figures"
    _plot_history(trials, config, figures / "history.png")
    lines = [f"# Study `{config.name}`", ""]
    counts = {s.name.lower(): sum(t.state == s for t in trials) for s in TrialState}
    lines.append("Trials: " + ", ".join(f"{n} {k}" for k, n in counts.items() if n) + ".")
    lines.append(f"Objective(s): {', '.join(f'{o} ({d})' for o, d in zip(config.objectives, config.directions))}; "
                 + (f"validation = RMS on the held-out series `{config.holdout}` of the model `fit` makes on the "
                    "training file" if config.holdout else
                    "validation = cross-validated RMS of the model `fit` keeps, on the folds it decides by")
                 + "; test poses are never optimized.")
    lines += ["", "![history](figures/history.png)", ""]
    complete = [t for t in trials if t.state == TrialState.COMPLETE]
    if len(config.objectives) == 1 and complete:
        default = [t for t in complete if t.user_attrs.get("default_configuration")]
        best = study.best_trial
        lines += ["## Best trial", "", (f"Trial {best.number}: {config.objectives[0]} = {best.values[0]:.4f}"
                                         f" (held-out test RMS {_mm(best.user_attrs.get('test_rms_mm'))}, "
                                         f"model {best.user_attrs.get('model')}, {best.user_attrs.get('model_size')} head parameters)."), ""]
        lines += ["```yaml"] + [f"{k}: {v}" for k, v in best.params.items()] + ["```", ""]
        if default:
            d = default[0]
            lines.append(f"Default configuration (trial {d.number}): {config.objectives[0]} = {d.values[0]:.4f}, "
                         f"test RMS {_mm(d.user_attrs.get('test_rms_mm'))}; the best trial is "
                         f"{100 * (1 - best.values[0] / d.values[0]):.1f} % lower on validation." if d.values[0] > 0 else "")
            lines.append("")
        else:
            queued = [t for t in trials if t.user_attrs.get("default_configuration")]
            if queued:
                states = ", ".join(f"trial {t.number} {t.state.name.lower()}" for t in queued)
                lines += [f"Default configuration: not scored ({states}); run the same command again to score it.", ""]
        scores = [t.values[0] for t in complete]
        spread = max(scores) - min(scores)
        if len(complete) >= 3 and len(best.params) >= 1 and spread <= 1e-9 * max(1.0, abs(max(scores))):
            # fANOVA splits zero variance evenly (0.5 / 0.5): a ranking there would be invented
            note = (f"Not ranked: the {len(complete)} complete trials give the same {config.objectives[0]} "
                    f"({scores[0]:.6g}), so no parameter explains any of its variance.")
            lines += ["## Parameter importances", "", note, ""]
        elif len(complete) >= 3 and len(best.params) >= 1:
            try:
                importances = optuna.importance.get_param_importances(study)
            except (RuntimeError, ValueError):
                importances = {}
            if importances:
                _plot_importances(importances, figures / "importances.png")
                lines += ["## Parameter importances", "", "![importances](figures/importances.png)", ""]
                lines += ["| parameter | importance |", "|---|---|"] + [f"| {k} | {v:.3f} |" for k, v in importances.items()] + [""]
    elif len(config.objectives) > 1 and complete:
        _plot_pareto(trials, config, figures / "tradeoff.png")
        lines += ["## Pareto front", "", "![trade-off](figures/tradeoff.png)", "",
                  "| trial | " + " | ".join(config.objectives) + " | params |", "|---|" + "---|" * (len(config.objectives) + 1)]
        for t in sorted(study.best_trials, key=lambda t: t.values[0]):
            lines.append(f"| {t.number} | " + " | ".join(f"{v:.4g}" for v in t.values) + f" | {t.params} |")
        lines.append("")
    if best_run is not None:
        lines += ["## Best configuration refitted", ""]
        if "test" in best_run:
            final = best_run["test"][best_run["final_stage"]]
            lines += [(f"Full run of trial {best_run['trial']} in `{best_run['run_folder']}`: held-out RMS "
                       f"{final['position_rms_mm']:.4f} mm ({best_run['final_stage']})."), ""]
        if "holdout" in best_run:
            lines += [(f"Trial {best_run['trial']} refitted with `fit` in `{best_run['run_folder']}`: RMS on the held-out "
                       f"series {best_run['holdout']['position_rms_mm']:.4f} mm."), ""]
        elif "test" not in best_run:
            lines += [f"Trial {best_run['trial']} refitted in `{best_run['run_folder']}` (no held-out file given).", ""]
    lines += ["## All trials", "", "| trial | state | value(s) | test RMS mm | model | params |", "|---|---|---|---|---|---|"]
    for t in trials:
        values = ", ".join(f"{v:.4f}" for v in t.values) if t.values else "-"
        test = t.user_attrs.get("test_rms_mm")
        model = t.user_attrs.get("model", "-")
        if "repeat_of" in t.user_attrs:
            model += f" (repeat of trial {t.user_attrs['repeat_of']}, not refitted)"
        lines.append(f"| {t.number} | {t.state.name.lower()} | {values} | {'-' if test is None else f'{test:.4f}'} | "
                     f"{model} | {t.params} |")
    path = study_dir / "report.md"
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path
