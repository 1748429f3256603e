#!/usr/bin/env bash
# Compiles scripts/tinybvh/harness.cpp against tinybvh and runs it.
#
#   TINYBVH_DIR=/path/to/tinybvh scripts/tinybvh/run.sh SCENE.tri PASSES RAYS.ray...
#
# TINYBVH_DIR holds tiny_bvh.h (a checkout or export of github.com/jbikker/tinybvh; the
# figures in BENCHMARKS.md §20 are v1.6.7). Nothing of tinybvh is part of rayd. The binary
# goes to $HARNESS_BIN (default target/tinybvh-harness) and is rebuilt only when the
# harness or the header is newer.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
: "${TINYBVH_DIR:?set TINYBVH_DIR to a directory holding tiny_bvh.h (tinybvh)}"
if [[ ! -f "$TINYBVH_DIR/tiny_bvh.h" ]]; then
  echo "run.sh: $TINYBVH_DIR/tiny_bvh.h not found" >&2
  exit 1
fi
bin="${HARNESS_BIN:-$here/../../target/tinybvh-harness}"
if [[ ! -x "$bin" || "$here/harness.cpp" -nt "$bin" || "$TINYBVH_DIR/tiny_bvh.h" -nt "$bin" ]]; then
  mkdir -p "$(dirname "$bin")"
  # -march=native: AVX2 + FMA, which BVH8_CPU needs (Zen 3 here).
  ${NICE:-nice -n 19} ${CXX:-g++} -O3 -march=native -std=c++17 -I"$TINYBVH_DIR" \
    "$here/harness.cpp" -o "$bin" -lpthread
fi
exec "$bin" "$@"
