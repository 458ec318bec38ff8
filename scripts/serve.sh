#!/usr/bin/env bash
# Set up, export the models (first run only) and serve the API on SQLite (./data/slloc.db) at
# http://127.0.0.1:8000. Without exported models the service runs the weight-free pipeline.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
scripts/build_models.sh || echo "WARNING: model export failed; serving the weight-free SIFT pipeline" >&2
.venv/bin/slloc db upgrade
exec .venv/bin/slloc serve "$@"
