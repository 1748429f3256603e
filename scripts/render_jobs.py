#!/usr/bin/env python3
"""Times small render jobs of one scene through `rayd serve`, job after job: what a client
that asks for previews again and again waits for each (BENCHMARKS.md §26).

For each binary: a server on a free loopback port with a fresh data directory
(`http_trace_cpu.serve`), the scene uploaded and its thumbnail left to be made, then JOBS
render jobs of the same request, each POSTed and polled to its end before the next.
Prints, per job, the wall time from the POST to the poll that saw it end, and the job's own
stats (evaluate: posing and textures; render: prepare + trace + shade + encode), in ms;
then the medians of jobs 2.. per binary, and the server's `rayd_texture_cache_bytes`.

    scripts/render_jobs.py SCENE [--bin B ...] [--jobs 6] [--width 64 --height 64]
        [--spp 1] [--integrator path] [--threads 2]
"""
import argparse
import json
import statistics
import time

from http_trace_cpu import request, serve, wait_thumbnail


def run(binary, args):
    """The jobs' (wall, evaluate, render) seconds, and the server's `/metrics` text."""
    with serve(binary, args.threads) as (port, _, _):
        def call(method, path, body=b"", ctype="application/json"):
            out, headers, _ = request(port, method, path, body, ctype)
            return headers, out

        with open(args.scene, "rb") as f:
            _, scene = call("POST", "/v1/scenes", f.read(), "model/gltf-binary")
        scene = json.loads(scene)
        wait_thumbnail(port, scene["id"])
        spec = json.dumps({"width": args.width, "height": args.height, "spp": args.spp,
                           "integrator": args.integrator}).encode()
        rows = []
        for _ in range(args.jobs):
            t0 = time.perf_counter()
            headers, _ = call("POST", f"/v1/scenes/{scene['id']}/render", spec)
            while True:
                job = json.loads(call("GET", headers["location"])[1])
                if job["state"] in ("succeeded", "failed", "cancelled"):
                    break
                time.sleep(0.002)
            wall = time.perf_counter() - t0
            if job["state"] != "succeeded":
                raise SystemExit(f"{binary}: job {job['id']} {job['state']}: {job.get('error')}")
            f = job["stats"]["frames"][0]
            render = sum(f[k] for k in ("prepare_seconds", "trace_seconds",
                                        "shade_seconds", "encode_seconds"))
            rows.append((wall, f["evaluate_seconds"], render))
        return rows, call("GET", "/metrics")[1].decode()


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--bin", action="append", help="rayd binaries (default target/release/rayd)")
    ap.add_argument("--jobs", type=int, default=6)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--height", type=int, default=64)
    ap.add_argument("--spp", type=int, default=1)
    ap.add_argument("--integrator", default="path")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    for binary in args.bin or ["target/release/rayd"]:
        rows, metrics = run(binary, args)
        print(f"{binary}:")
        for k, (wall, ev, render) in enumerate(rows, 1):
            print(f"  job {k}: wall {wall * 1e3:7.1f} ms  evaluate {ev * 1e3:7.1f}  render {render * 1e3:6.1f}")
        later = rows[1:] or rows
        print(f"  jobs 2..{len(rows)}, medians: wall {statistics.median(r[0] for r in later) * 1e3:.1f} ms, "
              f"evaluate {statistics.median(r[1] for r in later) * 1e3:.1f}, "
              f"render {statistics.median(r[2] for r in later) * 1e3:.1f}")
        cached = [l for l in metrics.splitlines() if l.startswith("rayd_texture_cache_bytes ")]
        print(f"  {cached[0] if cached else 'no rayd_texture_cache_bytes (a binary without it)'}")


if __name__ == "__main__":
    main()
