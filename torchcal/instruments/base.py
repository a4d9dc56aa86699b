"""The instrument protocol: what every measuring instrument plugs into torchcal with.

An instrument is a subpackage of :mod:`torchcal.instruments` (or of another distribution, see
:mod:`torchcal.instruments.registry`) whose ``INSTRUMENT`` is an :class:`Instrument`. It says

* how a file of its kind is **recognised** (the columns it needs; the user never names the
  instrument, the header tells),
* how such a file is **loaded** (validated, SI units),
* how ``torchcal fit`` **fits** it (a model folder; :attr:`Instrument.stage` names the model stage it
  adds: the robot ``geometry``, ``stiffness``, a ``sensor`` mounting...),
* how ``torchcal evaluate`` **scores** a model folder on it (a dict of metrics, mm),
* how ``torchcal simulate instrument=<name>`` writes a **twin** case with known truth, and
* which small twin case the shared contract suite (:mod:`torchcal.testing.instrument_contract`)
  runs it through, with the accuracy a fit must reach there.

Commands get results back and print them; an instrument does not print (warnings go through
:mod:`warnings`, which the command line shows as one line each).
"""

from __future__ import annotations

import shutil
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

from torchcal.core.errors import TorchcalError
from torchcal.core.folder import FolderError, check_output_folder, staged_folder
from torchcal.report.document import FIGURES, write_report

#: Model stages an instrument's fit can add to a model folder.
STAGES = ("geometry", "stiffness", "sensor")


@dataclass(frozen=True)
class FitRequest:
    """What ``torchcal fit`` passes to an instrument.

    Attributes:
        robot: robot file (MDH YAML or URDF).
        data: the measurement file.
        out: model folder to write.
        overrides: ``key=value`` options of the command line.
        base_link / end_link: URDF links of the robot base and the flange (``None``: root, last).
        progress: called with a one-line description of each long step (a spinner's text).
        previous: the folder the result will replace when ``out`` is a staging folder
            (:func:`fit_committed`); an instrument that adds a stage to an existing model reads it
            from there. ``None``: nothing is replaced.
        more_data: further measurement series of the same robot (``--data`` repeated), each in its
            own instrument frame; only instruments with :attr:`Instrument.multi_series` take them.
    """

    robot: Path
    data: Path
    out: Path
    overrides: list[str] = field(default_factory=list)
    base_link: str | None = None
    end_link: str | None = None
    progress: Callable[[str], None] = lambda _text: None
    previous: Path | None = None
    more_data: tuple[Path, ...] = ()


@dataclass(frozen=True)
class FitOutcome:
    """What a fit wrote and what the command line shows of it.

    Attributes:
        folder: the model folder written.
        lines: result lines for the user, in order (the CLI prints them; the last one names the
            chosen model and its figures).
        report: the report the instrument wrote into the folder (``report.md``, next to
            ``report.html``); ``None``: :func:`fit_committed` writes the shared summary report.
    """

    folder: Path
    lines: list[str] = field(default_factory=list)
    report: Path | None = None


@dataclass(frozen=True)
class EvaluateRequest:
    """What ``torchcal evaluate`` passes to an instrument.

    Attributes:
        model: the model folder.
        data: the measurement file to score.
        overrides: ``key=value`` options (units of the file and the like).
        register: re-fit only what a new set-up of the instrument changes (its frame, stations...)
            before scoring.
        report: folder to write ``report.md`` + ``report.html`` into (``evaluate --report``), or
            ``None``. An instrument that writes its own says so in :attr:`EvaluateOutcome.report`;
            otherwise :func:`evaluate_reported` writes the shared summary report.
    """

    model: Path
    data: Path
    overrides: list[str] = field(default_factory=list)
    register: bool = False
    report: Path | None = None


@dataclass(frozen=True)
class EvaluateOutcome:
    """Metrics of a model on a file (JSON-ready, lengths in mm), lines for the user, the report written (if any)."""

    metrics: dict[str, Any]
    lines: list[str] = field(default_factory=list)
    report: Path | None = None


@dataclass(frozen=True)
class TwinSpec:
    """How ``torchcal simulate instrument=<name>`` writes a case.

    Attributes:
        config_factory: the twin's configuration dataclass (its ``key=value`` options).
        write: ``write(out_dir, config) -> {name: path}``; the names include ``robot.yaml`` and
            the measurement files.
        description: one line for ``--help``.
    """

    config_factory: Callable[[], Any]
    write: Callable[[Path, Any], dict[str, Path]]
    description: str


