"""Secondary rays from hits without epsilons: hit points, geometric normals, robust offsets.

A ray leaving a surface must not hit that surface again because its origin was rounded to
the wrong side. A fixed epsilon is too large near the world origin (it skips thin features)
and too small far from it (the rounding error grows with the coordinates). Wächter and
Binder ("A Fast and Robust Method for Avoiding Self-Intersection", Ray Tracing Gems,
chapter 6) move the point a fixed number of float32 ULPs along the geometric normal
instead, which scales with the magnitude of each coordinate by construction, and fall back
to a small absolute step near zero where ULPs are tiny. :func:`offset_ray` is that method,
vectorised; :func:`spawn_rays` builds whole batches with it.

Hit points are interpolated from the triangle's vertices with the hit's barycentrics
(``(1-u-v)·v0 + u·v1 + v·v2``, ``proto/binary-formats.md``) in float64, so their error
does not grow with the distance travelled as ``origin + t·direction`` would.
"""

from __future__ import annotations

import numpy as np

from .formats import MISS_PRIM

# The constants of the method (Ray Tracing Gems, ch. 6): below ORIGIN in magnitude a
# coordinate moves by FLOAT_SCALE·n; elsewhere by INT_SCALE·n ULPs.
ORIGIN = 1.0 / 32.0
FLOAT_SCALE = 1.0 / 65536.0
INT_SCALE = 256.0


def offset_ray(points, normals) -> np.ndarray:
    """``points`` moved off their surface to the side ``normals`` point to.

    ``points`` and ``normals`` are ``(N, 3)`` (normals unit length, on the side the new
    ray leaves by); the result is float32 ``(N, 3)``. Each coordinate moves by
    ``INT_SCALE·n`` units in the last place of its float32 value, away from the surface,
    or by ``FLOAT_SCALE·n`` when it is within ``ORIGIN`` of zero.
    """
    p = np.ascontiguousarray(points, dtype=np.float32)
    n = np.asarray(normals, dtype=np.float32)
    if p.shape != n.shape or p.shape[-1:] != (3,):
        raise ValueError(f"points {p.shape} and normals {n.shape} must both be (N, 3)")
    steps = np.trunc(INT_SCALE * n).astype(np.int32)
    bits = p.view(np.int32)
    # A negative float's magnitude grows with its bit pattern, so moving it towards +n
    # means subtracting the step from the pattern.
    moved = np.where(p < 0, bits - steps, bits + steps).view(np.float32)
    near_zero = np.abs(p) < ORIGIN
    return np.where(near_zero, p + np.float32(FLOAT_SCALE) * n, moved).astype(np.float32)


def triangle_normals(triangles) -> np.ndarray:
    """Unit geometric normals ``normalize((v1-v0) × (v2-v0))`` of every triangle, ``(T, 3)``
    float32 (computed in float64, rounded once); zero for degenerate triangles, which are
    never hit. Index it with hit ids to shade many hits of one scene version cheaply."""
    t = np.asarray(triangles, dtype=np.float64)
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.where(length > 0, length, 1.0)).astype(np.float32)


def face_normals(triangles, prim) -> np.ndarray:
    """Unit geometric normals ``normalize((v1-v0) × (v2-v0))`` of triangles ``prim``.

    ``prim`` may hold the miss id (0xFFFFFFFF); those rows are zero. The cross product is
    taken in float64 and rounded once to float32.
    """
    tris = np.asarray(triangles, dtype=np.float32)
    prim = np.asarray(prim, dtype=np.uint32)
    hit = prim != MISS_PRIM
    out = np.zeros(prim.shape + (3,), dtype=np.float32)
    if not hit.any():
        return out
    ids = prim[hit].astype(np.int64)
    if ids.max() >= tris.shape[0]:
        raise ValueError(
            f"hit names triangle {int(ids.max())} but only {tris.shape[0]} triangles were given"
        )
    t = tris[ids].astype(np.float64)
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    # A hit triangle is never degenerate (proto/semantics.md), so length > 0 for hits.
    out[hit] = (n / np.where(length > 0, length, 1.0)).astype(np.float32)
    return out


def _hit_fields(hits):
    """``prim, u, v`` of a trace result (``Scene.trace``) or an Open3D-style one."""
    if "prim" in hits:
        prim, u, v = hits["prim"], hits.get("u"), hits.get("v")
    elif "primitive_ids" in hits:
        prim = hits["primitive_ids"]
        uv = hits.get("primitive_uvs")
        u, v = (None, None) if uv is None else (uv[..., 0], uv[..., 1])
    else:
        raise ValueError("hits need 'prim' (Scene.trace) or 'primitive_ids' (cast_rays)")
    if u is None or v is None:
        raise ValueError("hits need barycentrics: trace with hit='t_prim_uv'")
    return (
        np.asarray(prim, dtype=np.uint32).reshape(-1),
        np.asarray(u, dtype=np.float64).reshape(-1),
        np.asarray(v, dtype=np.float64).reshape(-1),
    )


