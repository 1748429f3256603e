#!/usr/bin/env python3
"""Plots a soak's RSS samples (the CSV that `RAYD_SOAK_CSV=FILE cargo test --release --test
soak` or `examples/load.rs --rss-csv FILE` writes) into a PNG: RSS over time, one colour per
server incarnation, with the restarts marked, and prints the Markdown table of each
process's RSS every 15 s from its start (the table of BENCHMARKS.md §12.7).

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
    print_table(runs)


def print_table(runs, every=15.0):
    """Each process's RSS (MiB) at every `every` seconds from its start, and its peak."""
    longest = max(pts[-1][0] - pts[0][0] for pts in runs.values())
    marks = [k * every for k in range(int(longest // every) + 1)]
    print("| process | " + " | ".join(f"{m:.0f}" for m in marks) + " | peak |")
    print("|---|" + "---:|" * (len(marks) + 1))
    for inc, pts in sorted(runs.items()):
        t0, cells = pts[0][0], []
        for m in marks:
            # The first sample at or after the mark, within a second of it.
            at = next((y for x, y in pts if t0 + m <= x <= t0 + m + 1.0), None)
            cells.append("—" if at is None else f"{at:.0f}")
        peak = max(y for _, y in pts)
        print(f"| {inc + 1} | " + " | ".join(cells) + f" | {peak:.0f} |")


if __name__ == "__main__":
    main()
