"""Compose ``configs/`` (Hydra config groups) with ``key=value`` overrides onto typed dataclasses.

This is the one override path of every command: :func:`compose_options` for a command's options
dataclass (``fit``, ``evaluate``, ``simulate``, ``motion``, every instrument), :func:`compose_run_config`
and :func:`merge_section` for ``run`` and ``study``. Each composes the group selections it accepts,
then sets the fields with :func:`torchcal.core.overrides.apply_overrides` (its checks and messages).

Overrides are of two kinds. A bare group name selects an option of a config group
(``model=mlp``, ``study=elm_mayfly``): Hydra composes those from ``configs/``. A dotted or plain
field (``twin.n_train=120``, ``name=trial``) sets one field: OmegaConf merges it onto the
dataclass schema, so a misspelt key or a wrong type is an error naming the key rather than a
silently ignored setting. Without a ``configs/`` folder (a wheel installed elsewhere) the
dataclass defaults stand in for it and group selections are refused with a clear message.
"""

from __future__ import annotations

import os
from dataclasses import is_dataclass
from pathlib import Path
from typing import Any, TypeVar, cast

import yaml

from torchcal.config.schema import FitConfig, RunConfig
from torchcal.core.errors import TorchcalError, did_you_mean
from torchcal.core.folder import CHECKSUMS, write_member_text
from torchcal.core.io import atomic_write_text
from torchcal.core.overrides import apply_overrides, field_names

GROUPS = ("robot", "measurement", "model", "experiment", "study")
T = TypeVar("T")
CONFIG_DIR_ENV = "TORCHCAL_CONFIG_DIR"


def config_dir() -> Path | None:
    """The ``configs/`` folder: ``$TORCHCAL_CONFIG_DIR``, ``./configs``, the source tree's, or the
    copy an installed wheel carries (``torchcal/configs``, written by the build)."""
    candidates = []
    if os.environ.get(CONFIG_DIR_ENV):
        named = Path(os.environ[CONFIG_DIR_ENV])
        if not (named / "config.yaml").is_file():  # asked for by name: never silently another folder
            what = "has no config.yaml" if named.is_dir() else "is not a folder"
            raise TorchcalError(f"{CONFIG_DIR_ENV}={named} {what}; point it at a configs/ folder or unset it")
        candidates.append(named)
    package = Path(__file__).resolve().parents[1]
    candidates += [Path.cwd() / "configs", package.parent / "configs", package / "configs"]
    for candidate in candidates:
        if (candidate / "config.yaml").is_file():
            return candidate.resolve()
    return None


def split_overrides(overrides: list[str]) -> tuple[list[str], list[str]]:
    """Separate group selections (``model=mlp``) from field overrides (``fit.seed=3``)."""
    bad = [o for o in overrides if "=" not in o]
    if bad:
        raise TorchcalError(f"override '{bad[0]}' is not of the form key=value")
    groups = [o for o in overrides if o.split("=", 1)[0].strip() in GROUPS]
    fields = [o for o in overrides if o.split("=", 1)[0].strip() not in GROUPS]
    return groups, fields


def _check_groups(group_overrides: list[str], folder: Path) -> None:
    """Refuse a group selection Hydra would misread: a group given twice (Hydra keeps the last
    silently), a value that is a path (``model=../config`` would load another folder's file as a
    model) or an option that is not a file of the group (listing the group's options)."""
    seen: dict[str, str] = {}
    for item in group_overrides:
        group, value = (part.strip() for part in item.split("=", 1))
        if group in seen:
            raise TorchcalError(f"config group '{group}' is given twice ('{seen[group]}' and '{item}'); give it once")
        seen[group] = item
        options = sorted(p.stem for p in (folder / group).glob("*.yaml")) if (folder / group).is_dir() else []
        if not value or "/" in value or "\\" in value or ".." in value:
            raise TorchcalError(f"'{item}': a config group takes the name of one of its options, not a path; "
                                f"{group} options: {', '.join(options) or 'none'}")
        if value not in options:
            raise TorchcalError(f"'{item}': no option '{value}' in config group '{group}'{did_you_mean(value, sorted(options))}; "
                                f"{group} options: {', '.join(options) or 'none'} (files of {folder / group})")


