"""Whole-or-absent output folders: staged commit, checksums, verification."""

from __future__ import annotations

import json

import pytest

from torchcal.core.folder import (
    CHECKSUMS,
    FolderError,
    check_output_folder,
    remove_member,
    staged_folder,
    verify_folder,
    write_member_json,
    write_member_text,
)
from torchcal.core.outputs import STAMP, OutputClaimError


def _folder(path, **files):
    for name, text in files.items():
        write_member_text(path, name, text)
    return path


def test_members_are_listed_and_verified(tmp_path):
    folder = _folder(tmp_path / "m", **{"calibration.json": "{}", "robot.yaml": "name: r\n"})
    listed = json.loads((folder / CHECKSUMS).read_text())["files"]
    assert sorted(listed) == ["calibration.json", "robot.yaml"]
    verify_folder(folder)
    remove_member(folder, "robot.yaml")
    assert not (folder / "robot.yaml").exists()
    verify_folder(folder)


@pytest.mark.parametrize("damage, message", [
    (lambda f: (f / "robot.yaml").write_text("name: other\n"), "robot.yaml: SHA-256 differs"),
    (lambda f: (f / "robot.yaml").unlink(), "robot.yaml: missing"),
    (lambda f: (f / "residual.safetensors").write_bytes(b"old"), "residual.safetensors: not listed"),
    (lambda f: (f / CHECKSUMS).unlink(), "no checksums.json"),
    (lambda f: (f / CHECKSUMS).write_text("{"), "checksums.json: unreadable"),
])
def test_damage_is_refused_naming_the_file(tmp_path, damage, message):
    folder = _folder(tmp_path / "m", **{"calibration.json": "{}", "robot.yaml": "name: r\n"})
    damage(folder)
    with pytest.raises(FolderError, match=message):
        verify_folder(folder)


def test_unlisted_notes_are_tolerated(tmp_path):
    folder = _folder(tmp_path / "m", **{"calibration.json": "{}"})
    (folder / "notes.txt").write_text("mine\n")
    verify_folder(folder)


def test_staged_folder_replaces_whole(tmp_path):
    dest = _folder(tmp_path / "m", **{"calibration.json": "{}", "residual.json": "{}"})
    with staged_folder(dest) as staging:
        write_member_json(staging, "calibration.json", {"new": True})
        assert not dest.joinpath("calibration.json").read_text().startswith('{\n  "new"')
    assert sorted(p.name for p in dest.iterdir()) == [STAMP, "calibration.json", CHECKSUMS]  # no old residual.json
    verify_folder(dest)
    assert [p.name for p in tmp_path.iterdir()] == ["m"]  # no staging folder left


def test_staged_folder_keeps_the_earlier_on_error(tmp_path):
    dest = _folder(tmp_path / "m", **{"calibration.json": "{}"})
    before = {p.name: p.read_bytes() for p in dest.iterdir()}
    with pytest.raises(KeyboardInterrupt), staged_folder(dest) as staging:
        write_member_json(staging, "calibration.json", {"new": True})
        raise KeyboardInterrupt
    assert {p.name: p.read_bytes() for p in dest.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["m"]


@pytest.mark.parametrize("moment", ["mkdtemp returned", "chmod"])
def test_an_interrupt_just_after_the_staging_folder_is_made_leaves_nothing(tmp_path, monkeypatch, moment):
    """Ctrl-C lands as the staging folder appears (before its name is even kept): cleaned up all the same."""
    import tempfile

    import torchcal.core.folder as folder

    dest = _folder(tmp_path / "m", **{"calibration.json": "{}"})
    before = {p.name: p.read_bytes() for p in dest.iterdir()}
    real_mkdtemp = tempfile.mkdtemp

    def interrupted_after(*args, **kwargs):
        real_mkdtemp(*args, **kwargs)
        raise KeyboardInterrupt

    def interrupted_chmod(*args, **kwargs):
        raise KeyboardInterrupt

    if moment == "mkdtemp returned":
        monkeypatch.setattr(folder.tempfile, "mkdtemp", interrupted_after)
    else:
        monkeypatch.setattr(folder.os, "chmod", interrupted_chmod)
    with pytest.raises(KeyboardInterrupt), staged_folder(dest):
        pass
    assert {p.name: p.read_bytes() for p in dest.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["m"]


def test_staged_folder_creates_a_new_one_and_seals_unrecorded_files(tmp_path):
    dest = tmp_path / "sub" / "export"
    with staged_folder(dest) as staging:
        (staging / "model.onnx").write_bytes(b"onnx")
    assert json.loads((dest / CHECKSUMS).read_text())["files"].keys() == {"model.onnx"}
    verify_folder(dest)


def test_output_paths_checked_before_work(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputClaimError, match="existing file"):
        check_output_folder(tmp_path / "file")
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "train.csv").write_text("q1\n")
    with pytest.raises(OutputClaimError, match="other files"):
        check_output_folder(tmp_path / "data")
    with pytest.raises(OutputClaimError, match="a file stands"):
        check_output_folder(tmp_path / "file" / "out")
    check_output_folder(tmp_path / "new" / "out")
    (tmp_path / "empty").mkdir()
    check_output_folder(tmp_path / "empty")
