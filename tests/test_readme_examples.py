"""The README's shell examples run as written: the serve line and every curl, against a live server.

The ``sh`` block of the README is run by bash with only the port changed. Every curl
must get a 2xx, except the rollback (a fresh device has no version 1 to go back to: a
4xx naming that, never 415 for a missing Content-Type, never 5xx).
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
pytestmark = pytest.mark.service


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.skipif(shutil.which("curl") is None, reason="curl is not installed")
def test_readme_serve_and_curl_examples(tmp_path):
    keys = re.search(r"SELFCAL_API_KEYS='([^']+)' selfcal serve --db selfcal.db", README)
    assert keys, "README has no serve line"
    for pair in keys.group(1).split(","):
        assert len(pair.split("=")[0]) >= 8, f"README key too short for the service: {pair}"
    block = re.search(r"```sh\n(.*?)```", README, re.S).group(1)
    assert "curl" in block
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
        rollback = [i for i, line in enumerate(re.findall(r"curl -s.*", block)) if "rollback" in line]
        for i, code in enumerate(codes):
            if i in rollback:
                assert 400 <= code < 500 and code != 415, (code, bodies[i])
            else:
                assert 200 <= code < 300, (i, code, bodies[i])
    finally:
        srv.terminate()
        srv.wait(timeout=30)
