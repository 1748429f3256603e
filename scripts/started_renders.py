#!/usr/bin/env python3
"""Renders of ever higher priority: how many run at once, and the server's peak RSS
(BENCHMARKS.md §12.16).

Starts `rayd serve` (2 threads, a temporary data directory; `http_trace_cpu.py`'s server),
uploads SCENE, then submits RENDERS long path renders (WIDTH × HEIGHT, spp 4096) one every
GAP seconds, each at a higher priority than the last. A render yields between waves and
keeps its image and paths, so without a bound on started jobs each newcomer would start
beside the others. Samples the server's RSS and `rayd_jobs_running` every 50 ms until
HOLD seconds after the last submission, then cancels every job and prints the peak RSS,
the most jobs running at once, and the states seen. Anything after `--` goes to `rayd
serve` (for example `-- --max-running 64`, to see the unbounded behaviour).

    scripts/started_renders.py ../shared/scenes/Fox.glb [--renders 12] [--gap 0.4]
        [--width 1024 --height 768] [--hold 4] [--bin target/release/rayd] [-- --max-running 4]
"""
import argparse
import json
import os
import re
import sys
import time

from http_trace_cpu import request, serve


def rss_mib(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return 0.0


def gauge(port, name):
    body, _, _ = request(port, "GET", "/metrics", b"", "text/plain")
    m = re.search(rf"^{name} ([0-9.e+]+)$", body.decode(), re.M)
    return float(m.group(1)) if m else 0.0


def main():
    argv = sys.argv[1:]
    extra = []
    if "--" in argv:
        k = argv.index("--")
        argv, extra = argv[:k], argv[k + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--renders", type=int, default=12)
    ap.add_argument("--gap", type=float, default=0.4)
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--height", type=int, default=768)
    ap.add_argument("--hold", type=float, default=4.0)
    ap.add_argument("--bin", default="target/release/rayd")
    args = ap.parse_args(argv)
    scene = open(args.scene, "rb").read()
    with serve(args.bin, 2, extra=extra) as (port, server, _):
        body, _, _ = request(port, "POST", "/v1/scenes?name=s.glb", scene, "model/gltf-binary")
        sid = json.loads(body)["id"]
        rss0 = rss_mib(server.pid)
        jobs, peak_rss, peak_running = [], rss0, 0
        next_submit = time.monotonic()
        end = None
        while end is None or time.monotonic() < end:
            now = time.monotonic()
            if len(jobs) < args.renders and now >= next_submit:
                spec = {"width": args.width, "height": args.height, "spp": 4096,
                        "integrator": "path", "priority": 10 + len(jobs)}
                body, _, _ = request(port, "POST", f"/v1/scenes/{sid}/render",
                                     json.dumps(spec).encode(), "application/json")
                jobs.append(json.loads(body)["id"])
                next_submit = now + args.gap
                if len(jobs) == args.renders:
                    end = now + args.hold
            peak_rss = max(peak_rss, rss_mib(server.pid))
            peak_running = max(peak_running, int(gauge(port, "rayd_jobs_running")))
            time.sleep(0.05)
        states = {}
        for j in jobs:
            body, _, _ = request(port, "GET", f"/v1/jobs/{j}", b"", "application/json")
            s = json.loads(body)["state"]
            states[s] = states.get(s, 0) + 1
        # Only after every state is read: a cancel lets a held-back job start.
        for j in jobs:
            request(port, "DELETE", f"/v1/jobs/{j}", b"", "application/json")
        print(json.dumps({"serve_args": extra, "renders": args.renders,
                          "size": f"{args.width}x{args.height}",
                          "rss_start_mib": round(rss0, 1), "rss_peak_mib": round(peak_rss, 1),
                          "most_running": peak_running, "states_at_end": states}))


if __name__ == "__main__":
    main()
