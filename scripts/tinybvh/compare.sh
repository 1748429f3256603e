#!/usr/bin/env bash
# rayd's mbvh8 (and Embree) against tinybvh's BVH8_CPU on the same rays, one thread,
# end to end: builds rayd (with Embree) and the examples, dumps the bench ray sets and the
# view's triangles, then alternates rounds of rayd (trace_loop: mbvh8 and Embree passes
# alternating in one process) and tinybvh (harness.cpp) so that a shared machine's load
# falls on all of them alike. BENCHMARKS.md §20 reads its output.
#
#   TINYBVH_DIR=/path/to/tinybvh scripts/tinybvh/compare.sh [SCENE.glb ...]
#
# Environment: SETS (primary,diffuse2), ROUNDS (3), PASSES per round (5), BUILD (sbvh),
# ACCELS (mbvh8,embree), OUT (target/tinybvh-compare), SCENES_DIR (../shared/scenes).
set -euo pipefail
root="$(cd "$(dirname "$0")/../.." && pwd)"
cd "$root"
: "${TINYBVH_DIR:?set TINYBVH_DIR to a directory holding tiny_bvh.h (tinybvh)}"
sets="${SETS:-primary,diffuse2}"
rounds="${ROUNDS:-3}"
passes="${PASSES:-5}"
build="${BUILD:-sbvh}"
accels="${ACCELS:-mbvh8,embree}"
out="${OUT:-target/tinybvh-compare}"
scenes_dir="${SCENES_DIR:-../shared/scenes}"
if [[ $# -eq 0 ]]; then
  set -- "$scenes_dir/nefertiti.from-obj.glb" "$scenes_dir/ReciprocatingSaw.glb" \
    "$scenes_dir/MetalRoughSpheresNoTextures.glb"
fi
nice -n 19 cargo build --quiet --release --features embree --bin rayd --example trace_loop --example export_view
mkdir -p "$out"
uptime
for scene in "$@"; do
  stem="$(basename "$scene" .glb)"
  # The ray sets (RAY1) and Embree's hits (HIT1) as rayd bench makes them.
  target/release/rayd bench "$scene" --accel embree --reference embree --sets "$sets" \
    --threads 1 --runs 1 --format table --dump "$out" > /dev/null
  target/release/examples/export_view "$scene" "$out/$stem.tri"
  files=""
  for s in ${sets//,/ }; do files="$files,$out/$stem-interior-$s.ray"; done
  files="${files#,}"
  echo "== $stem (load: $(cut -d' ' -f1-3 /proc/loadavg))"
  for r in $(seq "$rounds"); do
    echo "-- round $r: rayd ($accels, --build $build)"
    target/release/examples/trace_loop "$scene" "$files" "$accels" "$build" "$passes" 1
    echo "-- round $r: tinybvh"
    "$root/scripts/tinybvh/run.sh" "$out/$stem.tri" "$passes" ${files//,/ }
  done
done
uptime
