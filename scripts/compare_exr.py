#!/usr/bin/env python3
"""Compares rendered EXR images with a reference over the pixels that see geometry
(BENCHMARKS §19): for each image, its mean over those pixels beside the reference's, the
RMSE against the reference there, and how many pixels differ from the reference at all.

A pixel sees geometry when the reference's RGB is not the sky's (`--sky`, 1 by default:
`rayd render`'s white sky). Reads the RGBA part `rayd render` writes, with OpenEXR's own
Python bindings (PyPI `OpenEXR`).

    python3 scripts/compare_exr.py REFERENCE.exr IMAGE.exr [IMAGE.exr ...] [--sky 1.0]
"""
import argparse

import numpy as np
import OpenEXR


def rgb(path):
    with OpenEXR.File(path) as f:
        channels = f.channels()
        if "RGBA" in channels:
            return np.asarray(channels["RGBA"].pixels[..., :3], np.float64)
        if "RGB" in channels:
            return np.asarray(channels["RGB"].pixels, np.float64)
        return np.stack([np.asarray(channels[c].pixels, np.float64) for c in "RGB"], -1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("reference")
    ap.add_argument("images", nargs="+")
    ap.add_argument("--sky", type=float, default=1.0)
    args = ap.parse_args()
    ref = rgb(args.reference)
    seen = np.abs(ref - args.sky).max(-1) > 1e-3
    print(f"{args.reference}: {seen.sum()} of {seen.size} pixels see geometry, "
          f"mean there {ref[seen].mean():.5f}")
    for path in args.images:
        img = rgb(path)
        if img.shape != ref.shape:
            raise SystemExit(f"{path}: {img.shape[1]}x{img.shape[0]}, not the reference's size")
        rmse = np.sqrt(((img - ref)[seen] ** 2).mean())
        differ = int((img != ref).any(-1).sum())
        print(f"{path}: mean {img[seen].mean():.5f}, RMSE {rmse:.4f}, "
              f"{differ} of {seen.size} pixels differ from the reference")


if __name__ == "__main__":
    main()