def _check_field_keys(schema: Any, fields: list[str], extra: tuple[str, ...] = (), prefix: str = "") -> None:
    """Refuse a ``key=value`` whose key names no field of the dataclass ``schema``, with the closest
    key (a dotted key is followed through nested dataclasses; below a field that is not one, a
    mapping, it is left to the merge). ``extra``: other names a key may be (the config groups);
    ``prefix``: the section the keys were taken from (``study.``), for the message."""
    for item in fields:
        key = item.split("=", 1)[0].strip()
        node, done = schema, cast(list[str], [])
        for part in key.split("."):
            if not is_dataclass(node) or isinstance(node, type):
                break
            names = field_names(node)
            if part not in names:
                candidates = {".".join([*done, n]) for n in names} | (set(extra) if not done else set())
                section = (prefix + ".".join(done)).rstrip(".")
                where = f" in '{section}'" if section else ""
                match = did_you_mean(key, sorted(candidates), prefix)
                raise TorchcalError(f"invalid override (key '{prefix}{key}'): no key '{part}'{where}{match}")
            done.append(part)
            node = getattr(node, part)


def _compose_yaml(config_name: str, group_overrides: list[str]):
    """The Hydra composition of ``config_name`` with group selections (an OmegaConf node)."""
    from omegaconf import OmegaConf

    folder = config_dir()
    if folder is None:
        if group_overrides:
            raise TorchcalError(
                f"'{group_overrides[0]}' selects a config group, but no configs/ folder was found "
                f"(set {CONFIG_DIR_ENV} or run from the project folder)"
            )
        return OmegaConf.create({})
    _check_groups(group_overrides, folder)
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    try:
        with initialize_config_dir(config_dir=str(folder), version_base="1.3", job_name="torchcal"):
            node = compose(config_name=config_name, overrides=group_overrides)
    except (HydraException, OmegaConfBaseException) as exc:
        raise TorchcalError(f"configs: {str(exc).splitlines()[0]}") from None
    except yaml.YAMLError as exc:
        raise TorchcalError(_yaml_problem(exc, folder)) from None
    return node


