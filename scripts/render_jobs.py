#!/usr/bin/env python3
"""Times small render jobs of one scene through `rayd serve`, job after job: what a client
that asks for previews again and again waits for each (BENCHMARKS.md §26).

For each binary: a server on a free loopback port with a fresh data directory, the scene
uploaded, its thumbnail job left to finish, then JOBS render jobs of the same request,
each POSTed and polled to its end before the next. Prints, per job, the wall time from the
POST to the poll that saw it end, and the job's own stats (evaluate: posing and textures;
render: prepare + trace + shade + encode), in ms; then the medians of jobs 2.. per binary.

    scripts/render_jobs.py SCENE [--bin B ...] [--jobs 6] [--width 64 --height 64]
        [--spp 1] [--integrator path] [--threads 2]
"""
import argparse
import json
import socket
import statistics
import subprocess
import tempfile
import time
import urllib.request


def run(binary, args):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    base = f"http://127.0.0.1:{port}"

    def req(method, path, body=None, ctype="application/json"):
        r = urllib.request.Request(base + path, data=body, method=method,
                                   headers={"Content-Type": ctype})
        with urllib.request.urlopen(r) as resp:
            return resp.headers, json.loads(resp.read())

    with tempfile.TemporaryDirectory() as data:
        server = subprocess.Popen(
            [binary, "serve", "--threads", str(args.threads), "--data-dir", data,
             "--addr", f"127.0.0.1:{port}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            for _ in range(200):
                try:
                    socket.create_connection(("127.0.0.1", port)).close()
                    break
                except OSError:
                    time.sleep(0.05)
            with open(args.scene, "rb") as f:
                _, scene = req("POST", "/v1/scenes", f.read(), "model/gltf-binary")
            # The upload's thumbnail job runs at the lowest priority: let it end first.
            deadline = time.time() + 60
            while time.time() < deadline:
                _, jobs = req("GET", "/v1/jobs")
                if all(j["state"] not in ("queued", "running") for j in jobs["jobs"]):
                    break
                time.sleep(0.05)
            spec = json.dumps({"width": args.width, "height": args.height, "spp": args.spp,
                               "integrator": args.integrator}).encode()
            rows = []
            for _ in range(args.jobs):
                t0 = time.perf_counter()
                head, _ = req("POST", f"/v1/scenes/{scene['id']}/render", spec)
                location = head["Location"]
                while True:
                    _, job = req("GET", location)
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
            return rows
        finally:
            server.kill()
            server.wait()


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
        rows = run(binary, args)
        print(f"{binary}:")
        for k, (wall, ev, render) in enumerate(rows, 1):
            print(f"  job {k}: wall {wall * 1e3:7.1f} ms  evaluate {ev * 1e3:7.1f}  render {render * 1e3:6.1f}")
        later = rows[1:] or rows
        print(f"  jobs 2..{len(rows)}, medians: wall {statistics.median(r[0] for r in later) * 1e3:.1f} ms, "
              f"evaluate {statistics.median(r[1] for r in later) * 1e3:.1f}, "
              f"render {statistics.median(r[2] for r in later) * 1e3:.1f}")


if __name__ == "__main__":
    main()
