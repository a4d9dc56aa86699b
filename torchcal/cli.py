"""Command line: ``torchcal run | simulate | fit | evaluate | export | check | update | compensate | study | motion``.

Options follow the command-line contract of the design; ``key=value`` overrides set fields of
the command's configuration (dotted for nested ones, e.g. ``twin.n_train=120``). Heavy imports
happen inside each command so that ``torchcal --help`` starts fast. Every
:class:`~torchcal.core.errors.TorchcalError` becomes one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

from torchcal.core.shutdown import end_process
from torchcal.core.workers import stop_workers


def _split_instrument(overrides: list[str]) -> tuple[str, list[str]]:
    """Take ``instrument=<name>`` out of a list of ``key=value`` overrides (default: the registry's)."""
    from torchcal.instruments.registry import DEFAULT

    instrument, rest = DEFAULT, []
    for item in overrides:
        key, _, value = item.partition("=")
        if key.strip() == "instrument":
            instrument = value.strip()
        else:
            rest.append(item)
    return instrument, rest


def _console(stderr: bool = True):
    """A rich console; piped into a file or another program, its tables keep 160 columns instead of
    rich's 80 (they would wrap mid-row in a log)."""
    from rich.console import Console

    stream = sys.stderr if stderr else sys.stdout
    return Console(stderr=stderr, width=None if stream.isatty() else 160)


def _progress(status) -> Callable[[str], None]:
    """A progress callback that shows a step's text on a rich status spinner."""
    return lambda text: status.update(text)


def _cmd_simulate(args) -> int:
    from torchcal.config.compose import compose_options
    from torchcal.core.folder import staged_folder
    from torchcal.instruments.registry import get

    name, overrides = _split_instrument(args.overrides)
    twin = get(name).twin()
    config = compose_options(twin.config_factory(), overrides)
    out = Path(args.out)
    # built in a staging sibling and swapped in whole: an interrupted simulate leaves the earlier case
    with staged_folder(out, "--out", purpose="twin", sealed=False) as staging:
        paths = twin.write(staging, config)
    for key, path in paths.items():
        print(f"{key}: {out / Path(path).relative_to(staging)}")
    return 0


def _cmd_fit(args) -> int:

    from torchcal.core.errors import DataError
    from torchcal.instruments.base import FitRequest, check_fit_paths, fit_committed
    from torchcal.instruments.registry import recognise

    files = [Path(d) for d in args.data]  # --data repeated: several series of one robot
    for file in files:
        check_fit_paths(Path(args.out), file, Path(args.robot))
    instrument = recognise(files[0])
    for file in files[1:]:
        kind = recognise(file).name
        if kind != instrument.name:
            raise DataError(f"a {kind} file, but {files[0]} is a {instrument.name} file: "
                            "several --data files must be series of one kind", path=str(file))
    console = _console()
    with console.status(f"fitting {instrument.name} data") as status:
        outcome = fit_committed(instrument, FitRequest(
            robot=Path(args.robot), data=files[0], out=Path(args.out), overrides=list(args.overrides),
            base_link=args.base_link, end_link=args.end_link, progress=_progress(status),
            more_data=tuple(files[1:])))
    for line in outcome.lines:
        console.print(line, markup=False, highlight=False)
    print(f"model: {outcome.folder}")
    if outcome.report is not None:
        print(f"report: {outcome.report} (and {outcome.report.with_suffix('.html').name})")
    return 0


def _cmd_evaluate(args) -> int:
    from torchcal.core.io import atomic_write_json
    from torchcal.core.outputs import JSON_KEY, claim_file, is_metrics_json
    from torchcal.instruments.base import (
        EvaluateRequest,
        check_evaluate_overrides,
        evaluate_reported,
    )
    from torchcal.instruments.registry import recognise

    if args.json:
        claim_file(args.json, "metrics", "--json", is_metrics_json)
    instrument = recognise(args.data)
    check_evaluate_overrides(instrument, list(args.overrides))
    outcome = evaluate_reported(instrument, EvaluateRequest(
        model=Path(args.model), data=Path(args.data), overrides=list(args.overrides), register=args.register,
        report=Path(args.report) if args.report else None))
    if args.json:
        atomic_write_json(args.json, {JSON_KEY: "metrics", **outcome.metrics})
    for line in outcome.lines:
        print(f"torchcal: {line}", file=sys.stderr)
    if outcome.report is not None:
        print(f"torchcal: report: {outcome.report} (and {outcome.report.with_suffix('.html').name})", file=sys.stderr)
    print(json.dumps(instrument.shown_metrics(outcome.metrics), indent=2, default=str))
    return 0


def _cmd_export(args) -> int:
    from torchcal.compensate.export import export_model, turned_tool_warning

    manifest = export_model(args.model, args.out, iterations=args.iterations, portable=args.portable, task=args.task,
                            tcp_mm=args.tcp_mm, tcp_rpy_deg=args.tcp_rpy_deg,
                            allow_large_corrections=args.allow_large_corrections, tool_length_mm=args.tool_length_mm)
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
    tcp = manifest["tcp"]
    for where, e in manifest["corrections"]["extent"].items():
        what = "flange" if tcp.get("is_flange") else f"TCP {tcp['rpy_deg']} deg,"
        print(f"{what} {[round(v, 3) for v in tcp['position_mm']]} mm in the flange frame: over the {where} the largest joint "
              f"correction is {e['largest_joint_correction_deg']:.3g} deg (joint {e['joint']}"
              + (f"; 1-sigma {e['largest_joint_correction_sigma_deg']:.2g} deg from the calibration's uncertainty"
                 if e.get("largest_joint_correction_sigma_deg") is not None else "")
              + f"), the tool orientation deviation up to {e['largest_tool_rotation_deg']:.3g} deg")
    for line in manifest["corrections"]["exceeded_but_allowed"]:
        print(f"warning: {line} (allowed by --allow-large-corrections)")
    turned = turned_tool_warning(manifest)
    if turned:
        print(f"warning: {turned}")
    return 0


def _cmd_compensate(args) -> int:
    from torchcal.compensate.program import compensate_program

    outcome = compensate_program(args.model, args.targets, args.out, task=args.task, iterations=args.iterations,
                                 tcp_mm=args.tcp_mm, tcp_rpy_deg=args.tcp_rpy_deg,
                                 allow_large_corrections=args.allow_large_corrections, start_deg=args.start,
                                 tool_length_mm=args.tool_length_mm)
    for line in outcome.lines():
        print(line)
    return 0


def _cmd_check(args) -> int:
    from torchcal.app.check import check_model, check_report
    from torchcal.core.folder import check_output_folder, staged_folder
    from torchcal.core.io import atomic_write_json
    from torchcal.core.outputs import JSON_KEY, claim_file, json_of
    from torchcal.report.document import write_report

    if args.json:
        claim_file(args.json, "check", "--json", json_of("check"))
    if args.report:
        check_output_folder(args.report, "--report", purpose="report")
    result = check_model(args.model, args.data, _unit_options(args.overrides, "check"))
    if args.json:
        atomic_write_json(args.json, {JSON_KEY: "check", **result.to_dict()})
    if args.report:
        with staged_folder(args.report, "--report", purpose="report", sealed=False) as staging:
            write_report(staging, check_report(result, args.model))
    for line in result.lines():
        print(line)
    return 0


def _unit_options(overrides: list[str], command: str):
    """The units of a command's measurement file from its ``joint_unit=`` / ``length_unit=`` overrides."""
    from torchcal.config.compose import compose_options
    from torchcal.config.schema import UnitOptions
    from torchcal.core.errors import TorchcalError

    for item in overrides:
        if item.partition("=")[0].strip() not in ("joint_unit", "length_unit"):
            raise TorchcalError(f"{command}: unknown option '{item}'; the options are joint_unit=deg|rad and length_unit=mm|m")
    return compose_options(UnitOptions(), list(overrides))


def _cmd_update(args) -> int:
    from torchcal.app.update import update_model
    from torchcal.core.errors import TorchcalError

    free = "auto"
    units = []
    for item in args.overrides:
        key, _, value = item.partition("=")
        if key.strip() in ("joint_unit", "length_unit"):
            units.append(item)
            continue
        if key.strip() != "free":
            raise TorchcalError(f"update: unknown option '{item}'; the options are free=auto|frame|tool|offsets|all|<names>, "
                                "joint_unit=deg|rad and length_unit=mm|m")
        free = value
    result = update_model(args.model, args.data, args.out, free=free, units=_unit_options(units, "update"))
    for line in result.lines():
        print(line)
    print(f"model: {args.out}")
    return 0


def _cmd_motion(args) -> int:
    from torchcal.app.motion import run_motion

    outcome = run_motion(Path(args.robot), Path(args.path), Path(args.out), list(args.overrides),
                         model_dir=Path(args.model) if args.model else None,
                         report_dir=Path(args.report) if args.report else None)
    for line in outcome.lines:
        print(line)
    return 0


def _cmd_run(args) -> int:
    from torchcal.config import compose_run_config
    from torchcal.config.workers import start_fit_workers

    config, _ = compose_run_config(args.overrides)
    start_fit_workers(config.fit)  # before this process imports torch: their start-up overlaps it

    from torchcal.instruments.registry import default

    summary = default().run(config, console=_console(stderr=False))
    final = summary["test"][summary["final_stage"]]
    print(f"{summary['name']}: held-out RMS {final['position_rms_mm']:.4f} mm on {final['n_poses']} new twin poses "
          f"({summary['model']}, chosen by {config.fit.split} cross-validation on the training poses); "
          f"report in {Path(config.out) / config.name / 'report.md'}")
    return 0


def _cmd_study(args) -> int:

    from torchcal.config import compose_run_config
    from torchcal.config.compose import merge_section
    from torchcal.core.errors import TorchcalError
    from torchcal.studies.runner import run_study
    from torchcal.studies.spec import StudyConfig

    if args.workers < 1:
        raise TorchcalError(f"--workers must be at least 1, got {args.workers}")
    if args.n_trials is not None and args.n_trials < 1:
        raise TorchcalError(f"--n-trials must be at least 1, got {args.n_trials}")
    base, sections = compose_run_config(args.overrides, config_name="study", extra_sections=("study",))
    study = merge_section(StudyConfig(), sections["study"])
    if args.storage:
        study.storage = args.storage
    if args.n_trials is not None:
        study.n_trials = args.n_trials
    outcome = run_study(base, study, workers=args.workers, console=_console())
    print(outcome.summary(study.name))
    return 0


def option_listing(command: str) -> str:
    """The ``key=value`` options of ``command`` with defaults, from its configuration dataclasses."""
    from torchcal.core.options import format_options, list_options

    blocks: list[str] = []
    if command == "fit":
        from torchcal.instruments.registry import default, get, names

        first = default()
        blocks.append(format_options(f"key=value options ({first.name} files, and every kind unless listed below):",
                                     list_options(first.options())))
        common = {o.key for o in list_options(first.options())}
        for name in names():
            own = [o for o in list_options(get(name).options()) if o.key not in common]
            blocks.append(format_options(f"options of {name} files ({get(name).description}):", own))
    elif command == "evaluate":
        from torchcal.instruments.registry import get, names

        # only what evaluate reads: the model folder holds what the fit chose
        for name in names():
            instrument = get(name)
            used = instrument.evaluate_options()
            own = [o for o in list_options(instrument.options()) if used is None or o.key in used]
            blocks.append(format_options(f"key=value options of {name} files ({instrument.description}):", own))
    elif command == "motion":
        from torchcal.motion.planner import PlanOptions

        blocks.append(format_options("key=value options (mm, deg, s):", list_options(PlanOptions)))
    elif command == "simulate":
        from torchcal.instruments.registry import get, names

        for name in names():
            twin = get(name).twin()
            blocks.append(format_options(f"instrument={name}: {twin.description}", list_options(twin.config_factory)))
    elif command == "run":
        from torchcal.config import compose_run_config

        config, _ = compose_run_config([])
        blocks.append(format_options("key=value options, defaults as configs/ composes them (config groups: model=, "
                                     "measurement=, experiment=):", list_options(config)))
    elif command == "study":
        from torchcal.config import compose_run_config
        from torchcal.config.compose import merge_section
        from torchcal.studies.spec import StudyConfig

        base, sections = compose_run_config([], config_name="study", extra_sections=("study",))
        blocks.append(format_options("study options (study=<configs/study file> picks a search space):",
                                     list_options(merge_section(StudyConfig(), sections["study"]), prefix="study.")))
        blocks.append(format_options("options of the runs it scores:", list_options(base)))
    return "\n\n".join(b for b in blocks if b)


def _version() -> str:
    """The installed distribution's version (the source tree's when it is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("torchcal")
    except PackageNotFoundError:
        return "(not installed)"


def build_parser(with_options: bool | str = False) -> argparse.ArgumentParser:
    """The argument parser; ``with_options`` adds each command's ``key=value`` list to its help, or
    only that command's when it names one (it imports the configuration classes, so only
    ``<command> --help`` pays for it)."""
    parser = argparse.ArgumentParser(prog="torchcal", description="Calibrate industrial robots: geometry, stiffness, learned residual, ONNX compensator.")
    parser.add_argument("--version", action="version", version=f"torchcal {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    def listing(command: str) -> str | None:
        if with_options is True or with_options == command:
            return option_listing(command)
        return None

    def add(name: str, **kwargs) -> argparse.ArgumentParser:
        return sub.add_parser(name, epilog=listing(name), formatter_class=argparse.RawDescriptionHelpFormatter, **kwargs)

    p = add("run", help="the main job: default twin end to end (report and ONNX export)")
    p.add_argument("overrides", nargs="*", help="config groups and key=value, e.g. model=mlp twin.n_train=120 fit.method=lasso")
    p.set_defaults(func=_cmd_run)

    from torchcal.instruments.registry import names

    p = add("simulate", help=f"write a twin case (instrument={'|'.join(names())}): robot.yaml, data files, truth.json")
    p.add_argument("--out", required=True, metavar="DIR", help="twin case folder to write (new, empty, or an earlier twin case)")
    p.add_argument("overrides", nargs="*", help="key=value of the twin, e.g. gravity=true n_train=200")
    p.set_defaults(func=_cmd_simulate)

    p = add("fit", help="identify a robot from a measurement file")
    p.add_argument("--robot", required=True, help="robot YAML (MDH) or URDF")
    p.add_argument("--data", required=True, action="append",
                   help="measurement CSV; repeat --data for further series of the same robot (tracker points: "
                        "one fit, each series with its own instrument frame; series_tool=per_series for re-mounted probes)")
    p.add_argument("--out", required=True, help="model folder to write")
    p.add_argument("--base-link", default=None, help="URDF link of the robot base (default: root)")
    p.add_argument("--end-link", default=None, help="URDF link of the flange (default: last link)")
    p.add_argument("overrides", nargs="*", help="model=<configs/model file> and key=value, e.g. method=lasso residual=none")
    p.set_defaults(func=_cmd_fit)

    p = add("evaluate", help="score a model on a measurement file")
    p.add_argument("--model", required=True, metavar="DIR", help="model folder written by fit")
    p.add_argument("--data", required=True, metavar="CSV", help="measurement CSV to score (poses the fit has not seen)")
    p.add_argument("--json", default=None, help="write the metrics to this JSON file")
    p.add_argument("--register", action="store_true", help="re-fit only the rigid instrument frame to the file first")
    p.add_argument("--report", default=None, metavar="DIR",
                   help="write report.md and report.html (figures inline) of this evaluation into DIR")
    p.add_argument("overrides", nargs="*", help="key=value options of the file (listed below); fit options are refused: "
                   "the model folder holds what the fit chose")
    p.set_defaults(func=_cmd_evaluate)

    p = add("study", help="Optuna study over a search space from configs/study/ (resumable)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default 1)")
    p.add_argument("--storage", default=None, help="RDB URL shared by workers on several machines (default: SQLite in the study folder)")
    p.add_argument("--n-trials", type=int, default=None, help="finished trials to reach (overrides study.n_trials)")
    p.add_argument("overrides", nargs="*", help="study=<name>, config groups (model=mlp) and key=value, e.g. study.n_trials=40")
    p.set_defaults(func=_cmd_study)

    p = add("export", help="export the compensator to ONNX with a manifest")
    p.add_argument("--model", required=True, metavar="DIR", help="model folder written by fit")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="export folder to write (new, empty, or an earlier export; never the model folder)")
    p.add_argument("--task", choices=["position", "pose"], default="position",
                   help="position: TCP position exactly, orientation as far as the position leaves room (default); "
                        "pose: the full 6-D pose (partial near singularities)")
    p.add_argument("--iterations", type=int, default=None,
                   help="Newton steps of the compensator (default: 6 for position, 3 for pose)")
    p.add_argument("--portable", action="store_true",
                   help="standard ONNX operators only (no onnxruntime contrib Inverse): for other runtimes, slower")
    p.add_argument("--tcp-mm", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="production TCP in the flange frame, mm (default: the flange); the compensator serves it, "
                        "not the calibration's measured point")
    p.add_argument("--tcp-rpy-deg", type=float, nargs=3, default=None, metavar=("RX", "RY", "RZ"),
                   help="orientation of the production TCP in the flange frame, fixed-axis XYZ deg (default: 0 0 0)")
    p.add_argument("--allow-large-corrections", action="store_true",
                   help="export even when a joint correction or the tool's orientation deviation exceeds the limits")
    p.add_argument("--tool-length-mm", type=float, default=0.0, metavar="L",
                   help="keep the nominal command wherever the corrected one would leave a point L mm beyond the TCP "
                        "further off (position error + L * tool turn; default 0: the TCP alone)")
    p.set_defaults(func=_cmd_export)

    p = add("check", help="test a model against a few new poses: valid, or which parameter group changed")
    p.add_argument("--model", required=True, help="model folder")
    p.add_argument("--data", required=True, help="a few new measured poses (x,y,z,q1..qN; any tracker set-up)")
    p.add_argument("--json", default=None, help="write verdict, changed and the evidence to this JSON file")
    p.add_argument("--report", default=None, metavar="DIR", help="write report.md and report.html into DIR")
    p.add_argument("overrides", nargs="*", help="joint_unit=deg|rad, length_unit=mm|m of the file (default deg, mm)")
    p.set_defaults(func=_cmd_check)

    p = add("update", help="a new model folder from an old one and a few new poses (frame re-registered, changed group refitted)")
    p.add_argument("--model", required=True, help="the old model folder (the prior)")
    p.add_argument("--data", required=True, help="a few new measured poses (x,y,z,q1..qN; any tracker set-up)")
    p.add_argument("--out", required=True, help="the new model folder to write (never the old one)")
    p.add_argument("overrides", nargs="*", help="free=auto (default: what check names) | frame | tool | offsets | all | "
                                                "names, e.g. free=tool,theta3; joint_unit=deg|rad, length_unit=mm|m of "
                                                "the file (default deg, mm)")
    p.set_defaults(func=_cmd_update)

    p = add("compensate", help="correct the joint targets of a robot program offline with a model's compensator")
    p.add_argument("--model", required=True, help="model folder")
    p.add_argument("--targets", required=True,
                   help="program CSV: q1..qN (deg), one target per row; or TCP poses x,y,z (mm) [rx,ry,rz (deg)] in the "
                        "base frame with --start")
    p.add_argument("--start", type=float, nargs="+", default=None, metavar="DEG",
                   help="start configuration q1 .. qN (deg) of a program of TCP poses")
    p.add_argument("--out", required=True, help="corrected CSV to write: q1..qN (deg), corrected, correction_deg, remaining_mm")
    p.add_argument("--task", choices=["position", "pose"], default="position", help="as for export (default: position)")
    p.add_argument("--iterations", type=int, default=None, help="Newton steps (default: as for export)")
    p.add_argument("--tcp-mm", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="production TCP in the flange frame, mm, as for export (default: the flange)")
    p.add_argument("--tcp-rpy-deg", type=float, nargs=3, default=None, metavar=("RX", "RY", "RZ"),
                   help="orientation of the production TCP in the flange frame, fixed-axis XYZ deg")
    p.add_argument("--allow-large-corrections", action="store_true",
                   help="as for export: compensate even when the model's corrections exceed the export's limits")
    p.add_argument("--tool-length-mm", type=float, default=0.0, metavar="L", help="as for export (default 0)")
    p.set_defaults(func=_cmd_compensate)

    p = add("motion", help="joint trajectory of a TCP path through singularities (position first, within joint limits)")
    p.add_argument("--robot", required=True, help="robot YAML (MDH) or URDF; its velocity/acceleration limits apply")
    p.add_argument("--model", default=None, help="model folder: plan with the calibrated kinematics (the real robot)")
    p.add_argument("--path", required=True, help="waypoint CSV: x,y,z (mm), rx,ry,rz (deg, R = Rz Ry Rx), base frame")
    p.add_argument("--out", required=True, help="trajectory CSV to write: t (s), q1..qN (deg) every dt")
    p.add_argument("--report", default=None, metavar="DIR", help="report folder (default: <out stem>_report next to --out)")
    p.add_argument("overrides", nargs="*", help="key=value, e.g. start=[10,-80,10,0,30,20] speed=250 dt=0.004")
    p.set_defaults(func=_cmd_motion)
    return parser


#: Set when SIGTERM arrived (a job scheduler, ``systemctl stop``, ``kill``): the command ends as after Ctrl-C.
_terminated = False


def _on_sigterm(signum, frame) -> None:
    """SIGTERM handled like Ctrl-C: raised as ``KeyboardInterrupt`` so staged outputs are cleaned up."""
    global _terminated
    _terminated = True
    raise KeyboardInterrupt


def _write_failure(exc: OSError) -> str | None:
    """The one line of a file operation the system refused (no space, file too large, path too long), or ``None`` for other errors."""
    import errno

    where = exc.filename or "a file"
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"{where}: no space left on the device (or the quota is used up); free space there and run again"
    if exc.errno == errno.EFBIG:
        return (f"{where}: file larger than this process may write (the shell's `ulimit -f`, or the file "
                "system's limit); raise the limit or free space and run again")
    if exc.errno == errno.ENAMETOOLONG:
        shown = str(where) if len(str(where)) <= 80 else f"{str(where)[:40]}...{str(where)[-30:]}"
        return f"{shown}: path too long for the file system (a name over 255 bytes, or a path over 4096); give a shorter one"
    return None


def main(argv: list[str] | None = None) -> int:
    """The command line; every :class:`~torchcal.core.errors.TorchcalError` is one line and exit status 2."""
    import signal
    import threading

    global _terminated
    _terminated = False
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if in_main_thread else None
    try:
        return _main(argv)
    finally:
        if in_main_thread:
            signal.signal(signal.SIGTERM, previous)


def _main(argv: list[str] | None) -> int:
    import warnings

    from torchcal.core.errors import TorchcalError


    given = argv if argv is not None else sys.argv[1:]
    # only `<command> --help` lists that command's options; `torchcal --help` alone lists commands
    asked = any(a in ("-h", "--help") for a in given)
    command = next((a for a in given if not a.startswith("-")), None)
    parser = build_parser(with_options=command if asked and command else False)
    args, extra = parser.parse_known_args(argv)
    # key=value overrides may come before and after the options (`simulate instrument=x --out D n=3`)
    if extra and hasattr(args, "overrides") and all("=" in e and not e.startswith("-") for e in extra):
        args.overrides = list(args.overrides) + extra
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    warnings.formatwarning = lambda message, category, *rest: f"torchcal: warning: {message}\n"
    # each warning once per command: fold and candidate fits repeat the full fit's warnings, and every
    # `catch_warnings` block on the way resets Python's own once-per-location registry
    shown: set[str] = set()
    show = warnings.showwarning

    def show_once(message, category, filename, lineno, file=None, line=None):
        if str(message) not in shown:
            shown.add(str(message))
            show(message, category, filename, lineno, file, line)

    warnings.showwarning = show_once
    try:
        return int(args.func(args) or 0)
    except TorchcalError as exc:
        print(f"torchcal: error: {exc}", file=sys.stderr)
        return 2
    except FileNotFoundError as exc:
        print(f"torchcal: error: {exc.filename or exc}: file not found", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # output folders are staged and files written atomically: an interrupted command leaves what was there
        how = "terminated (SIGTERM)" if _terminated else "interrupted"
        print(f"torchcal: {how}; nothing written ({args.command} leaves earlier outputs as they were)",
              file=sys.stderr)
        return 143 if _terminated else 130
    except UnicodeDecodeError as exc:
        print(f"torchcal: error: a file is not UTF-8 text (byte {exc.start}: {exc.reason})", file=sys.stderr)
        return 2
    except IsADirectoryError as exc:
        print(f"torchcal: error: {exc.filename or exc}: is a folder, a file was expected", file=sys.stderr)
        return 2
    except PermissionError as exc:
        print(f"torchcal: error: {exc.filename or exc}: permission denied", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader closed the pipe (`torchcal evaluate ... | head`): it has what it wanted; stdout
        # goes to devnull so that the interpreter's final flush raises nothing either
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:
        line = _write_failure(exc)
        if line is None:
            raise
        print(f"torchcal: error: {line}; earlier outputs were left as they were", file=sys.stderr)
        return 2
    finally:
        warnings.showwarning = show
        stop_workers()  # idle by now, or still busy after an interrupt; os._exit below would orphan them


def console_main() -> NoReturn:
    """The ``torchcal`` command: :func:`main`, then the process ends without tearing down its modules
    (:func:`torchcal.core.shutdown.end_process`: with torch imported the teardown took 0.5-0.9 s at
    the end of every command; files are closed by then, every write is atomic). A command stopped by
    Ctrl-C or SIGTERM ends at once: its outputs are already cleaned up when ``main`` returns.

    ``python -m torchcal.cli`` ends here too, for a second reason: under ``-m``, CPython remembers a
    ``KeyboardInterrupt`` that ended any code run from a string (``exec`` of source text, as
    ``dataclasses`` and other libraries do) even when it was caught, and at exit kills the
    interpreter with SIGINT instead of returning the status: a terminated command would say
    "terminated" and end as if interrupted (seen as status -2).
    """
    end_process(main())


if __name__ == "__main__":
    console_main()
