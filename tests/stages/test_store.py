"""Loading a model folder: entries a fit could not have written are refused in one line."""

from __future__ import annotations

import pytest
import torch

from torchcal.stages.store import load_model


@pytest.mark.parametrize("edit, message", [
    (lambda m: m["joint_harmonics"]["coefficients_rad"][0].__setitem__(0, float("nan")), "finite numbers"),
    (lambda m: m["joint_harmonics"]["coefficients_rad"].append([0.0] * 6), "in pairs"),
    (lambda m: m["joint_harmonics"]["coefficients_rad"][0].__setitem__(0, "abc"), "table of numbers"),
    (lambda m: m["joint_harmonics"]["coefficients_rad"][0].__setitem__(5, 0.01), "last joint"),
    (lambda m: m["gravity_compliance"].__setitem__("points", ["knee"]), "gravity_compliance.points"),
    (lambda m: m["gravity_compliance"].__setitem__("points", ["tcp", "elbow"]), "per term"),
    (lambda m: m["gravity_compliance"].__setitem__("tcp_point_m", [0.1, "x"]), "tcp_point_m"),
    (lambda m: m.__setitem__("with_orientation", "yes"), "with_orientation must be true or false"),
])
def test_edited_joint_space_entries_are_one_line_naming_calibration_json(tmp_path, edit, message):
    """A model folder edited by hand (and its checksums rewritten to match) is refused at load, not deep in a graph."""
    import json

    from torchcal.config.schema import FitConfig
    from torchcal.core.errors import ModelError
    from torchcal.core.folder import write_member
    from torchcal.sim.twin import Twin, TwinConfig
    from torchcal.stages.pipeline import fit_model

    twin = Twin.create(TwinConfig(seed=3, gravity=True, gear=True))
    folder = tmp_path / "m"
    fit_model(folder, twin.robot, twin.sample(150, torch.Generator().manual_seed(11)),
              FitConfig(residual="none", gravity_compliance="wrist", joint_harmonics="first", progress=False))
    meta = json.loads((folder / "calibration.json").read_text())
    assert meta.get("gravity_compliance") and meta.get("joint_harmonics")
    load_model(folder)  # as written: loads
    edit(meta)
    write_member(folder, "calibration.json", json.dumps(meta).encode())  # checksums rewritten to match
    with pytest.raises(ModelError, match=message) as caught:
        load_model(folder)
    assert "calibration.json" in str(caught.value) and "\n" not in str(caught.value)
