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

    if command in ("fit", "evaluate"):
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


@pytest.mark.parametrize("command", ["fit", "evaluate", "simulate", "run", "study", "motion"])
def test_help_lists_every_option_with_its_default_and_a_description(command):
    text = _help(command)
    listed = {line.split()[0] for line in text.splitlines() if line.startswith("  ") and "=" in line.split()[0]}
    listed_keys = {item.split("=", 1)[0] for item in listed}
    for config, prefix in _expected(command):
        options = {o.key: o for o in list_options(config, prefix=prefix)}
        assert set(options) == set(_dotted_fields(config, prefix))  # every field, nested ones dotted
        for key, option in options.items():
            if command in ("fit", "evaluate"):
                # fit and evaluate list a key shared by several instruments once, with the first one's default
                assert key in listed_keys, f"{command}: {key} not listed"
            else:
                assert f"{key}={option.default}" in listed, f"{command}: {key} not listed"
            assert option.help, f"{command}: {key} has no description in its class's Attributes"
    if command in ("fit", "evaluate"):  # instrument options extend the tracker's: each key once, with its default
        from torchcal.config.schema import FitConfig

        assert all(f"{o.key}={o.default}" in listed for o in list_options(FitConfig))
