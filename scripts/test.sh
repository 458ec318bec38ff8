#!/usr/bin/env bash
# Set up, then lint, type-check and run the whole test suite (SQLite and PostgreSQL).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh dev
scripts/postgres.sh
scripts/lint.sh
.venv/bin/python -m pytest -q -ra "$@"
