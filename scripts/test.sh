#!/usr/bin/env bash
# Set up, export the models of every feature configuration (`--features all`), then lint,
# type-check and run the whole test suite (SQLite and PostgreSQL, weight-free and ONNX pipelines,
# the viewer in headless Chromium).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh dev
scripts/build_models.sh --features all
scripts/postgres.sh
scripts/build_web.sh
scripts/install_chromium.sh
scripts/lint.sh
.venv/bin/python -m pytest -q -ra --durations=25 "$@"
