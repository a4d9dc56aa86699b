"""Build hook: the top-level ``configs/`` ships inside the wheel as ``torchcal/configs``.

Everything else is declared in pyproject.toml. A source checkout reads ``configs/`` in place; an
installed wheel reads the copy (see :func:`torchcal.config.compose.config_dir`).
"""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildPyWithConfigs(build_py):
    """``build_py`` that also copies ``configs/`` into the built package."""

    def run(self) -> None:
        super().run()
        source = Path(__file__).parent / "configs"
        if source.is_dir():
            self.copy_tree(str(source), str(Path(self.build_lib) / "torchcal" / "configs"))


setup(cmdclass={"build_py": BuildPyWithConfigs})
