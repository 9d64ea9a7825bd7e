"""The README's shell examples run as written.

* The CLI block ("Try it on the repository's data", between ``<!-- cli-example:begin -->``
  and ``<!-- cli-example:end -->``) is run by bash with ``set -e`` from the repository
  root, the venv's ``selfcal`` first on ``PATH``: every command must exit 0 and leave
  its outputs.
* The service's ``sh`` block (the one with the curls) is run by bash against a live
  server with only the port changed. Every curl must get a 2xx, except the rollback (a
  fresh device has no version 1 to go back to: a 4xx naming that, never 415 for a
  missing Content-Type, never 5xx).
"""

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def sh_blocks() -> list[str]:
    """Every ``sh`` block of the README (indented ones too), in order."""
    return re.findall(r"```sh\n(.*?)```", README, re.S)


def test_readme_cli_examples_on_the_repository_data(tmp_path):
    m = re.search(r"<!-- cli-example:begin -->\s*```sh\n(.*?)```\s*<!-- cli-example:end -->", README, re.S)
    assert m, "README has no cli-example block"
    block = m.group(1)
    commands = [ln for ln in block.splitlines() if ln.startswith("selfcal ")]
    assert len(commands) >= 8
    for needed in ("selfcal --version", "selfcal calibrate ", "--history", "selfcal apply ", "selfcal diagnose ",
                   "selfcal simulate ", "selfcal replay --recording ", "selfcal replay --days "):
        assert needed in block, needed
    assert "curl" not in block
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
               TMPDIR=str(tmp))  # mktemp -d: under the test's own folder
    # -x traces every command as it starts: with -e, each one traced before the end exited 0
    p = subprocess.run(["bash", "-c", "set -ex\n" + block], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "Traceback" not in p.stderr, p.stderr[-3000:]
    traced = [ln for ln in p.stderr.splitlines() if ln.startswith("+ selfcal ")]
    assert len(traced) == len(commands), traced
    (out,) = [d for d in tmp.iterdir() if d.is_dir()]  # $OUT
    # outputs: stdout of each command, files under $OUT
    assert re.search(r"^selfcal \d+\.\d+", p.stdout, re.M)
    cal_json = json.loads(next(ln for ln in p.stdout.splitlines() if ln.startswith("{")))
    assert cal_json["format"] == "selfcal-calibration" and cal_json["unit"] == "counts"
    cal = json.loads((out / "cal.json").read_text())
    assert cal["format"] == "selfcal-calibration" and set(cal["params"]) >= {"bx", "sx", "nxy"}
    history = [json.loads(ln) for ln in (out / "history.jsonl").read_text().splitlines()]
    assert len(history) >= 2 and history[-1]["version"] == cal["version"]
    applied = (out / "poses_g.csv").read_text().splitlines()
    assert applied[0] == "# selfcal-recording v1" and len(applied) > 1000
    assert "cause:" in p.stdout  # diagnose
    assert (out / "sim.csv").stat().st_size > 0 and json.loads((out / "sim.truth.json").read_text())["params"]
    assert "truth: " + str(out / "sim.truth.json") in p.stdout and "final: true" in p.stdout  # replay --recording
    assert "replay seed 7: 3 days" in p.stdout  # simulated replay


@pytest.mark.service
@pytest.mark.skipif(shutil.which("curl") is None, reason="curl is not installed")
def test_readme_serve_and_curl_examples(tmp_path):
    keys = re.search(r"SELFCAL_API_KEYS='([^']+)' selfcal serve --db selfcal.db", README)
    assert keys, "README has no serve line"
    for pair in keys.group(1).split(","):
        assert len(pair.split("=")[0]) >= 8, f"README key too short for the service: {pair}"
    curl_blocks = [b for b in sh_blocks() if "curl -s" in b]  # the service's block, not the CLI one
    assert len(curl_blocks) == 1, "README: expected exactly one sh block with curl"
    block = curl_blocks[0]
    port = free_port()
    env = dict(os.environ, SELFCAL_API_KEYS=keys.group(1), PYTHONPATH=str(ROOT))
    srv = subprocess.Popen([sys.executable, "-m", "selfcal.cli", "serve", "--db", str(tmp_path / "selfcal.db"),
                            "--port", str(port)], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for _ in range(150):
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=1).read()
                break
            except OSError:
                time.sleep(0.2)
        script = block.replace("http://127.0.0.1:8000", f"http://127.0.0.1:{port}")
        # every curl also prints its status code on a line of its own
        script = script.replace("curl -s ", "curl -s -w '\\nHTTP %{http_code}\\n' ")
        p = subprocess.run(["bash", "-c", "set -e\n" + script], capture_output=True, text=True, timeout=60)
        assert p.returncode == 0, p.stderr
        codes = [int(c) for c in re.findall(r"^HTTP (\d{3})$", p.stdout, re.M)]
        bodies = re.split(r"^HTTP \d{3}$", p.stdout, flags=re.M)
        assert len(codes) == block.count("curl -s"), p.stdout
        ack = json.loads(bodies[0])
        assert codes[0] == 200 and ack["accepted"] == 2 and ack["duplicate"] is False
        for i, code in enumerate(codes):  # (the block seeds version 1 before it rolls back to it: a 404 before)
            assert 200 <= code < 300, (i, code, bodies[i])
        rollback = [i for i, line in enumerate(re.findall(r"curl -s.*", block)) if "rollback" in line]
        assert len(rollback) == 1
        back = json.loads(bodies[rollback[0]])
        assert back["source"] == "rollback" and back["version"] == 2
    finally:
        srv.terminate()
        srv.wait(timeout=30)
