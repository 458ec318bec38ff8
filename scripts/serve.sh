#!/usr/bin/env bash
# Set up, export the serving models (first run only) and serve the API on SQLite
# (./data/slloc.db). Arguments go to `slloc serve` (e.g. --host 0.0.0.0 --port 8000).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
if ! scripts/build_models.sh; then
  echo "WARNING: the model export failed (see above). The server starts with the models that" \
    "${SLLOC_MODELS_DIR:-./models} already holds; without XFeat + LighterGlue or ALIKED +" \
    "LightGlue it serves the weight-free SIFT pipeline (GET /v1/health names the features" \
    "in use)." >&2
fi
scripts/build_web.sh || echo "WARNING: the viewer's three.js could not be installed; /viewer/" \
  "works without its 3D view" >&2
.venv/bin/slloc db upgrade
# two glibc malloc arenas instead of eight per core: the server's peak under 4 clients fell from
# 781–1306 MiB to 797–969 MiB in the same benchmark (docs/deploying.md, Memory)
export MALLOC_ARENA_MAX="${MALLOC_ARENA_MAX:-2}"
exec .venv/bin/slloc serve "$@"
