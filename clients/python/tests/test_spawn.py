"""Wächter & Binder's offset and the secondary-ray builder, without a server."""

from __future__ import annotations

import numpy as np
import pytest

import rayd
from rayd.spawn import FLOAT_SCALE, INT_SCALE


def _ulps_between(a, b):
    """Signed distance from ``a`` to ``b`` in float32 units in the last place (same sign)."""
    return b.view(np.int32).astype(np.int64) - a.view(np.int32).astype(np.int64)


def test_far_from_zero_each_coordinate_moves_by_whole_ulps_along_the_normal():
    p = np.array([[100.0, -2000.0, 3.5]], np.float32)
    n = np.array([[0.6, 0.0, -0.8]], np.float32)
    q = rayd.offset_ray(p, n)
    steps = np.trunc(INT_SCALE * n[0]).astype(int)  # 153, 0, -204
    moved = _ulps_between(p[0], q[0])
    # Positive coordinates gain magnitude with +n; negative ones lose it (bits go down).
    assert moved.tolist() == [steps[0], 0, steps[2]]
    assert np.sign(q[0] - p[0]).tolist() == [1.0, 0.0, -1.0]
    p_neg = np.array([[-100.0, 5.0, 5.0]], np.float32)
    q_neg = rayd.offset_ray(p_neg, np.array([[1.0, 0.0, 0.0]], np.float32))
    assert q_neg[0, 0] > p_neg[0, 0] and _ulps_between(p_neg[0], q_neg[0])[0] == -256


def test_near_zero_coordinates_move_by_a_fixed_small_step():
    p = np.array([[0.0, 0.01, -0.02]], np.float32)
    n = np.array([[0.0, 1.0, 0.0]], np.float32)
    q = rayd.offset_ray(p, n)
    assert q[0, 0] == 0 and q[0, 2] == p[0, 2]
    assert q[0, 1] == np.float32(0.01) + np.float32(FLOAT_SCALE)


def test_the_offset_scales_with_magnitude():
    n = np.array([[0.0, 0.0, 1.0]] * 3, np.float32)
    p = np.array([[0, 0, 1.0], [0, 0, 1e3], [0, 0, 1e6]], np.float32)
    gap = rayd.offset_ray(p, n)[:, 2].astype(np.float64) - p[:, 2]
    assert (gap > 0).all() and gap[1] > 500 * gap[0] and gap[2] > 500 * gap[1]


def test_face_normals_follow_v1_minus_v0_cross_v2_minus_v0():
    tris = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, 0], [0, 1, 0], [1, 0, 0]]],
                    np.float32) * 1e3
    n = rayd.face_normals(tris, np.array([0, 1, rayd.INVALID_ID], np.uint32))
    assert n.tolist() == [[0, 0, 1], [0, 0, -1], [0, 0, 0]]
    with pytest.raises(ValueError, match="triangle 5"):
        rayd.face_normals(tris, np.array([5], np.uint32))


def test_spawned_origins_lie_on_the_side_the_new_ray_leaves_by():
    tri = np.array([[[0, 0, 10], [40, 0, 10], [0, 40, 10]]], np.float32)
    hits = {"prim": np.array([0, 0, rayd.INVALID_ID], np.uint32),
            "u": np.array([0.25, 0.25, 0], np.float32), "v": np.array([0.5, 0.5, 0], np.float32)}
    dirs = np.array([[0, 0, 1], [0.3, 0, -1], [0, 0, 0]], np.float32)
    rays = rayd.spawn_rays(hits, dirs, tri, tmax=5.0)
    assert rays.valid.tolist() == [True, True, False]
    o = rays["origins"]
    assert o[0, 2] > 10 and o[1, 2] < 10, "offset towards each ray's own side"
    assert o[0, :2].tolist() == [10, 20] and o[1, :2].tolist() == [10, 20]
    assert rays["tmin"].tolist() == [0, 0, np.inf] and rays["tmax"].tolist() == [5, 5, np.inf]
    assert rays["directions"][2].tolist() == [0, 0, 1], "a miss still gets a valid direction"
    assert rays.as_open3d().shape == (3, 6)
    with pytest.raises(ValueError, match="2 directions for 3 hits"):
        rayd.spawn_rays(hits, dirs[:2], tri)
    with pytest.raises(ValueError, match="barycentrics"):
        rayd.spawn_rays({"prim": hits["prim"]}, dirs, tri)


def test_triangle_normals_agree_with_face_normals_and_zero_degenerate_ones():
    rng = np.random.default_rng(2)
    tris = rng.uniform(-5, 5, size=(50, 3, 3)).astype(np.float32)
    tris[7, 2] = tris[7, 0]  # coincident vertices: degenerate
    table = rayd.triangle_normals(tris)
    ids = np.arange(50, dtype=np.uint32)
    assert np.array_equal(table[ids != 7], rayd.face_normals(tris, ids)[ids != 7])
    assert (table[7] == 0).all()


def _enters_box(o, d, lo, hi) -> np.ndarray:
    """Whether each ray ``o + t·d`` (t >= 0) meets the box ``lo``–``hi`` (slab test)."""
    o, d = o.astype(np.float64), d.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    inside = (o >= lo) & (o <= hi)
    near = np.where(d == 0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    far = np.where(d == 0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    return far.min(axis=1) >= np.maximum(near.max(axis=1), 0)


def test_spawned_rays_of_misses_leave_the_triangles_bounds_without_their_interval():
    # Rays.as_open3d() has no tmin/tmax: the rays of misses must miss by where they go.
    rng = np.random.default_rng(3)
    tris = (rng.uniform(-1, 1, size=(40, 3, 3)) * [30, 2, 5] + [7, -3, 2]).astype(np.float32)
    n = 500
    prim = np.where(rng.uniform(size=n) < 0.5, rng.integers(0, 40, n), rayd.INVALID_ID)
    hits = {"prim": prim.astype(np.uint32), "u": np.full(n, 0.25, np.float32),
            "v": np.full(n, 0.25, np.float32)}
    dirs = rng.normal(size=(n, 3)).astype(np.float32)
    dirs[:5] = 0  # unusable: replaced by (0, 0, 1)
    rays = rayd.spawn_rays(hits, dirs, tris)
    miss = ~rays.valid
    assert miss.sum() > 100
    assert np.isinf(rays["tmin"][miss]).all() and np.isinf(rays["tmax"][miss]).all()
    o, d = rays.as_open3d()[miss, :3], rays.as_open3d()[miss, 3:]
    assert np.isfinite(o).all() and (d != 0).any(axis=1).all()
    lo, hi = tris.reshape(-1, 3).min(axis=0), tris.reshape(-1, 3).max(axis=0)
    assert not _enters_box(o, d, lo, hi).any(), "a ray of a miss crosses the triangles"
    kept = miss & (np.arange(n) >= 5)
    assert np.array_equal(rays["directions"][kept], dirs[kept]), "directions are kept"
