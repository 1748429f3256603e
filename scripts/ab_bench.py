#!/usr/bin/env python3
"""Alternate two rayd binaries on one `rayd bench` measurement and report paired ratios.

A and B run alternately (`ab_pairs.py`), pinned to one core, and the median of the
per-pair ratios B/A is reported with its quartiles.

    scripts/ab_bench.py A B [--pairs 16] [--scene S] [--accel mbvh8] [--sets primary,diffuse2]
        [--cpu 1] [--width 512 --height 384] [--threads 1] [--precision watertight]
"""
import re
import statistics
import subprocess

import ab_pairs


def main():
    ap = ab_pairs.parser(__doc__, 16)
    ap.add_argument("--scene", default="../shared/scenes/dragon-100k.from-ply.glb")
    ap.add_argument("--accel", default="mbvh8")
    ap.add_argument("--build", default="sah")
    ap.add_argument("--precision", default="watertight")
    ap.add_argument("--sets", default="primary,diffuse2")
    ap.add_argument("--cpu", default="1", help="core to pin to (taskset -c)")
    ap.add_argument("--threads", default="1")
    ap.add_argument("--width", default="512")
    ap.add_argument("--height", default="384")
    args = ap.parse_args()

    def run(binary):
        cmd = ["taskset", "-c", args.cpu, binary, "bench", args.scene, "--accel", args.accel,
               "--build", args.build, "--precision", args.precision, "--sets", args.sets, "--threads", args.threads,
               "--runs", "5", "--width", args.width, "--height", args.height,
               "--reference", args.accel]
        err = subprocess.run(cmd, capture_output=True, text=True, check=True).stderr
        pat = r"bench: +" + re.escape(args.accel) + r" "
        return [float(l.split()[5]) for l in err.splitlines() if re.match(pat, l)]

    ra, rb = ab_pairs.alternate(run, args.a, args.b, args.pairs)
    for j, name in enumerate(args.sets.split(",")):
        a = [x[j] for x in ra]
        b = [x[j] for x in rb]
        r = sorted(y / x for x, y in zip(a, b))
        q = len(r) // 4
        print(f"{name}: A median {statistics.median(a):.3f} Mray/s, B median "
              f"{statistics.median(b):.3f}; B/A paired median {statistics.median(r):.3f} "
              f"(quartiles {r[q]:.3f}-{r[-1 - q]:.3f}, {len(r)} pairs)")


if __name__ == "__main__":
    main()
