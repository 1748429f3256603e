#!/usr/bin/env python3
"""What building Open3D's ``cast_rays`` answer from a trace's hits costs the client
(BENCHMARKS §15), without a server: ``rayd.client.open3d_answer`` on synthetic
``t_prim_uv`` records against the construction it replaced (field copies, ``np.where``,
``np.stack`` and a row ``np.take``). Median of ``--runs``, ms; both answers compared.

    python3 clients/python/bench/open3d_answer.py [--rays 786432] [--triangles 100012]
"""
import argparse

import numpy as np

from rayd import formats
from rayd.client import open3d_answer
from timing import median_ms as timed

MISS = formats.MISS_PRIM


def replaced(records, normals):
    """The construction before 438b56b, kept here as the baseline."""
    prim = records["prim"]
    hit = prim != MISS
    gathered = np.take(normals, np.where(hit, prim, normals.shape[0] - 1), axis=0)
    return {
        "t_hit": np.array(records["t"]),
        "geometry_ids": np.where(hit, np.uint32(0), np.uint32(MISS)),
        "primitive_ids": np.array(prim),
        "primitive_uvs": np.stack([records["u"], records["v"]], axis=-1),
        "primitive_normals": gathered,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rays", type=int, default=786432)
    ap.add_argument("--triangles", type=int, default=100012)
    ap.add_argument("--runs", type=int, default=9)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    records = np.zeros(args.rays, formats.HIT_DTYPES[0])
    records["t"] = rng.random(args.rays)
    # Ids in runs, as neighbouring rays hit neighbouring triangles, and one miss in 50.
    records["prim"] = np.sort(rng.integers(0, args.triangles, args.rays))
    records["prim"][::50] = MISS
    records["u"], records["v"] = rng.random(args.rays), rng.random(args.rays)
    normals = np.concatenate([rng.random((args.triangles, 3), dtype=np.float32),
                              np.zeros((1, 3), np.float32)])
    new, old = open3d_answer(records, normals), replaced(records, normals)
    for k in old:
        assert new[k].dtype == old[k].dtype and np.array_equal(new[k], old[k]), k
    for name, fn in [("open3d_answer (the package)", lambda: open3d_answer(records, normals)),
                     ("the construction it replaced", lambda: replaced(records, normals))]:
        print(f"{name}: {timed(fn, args.runs):.2f} ms for {args.rays} rays")


if __name__ == "__main__":
    main()
