#!/usr/bin/env bash
# Proves proto/openapi.yaml against a live `rayd serve`: starts the server on a free
# loopback port with a temporary data directory and tight limits, uploads a scene and runs
# a small render (so `{id}` and `{job}` name real things), then runs schemathesis with
# scripts/schemathesis_hooks.py. Exits non-zero on any failure.
#
#   scripts/schemathesis.sh            # 120 seconds
#   scripts/schemathesis.sh 600        # a time budget in seconds
#   scripts/schemathesis.sh --max-examples 50
#
# Needs target/release/rayd (built here when missing or stale) and the `schemathesis`
# Python package (pip install schemathesis).
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
cargo build --release --quiet --bin rayd
rayd=target/release/rayd

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

for _ in $(seq 100); do
  curl -sf "$url/readyz" >/dev/null && break
  kill -0 "$server" 2>/dev/null || { cat "$data/server.log" >&2; exit 1; }
  sleep 0.1
done
curl -sf "$url/readyz" >/dev/null || { echo "the server did not get ready" >&2; exit 1; }

scene_json=$(curl -sf -H 'Content-Type: model/gltf-binary' --data-binary @scenes/BoxAnimated.glb "$url/v1/scenes")
scene=$(python3 -c 'import json, sys; print(json.load(sys.stdin)["id"])' <<<"$scene_json")
triangles=$(python3 -c 'import json, sys; print(json.load(sys.stdin)["triangles"])' <<<"$scene_json")
job_json=$(curl -sf -H 'Content-Type: application/json' -d '{"width": 8, "height": 8}' "$url/v1/scenes/$scene/render")
job=$(python3 -c 'import json, sys; print(json.load(sys.stdin)["id"])' <<<"$job_json")
for _ in $(seq 100); do
  state=$(curl -sf "$url/v1/jobs/$job" | python3 -c 'import json, sys; print(json.load(sys.stdin)["state"])')
  [ "$state" = succeeded ] && break
  sleep 0.1
done
[ "$state" = succeeded ] || { echo "the setup render did not succeed ($state)" >&2; exit 1; }

echo "schemathesis: $url, scene $scene ($triangles triangles), job $job, ${budget[*]}"
status=0
RAYD_URL="$url" RAYD_SCENE="$scene" RAYD_SCENE_TRIANGLES="$triangles" RAYD_JOB="$job" \
  SCHEMATHESIS_HOOKS=scripts.schemathesis_hooks PYTHONPATH=. \
  schemathesis run "$url/v1/openapi.json" \
  --checks status_code_conformance,content_type_conformance,response_headers_conformance,response_schema_conformance,no_server_error_but_documented_503 \
  --workers 1 --seed "${SCHEMATHESIS_SEED:-1}" --request-timeout 30 \
  --suppress-health-check too_slow,filter_too_much,data_too_large \
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
