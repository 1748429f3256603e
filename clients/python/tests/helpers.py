"""Ray sets and the ``rayd trace`` reference the service tests compare with."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np


def rays_at(info: dict, n: int, seed: int = 0, spread: float = 1.5):
    """``n`` rays from a sphere around the scene's bounds towards random points of the
    bounds grown by ``spread`` (so some miss), with a few of every kind of direction length."""
    rng = np.random.default_rng(seed)
    lo = np.array(info["bounds"]["min"], dtype=np.float64)
    hi = np.array(info["bounds"]["max"], dtype=np.float64)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    radius = 2.0 * np.linalg.norm(half) + 1e-3
    on_sphere = rng.normal(size=(n, 3))
    on_sphere /= np.linalg.norm(on_sphere, axis=1, keepdims=True)
    origins = centre + radius * on_sphere
    targets = centre + spread * half * rng.uniform(-1, 1, size=(n, 3))
    directions = (targets - origins) * rng.uniform(0.1, 3.0, size=(n, 1))
    return origins.astype(np.float32), directions.astype(np.float32)


def rayd_trace(rayd_bin: Path, scene: Path, rays_body, tmp: Path, **flags) -> tuple[bytes, dict]:
    """HIT1 bytes and the JSON report of ``rayd trace`` on a RAY1 body."""
    rays = tmp / "rays.ray"
    out = tmp / "hits.hit"
    rays.write_bytes(bytes(rays_body))
    cmd = [str(rayd_bin), "trace", str(scene), "--rays", str(rays), "--out", str(out)]
    for k, v in flags.items():
        if v is not None:
            cmd += [f"--{k}", str(v)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"{' '.join(cmd)}: {done.stderr}"
    return out.read_bytes(), json.loads(done.stdout)


def read_request(reader):
    """One HTTP/1.1 request from a socket's binary reader, for the tests' stand-in servers:
    ``(method, path, headers, body)`` (path without its query, header names lowercase), or
    None when the connection closed first."""
    line = reader.readline()
    if not line:
        return None
    method, target, _ = line.decode().split(" ", 2)
    headers = {}
    while (header := reader.readline()) not in (b"\r\n", b""):
        name, _, value = header.decode().partition(":")
        headers[name.strip().lower()] = value.strip()
    body = reader.read(int(headers.get("content-length", 0)))
    return method, target.split("?")[0], headers, body
