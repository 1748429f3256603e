#!/usr/bin/env python3
"""Uploads many distinct scenes to one `rayd serve` and prints the server's resident memory
as they accumulate: what the parsed scenes it keeps cost (BENCHMARKS.md §27).

Each scene is a TRI1 body of TRIANGLES triangles of its own (a grid shifted by the scene's
number, so every upload is new content), uploaded to one server (`http_trace_cpu.serve`,
2 threads) and then traced once with 1024 rays. Every EVERY uploads the server's resident memory (VmRSS) is printed. With --traces K the
last scene is then traced K more times (1,024 rays, `accel=mbvh8`, one request after
another, once the last upload's thumbnail is made) and each answer's wall time printed: what a scene that fills most of the memory
budget costs each request (a 1M-triangle scene is 34 MiB of positions).

    scripts/many_scenes.py [--bin B] [--scenes 200] [--triangles 100000] [--every 20]
        [--traces K] [-- EXTRA SERVE ARGS]   (for example -- --geometry-bytes 67108864)
"""
import argparse
import json
import struct
import sys
import time

from http_trace_cpu import request, serve, wait_thumbnail


def tri1(n, shift):
    """TRI1 (proto/binary-formats.md): the 16-byte header, then n triangles of nine f32."""
    out = bytearray(b"TRI1" + struct.pack("<HHQ", 1, 0, n))
    row = struct.Struct("<9f")
    side = int(n ** 0.5) + 1
    for i in range(n):
        x, y = float(i % side), float(i // side)
        out += row.pack(x, y, shift, x + 1.0, y, shift, x, y + 1.0, shift)
    return bytes(out)


def ray1(n, z):
    """RAY1: the header, then n rays (origin, tmin, direction, tmax) straight down."""
    out = bytearray(b"RAY1" + struct.pack("<HHQ", 1, 0, n))
    row = struct.Struct("<8f")
    for i in range(n):
        out += row.pack(0.25 + i % 32, 0.25 + i // 32, z + 10.0, 0.0, 0.0, 0.0, -1.0,
                        float("inf"))
    return bytes(out)


def rss_mib(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def main():
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", default="target/release/rayd")
    ap.add_argument("--scenes", type=int, default=200)
    ap.add_argument("--triangles", type=int, default=100_000)
    ap.add_argument("--every", type=int, default=20)
    ap.add_argument("--traces", type=int, default=0)
    args, extra = ap.parse_args(argv[:cut]), argv[cut + 1:]
    with serve(args.bin, 2, extra=extra) as (port, server, _):
        def post(path, body, ctype):
            return request(port, "POST", path, body, ctype)[0]

        print(f"{args.bin} serve {' '.join(extra)}: {args.scenes} scenes of "
              f"{args.triangles} triangles ({36 * args.triangles / 2**20:.1f} MiB of "
              "positions each)")
        print(f"  start: RSS {rss_mib(server.pid):.0f} MiB")
        t0 = time.time()
        for k in range(1, args.scenes + 1):
            scene = json.loads(post("/v1/scenes", tri1(args.triangles, float(k)),
                                    "application/x-rayd-tri"))
            post(f"/v1/scenes/{scene['id']}/trace", ray1(1024, float(k)),
                 "application/octet-stream")
            if k % args.every == 0:
                print(f"  {k:4d} scenes: RSS {rss_mib(server.pid):.0f} MiB "
                      f"({time.time() - t0:.0f} s)")
        if args.traces:
            wait_thumbnail(port, scene["id"])
        rays = ray1(1024, float(args.scenes))
        for _ in range(args.traces):
            t1 = time.perf_counter()
            post(f"/v1/scenes/{scene['id']}/trace?accel=mbvh8", rays,
                 "application/octet-stream")
            print(f"  trace of the last scene: {1e3 * (time.perf_counter() - t1):.1f} ms")


if __name__ == "__main__":
    main()
