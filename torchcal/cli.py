"""Command line: ``torchcal run | simulate | fit | evaluate | export | study``.

Options follow the command-line contract of the design; ``key=value`` overrides set fields of
the command's configuration (dotted for nested ones, e.g. ``twin.n_train=120``). Heavy imports
happen inside each command so that ``torchcal --help`` starts fast. Every
:class:`~torchcal.errors.TorchcalError` becomes one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def _apply_overrides(config, overrides: list[str]):
    """Merge ``key=value`` strings into a dataclass config, rejecting unknown keys."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from torchcal.errors import TorchcalError

    bad = [o for o in overrides if "=" not in o]
    if bad:
        raise TorchcalError(f"override '{bad[0]}' is not of the form key=value")
    base = OmegaConf.structured(config)
    try:
        merged = OmegaConf.merge(base, OmegaConf.from_dotlist(overrides))
    except OmegaConfBaseException as exc:
        msg = str(exc).splitlines()[0]
        raise TorchcalError(f"invalid override: {msg}") from None
    return OmegaConf.to_object(merged)


def _cmd_simulate(args) -> int:
    from torchcal.sim.instruments import split_instrument, twin_writer

    instrument, overrides = split_instrument(args.overrides)
    writer = twin_writer(instrument)
    config = _apply_overrides(writer.config_factory(), overrides)
    paths = writer.write(Path(args.out), config)
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0


def _cmd_fit(args) -> int:
    from torchcal.data.kinds import measurement_kind

    kind = measurement_kind(args.data)
    if kind != "tracker":
        from torchcal.commands_by_kind import handlers_for

        folder = handlers_for(kind, "fit").fit(
            args.robot, args.data, args.out, args.overrides, base_link=args.base_link, end_link=args.end_link
        )
        print(f"model: {folder}")
        return 0
    from rich.console import Console

    from torchcal.config.compose import compose_fit_config
    from torchcal.data.measurements import load_measurements
    from torchcal.kinematics.robot import load_robot
    from torchcal.metrics import position_metrics
    from torchcal.pipeline import (
        describe_structure,
        fit_with_selection,
        nominal_errors,
        save_fit,
        with_tool,
    )

    config = compose_fit_config(args.overrides)
    console = Console(stderr=True)
    robot = with_tool(load_robot(args.robot, base_link=args.base_link, end_link=args.end_link), config)
    data = load_measurements(args.data, robot, joint_unit=config.joint_unit, length_unit=config.length_unit)
    with console.status(f"identifying {robot.name} from {len(data)} poses") as status:
        result, structure = fit_with_selection(robot, data, config, progress=status.update)
    before = position_metrics(nominal_errors(robot, data))
    from torchcal.identify.joint_fit import predicted_positions

    after = position_metrics(data.position - predicted_positions(result, data.q))
    folder = save_fit(Path(args.out), robot, data, result, {"fit_metrics": {"nominal_registered": before, "geometric": after}})
    from torchcal.config import save_resolved_config

    save_resolved_config(folder / "config.yaml", config)
    console.print(result.identifiability.summary())
    console.print(
        f"training RMS {before['position_rms_mm']:.4f} mm (nominal, registered) -> {after['position_rms_mm']:.4f} mm "
        f"({describe_structure(result)}, on the poses it was fitted to)"
    )
    if config.residual != "none":
        from torchcal.residual_stage import fit_residual_stage

        with console.status("cross-validating residual heads") as status:
            summary = fit_residual_stage(folder, data, config, structure=structure)
        console.print(summary["table"])
        console.print(summary["decision"])
    elif structure is not None:
        from torchcal.residual_stage import write_selection

        write_selection(folder, structure.comparison, "residual=none: no head considered")
        console.print(structure.comparison.format_table())
    print(f"model: {folder}")
    return 0


def _cmd_evaluate(args) -> int:
    from torchcal.data.kinds import measurement_kind
    from torchcal.io import atomic_write_json
    from torchcal.pipeline import FitConfig, evaluate

    kind = measurement_kind(args.data)
    if kind != "tracker":
        from torchcal.commands_by_kind import handlers_for

        metrics = handlers_for(kind, "evaluate").evaluate(args.model, args.data, args.overrides, register=args.register)
        if args.json:
            atomic_write_json(args.json, metrics)
        print(json.dumps(metrics, indent=2, default=str))
        return 0
    metrics = evaluate(args.model, args.data, register=args.register, config=_apply_overrides(FitConfig(), args.overrides))
    if args.json:
        atomic_write_json(args.json, metrics)
    if "leakage" in metrics:
        from torchcal.model_selection.leakage import LeakageReport

        report = LeakageReport(**metrics["leakage"])
        print(f"torchcal: {'warning: ' if report.warning else ''}{report.summary()}", file=sys.stderr)
    comp = metrics["compensator"]
    print(f"torchcal: the exported compensator ({comp['task']} first, {comp['iterations']} steps) solves "
          f"{100 * comp['solved_share']:.1f} % of these poses to 1 um (worst {comp['unsolved_max_mm']:.2e} mm); "
          f"tool orientation deviation median {comp['orientation_deviation_median_rad']:.1e} rad, "
          f"max {comp['orientation_deviation_max_rad']:.1e} rad", file=sys.stderr)
    print(json.dumps({k: v for k, v in metrics.items() if k.startswith(("n_", "position_"))}, indent=2))
    return 0


