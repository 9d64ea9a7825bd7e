#!/usr/bin/env bash
# Set up a virtual environment with everything the tests need, then run the whole suite.
# Works on a fresh machine with only Python 3.11 (pip reaches PyPI; as root, apt-get adds
# Chromium and PostgreSQL when missing). The service suite then runs a second time
# against PostgreSQL (a throw-away cluster the tests start;
# scripts/postgres.sh installs the server binaries when they are missing and it can).
# Without PostgreSQL that second run is skipped with the reason printed, except in CI
# (CI=true) on a machine that could have installed it, where that is a failure.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check -e '.[dev]'
# Chromium for the dashboard's browser tests (Playwright drives the system's; scripts/chromium.sh
# installs Debian's when missing and it can). Without it those tests skip with the reason,
# except in CI on a machine that could have installed it, where that is a failure.
if ! bash scripts/chromium.sh; then
  if [ "${CI:-}" = "true" ] && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "FAILED: Chromium should have been installable here (root, apt-get), so the dashboard tests must run" >&2
    exit 1
  fi
  echo "SKIPPING: the dashboard's browser tests (no Chromium; see above)" >&2
fi
if [ $# -gt 0 ]; then exec .venv/bin/python -m pytest -q "$@"; fi
# The suite in two parts. The tests that start a server, a gateway, BLE peripherals or
# subprocesses with deadlines run alone (their timeouts assume the machine is theirs); the
# rest, pure computation with no timing in any assertion, runs on 2 pytest-xdist workers
# (~1.4x faster on 2 cores: each test slows ~1.3x beside another). A new test that waits on
# a clock belongs in ALONE.
ALONE=(tests/service tests/gateway tests/test_demo.py tests/test_wheel.py tests/test_readme_examples.py
       tests/test_cli_errors.py)
IGNORE=()
for p in "${ALONE[@]}"; do IGNORE+=("--ignore=$p"); done
echo "== the computation tests, on 2 workers =="
.venv/bin/python -m pytest -q -n 2 --dist worksteal "${IGNORE[@]}"
echo "== the tests that run alone (servers, gateways, BLE, subprocess deadlines) =="
.venv/bin/python -m pytest -q "${ALONE[@]}"
if bash scripts/postgres.sh; then
  echo "== the service suite again, on PostgreSQL =="
  SELFCAL_TEST_BACKEND=postgresql .venv/bin/python -m pytest -q tests/service
elif [ "${CI:-}" = "true" ] && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "FAILED: PostgreSQL should have been installable here (root, apt-get), so its tests must run" >&2
  exit 1
else
  echo "SKIPPED: the service suite on PostgreSQL (no PostgreSQL server binaries; see above)" >&2
fi
