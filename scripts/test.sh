#!/usr/bin/env bash
# Set up a virtual environment with everything the tests need, then run the whole suite.
# Works on a fresh machine with only Python 3.11 (pip reaches PyPI).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check -e '.[dev]'
exec .venv/bin/python -m pytest -q "$@"
