"""One BLAS thread for a selfcal process (selfcal.blas_threads): set by the command line and
the service, never over a count the user chose, and the same results either way."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from selfcal.blas_threads import SET_VARIABLES, THREAD_VARIABLES, one_blas_thread
from selfcal.config import load_config
from selfcal.replay import replay


def blas_threads() -> list[int]:
    """The thread count of every BLAS library loaded in this process."""
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


@pytest.fixture
def no_thread_variables(monkeypatch):
    for name in THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)


def env_without_thread_variables() -> dict[str, str]:
    """This process's environment without any BLAS thread count (a fresh process's default)."""
    return {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}


def two_threads_or_skip() -> None:
    if blas_threads() != [2] * len(blas_threads()) or not blas_threads():
        pytest.skip("the BLAS library here cannot run 2 threads (one core?)")


def test_one_thread_is_set_for_the_loaded_libraries_and_for_those_loaded_later(no_thread_variables):
    with threadpool_limits(limits=2, user_api="blas"):  # restores this process's counts after the test
        two_threads_or_skip()
        assert one_blas_thread() is True
        assert blas_threads() == [1] * len(blas_threads())
        assert all(os.environ[name] == "1" for name in SET_VARIABLES)
        assert "OMP_NUM_THREADS" not in os.environ  # it sizes other libraries' pools too


@pytest.mark.parametrize("name", THREAD_VARIABLES)
def test_a_thread_count_the_user_set_is_kept(no_thread_variables, monkeypatch, name):
    monkeypatch.setenv(name, "2")
    with threadpool_limits(limits=2, user_api="blas"):
        two_threads_or_skip()
        assert one_blas_thread() is False
        assert blas_threads() == [2] * len(blas_threads())
        assert [n for n in SET_VARIABLES if n in os.environ and n != name] == []


#: A command's run replaced by one that prints the BLAS thread counts it runs with.
_PROBE = """
import json, os, sys
from threadpoolctl import threadpool_info
import selfcal.commands.simulate as cmd
cmd.run = lambda args: print(json.dumps({
    "threads": [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"],
    "env": os.environ.get("OPENBLAS_NUM_THREADS")})) or 0
from selfcal.cli import main
sys.exit(main(["simulate", "--seed", "1", "--out", "unused"]))
"""


def run_probe(env_extra: dict[str, str]) -> dict:
    q = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120,
                       env={**env_without_thread_variables(), **env_extra})
    assert q.returncode == 0, q.stderr
    return json.loads(q.stdout.strip().splitlines()[-1])


def test_the_command_line_runs_its_commands_with_one_blas_thread():
    got = run_probe({})
    assert got["threads"] and all(n == 1 for n in got["threads"])
    assert got["env"] == "1"  # what the processes it starts inherit


def test_the_command_line_keeps_a_count_set_in_the_environment():
    if os.cpu_count() and os.cpu_count() < 2:
        pytest.skip("one core: OpenBLAS runs one thread whatever is asked")
    got = run_probe({"OPENBLAS_NUM_THREADS": "2"})
    assert got == {"threads": [2] * len(got["threads"]), "env": "2"} and got["threads"]


#: A fresh process that starts the service's app (its lifespan) and prints the BLAS thread
#: counts before and after. (OpenBLAS ignores a count set from another thread once the main
#: thread has set one, so this runs where nothing set one before, as a server process.)
_SERVICE_PROBE = """
import json, sys
from threadpoolctl import threadpool_info
from fastapi.testclient import TestClient
from selfcal_service.main import create_app
from selfcal_service.settings import load_settings
count = lambda: [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]
settings = load_settings(None, environ={}, overrides={"db_path": sys.argv[1], "gc_freeze": False,
                                                      "api_keys": "admin-key-for-this-test=admin"})
before = count()
with TestClient(create_app(settings)) as client:
    assert client.get("/healthz").status_code == 200
    print(json.dumps({"before": before, "after": count()}))
"""


def test_the_service_sets_one_blas_thread_when_it_starts(tmp_path):
    if not os.cpu_count() or os.cpu_count() < 2:
        pytest.skip("one core: OpenBLAS runs one thread anyway")
    q = subprocess.run([sys.executable, "-c", _SERVICE_PROBE, str(tmp_path / "s.db")], capture_output=True,
                       text=True, timeout=120, env=env_without_thread_variables())
    assert q.returncode == 0, q.stderr
    got = json.loads(q.stdout.strip().splitlines()[-1])
    assert got["before"] and all(n >= 2 for n in got["before"])
    assert got["after"] and all(n == 1 for n in got["after"])


def test_a_replay_is_the_same_with_one_blas_thread_and_with_two():
    cfg = load_config()

    def run():
        r = replay(days=10, seed=100, config=cfg)
        return [{k: v for k, v in row.items() if k != "fit_ms"} for row in r["refits"]], r["final"]

    with threadpool_limits(limits=2, user_api="blas"):
        two_threads_or_skip()
        many = run()
    with threadpool_limits(limits=1, user_api="blas"):
        one = run()
    assert json.dumps(one, sort_keys=True, default=str) == json.dumps(many, sort_keys=True, default=str)
    assert np.isfinite(one[0][-1]["sphere_norm_rms_mg"])