def _yaml_problem(exc: Exception, folder: Path) -> str:
    """One line for a config file YAML cannot read: the file, the line and the problem. Hydra reads
    the files with OmegaConf's loader, a ``yaml.SafeLoader`` that refuses a key given twice and any
    ``!!python`` tag (nothing of a file is run)."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    problem = str(getattr(exc, "problem", None) or exc).splitlines()[0]
    if mark is None:
        return f"configs: a file of {folder} is not valid YAML: {problem}"
    first = getattr(exc, "context_mark", None)
    if problem.startswith("found duplicate key") and first is not None:
        key = problem[len("found duplicate key"):].strip()
        again = "" if first.line == mark.line else f" (first on line {first.line + 1})"
        problem = (f"key {key!r} is given twice in one mapping{again}; YAML would keep only the last value, "
                   "so give each key once")
    elif problem.startswith("could not determine a constructor for the tag"):
        problem += " (config files are plain YAML: no Python tags)"
    return f"configs: {mark.name}, line {mark.line + 1}: {problem}"


def _merge(schema: Any, *nodes) -> Any:
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        merged = OmegaConf.merge(OmegaConf.structured(schema), *nodes)
        return OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None)
        where = f" (key '{key}')" if key else ""
        raise TorchcalError(f"invalid configuration{where}: {str(exc).splitlines()[0]}") from None


def compose_run_config(overrides: list[str], config_name: str = "config", extra_sections: tuple[str, ...] = ()):
    """A :class:`~torchcal.config.schema.RunConfig` from ``configs/`` plus overrides.

    Returns ``(run_config, sections)`` where ``sections`` maps each name in ``extra_sections``
    (e.g. ``study``) to its composed OmegaConf node, taken out before the run schema is applied.
    """
    from omegaconf import OmegaConf

    group_overrides, field_overrides = split_overrides(overrides)
    composed = _compose_yaml(config_name, group_overrides)
    OmegaConf.set_struct(composed, False)
    sections = {}
    field_by_section: dict[str, list[str]] = {name: [] for name in extra_sections}
    run_fields: list[str] = []
    for item in field_overrides:
        head = item.split("=", 1)[0].split(".", 1)[0].strip()
        field_by_section.get(head, run_fields).append(item)
    for name in extra_sections:
        node = composed.pop(name, None) if name in composed else None
        sections[name] = (node, field_by_section[name])
    merged = _merge(RunConfig(), composed)
    _check_field_keys(merged, run_fields, extra=GROUPS)
    config = apply_overrides(merged, run_fields)
    return config, sections


def merge_section(schema: Any, section: tuple[Any, list[str]]):
    """A composed section plus its ``section.key=value`` overrides, merged onto ``schema``."""
    node, fields = section
    stripped = [item.split(".", 1)[1] for item in fields if "." in item.split("=", 1)[0]]
    base = _merge(schema, node) if node is not None else schema
    _check_field_keys(base, stripped, prefix=fields[0].split(".", 1)[0] + "." if fields else "")
    return apply_overrides(base, stripped)


def save_resolved_config(path: str | Path, config: Any, **sections: Any) -> Path:
    """Write the fully resolved configuration (dataclasses) as YAML, atomically."""
    from omegaconf import DictConfig, OmegaConf

    tree = OmegaConf.structured(config)
    if sections:
        tree = cast(DictConfig, OmegaConf.merge(OmegaConf.create({}), tree))  # merged onto a mapping
        OmegaConf.set_struct(tree, False)
        for key, value in sections.items():
            tree[key] = OmegaConf.structured(value) if not isinstance(value, dict) else OmegaConf.create(value)
    path = Path(path)
    if (path.parent / CHECKSUMS).is_file():  # a member of a model folder: recorded with the others
        write_member_text(path.parent, path.name, OmegaConf.to_yaml(tree, resolve=True))
    else:
        atomic_write_text(path, OmegaConf.to_yaml(tree, resolve=True))
    return Path(path)


def compose_options(schema: T, overrides: list[str], *, groups: tuple[str, ...] = (), section: str | None = None) -> T:
    """``schema`` (a dataclass instance) with a command's ``key=value`` overrides.

    ``groups``: the config groups this command accepts (``model=mlp`` picks ``configs/model/mlp.yaml``);
    their composition, the ``section`` node of it where given, is merged first. Every other item sets
    a field. A group the command does not accept is refused in one line.
    """
    from omegaconf import OmegaConf

    group_overrides, _ = split_overrides(overrides)
    own = field_names(type(schema))  # a field named like a group (a twin's ``robot=``) is a field
    group_overrides = [g for g in group_overrides if g.split("=", 1)[0].strip() not in own]
    chosen = [g for g in group_overrides if g.split("=", 1)[0].strip() in groups]
    refused = [g for g in group_overrides if g not in chosen]
    if refused:
        accepted = f"only the {', '.join(groups)} group applies" if groups else "no config group applies"
        raise TorchcalError(f"'{refused[0]}': {accepted} to this command")
    fields = [o for o in overrides if o not in chosen]
    if chosen:
        composed = _compose_yaml("config", chosen)
        node = composed.get(section, OmegaConf.create({})) if section else composed
        schema = _merge(schema, node)
    _check_field_keys(schema, fields, extra=groups)
    return apply_overrides(schema, fields)


def compose_fit_config(overrides: list[str]) -> FitConfig:
    """A :class:`~torchcal.config.schema.FitConfig` for ``torchcal fit``: ``model=<name>`` picks a file
    of ``configs/model/``, other ``key=value`` set fields (``method=lasso``, ``seed=3``)."""
    return compose_options(FitConfig(), overrides, groups=("model",), section="fit")
