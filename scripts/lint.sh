#!/usr/bin/env bash
# Format check, lint, type check and the documentation site's strict build; CI runs this.
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff format --check .
.venv/bin/ruff check .
.venv/bin/mypy app services db tools clients/python
# offline (font: false, no social cards); --strict fails on a broken link or an unlisted page
site=$(mktemp -d)
trap 'rm -rf "$site"' EXIT
NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict --quiet --site-dir "$site"
