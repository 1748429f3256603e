#!/usr/bin/env python3
"""Alternate two rayd binaries on the build time of one accelerator, each run beside
Embree's build of the matching quality, and report paired ratios.

Each run is `rayd bench SCENE --accel embree,ACCEL --build Q --sets primary` on a tiny
ray set (64×48), so that it measures builds; the bench reports the median of its runs.
Printed: the medians of A's and B's build ms, the paired median of B/A, and each binary's
median of ours / Embree within the same run.

    scripts/ab_build.py A B [--pairs 8] [--scene S] [--accel mbvh8] [--build fast]
        [--threads 1] [--cpu 1]
"""
import statistics
import subprocess

import ab_pairs


def main():
    ap = ab_pairs.parser(__doc__, 8)
    ap.add_argument("--scene", default="../shared/scenes/dragon-100k.from-ply.glb")
    ap.add_argument("--accel", default="mbvh8")
    ap.add_argument("--build", default="fast")
    ap.add_argument("--threads", default="1")
    ap.add_argument("--cpu", default=None, help="cores to pin to (taskset -c)")
    ap.add_argument("--runs", default="5")
    args = ap.parse_args()

    def run(binary):
        cmd = [binary, "bench", args.scene, "--accel", f"embree,{args.accel}",
               "--build", args.build, "--sets", "primary", "--threads", args.threads,
               "--runs", args.runs, "--width", "64", "--height", "48", "--format", "table"]
        if args.cpu is not None:
            cmd = ["taskset", "-c", args.cpu] + cmd
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        ms = {}
        for line in out.splitlines():
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if len(cells) >= 3 and cells[0] in ("embree", args.accel) and cells[0] not in ms:
                ms[cells[0]] = float(cells[2])
        return ms["embree"], ms[args.accel]

    ra, rb = ab_pairs.alternate(run, args.a, args.b, args.pairs)
    med = statistics.median

    def quart(r):
        r = sorted(r)
        q = len(r) // 4
        return f"{med(r):.3f} (quartiles {r[q]:.3f}-{r[-1 - q]:.3f})"

    print(f"{args.scene} {args.accel} --build {args.build}, {args.threads} thread(s), "
          f"{args.pairs} pairs")
    print(f"  A: {med([x[1] for x in ra]):.1f} ms, Embree beside it {med([x[0] for x in ra]):.1f}"
          f" ms; A / Embree {quart([x[1] / x[0] for x in ra])}")
    print(f"  B: {med([x[1] for x in rb]):.1f} ms, Embree beside it {med([x[0] for x in rb]):.1f}"
          f" ms; B / Embree {quart([x[1] / x[0] for x in rb])}")
    print(f"  B / A paired: {quart([y[1] / x[1] for x, y in zip(ra, rb)])}")


if __name__ == "__main__":
    main()
