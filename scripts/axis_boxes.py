#!/usr/bin/env python3
"""Writes BENCHMARKS §42's axis-aligned scene: 10,000 random boxes (120,000 triangles) in
[0, 102]^3 as TRI1, and 500,000 rays straight down (direction (0, -1, 0), from y = 200) as
RAY1. Every vertical wall contains the rays' direction, so Möller–Trumbore's determinant is
exactly 0 in each of its triangles: the case that made `fast`'s range check slow.

    scripts/axis_boxes.py DIR
    for a in mbvh8 dacrt; do taskset -c 1 target/release/rayd trace DIR/boxes.tri \\
        --rays DIR/down.ray --accel $a --precision fast --threads 1 --out DIR/$a.hit; done
"""
import random
import struct
import sys
from pathlib import Path


def main():
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    random.seed(5)
    tris = []

    def quad(a, b, c, d):
        tris.append((a, b, c))
        tris.append((a, c, d))

    for _ in range(10000):
        x, y, z = (random.uniform(0, 100) for _ in range(3))
        sx, sy, sz = (random.uniform(0.3, 2) for _ in range(3))
        X, Y, Z = x + sx, y + sy, z + sz
        quad((x, y, z), (X, y, z), (X, Y, z), (x, Y, z))
        quad((x, y, Z), (X, y, Z), (X, Y, Z), (x, Y, Z))
        quad((x, y, z), (x, Y, z), (x, Y, Z), (x, y, Z))
        quad((X, y, z), (X, Y, z), (X, Y, Z), (X, y, Z))
        quad((x, y, z), (X, y, z), (X, y, Z), (x, y, Z))
        quad((x, Y, z), (X, Y, z), (X, Y, Z), (x, Y, Z))
    with open(out / "boxes.tri", "wb") as f:
        f.write(b"TRI1" + struct.pack("<IQ", 1, len(tris)))
        for t in tris:
            f.write(struct.pack("<9f", *[c for v in t for c in v]))
    n = 500000
    with open(out / "down.ray", "wb") as f:
        f.write(b"RAY1" + struct.pack("<IQ", 1, n))
        for _ in range(n):
            x, z = random.uniform(0, 102), random.uniform(0, 102)
            f.write(struct.pack("<8f", x, 200, z, 0, 0, -1, 0, float("inf")))


if __name__ == "__main__":
    main()
