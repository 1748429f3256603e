#!/usr/bin/env bash
# Re-measures every table of BENCHMARKS.md that the cores' speed stands on, with the
# commands those sections give, one after another, each output in its own file under OUT
# (default target/remeasure). Issue 12 asks for this at its end: nothing may have become
# slower elsewhere. Run it on a quiet machine (about 45 minutes on 2 cores); it records
# the load before every command.
#
#   scripts/remeasure_cores.sh [OUT]            # TINYBVH_DIR=... adds §20.4
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"
out="${1:-target/remeasure}"
S="${SCENES_DIR:-../shared/scenes}"
mkdir -p "$out"
cargo build --release --features embree --bin rayd
rayd=target/release/rayd
run() { # run NAME COMMAND...: the command's output and the load before it into OUT/NAME.txt
  local name="$1"; shift
  { echo "# load $(cut -d' ' -f1-3 /proc/loadavg); $*"; "$@" 2>&1; } >> "$out/$name.txt"
}

# §1: static scenes, every core, every set, 1 and 2 threads.
for s in dragon-100k.from-ply lucy-100k.from-drc ReciprocatingSaw MetalRoughSpheresNoTextures; do
  run s01_static "$rayd" bench "$S/$s.glb" --accel embree,mbvh8,mbvh4,bvh2,dacrt,dacrt-sampled \
    --build sbvh --threads 1,2 --runs 3 --format table
done
# §3: a frame of changing geometry.
for s in dragon-100k.from-ply BrainStem; do
  run s03_frames "$rayd" bench "$S/$s.glb" --frames 4 --accel dacrt,dacrt-sampled,mbvh8,embree \
    --build fast --sets primary,diffuse2 --rays-per-frame 65536,262144,1048576,4194304 \
    --threads 1,2 --format table
done
# §4: refit against rebuild over many frames.
for s in dragon-100k.from-ply BrainStem; do
  run s04_refit "$rayd" bench "$S/$s.glb" --frames 12 --accel mbvh8,embree --build sah \
    --sets primary,diffuse2 --rays-per-frame 1048576 --threads 1 --format table
done
# §5: DACRT against the batch size.
for side in 256 512 1024 2048 4096; do
  run s05_batch "$rayd" bench "$S/dragon-100k.from-ply.glb" --accel dacrt,dacrt-sampled,mbvh8,embree \
    --build sbvh --sets primary,diffuse2 --width $side --height $side --threads 1 --runs 3 --format table
done
# §21 / §21.1: builds against Embree's, quality for quality.
for q in fast sah sbvh; do
  run s21_builds "$rayd" bench "$S/nefertiti.from-obj.glb" "$S/ReciprocatingSaw.glb" \
    "$S/MetalRoughSpheresNoTextures.glb" --accel embree,mbvh8 --build $q --sets primary,diffuse2 \
    --width 512 --height 384 --threads 1,2 --runs 3 --reference embree --format table
done
# §22.2 (quiet): DACRT's 2-thread scaling beside Embree's.
for s in dragon-100k.from-ply lucy-100k.from-drc ReciprocatingSaw MetalRoughSpheresNoTextures; do
  run s22_scaling "$rayd" bench "$S/$s.glb" --accel dacrt,dacrt-sampled,embree \
    --sets primary,diffuse2 --threads 1,2 --runs 5 --format table
done
# §22.6: a frame of moving geometry against every rebuild.
for s in BrainStem CesiumMan dragon-100k.from-ply; do
  run s22_moving "$rayd" bench "$S/$s.glb" --frames 3 --accel dacrt,dacrt-sampled,mbvh8,mbvh4,bvh2,embree \
    --build fast --sets primary --rays-per-frame 262144,1048576,4194304 --threads 1,2 --format table
done
# §20.4: mbvh8 against tinybvh (needs its header).
if [[ -n "${TINYBVH_DIR:-}" ]]; then
  OUT="$out/tinybvh" scripts/tinybvh/compare.sh > "$out/s20_tinybvh.txt" 2>&1
fi
echo "done: $out"
