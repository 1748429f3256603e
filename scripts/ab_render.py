#!/usr/bin/env python3
"""Alternate two rayd binaries on one `rayd render` frame and report paired shade ratios.

The renderer's counterpart of `ab_bench.py`: A and B render the same frame alternately
(`ab_pairs.py`), and the median of the per-pair ratios B/A of `shade_seconds` (the frame's
time outside the intersector) is reported with both sides' median shade and trace seconds
and trace shares (trace / (trace + shade)), as BENCHMARKS.md §19 tabulates them.

    scripts/ab_render.py A B [--pairs 6] [--scene S] [--threads 2] [--spp 4] [--bounces 2]
        [--width 640 --height 480] [--integrator path] [-- EXTRA RAYD RENDER ARGS]
"""
import json
import os
import statistics
import subprocess
import sys
import tempfile

import ab_pairs


def main():
    ap = ab_pairs.parser(__doc__, 6)
    ap.add_argument("--scene", default="../shared/scenes/DamagedHelmet.glb")
    ap.add_argument("--threads", default="2")
    ap.add_argument("--integrator", default="path")
    ap.add_argument("--spp", default="4")
    ap.add_argument("--bounces", default="2")
    ap.add_argument("--width", default="640")
    ap.add_argument("--height", default="480")
    # Anything after `--` goes to `rayd render` as it is (`-- --accel dacrt-sampled`).
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    args, extra = ap.parse_args(argv[:cut]), argv[cut + 1:]

    def run(binary):
        with tempfile.TemporaryDirectory() as d:
            cmd = [binary, "render", args.scene, "--out", os.path.join(d, "f-####.png"),
                   "--integrator", args.integrator, "--bounces", args.bounces, "--spp", args.spp,
                   "--width", args.width, "--height", args.height, "--threads", args.threads,
                   "--frames", "0:0:1"] + extra
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        frame = json.loads(out)["frames"][0]
        return frame["shade_seconds"], frame["trace_seconds"]

    ra, rb = ab_pairs.alternate(run, args.a, args.b, args.pairs)

    def med(v, k):
        return statistics.median(x[k] for x in v)

    ratio = statistics.median(b[0] / a[0] for a, b in zip(ra, rb))
    share = lambda v: med(v, 1) / (med(v, 0) + med(v, 1))
    print(f"{os.path.basename(args.scene)}, {args.threads} thread(s): "
          f"A shade {med(ra, 0):.3f} s, trace {med(ra, 1):.3f} s; "
          f"B shade {med(rb, 0):.3f} s, trace {med(rb, 1):.3f} s; "
          f"B/A shade, paired median {ratio:.3f} ({args.pairs} pairs); "
          f"trace share A {share(ra):.2f}, B {share(rb):.2f}")


if __name__ == "__main__":
    main()
