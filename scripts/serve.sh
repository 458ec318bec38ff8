#!/usr/bin/env bash
# Set up and serve the API on SQLite (./data/slloc.db) at http://127.0.0.1:8000.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
.venv/bin/slloc db upgrade
exec .venv/bin/slloc serve "$@"
