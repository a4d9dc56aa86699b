"""The contract every instrument meets: simulate -> recognise -> load -> fit -> evaluate, with known truth.

Run it for the registered instruments (``tests/instruments/test_contract.py`` does) or for an
instrument that lives outside torchcal::

    from torchcal.testing.instrument_contract import InstrumentContract

    class TestMyProbe(InstrumentContract):
        instrument_name = "my_probe"      # registered under the entry-point group

The instrument's :meth:`~torchcal.instruments.base.Instrument.contract_case` twin is written into
a temporary folder once per test session and instrument (the tests only read it; each fit writes
into its own folder), so the suite needs nothing but the instrument. Needs pytest.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from torchcal.config.compose import compose_options
from torchcal.instruments.base import (
    STAGES,
    ContractCase,
    EvaluateOutcome,
    EvaluateRequest,
    FitOutcome,
    FitRequest,
    Instrument,
    evaluate_reported,
    fit_committed,
)
from torchcal.instruments.registry import get, recognise
from torchcal.kinematics.robot import load_robot

# The twin files of each (instrument, twin overrides) in this test session: simulating a twin
# (a profile scan, a stiffness plan) costs seconds, and the tests read the files only.
_TWIN_FILES: dict[tuple[str, str], dict[str, Path]] = {}


class InstrumentContract:
    """Tests every instrument passes; subclasses set :attr:`instrument_name` (or parametrize it)."""

    instrument_name: str

    @pytest.fixture
    def instrument(self) -> Instrument:
        return get(self.instrument_name)

    @pytest.fixture
    def twin_files(self, instrument: Instrument, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
        overrides = list(instrument.contract_case().twin_overrides)
        key = (instrument.name, repr(overrides))
        if key not in _TWIN_FILES:
            spec = instrument.twin()
            config = compose_options(spec.config_factory(), overrides)
            folder = tmp_path_factory.mktemp(f"twin-{instrument.name}")
            _TWIN_FILES[key] = {name: Path(path) for name, path in spec.write(folder, config).items()}
        return _TWIN_FILES[key]

    def test_declares_what_it_is(self, instrument: Instrument) -> None:
        assert instrument.name == self.instrument_name
        assert instrument.stage in STAGES
        assert instrument.required_columns and all(c == c.lower() for c in instrument.required_columns)
        assert isinstance(instrument.contract_case(), ContractCase)

    def test_its_twin_files_are_recognised_as_its_own(self, instrument: Instrument, twin_files: dict[str, Path]) -> None:
        case = instrument.contract_case()
        assert "robot.yaml" in twin_files and case.fit_file in twin_files and case.test_file in twin_files
        assert recognise(twin_files[case.fit_file]).name == instrument.name

    def test_loads_every_row_of_its_twin(self, instrument: Instrument, twin_files: dict[str, Path]) -> None:
        case = instrument.contract_case()
        robot = load_robot(twin_files["robot.yaml"], end_link=case.end_link)
        path = twin_files[case.fit_file]
        data = instrument.load(path, robot, case.fit_overrides)
        rows = sum(1 for line in path.read_text().splitlines()[1:] if line.strip())
        assert len(data) > 0 and len(data) <= rows

    def test_fit_then_evaluate_reaches_the_truth_bound(
        self, instrument: Instrument, twin_files: dict[str, Path], tmp_path: Path
    ) -> None:
        case = instrument.contract_case()
        steps: list[str] = []
        outcome = fit_committed(instrument, FitRequest(
            robot=twin_files["robot.yaml"], data=twin_files[case.fit_file], out=tmp_path / "model",
            overrides=list(case.fit_overrides), end_link=case.end_link, progress=steps.append))
        assert isinstance(outcome, FitOutcome) and outcome.folder.is_dir()
        assert all(isinstance(line, str) for line in outcome.lines)
        scorer = recognise(twin_files[case.test_file])
        result = evaluate_reported(scorer, EvaluateRequest(
            model=outcome.folder, data=twin_files[case.test_file], overrides=list(case.evaluate_overrides),
            register=case.register, report=tmp_path / "evaluation"))
        assert isinstance(result, EvaluateOutcome)
        # every instrument's fit and evaluation leave a report (its own, or the shared summary)
        for folder in (outcome.folder, tmp_path / "evaluation"):
            for name in ("report.md", "report.html"):
                assert (folder / name).is_file() and (folder / name).stat().st_size > 200, folder / name
        assert result.report == tmp_path / "evaluation" / "report.md"
        value = float(result.metrics[case.metric])
        assert math.isfinite(value) and value <= case.bound, (
            f"{instrument.name}: {case.metric} = {value:.4f} mm on the held-out twin file, bound {case.bound} mm")
