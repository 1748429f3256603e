#!/usr/bin/env python3
"""Plots a soak's RSS samples (the CSV that `RAYD_SOAK_CSV=FILE cargo test --release --test
soak` or `examples/load.rs --rss-csv FILE` writes) into a PNG: RSS over time, one colour per
server incarnation, with the restarts marked.

    python3 -m pip install matplotlib
    python3 scripts/plot_soak.py soak.csv docs/soak-rss.png "title"
"""
import csv
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main():
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    src, dst = sys.argv[1], sys.argv[2]
    title = sys.argv[3] if len(sys.argv) > 3 else "rayd serve RSS during a soak"
    runs = {}
    with open(src, newline="") as f:
        for row in csv.DictReader(f):
            runs.setdefault(int(row["incarnation"]), []).append(
                (float(row["seconds"]), int(row["rss_bytes"]) / 2**20)
            )
    if not runs:
        sys.exit(f"{src}: no samples")
    fig, ax = plt.subplots(figsize=(8, 3.5), dpi=120)
    for inc, pts in sorted(runs.items()):
        xs, ys = zip(*pts)
        ax.plot(xs, ys, lw=1.2, label=f"process {inc + 1}")
        if inc > 0:
            ax.axvline(xs[0], color="grey", lw=0.6, ls=":")
    ax.set_xlabel("seconds since the mix started")
    ax.set_ylabel("RSS, MiB")
    ax.set_title(title)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    if len(runs) <= 12:
        ax.legend(fontsize=7, ncol=4, loc="lower right")
    fig.tight_layout()
    fig.savefig(dst)


if __name__ == "__main__":
    main()