def hit_points(hits, triangles) -> np.ndarray:
    """The world-space hit points ``(1-u-v)·v0 + u·v1 + v·v2`` (float32, zero for misses)."""
    prim, u, v = _hit_fields(hits)
    tris = np.asarray(triangles, dtype=np.float32)
    hit = prim != MISS_PRIM
    out = np.zeros((prim.size, 3), dtype=np.float32)
    t = tris[prim[hit].astype(np.int64)].astype(np.float64)
    uh, vh = u[hit, None], v[hit, None]
    out[hit] = ((1.0 - uh - vh) * t[:, 0] + uh * t[:, 1] + vh * t[:, 2]).astype(np.float32)
    return out


class Rays(dict):
    """A batch of rays as ``Scene.trace`` keywords, plus ``valid``: which rays are real."""

    def __init__(self, *, valid, **arrays):
        super().__init__(**arrays)
        self.valid = valid

    def as_open3d(self) -> np.ndarray:
        """The rays as an ``(N, 6)`` float32 array (origins, directions), Open3D's layout.

        That layout has no ``tmin``/``tmax``: every ray spans ``0 <= t < inf``. The rays
        :func:`spawn_rays` gives for misses still miss so (they start outside the
        triangles' bounds and leave them); a finite ``tmax`` is lost, so pass
        ``tmax=rays["tmax"]`` to :meth:`rayd.Scene.cast_rays` to keep it."""
        return np.concatenate([self["origins"], self["directions"]], axis=1).astype(
            np.float32, copy=False
        )


def _outside(triangles, directions) -> np.ndarray:
    """Origins from which ``directions`` (``(N, 3)``, non-zero) lead away from every
    triangle: on the sphere around the triangles' bounds of twice their radius plus one,
    on the side each direction points to, so the whole ray stays outside the bounding
    sphere and hits nothing with any interval. (Rounding to float32 moves an origin by
    far less than the margin of one radius plus one.)"""
    t = np.asarray(triangles, dtype=np.float64).reshape(-1, 3)
    if t.shape[0]:
        lo, hi = t.min(axis=0), t.max(axis=0)
        centre, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    else:
        centre, radius = np.zeros(3), 0.0
    d = np.asarray(directions, dtype=np.float64)
    unit = d / np.linalg.norm(d, axis=1, keepdims=True)
    # Bounds near float32's largest value would overflow; clipped, such a ray is still a
    # miss in trace(), by its empty interval.
    big = float(np.finfo(np.float32).max)
    return np.clip(centre + (2.0 * radius + 1.0) * unit, -big, big).astype(np.float32)


def spawn_rays(hits, directions, triangles, *, tmax=np.inf) -> dict:
    """Rays that leave each hit in ``directions``, safe from hitting their own surface.

    ``hits`` is a :meth:`Scene.trace` result with ``hit='t_prim_uv'`` (or a
    :meth:`Scene.cast_rays` result); ``triangles`` the ``(T, 3, 3)`` positions that were
    traced (:meth:`Scene.triangles` with the same version and time); ``directions`` the new
    ``(N, 3)`` directions, or one ``(3,)`` for all. Each origin is the hit point moved by
    :func:`offset_ray` along the geometric normal turned to the side its direction leaves
    by (so reflection and transmission both work), and ``tmin`` is 0: no epsilon to choose.

    Returns :class:`Rays`, a dict ``{"origins", "directions", "tmin", "tmax"}`` ready for
    ``scene.trace(**rays)``. A ray whose hit was a miss has no origin: it gets an empty
    interval (``tmin = tmax = inf``), so it is answered as a miss, and ``rays.valid`` (one
    bool a ray) is False for it. Its origin is put outside the triangles' bounds, on the
    side its direction leaves by, so that it misses without its interval too, as the
    rays of :meth:`Rays.as_open3d` (Open3D's layout, which has no interval) are traced.
    """
    prim, _, _ = _hit_fields(hits)
    n_rays = prim.size
    d = np.asarray(directions, dtype=np.float32)
    d = np.broadcast_to(d, (n_rays, 3)).copy() if d.ndim == 1 else d.reshape(-1, 3).copy()
    if d.shape[0] != n_rays:
        raise ValueError(f"{d.shape[0]} directions for {n_rays} hits")
    valid = prim != MISS_PRIM
    normal = face_normals(triangles, prim)
    side = np.einsum("ij,ij->i", normal, d)
    normal[side < 0] *= -1.0
    origins = offset_ray(hit_points(hits, triangles), normal)
    # A miss's direction is never used, but it must still be a valid direction.
    unusable = ~valid & ~(np.isfinite(d).all(axis=1) & (d != 0).any(axis=1))
    d[unusable] = (0.0, 0.0, 1.0)
    origins[~valid] = _outside(triangles, d[~valid])
    tmin = np.where(valid, np.float32(0.0), np.float32(np.inf)).astype(np.float32)
    hi = np.broadcast_to(np.asarray(tmax, dtype=np.float32), (n_rays,)).copy()
    hi[~valid] = np.inf
    return Rays(origins=origins, directions=d, tmin=tmin, tmax=hi, valid=valid)