def _cmd_export(args) -> int:
    from torchcal.compensate.export import export_model

    manifest = export_model(args.model, args.out, iterations=args.iterations, portable=args.portable, task=args.task)
    conv = manifest["convergence"]
    wrist = conv["strata"]["wrist_singular"]
    wrist_text = "" if not wrist.get("n_poses") else (
        f"; near the wrist singularity {100 * wrist['share_within_1um']:.1f} % within 1 um, orientation deviation up to "
        f"{wrist['orientation_deviation_rad']['max']:.1e} rad")
    print(
        f"exported {manifest['files']['compensator']} (sha256 {manifest['sha256']['compensator'][:12]}...); task {conv['task']}, "
        f"{manifest['iterations']} steps leave {100 * conv['share_within_1um']:.1f} % of random poses within 1 um "
        f"(p99 {conv['unsolved_tcp_mm']['p99']:.2e} mm){wrist_text}"
    )
    return 0


def _cmd_run(args) -> int:
    from torchcal.config import compose_run_config
    from torchcal.pipeline import run

    config, _ = compose_run_config(args.overrides)
    summary = run(config)
    final = summary["test"][summary["final_stage"]]
    print(f"{summary['name']}: held-out RMS {final['position_rms_mm']:.4f} mm on {final['n_poses']} new twin poses "
          f"({summary['model']}, chosen by grouped CV on the training poses); "
          f"report in {Path(config.out) / config.name / 'report.md'}")
    return 0


def _cmd_study(args) -> int:
    from rich.console import Console

    from torchcal.config import compose_run_config
    from torchcal.config.compose import merge_section
    from torchcal.studies.runner import run_study
    from torchcal.studies.spec import StudyConfig

    base, sections = compose_run_config(args.overrides, config_name="study", extra_sections=("study",))
    study = merge_section(StudyConfig(), sections["study"])
    if args.storage:
        study.storage = args.storage
    if args.n_trials:
        study.n_trials = args.n_trials
    outcome = run_study(base, study, workers=args.workers, console=Console(stderr=True))
    print(outcome.summary(study.name))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchcal", description="Calibrate industrial robots: geometry, stiffness, learned residual, ONNX compensator.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="the main job: default twin end to end (report and ONNX export)")
    p.add_argument("overrides", nargs="*", help="config groups and key=value, e.g. model=mlp twin.n_train=120 fit.method=lasso")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("simulate", help="write a twin case (instrument=tracker|tracer|stiffness|profile): robot.yaml, data files, truth.json")
    p.add_argument("--out", required=True)
    p.add_argument("overrides", nargs="*", help="key=value of the twin, e.g. gravity=true n_train=200")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser("fit", help="identify a robot from a measurement file")
    p.add_argument("--robot", required=True, help="robot YAML (MDH) or URDF")
    p.add_argument("--data", required=True, help="measurement CSV")
    p.add_argument("--out", required=True, help="model folder to write")
    p.add_argument("--base-link", default=None, help="URDF link of the robot base (default: root)")
    p.add_argument("--end-link", default=None, help="URDF link of the flange (default: last link)")
    p.add_argument("overrides", nargs="*", help="model=<configs/model file> and key=value, e.g. method=lasso residual=none")
    p.set_defaults(func=_cmd_fit)

    p = sub.add_parser("evaluate", help="score a model on a measurement file")
    p.add_argument("--model", required=True)
    p.add_argument("--data", required=True)
    p.add_argument("--json", default=None, help="write the metrics to this JSON file")
    p.add_argument("--register", action="store_true", help="re-fit only the rigid instrument frame to the file first")
    p.add_argument("overrides", nargs="*")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("study", help="Optuna study over a search space from configs/study/ (resumable)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default 1)")
    p.add_argument("--storage", default=None, help="RDB URL shared by workers on several machines (default: SQLite in the study folder)")
    p.add_argument("--n-trials", type=int, default=None, help="finished trials to reach (overrides study.n_trials)")
    p.add_argument("overrides", nargs="*", help="study=<name>, config groups (model=mlp) and key=value, e.g. study.n_trials=40")
    p.set_defaults(func=_cmd_study)

    p = sub.add_parser("export", help="export the compensator to ONNX with a manifest")
    p.add_argument("--model", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--task", choices=["position", "pose"], default="position",
                   help="position: TCP position exactly, orientation as far as the position leaves room (default); "
                        "pose: the full 6-D pose (partial near singularities)")
    p.add_argument("--iterations", type=int, default=None,
                   help="Newton steps of the compensator (default: 6 for position, 3 for pose)")
    p.add_argument("--portable", action="store_true",
                   help="standard ONNX operators only (no onnxruntime contrib Inverse): for other runtimes, slower")
    p.set_defaults(func=_cmd_export)
    return parser


def main(argv: list[str] | None = None) -> int:
    import warnings

    from torchcal.errors import TorchcalError

    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    # key=value overrides may come before and after the options (`simulate instrument=x --out D n=3`)
    if extra and hasattr(args, "overrides") and all("=" in e and not e.startswith("-") for e in extra):
        args.overrides = list(args.overrides) + extra
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    warnings.formatwarning = lambda message, category, *rest: f"torchcal: warning: {message}\n"
    try:
        return int(args.func(args) or 0)
    except TorchcalError as exc:
        print(f"torchcal: error: {exc}", file=sys.stderr)
        return 2
    except FileNotFoundError as exc:
        print(f"torchcal: error: {exc.filename or exc}: file not found", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader closed the pipe (`torchcal evaluate ... | head`): it has what it wanted; stdout
        # goes to devnull so that the interpreter's final flush raises nothing either
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    raise SystemExit(main())
