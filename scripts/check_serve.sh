#!/usr/bin/env bash
# The README's serve promise, checked as a new user would meet it: runs the README's serve
# command as written, waits for GET /v1/health, runs the README's example session (taken from
# the README itself, so the two cannot drift), checks the localized pose against the demo's
# ground truth (2 cm, 0.25°: the default xfeat-lg answers it 1.2 cm and 0.13° off, aliked 0.3 cm
# and 0.04°; a wrong pose is metres off) and stops the server. CI runs it before the test
# command.
set -euo pipefail
cd "$(dirname "$0")/.."
readme_block() {  # the fenced block after the HTML comment marker $1
  awk -v marker="<!-- $1 -->" '
    $0 == marker { found = 1; next }
    found && /^```/ { if (inside) exit; inside = 1; next }
    inside { print }' README.md
}
serve=$(readme_block serve-command)
session=$(readme_block example-session)
[ -n "$serve" ] && [ -n "$session" ] || { echo "README markers not found" >&2; exit 1; }
log=$(mktemp -d)
echo "== $serve (log: $log/serve.log)"
setsid bash -c "$serve" > "$log/serve.log" 2>&1 < /dev/null &
server=$!
stop() { kill -- -"$server" 2>/dev/null || true; wait "$server" 2>/dev/null || true; }
trap stop EXIT
start=$(date +%s)
until curl -sf http://127.0.0.1:8000/v1/health > "$log/health.json"; do
  if ! kill -0 "$server" 2>/dev/null; then
    echo "the server exited before it was healthy:" >&2; tail -n 40 "$log/serve.log" >&2; exit 1
  fi
  if [ $(( $(date +%s) - start )) -gt 1800 ]; then
    echo "no health after 30 min" >&2; tail -n 40 "$log/serve.log" >&2; exit 1
  fi
  sleep 2
done
echo "== healthy after $(( $(date +%s) - start )) s: $(cat "$log/health.json")"
echo "== README example session"
bash -euo pipefail -c "$session" | tee "$log/session.out"
.venv/bin/python - "$log/session.out" <<'PY'
import csv, json, sys
import numpy as np
from services.geometry.rigid import Rigid3d, pose_error

lines = open(sys.argv[1]).read().splitlines()
result = json.loads(next(line for line in reversed(lines) if line.startswith('{"localized"')))
assert result["localized"], f"the demo query was not localized: {result['reason']}"
truth = next(r for r in csv.DictReader(open("demo/queries/ground_truth.csv")) if r["image"] == "query0000.png")
expected = Rigid3d.from_quaternion(
    np.array([float(truth[k]) for k in ("qw", "qx", "qy", "qz")]),
    np.array([float(truth[k]) for k in ("tx", "ty", "tz")]),
)
pose = result["cam_from_world"]
estimate = Rigid3d.from_quaternion(np.array(pose["rotation"]), np.array(pose["translation"]))
metres, degrees = pose_error(estimate, expected)
print(f"== demo query: {metres * 100:.2f} cm, {degrees:.3f}° from the ground truth, "
      f"{result['num_inliers']} inliers, {result['timings_ms']['total']:.0f} ms")
assert metres < 0.02 and degrees < 0.25, "the demo query is off its ground truth"
PY
echo "== serve promise kept"
