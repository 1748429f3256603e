#!/usr/bin/env bash
# The service under load, by hand (BENCHMARKS.md §12.6): the mixed load test, then the
# 8-client goal, against a release `rayd serve` on loopback. Exits non-zero on any error
# other than a documented 503 with Retry-After.
#
#   scripts/load.sh [SCENE] [SECONDS]
#
# SCENE defaults to the shared 100K-triangle dragon when present, else scenes/Fox.glb;
# SECONDS (default 60) bounds the mix. The figures are Markdown rows for BENCHMARKS.md.
set -euo pipefail
cd "$(dirname "$0")/.."
scene=${1:-../shared/scenes/dragon-100k.from-ply.glb}
[ -f "$scene" ] || scene=scenes/Fox.glb
seconds=${2:-60}
cargo build --release --bin rayd --example load
echo "load average before: $(cut -d' ' -f1-3 /proc/loadavg)"
target/release/examples/load mix "$scene" --workers 8 --seconds "$seconds" --threads 2
target/release/examples/load goal "$scene" --clients 8 --batches 4 --rays 262144 --threads 2
echo "load average after: $(cut -d' ' -f1-3 /proc/loadavg)"
