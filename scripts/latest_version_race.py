#!/usr/bin/env python3
"""Renders of the latest version while geometry versions arrive without pause.

Starts `rayd serve --keep-versions 1` on a fresh data directory, uploads Fox, and for
`--seconds` POSTs small renders that name no version while two threads PUT Fox's positions
again and again (each PUT makes a new version and deletes the one before). A request that
names no version asked for whatever is latest: every answer must be 202 (or 503 for a full
queue), never a 404 for a version the client never named. Prints the counts.

    python3 scripts/latest_version_race.py [--rayd target/release/rayd] [--port 18555]
"""

import argparse
import json
import subprocess
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rayd", default=str(ROOT / "target" / "release" / "rayd"))
    ap.add_argument("--port", type=int, default=18555)
    ap.add_argument("--seconds", type=float, default=10.0)
    a = ap.parse_args()
    base = f"http://127.0.0.1:{a.port}"
    data = tempfile.mkdtemp()
    server = subprocess.Popen(
        [a.rayd, "serve", "--addr", f"127.0.0.1:{a.port}", "--data-dir", data + "/data",
         "--threads", "2", "--keep-versions", "1", "--max-client-requests", "64"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def req(method, path, body=None, ctype=None):
        r = urllib.request.Request(base + path, data=body, method=method)
        if ctype:
            r.add_header("Content-Type", ctype)
        try:
            with urllib.request.urlopen(r, timeout=30) as f:
                return f.status, f.read()
        except urllib.error.HTTPError as e:
            return e.code, e.read()

    try:
        for _ in range(200):
            try:
                if req("GET", "/readyz")[0] == 200:
                    break
            except OSError:
                pass
            time.sleep(0.05)
        fox = (ROOT.parent / "shared" / "scenes" / "Fox.glb").read_bytes()
        scene = json.loads(req("POST", "/v1/scenes", fox, "model/gltf-binary")[1])["id"]
        positions = req("GET", f"/v1/scenes/{scene}/geometry")[1]
        stop = threading.Event()

        def put():
            while not stop.is_set():
                req("PUT", f"/v1/scenes/{scene}/geometry", positions, "application/x-rayd-tri")

        updates = [threading.Thread(target=put) for _ in range(2)]
        for t in updates:
            t.start()
        t0, renders, wrong = time.time(), 0, []
        while time.time() - t0 < a.seconds:
            status, body = req("POST", f"/v1/scenes/{scene}/render",
                               b'{"width": 4, "height": 4}', "application/json")
            renders += 1
            if status not in (202, 503):
                wrong.append((status, body[:200]))
        stop.set()
        for t in updates:
            t.join()
        print(f"{renders} renders of the latest, {len(wrong)} answered otherwise than 202/503")
        for w in wrong[:3]:
            print("  ", w)
    finally:
        server.terminate()
        server.wait()


if __name__ == "__main__":
    main()
