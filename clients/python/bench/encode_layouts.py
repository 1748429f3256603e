#!/usr/bin/env python3
"""What encoding N rays into RAY1 records costs the client (BENCHMARKS §15): the package's
own `formats.RaySegments` (field by field, a 64K-ray segment at a time), against the same
records written through an `(N, 8)` float32 view and through 12-byte void views of the
origin and direction rows. Median of `--runs`, ms.

    python3 clients/python/bench/encode_layouts.py [--rays 786432] [--runs 7]
"""
import argparse

import numpy as np
from rayd import formats
from timing import median_ms as timed

SEGMENT = formats.SEGMENT


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rays", type=int, default=786432)
    ap.add_argument("--runs", type=int, default=7)
    args = ap.parse_args()
    n = args.rays
    rng = np.random.default_rng(1)
    o = rng.random((n, 3), dtype=np.float32)
    d = rng.random((n, 3), dtype=np.float32)
    rec = np.empty(SEGMENT, dtype=formats.RAY_DTYPE)

    def package():
        for _ in formats.RaySegments(o, d, 0.0, np.inf, segment=SEGMENT):
            pass

    flat = rec.view(np.float32).reshape(-1, 8)

    def float_view():
        for s in range(0, n, SEGMENT):
            k = min(SEGMENT, n - s)
            flat[:k, 0:3] = o[s:s + k]
            flat[:k, 3] = 0.0
            flat[:k, 4:7] = d[s:s + k]
            flat[:k, 7] = np.inf

    v12 = np.dtype({"names": ["o", "lo", "d", "hi"], "formats": ["V12", "<f4", "V12", "<f4"],
                    "offsets": [0, 12, 16, 28], "itemsize": 32})
    rows = rec.view(v12)
    ov, dv = o.view("V12").reshape(-1), d.view("V12").reshape(-1)

    def void_view():
        for s in range(0, n, SEGMENT):
            k = min(SEGMENT, n - s)
            rows["o"][:k] = ov[s:s + k]
            rows["lo"][:k] = 0.0
            rows["d"][:k] = dv[s:s + k]
            rows["hi"][:k] = np.inf

    for name, fn in [("RaySegments (the package)", package), ("(N, 8) float32 view", float_view),
                     ("12-byte void views", void_view)]:
        print(f"{name}: {timed(fn, args.runs):.2f} ms for {n} rays")


if __name__ == "__main__":
    main()
