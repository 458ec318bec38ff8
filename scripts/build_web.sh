#!/usr/bin/env bash
# Install the viewer's browser dependencies and the compose-spec schema the deployment test
# reads (web/package-lock.json, from the npm registry) and copy the modules the page loads into
# app/web/vendor/ (ignored by git); install and build the TypeScript SDK (clients/typescript,
# its package-lock.json: openapi-typescript and tsc) that tests/clients drives. Without npm it
# says so and exits 0: the service runs without them (the viewer's 3D view is then off).
set -euo pipefail
cd "$(dirname "$0")/.."
vendor=app/web/vendor
if ! command -v npm >/dev/null 2>&1; then
  echo "build_web: npm not found; the viewer's 3D view stays off (install Node.js + npm and" \
    "re-run scripts/build_web.sh)" >&2
  exit 0
fi
npm ci --prefix web --no-audit --no-fund --loglevel=error
three=web/node_modules/three
rm -rf "$vendor"
mkdir -p "$vendor/addons/controls"
cp "$three/build/three.module.js" "$three/build/three.core.js" "$three/LICENSE" "$vendor/"
cp "$three/examples/jsm/controls/OrbitControls.js" "$vendor/addons/controls/"
echo "build_web: three $(node -p "require('./$three/package.json').version") in $vendor"
npm ci --prefix clients/typescript --no-audit --no-fund --loglevel=error
npm run --prefix clients/typescript --silent build
echo "build_web: clients/typescript built in clients/typescript/dist"
