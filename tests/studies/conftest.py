"""Fixtures of the study tests."""

from __future__ import annotations

import glob
import os
import socket
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def postgres_url() -> str:
    url = os.environ.get("TORCHCAL_TEST_PG_URL")
    if not url:
        pytest.skip("no PostgreSQL server: set TORCHCAL_TEST_PG_URL (.ci/run starts one)")
    return url


@dataclass(frozen=True)
class PrivateServer:
    """A PostgreSQL server of one test's own, which that test may stop and restart."""

    url: str
    data: str
    port: int

    def control(self, action: str) -> None:
        """``restart``, ``stop`` or ``start`` this server (started again on its own port)."""
        pg_ctl = max(glob.glob("/usr/lib/postgresql/*/bin/pg_ctl"))
        options = ""
        if action == "start":
            options = (f"-l {self.data}/server.log -o "
                       f"'-p {self.port} -k {self.data} -c listen_addresses=127.0.0.1'")
        subprocess.run(["su", "postgres", "-s", "/bin/sh", "-c", f"{pg_ctl} -D {self.data} -m fast -w {options} {action}"],
                       check=True, stdout=subprocess.DEVNULL)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def private_postgres():
    """A throw-away server (``.ci/postgres.sh`` on a free port), so that a test stopping it
    never takes the shared server away from tests running beside it."""
    if os.geteuid() != 0 or not glob.glob("/usr/lib/postgresql/*/bin/pg_ctl") or not os.environ.get("TORCHCAL_TEST_PG_URL"):
        pytest.skip("a private PostgreSQL server needs root and the server installed (.ci/run does both)")
    port = _free_port()
    env = {**os.environ, "TORCHCAL_PG_PORT": str(port)}
    data = subprocess.run(["bash", str(REPO / ".ci" / "postgres.sh"), "start"], env=env, check=True,
                          capture_output=True, text=True).stdout.strip()
    try:
        yield PrivateServer(f"postgresql://postgres@127.0.0.1:{port}/torchcal_test", data, port)
    finally:
        subprocess.run(["bash", str(REPO / ".ci" / "postgres.sh"), "stop", data], env=env, check=False)
