"""What `ab_bench.py` and `ab_render.py` share: the two binaries on the command line and
their alternating runs.

These machines are shared and noisy: the same binary run twice in a row differs by up to
~20%. Running A and B alternately (ABBA order), many times, and taking the median of the
per-pair ratios B/A cancels most of the drift between pairs.
"""
import argparse


def parser(doc, pairs):
    """An argument parser with the binaries A and B and `--pairs` (default `pairs`)."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("a", help="path of binary A (the reference)")
    ap.add_argument("b", help="path of binary B")
    ap.add_argument("--pairs", type=int, default=pairs)
    return ap


def alternate(run, a, b, pairs):
    """`run(a)` and `run(b)` for `pairs` pairs in ABBA order: the lists of A's and B's
    results, pair by pair."""
    ra, rb = [], []
    for i in range(pairs):
        if i % 2 == 0:
            x, y = run(a), run(b)
        else:
            y, x = run(b), run(a)
        ra.append(x)
        rb.append(y)
    return ra, rb
