"""Fixtures of the study tests."""

from __future__ import annotations

import os

import pytest


@pytest.fixture
def postgres_url() -> str:
    url = os.environ.get("TORCHCAL_TEST_PG_URL")
    if not url:
        pytest.skip("no PostgreSQL server: set TORCHCAL_TEST_PG_URL (.ci/run starts one)")
    return url
