#!/usr/bin/env bash
# Renders the README's pictures into docs/pictures/ with the `path` integrator, and the
# per-frame timing plot of the skinned sequence (issue 9 item 9). Re-runnable as it is:
# every file is written anew, so after a renderer change one command refreshes them all.
#
#   scripts/pictures.sh            # builds target/release/rayd if missing
#   SPP=64 scripts/pictures.sh     # more samples
#
# Scenes come from ../shared/scenes (MANIFEST.md there) and, for the Fox, scenes/. Sizes and
# samples are kept small (320x240, 16 spp): about a minute on two cores.
set -euo pipefail
cd "$(dirname "$0")/.."

RAYD=${RAYD:-target/release/rayd}
SHARED=${SHARED:-../shared/scenes}
OUT=docs/pictures
SPP=${SPP:-16}
BOUNCES=${BOUNCES:-3}
W=${W:-320}
H=${H:-240}

if [ ! -x "$RAYD" ]; then
  cargo build --release
fi
for s in DamagedHelmet ReciprocatingSaw CesiumMan AnimatedMorphSphere; do
  if [ ! -f "$SHARED/$s.glb" ]; then
    echo "pictures: $SHARED/$s.glb is missing (set SHARED to the shared scenes folder)" >&2
    exit 1
  fi
done
mkdir -p "$OUT"

render() { # render SCENE NAME IMAGE [options...]: the image, and rayd's JSON as NAME.json
  local scene=$1 name=$2 image=$3
  shift 3
  echo "pictures: $name" >&2
  "$RAYD" render "$scene" -o "$OUT/$image" --integrator "${INTEGRATOR:-path}" --spp "$SPP" --bounces "$BOUNCES" \
    --width "$W" --height "$H" "$@" >"$OUT/$name.json"
}

render "$SHARED/DamagedHelmet.glb" damaged-helmet damaged-helmet.png
render "$SHARED/ReciprocatingSaw.glb" reciprocating-saw reciprocating-saw.png
# Under the uniform white sky (the only light these files have) a white surface has the sky's
# radiance and vanishes into it, so the two near-white animated ones show their shape through
# the normals integrator instead.
INTEGRATOR=normals render "$SHARED/AnimatedMorphSphere.glb" animated-morph-sphere animated-morph-sphere.png --time 1.8
render scenes/Fox.glb fox fox.png --time 0.5
# A skinned walk as a short sequence: half the size, every quarter second of its 2 s.
W=$((W / 2)) H=$((H / 2)) INTEGRATOR=normals render "$SHARED/CesiumMan.glb" cesium-man-frames cesium-man-##.png --frames 0:2:0.25
cargo run --release --quiet --example frame_plot -- "$OUT/cesium-man-frames.json" "$OUT/cesium-man-frames.png" \
  "CesiumMan, $((W / 2))x$((H / 2)), normals, $SPP spp: seconds per frame"
echo "pictures: done ($OUT)" >&2