@dataclass(frozen=True)
class ContractCase:
    """A small twin case the contract suite fits and scores, with its known-truth bound.

    Attributes:
        twin_overrides: ``key=value`` options of the twin (small, seconds to fit).
        fit_file / test_file: names (keys of the twin writer's result) of the file to fit and of
            the held-out file to score.
        fit_overrides / evaluate_overrides: options of ``fit`` and ``evaluate``.
        end_link: URDF end link, where the twin's robot file needs one.
        metric: the key of :attr:`EvaluateOutcome.metrics` to check (mm).
        bound: the value of ``metric`` a correct fit reaches on the held-out file, from the twin's
            noise and truth (a nominal model misses it).
        register: score with ``evaluate --register`` (the test file comes from another set-up).
    """

    twin_overrides: list[str]
    fit_file: str
    test_file: str
    metric: str
    bound: float
    fit_overrides: list[str] = field(default_factory=list)
    evaluate_overrides: list[str] = field(default_factory=list)
    end_link: str | None = None
    register: bool = False


class Instrument(ABC):
    """A measuring instrument: recognise, load, fit, evaluate, simulate.

    Attributes:
        name: registry name, the subpackage's name (``"tracker"``, ``"tracer"``...).
        description: one line saying what the instrument measures.
        stage: the model stage its fit adds (one of :data:`STAGES`).
        required_columns: columns (lower case) whose presence marks a file of this kind. Where the
            columns of several instruments are present, the one requiring most of them wins (a
            stiffness file with ``x, y, z`` is a stiffness file).
        multi_series: ``fit`` takes several files of one robot, each its own set-up (``--data`` repeated).
    """

    name: ClassVar[str]
    description: ClassVar[str]
    stage: ClassVar[str]
    required_columns: ClassVar[frozenset[str]]
    multi_series: ClassVar[bool] = False

    def recognises(self, columns: set[str]) -> bool:
        """Whether a header with ``columns`` (lower case) is a file of this instrument."""
        return self.required_columns <= columns

    @abstractmethod
    def load(self, path: Path, robot: Any, overrides: list[str] | None = None) -> Any:
        """The validated measurements of ``path`` (SI units) for ``robot`` (a ``RobotModel``).

        ``len()`` of the result is the number of measurement rows kept.

        Raises:
            DataError: naming file, row and column of the first bad cell.
        """

    @abstractmethod
    def fit(self, request: FitRequest) -> FitOutcome:
        """Fit the file and write a model folder (committed whole) at ``request.out``."""

    @abstractmethod
    def evaluate(self, request: EvaluateRequest) -> EvaluateOutcome:
        """Score the model folder ``request.model`` on ``request.data``."""

    @abstractmethod
    def options(self) -> type:
        """The configuration dataclass of ``fit`` / ``evaluate`` on this instrument's files (their
        ``key=value`` options; ``--help`` lists its fields)."""

    def evaluate_options(self) -> tuple[str, ...] | None:
        """The keys of :meth:`options` that ``evaluate`` reads (the file's units and the like); the
        others are fit options, which ``evaluate --help`` does not list and ``evaluate`` refuses.
        ``None``: every option is read by ``evaluate`` too."""
        return None

    def shown_metrics(self, metrics: dict) -> dict:
        """The part of ``evaluate``'s metrics the command prints as JSON (all of them unless the
        instrument's lines already say the rest); ``--json`` writes all of them."""
        return metrics

    @abstractmethod
    def twin(self) -> TwinSpec:
        """The twin writer of ``torchcal simulate instrument=<name>``."""

    def run(self, config: Any, console: Any = None) -> dict:
        """``torchcal run``: the twin end to end (simulate, fit, held-out evaluation, report, export)
        for a :class:`~torchcal.config.schema.RunConfig`; returns the run's ``metrics.json`` dict.
        Only the default instrument has one."""
        raise TorchcalError(f"instrument {self.name} has no end-to-end twin run")

    @abstractmethod
    def contract_case(self) -> ContractCase:
        """The small known-truth case of the shared contract suite."""


def check_evaluate_overrides(instrument: Instrument, overrides: list[str]) -> None:
    """Refuse a fit option given to ``evaluate`` (one that would change nothing) in one line."""
    from torchcal.core.errors import TorchcalError
    from torchcal.core.options import list_options

    used = instrument.evaluate_options()
    if used is None:
        return
    fit_only = {o.key for o in list_options(instrument.options())} - set(used)
    for item in overrides:
        key = item.split("=", 1)[0].strip()
        if key in fit_only:
            raise TorchcalError(f"{key} is an option of fit, not of evaluate (the model folder holds what the fit chose); "
                              f"evaluate on {instrument.name} files takes {', '.join(used)}")


