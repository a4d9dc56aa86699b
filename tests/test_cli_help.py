"""``--help`` of each command lists every key=value option with its default, from the config dataclasses."""

from __future__ import annotations

import contextlib
import dataclasses
import io

import pytest

from torchcal.cli import main
from torchcal.core.options import list_options


def _help(command: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as stop:
        main([command, "--help"])
    assert stop.value.code == 0
    return out.getvalue()


def _dotted_fields(config, prefix: str = "") -> list[str]:
    keys = []
    for field in dataclasses.fields(config):
        value = getattr(config, field.name) if not isinstance(config, type) else None
        if value is not None and dataclasses.is_dataclass(value):
            keys += _dotted_fields(value, f"{prefix}{field.name}.")
        else:
            keys.append(f"{prefix}{field.name}")
    return keys


def _expected(command: str) -> list[tuple[object, str]]:
    from torchcal.config import compose_run_config
    from torchcal.config.schema import FitConfig
    from torchcal.instruments.registry import get, names

    if command == "fit":
        return [(FitConfig, "")] + [(get(n).options(), "") for n in names()]
    if command == "simulate":
        return [(get(n).twin().config_factory, "") for n in names()]
    if command == "run":
        return [(compose_run_config([])[0], "")]
    if command == "motion":
        from torchcal.motion.planner import PlanOptions

        return [(PlanOptions, "")]
    from torchcal.config.compose import merge_section
    from torchcal.studies.spec import StudyConfig

    base, sections = compose_run_config([], config_name="study", extra_sections=("study",))
    return [(merge_section(StudyConfig(), sections["study"]), "study."), (base, "")]


@pytest.mark.parametrize("command", ["fit", "simulate", "run", "study", "motion"])
def test_help_lists_every_option_with_its_default_and_a_description(command):
    text = _help(command)
    listed = {line.split()[0] for line in text.splitlines() if line.startswith("  ") and "=" in line.split()[0]}
    listed_keys = {item.split("=", 1)[0] for item in listed}
    for config, prefix in _expected(command):
        options = {o.key: o for o in list_options(config, prefix=prefix)}
        assert set(options) == set(_dotted_fields(config, prefix))  # every field, nested ones dotted
        for key, option in options.items():
            if command == "fit":
                # fit lists a key shared by several instruments once, with the first one's default
                assert key in listed_keys, f"{command}: {key} not listed"
            else:
                assert f"{key}={option.default}" in listed, f"{command}: {key} not listed"
            assert option.help, f"{command}: {key} has no description in its class's Attributes"
    if command == "fit":  # instrument options extend the tracker's: each key once, with its default
        from torchcal.config.schema import FitConfig

        assert all(f"{o.key}={o.default}" in listed for o in list_options(FitConfig))


def test_evaluate_help_lists_only_what_evaluate_reads():
    """Each kind of file lists the options its evaluate reads (units, ...), none of fit's choices."""
    from torchcal.instruments.registry import get, names

    text = _help("evaluate")
    blocks = text.split("\nkey=value options of ")[1:]
    assert [b.split(" ", 1)[0] for b in blocks] == list(names())
    for name, block in zip(names(), blocks):
        instrument = get(name)
        listed = {line.split()[0].split("=", 1)[0] for line in block.splitlines()[1:] if line.startswith("  ") and "=" in line.split()[0]}
        assert listed == set(instrument.evaluate_options()), name
    for fit_only in ("residual=", "split=", "cv_folds=", "prior_scale=", "gravity_compliance="):
        assert f"  {fit_only}" not in text


@pytest.mark.parametrize("option, rc", [("residual=mlp", 2), ("split=random", 2), ("joint_unit=rad", None)])
def test_evaluate_refuses_a_fit_option_in_one_line(tmp_path, capsys, option, rc):
    data = tmp_path / "test.csv"
    data.write_text("q1,q2,q3,q4,q5,q6,x,y,z\n" + "0,0,0,0,0,0,1000,0,500\n" * 6)
    code = main(["evaluate", "--model", str(tmp_path / "no-model"), "--data", str(data), option])
    err = capsys.readouterr().err
    assert code == 2 and len([line for line in err.splitlines() if line.startswith("torchcal: error:")]) == 1
    key = option.split("=")[0]
    if rc == 2:
        assert f"{key} is an option of fit, not of evaluate" in err and "joint_unit, length_unit" in err
    else:  # an option evaluate reads passes the check; the missing model folder is what stops it
        assert "option of fit" not in err and "no-model" in err
