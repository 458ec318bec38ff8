#!/usr/bin/env bash
# Create .venv and install slloc into it (editable). Usage: scripts/setup.sh [extras], e.g. dev
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
extras=${1:-}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".${extras:+[$extras]}"
# the dev tools' tests drive the Python SDK (clients/python) against a live server
if [[ ",$extras," == *",dev,"* ]]; then
  .venv/bin/python -m pip install -q --disable-pip-version-check -e ./clients/python
fi