def check_fit_paths(out: Path, data: Path, robot: Path) -> None:
    """Refuse, before any work, a fit whose ``--out`` folder holds its own input files, then an ``--out``
    torchcal may not write (:func:`torchcal.core.folder.check_output_folder`)."""
    for what, path in (("--data", data), ("--robot", robot)):
        if Path(out).resolve() in Path(path).resolve().parents:
            raise FolderError(f"{out}: --out holds the {what} file {path}; a fit replaces the whole folder, "
                              "so give another --out")
    check_output_folder(out)


def fit_committed(instrument: Instrument, request: FitRequest) -> FitOutcome:
    """Run ``instrument.fit`` into a staging folder and swap it into ``request.out`` when it has finished.

    The destination is checked before any work (an existing file, or a folder that is not
    torchcal output, is refused). A crash, ``kill -9`` or Ctrl-C at any moment leaves the earlier
    folder or the new one, whole (:func:`torchcal.core.folder.staged_folder`); the files of an
    earlier result never mix with the new ones.
    """
    out = Path(request.out)
    for data in (request.data, *request.more_data):
        check_fit_paths(out, Path(data), Path(request.robot))
    if request.more_data and not instrument.multi_series:
        from torchcal.core.errors import DataError

        raise DataError(f"{instrument.name} files are fitted one at a time: give one --data", path=str(request.more_data[0]))
    previous = out if out.is_dir() else None
    with staged_folder(out, purpose="model") as staging:
        outcome = instrument.fit(replace(request, out=staging, previous=previous))
        if outcome.report is None:  # none of its own: the shared one, replacing any copied from an earlier model
            shutil.rmtree(staging / FIGURES, ignore_errors=True)
            write_summary_report(staging, f"torchcal fit: {instrument.name} file {Path(request.data).name}", outcome.lines,
                                 folder=staging, kind=instrument.name, member=True)
    return FitOutcome(folder=out, lines=outcome.lines, report=out / REPORT)


#: The report a fit writes into its model folder (next to ``report.html``).
REPORT = "report.md"


def write_summary_report(target: Path, title: str, lines: list[str], *, metrics: dict | None = None,
                         folder: Path | None = None, kind: str = "", member: bool = False) -> Path:
    """The shared report (:mod:`torchcal.report.generic`) of an instrument that writes none of its own."""
    # the shared report pulls in the stored-model and calibration-report code: loaded when a report is
    # written, not whenever the registry (which --help and header recognition use) imports this module
    from torchcal.report.generic import summary_report

    write_report(target, summary_report(title, lines, metrics=metrics, folder=folder, kind=kind), member=member)
    return Path(target) / REPORT


def check_report_folder(report: Path, model: Path) -> None:
    """Refuse, before any work, an ``evaluate --report`` folder torchcal may not write: a file, the
    model folder itself, a folder inside another torchcal output, or one that is not a report of its own."""
    report = Path(report)
    if report.resolve() == Path(model).resolve():
        raise FolderError(f"{report}: --report names the model folder, whose report.md is the fit's; give another folder")
    check_output_folder(report, "--report", purpose="report")


def evaluate_reported(instrument: Instrument, request: EvaluateRequest) -> EvaluateOutcome:
    """``instrument.evaluate``, then, with ``request.report``, the shared summary report where it wrote none.

    The report folder is built in a staging sibling and swapped into place when it is complete
    (:func:`torchcal.core.folder.staged_folder`): an interrupted evaluation leaves the earlier report, whole.
    """
    if request.report is None:
        return instrument.evaluate(request)
    final = Path(request.report)
    check_report_folder(final, request.model)
    with staged_folder(final, "--report", purpose="report", sealed=False) as staging:
        outcome = instrument.evaluate(replace(request, report=staging))
        name = REPORT if outcome.report is None else outcome.report.name
        if outcome.report is None:
            write_summary_report(staging, f"torchcal evaluate: {instrument.name} file "
                                 f"{Path(request.data).name} on {Path(request.model).name}", outcome.lines,
                                 metrics=outcome.metrics, folder=Path(request.model), kind=instrument.name)
    return replace(outcome, report=final / name)
