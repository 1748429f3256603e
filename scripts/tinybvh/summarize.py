#!/usr/bin/env python3
"""Reads compare.sh's output (stdin) and prints a Markdown table: per scene and set, the
median over rounds of each tracer's Mray/s per CPU-second (steadier than wall time on a
shared machine) and the ratios that BENCHMARKS.md §20 quotes."""
import re
import statistics
import sys
from collections import defaultdict

per = defaultdict(list)  # (scene, set, tracer) -> [Mray/s per CPU-second]
builds = defaultdict(list)  # (scene, tracer) -> [ms]
scene = set_name = None
for line in sys.stdin:
    m = re.match(r"== (\S+)", line)
    if m:
        scene = m.group(1)
        continue
    m = re.match(r"(\S+)-interior-(\w+)\.ray:$", line.strip())
    if m:
        set_name = m.group(2)
        continue
    m = re.match(r"\s*(\w+): median [\d.]+ Mray/s .* per CPU-second ([\d.]+) Mray", line)
    if m and scene:
        per[(scene, set_name, m.group(1))].append(float(m.group(2)))
        continue
    m = re.match(r"tinybvh .* build ([\d.]+) ms", line)
    if m and scene:
        builds[(scene, "tinybvh")].append(float(m.group(1)))
        continue
    m = re.match(r"(\S+)-interior-(\w+)\.ray: \d+ rays, median [\d.]+ Mray/s \(per CPU-second ([\d.]+)\)", line.strip())
    if m and scene:
        per[(scene, m.group(2), "tinybvh")].append(float(m.group(3)))

keys = sorted({(s, k) for (s, k, _) in per}, key=lambda x: (x[0], x[1] != "primary", x[1]))
print("| scene | set | mbvh8 | Embree | tinybvh | mbvh8 / tinybvh | mbvh8 / Embree | tinybvh / Embree | rounds |")
print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
for s, k in keys:
    med = {t: statistics.median(per[(s, k, t)]) for t in ("mbvh8", "embree", "tinybvh") if per[(s, k, t)]}
    if len(med) < 3:
        continue
    print(f"| {s} | {k} | {med['mbvh8']:.3f} | {med['embree']:.3f} | {med['tinybvh']:.3f} | "
          f"{med['mbvh8'] / med['tinybvh']:.2f} | {med['mbvh8'] / med['embree']:.2f} | "
          f"{med['tinybvh'] / med['embree']:.2f} | {len(per[(s, k, 'mbvh8')])} |")
