#!/usr/bin/env bash
# Install Debian's chromium for the viewer's browser test (tests/browser) when it is missing
# and this user may use apt-get; otherwise say why and go on (the test then skips locally,
# and fails under CI=true, where chromium must be present).
set -euo pipefail
if command -v chromium >/dev/null 2>&1; then
  exit 0
fi
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
else
  echo "install_chromium: chromium is missing and apt-get needs root; the viewer test" \
    "will skip (install Debian's chromium package to run it)" >&2
fi
