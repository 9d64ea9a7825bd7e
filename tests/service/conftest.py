"""Fixtures for the service tests: a real ``selfcal serve`` subprocess on 127.0.0.1.

``tests/`` has no ``__init__.py``, so this folder is *not* a package (a package named
``service`` here would shadow the real ``service`` package); helper modules have
unique top-level names (``service_fakes``, ``service_helpers``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from service_helpers import KEYS, ServerProcess, backend  # noqa: E402


@pytest.fixture(scope="session", autouse=True)
def database_backend():
    """On a PostgreSQL run, one throw-away cluster for the session (each server gets its
    own database). Refuses to run, rather than skip, when asked for PostgreSQL and none
    can be started: CI must not pass without having tested it."""
    if backend() != "postgresql":
        yield "sqlite"
        return
    import os

    if os.environ.get("SELFCAL_TEST_PG_URL"):  # a server given from outside
        yield "postgresql"
        return
    sys.path.insert(0, str(HERE.parent))
    from pg_cluster import PgCluster, unavailable

    why = unavailable()
    if why:
        pytest.fail(f"SELFCAL_TEST_BACKEND=postgresql but no PostgreSQL can be started: {why}")
    cluster = PgCluster().start()
    os.environ["SELFCAL_TEST_PG_URL"] = cluster.base_url
    try:
        yield "postgresql"
    finally:
        os.environ.pop("SELFCAL_TEST_PG_URL", None)
        cluster.stop()


@pytest.fixture(scope="module")
def fake_server(tmp_path_factory):
    """One server with the fake calibrator (publishes after 200 samples), shared by a module."""
    tmp = tmp_path_factory.mktemp("svc")
    srv = ServerProcess(tmp / "selfcal.db", tmp, calibrator="service_fakes:FakeCalibrator")
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture()
def keys():
    return KEYS
