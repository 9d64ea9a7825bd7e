"""The wheel a user installs works on its own: build it, install it in a fresh venv, run it.

``python -m build --wheel``, then a new virtual environment with nothing but the wheel
and its declared extras (``service``, ``ble``). From outside the repository it runs
``selfcal --version``, ``selfcal calibrate`` on a copied recording, ``selfcal serve``
(``/healthz`` answers, the dashboard's files are served), and a short ``selfcal demo``.
The wheel installs no generic top-level name: ``import service`` fails.
"""

import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def sh(*args, cwd=None, timeout=900, env=None):
    p = subprocess.run([str(a) for a in args], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)
    assert p.returncode == 0, f"{args}\nstdout: {p.stdout[-2000:]}\nstderr: {p.stderr[-4000:]}"
    return p


@pytest.fixture(scope="module")
def venv(tmp_path_factory):
    pytest.importorskip("build")
    work = tmp_path_factory.mktemp("wheel")
    src = work / "src"  # build from a copy: nothing is written into the checkout
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".venv", ".git", "build", "dist", "*.egg-info",
                                                              "__pycache__", ".pytest_cache", ".hypothesis"))
    sh(sys.executable, "-m", "build", "--wheel", "--no-isolation", "--outdir", work / "dist", src)
    wheels = list((work / "dist").glob("selfcal-*.whl"))
    assert len(wheels) == 1
    env_dir = work / "venv"
    sh(sys.executable, "-m", "venv", env_dir)
    py = env_dir / "bin" / "python"
    sh(py, "-m", "pip", "install", "-q", "--disable-pip-version-check", f"{wheels[0]}[service,ble]")
    return env_dir, work


def test_installed_wheel_runs_calibrate_serve_and_demo(venv):
    env_dir, work = venv
    exe = env_dir / "bin" / "selfcal"
    py = env_dir / "bin" / "python"
    run_dir = work / "elsewhere"
    run_dir.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    assert sh(exe, "--version", cwd=run_dir, env=env).stdout.startswith("selfcal ")
    # no generic top-level package, and the default config comes from inside the package
    p = subprocess.run([str(py), "-c", "import service"], cwd=run_dir, capture_output=True, text=True, env=env)
    assert p.returncode != 0 and "No module named 'service'" in p.stderr
    sh(py, "-c", "import selfcal_service.main, selfcal.config as c; assert c.load_config()['fit']", cwd=run_dir, env=env)
    # calibrate a recording copied out of the repository
    rec = run_dir / "poses.csv"
    shutil.copy(ROOT / "data" / "ggir-wrist-84h" / "poses.csv", rec)
    out = json.loads(sh(exe, "calibrate", rec, "--json", "--out", run_dir / "cal.json", cwd=run_dir, env=env).stdout)
    assert out["status"] in ("provisional", "calibrated") and (run_dir / "cal.json").exists()
    # serve: /healthz answers
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env_s = dict(env, SELFCAL_API_KEYS="app-key-0001=read")
    srv = subprocess.Popen([str(exe), "serve", "--db", str(run_dir / "s.db"), "--port", str(port)], cwd=run_dir,
                           env=env_s, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        body = None
        for _ in range(100):
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=2) as r:
                    body = json.loads(r.read())
                break
            except OSError:
                time.sleep(0.2)
        assert body is not None, "selfcal serve never answered /healthz"
        # the dashboard's pages and its vendored plotting library come from the wheel
        for path, needle in (("/ui", b"fleet.js"), ("/ui/static/device.js", b"uPlot"),
                             ("/ui/static/vendor/uplot/uPlot.iife.min.js", b"uPlot"),
                             ("/ui/static/vendor/uplot/LICENSE", b"MIT")):
            with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as r:
                assert r.status == 200 and needle in r.read(), path
    finally:
        srv.terminate()
        srv.wait(timeout=30)
    # a short demo: service subprocess, one virtual insole, the gateway
    demo = json.loads(sh(exe, "demo", "--devices", "1", "--hours", "0.2", "--json", "--no-progress",
                         cwd=run_dir, env=env, timeout=600).stdout)
    assert demo["lost_samples"] == 0 and demo["devices"][0]["samples_sent"] > 0
