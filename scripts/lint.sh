#!/usr/bin/env bash
# Format check, lint and type check; CI runs this.
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff format --check .
.venv/bin/ruff check .
.venv/bin/mypy app services db tools
