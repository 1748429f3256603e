#!/usr/bin/env bash
# Proves proto/openapi.yaml against a live `rayd serve`: starts the server on a free
# loopback port with a temporary data directory and tight limits, uploads a scene and runs
# a small render (so `{id}` and `{job}` name real things), then runs schemathesis on
# proto/openapi.yaml (the document the server serves at /v1/openapi.json; tests/http_infra.rs
# keeps the two equal) with scripts/schemathesis_hooks.py. Exits non-zero on any failure.
#
#   scripts/schemathesis.sh            # 120 seconds
#   scripts/schemathesis.sh 600        # a time budget in seconds
#   scripts/schemathesis.sh --max-examples 50
#
# Needs target/release/rayd (built here when missing or stale), python3 and the
# `schemathesis` Python package (pip install schemathesis).
set -euo pipefail
cd "$(dirname "$0")/.."

budget=(--max-time 120)
case "${1:-}" in
  "") ;;
  --max-examples) budget=(--max-examples "${2:?--max-examples needs a number}") ;;
  *[!0-9]*) echo "usage: $0 [SECONDS|--max-examples N]" >&2; exit 2 ;;
  *) budget=(--max-time "$1") ;;
esac

command -v schemathesis >/dev/null || { echo "schemathesis: not installed (pip install schemathesis)" >&2; exit 1; }
# RAYD_BIN: a binary built elsewhere, used as it is (CI: target/ci/rayd, which the test
# suite has just built). Without it, target/release/rayd is built here (if stale), with
# the cargo features in RAYD_FEATURES (e.g. embree).
if [ -z "${RAYD_BIN:-}" ]; then
  cargo build --release --quiet --bin rayd ${RAYD_FEATURES:+--features "$RAYD_FEATURES"}
fi
rayd=${RAYD_BIN:-target/release/rayd}

data=$(mktemp -d)
server=""
cleanup() {
  if [ -n "$server" ]; then
    kill "$server" 2>/dev/null || true
    wait "$server" 2>/dev/null || true
  fi
  rm -rf "$data"
}
trap cleanup EXIT

port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
url="http://127.0.0.1:$port"

# Tight limits, so that the generated bodies and requests reach them: bodies of 64 KiB
# (Fox.glb is larger), 64 rays, 4096 pixels, 4 samples per pixel, 4 queued jobs.
RAYD_LOG=warn "$rayd" serve --addr "127.0.0.1:$port" --data-dir "$data/store" --threads 2 \
  --max-body 65536 --max-rays 64 --max-pixels 4096 --max-spp 4 --max-queued 4 \
  --max-client-requests 64 --grace 1 2>"$data/server.log" &
server=$!

# Waits for readiness, uploads a scene and renders it (8×8); prints the scene id, its
# triangle count and the finished job's id.
read -r scene triangles job < <(python3 - "$url" "$server" <<'PY'
import json, os, sys, time, urllib.request
url, server = sys.argv[1], int(sys.argv[2])
def call(method, path, body=None, ctype=None):
    req = urllib.request.Request(url + path, data=body, method=method)
    if ctype:
        req.add_header("Content-Type", ctype)
    with urllib.request.urlopen(req, timeout=30) as r:
        return json.loads(r.read())
for _ in range(200):
    try:
        call("GET", "/readyz")
        break
    except OSError:
        os.kill(server, 0)  # raises when the server has exited
        time.sleep(0.1)
else:
    sys.exit("the server did not get ready")
with open("scenes/BoxAnimated.glb", "rb") as f:
    scene = call("POST", "/v1/scenes", f.read(), "model/gltf-binary")
job = call("POST", f"/v1/scenes/{scene['id']}/render", b'{"width": 8, "height": 8}', "application/json")
for _ in range(300):
    state = call("GET", f"/v1/jobs/{job['id']}")["state"]
    if state == "succeeded":
        break
    if state in ("failed", "cancelled"):
        sys.exit(f"the setup render {state}")
    time.sleep(0.1)
else:
    sys.exit("the setup render did not finish")
print(scene["id"], scene["triangles"], job["id"])
PY
) || { echo "setup failed; the server's log:" >&2; cat "$data/server.log" >&2; exit 1; }

echo "schemathesis: $url, scene $scene ($triangles triangles), job $job, ${budget[*]}"
status=0
RAYD_URL="$url" RAYD_SCENE="$scene" RAYD_SCENE_TRIANGLES="$triangles" RAYD_JOB="$job" \
  SCHEMATHESIS_HOOKS=scripts.schemathesis_hooks PYTHONPATH=. \
  schemathesis run proto/openapi.yaml --url "$url" \
  --checks status_code_conformance,content_type_conformance,response_headers_conformance,response_schema_conformance,no_server_error_but_documented_503,hit1_answers_every_ray \
  --workers 1 --seed "${SCHEMATHESIS_SEED:-1}" --request-timeout 30 \
  --suppress-health-check too_slow,filter_too_much,data_too_large,large_base_example \
  --report junit --report-dir "${SCHEMATHESIS_REPORT_DIR:-$data/report}" \
  "${budget[@]}" || status=$?

if ! kill -0 "$server" 2>/dev/null; then
  echo "the server died during the run:" >&2
  tail -50 "$data/server.log" >&2
  status=1
fi
if grep -q "panicked" "$data/server.log"; then
  echo "the server panicked:" >&2
  grep -A5 "panicked" "$data/server.log" >&2
  status=1
fi
exit "$status"
