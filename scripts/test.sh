#!/usr/bin/env bash
# Set up, export the models of every feature configuration (`--features all`), then lint,
# type-check and run the whole test suite (SQLite and PostgreSQL, weight-free and ONNX pipelines,
# the viewer in headless Chromium). With arguments, pytest runs with them alone; without, the
# fuzz modules run first in a process of their own (hypothesis draws subnormal floats, which
# a process that has created an onnxruntime session flushes to zero), then the rest on two
# workers, a test module per worker at a time.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh dev
scripts/build_models.sh --features all
scripts/postgres.sh
scripts/build_web.sh
scripts/install_chromium.sh
scripts/lint.sh
if [ $# -gt 0 ]; then
  exec .venv/bin/python -m pytest -q -ra "$@"
fi
fuzz=(tests/api/test_fuzz.py tests/api/test_fuzz_stateful.py)
.venv/bin/python -m pytest -q -ra "${fuzz[@]}"
exec .venv/bin/python -m pytest -q -ra --durations=25 -n 2 --dist loadfile \
  "${fuzz[@]/#/--ignore=}"
