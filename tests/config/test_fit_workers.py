"""A fit's worker processes are started from its options alone, before the command imports torch."""

from __future__ import annotations

import subprocess
import sys

from torchcal.config.schema import FitConfig
from torchcal.config.workers import cross_validates
from torchcal.stages.geometry import structure_options


def test_the_configuration_imports_no_numerical_module():
    """`torchcal run` composes its options and starts its workers first: nothing on that path may
    import torch (about a second), or the workers' start-up would follow it instead of overlapping it."""
    code = ("import sys; from torchcal.config import compose_run_config; from torchcal.config.workers import start_fit_workers; "
            "compose_run_config([]); print(sorted(m for m in ('torch', 'numpy', 'sklearn', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_workers_are_wanted_exactly_where_the_fit_compares_structures_or_heads():
    for residual in ("none", "auto"):
        for gravity in ("none", "wrist", "auto"):
            for harmonics in ("none", "first", "auto"):
                config = FitConfig(residual=residual, gravity_compliance=gravity, joint_harmonics=harmonics)
                expected = residual != "none" or len(structure_options(config)) > 1
                assert cross_validates(config) == expected, (residual, gravity, harmonics)
