"""The client against a live ``rayd serve``: every method, compared with ``rayd trace``.

Traces must be bit-identical to the command line's HIT1 on the same rays: the service and
the CLI run the same engine, so any difference is a client bug (a field written to the
wrong place, a rounding on the way, a lost parameter).
"""

from __future__ import annotations

import concurrent.futures
import pickle
import shutil
import signal
import subprocess
import threading
import time

import numpy as np
import pytest
import requests
from conftest import SCENES, Server
from helpers import rays_at, rayd_trace

import rayd
from rayd import formats

HIT_FORMATS = ["t_prim_uv", "t_prim", "t", "occluded"]


@pytest.fixture(scope="module")
def fox_rays(fox):
    return rays_at(fox.info, 3000, seed=1)


# -- scenes -------------------------------------------------------------------------------


def test_demo_scenes_are_listed_and_an_upload_of_the_same_bytes_finds_them(client, fox):
    listed = {s.id: s for s in client.scenes()}
    assert fox.id in listed
    assert len(listed) >= 3, "the demo uploads Fox, Box and SimpleMeshes"
    assert listed[fox.id].info["triangles"] == fox.info["triangles"] > 0
    assert client.scene(fox.id) == fox
    again = client.upload((SCENES / "Fox.glb").read_bytes())  # the type sniffed from bytes
    assert again.id == fox.id


def test_an_upload_may_name_its_scene(client):
    tris = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], np.float32) + np.float32(3.125)
    scene = client.upload(bytes(formats.encode_triangles(tris)), name="a näme")
    assert scene.info["name"] == "a näme"
    assert {s.id: s.info.get("name") for s in client.scenes()}[scene.id] == "a näme"
    with pytest.raises(rayd.ProblemError) as e:
        client.upload(bytes(formats.encode_triangles(tris + 1)), name="bad\nname")
    assert e.value.status == 400 and e.value.field == "name"
    scene.delete()


def test_upload_of_unknown_bytes_names_the_problem(client):
    with pytest.raises(ValueError, match="content_type"):
        client.upload(b"\x00\x01 not a scene")


def test_delete_removes_the_scene(client):
    tris = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], np.float32) + np.float32(7.25)
    scene = client.upload(bytes(formats.encode_triangles(tris)))
    assert scene.id in {s.id for s in client.scenes()}
    scene.delete()
    assert scene.id not in {s.id for s in client.scenes()}
    with pytest.raises(rayd.ProblemError) as e:
        client.scene(scene.id)
    assert e.value.status == 404 and e.value.type == "/problems/not-found"


# -- tracing: bit-identical to rayd trace -------------------------------------------------


@pytest.mark.parametrize("hit", HIT_FORMATS)
@pytest.mark.parametrize("query", ["closest", "any"])
def test_trace_is_bit_identical_to_rayd_trace(rayd_bin, tmp_path, fox, fox_rays, hit, query):
    origins, directions = fox_rays
    tmax = np.where(np.arange(len(origins)) % 7 == 0, np.float32(3.0), np.float32(np.inf))
    hits = fox.trace(origins, directions, 0.0, tmax, query=query, hit=hit, accel="mbvh8")
    body = formats.encode_rays(origins, directions, 0.0, tmax)
    want, report = rayd_trace(rayd_bin, SCENES / "Fox.glb", body, tmp_path,
                              hit=hit, query=query, accel="mbvh8")
    assert hits.body == want
    assert hits.accel == report["accel"] == "mbvh8"
    assert set(hits.server_timing) == {"build", "trace"}
    if hit == "occluded":
        assert hits["occluded"].dtype == np.bool_ and hits["occluded"].any()
    else:
        t = hits["t"]
        assert t.dtype == np.float32 and np.isinf(t).any() and np.isfinite(t).any()
        if "prim" in hits:
            assert hits["prim"].dtype == np.uint32
            assert ((hits["prim"] == rayd.INVALID_ID) == np.isinf(t)).all()


def test_default_trace_matches_rayd_trace_whatever_auto_picks(rayd_bin, tmp_path, fox, fox_rays):
    origins, directions = fox_rays
    hits = fox.trace(origins, directions)
    want, _ = rayd_trace(rayd_bin, SCENES / "Fox.glb",
                         formats.encode_rays(origins, directions), tmp_path)
    assert hits.body == want
    assert set(hits) == {"t", "prim", "u", "v"}


def test_trace_at_an_animation_time_matches_rayd_trace(rayd_bin, tmp_path, fox, fox_rays):
    origins, directions = fox_rays
    assert fox.info["animations"], "Fox is animated"
    hits = fox.trace(origins, directions, time=0.75, version=1)
    want, _ = rayd_trace(rayd_bin, SCENES / "Fox.glb",
                         formats.encode_rays(origins, directions), tmp_path, time=0.75)
    assert hits.body == want
    assert hits.body != fox.trace(origins, directions).body, "the pose at 0.75 s differs"


def test_broadcast_origin_and_a_ray1_body_trace_alike(fox, fox_rays):
    _, directions = fox_rays
    eye = np.array(fox.info["bounds"]["max"], np.float32) * 3
    a = fox.trace(eye, directions - 0 * eye)
    b = fox.trace_ray1(formats.encode_rays(np.tile(eye, (len(directions), 1)), directions))
    assert a.body == b.body


def test_trace_async_gives_the_same_hits_as_a_synchronous_trace(fox, fox_rays):
    origins, directions = fox_rays
    job = fox.trace_async(origins, directions, hit="t_prim")
    final = job.wait(progress=False, timeout=120).info
    assert final["state"] == "succeeded" and final["kind"] == "trace"
    hits = job.result()
    assert hits.body == fox.trace(origins, directions, hit="t_prim").body
    assert set(hits) == {"t", "prim"}
    # A retried submission with the same key is the same job.
    first = fox.trace_async(origins, directions, hit="t_prim", idempotency_key="fox-once")
    again = fox.trace_async(origins, directions, hit="t_prim", idempotency_key="fox-once")
    assert again.id == first.id


# -- cast_rays: Open3D's answer -------------------------------------------------------------


def test_cast_rays_has_open3d_names_dtypes_shapes_and_miss_values(fox, fox_rays):
    origins, directions = fox_rays
    rays = np.concatenate([origins, directions], axis=1)[:3000].reshape(50, 60, 6)
    ans = fox.cast_rays(rays)
    assert set(ans) == {"t_hit", "geometry_ids", "primitive_ids", "primitive_uvs",
                        "primitive_normals"}
    assert ans["t_hit"].shape == (50, 60) and ans["t_hit"].dtype == np.float32
    assert ans["primitive_ids"].dtype == ans["geometry_ids"].dtype == np.uint32
    assert ans["primitive_uvs"].shape == (50, 60, 2) and ans["primitive_uvs"].dtype == np.float32
    assert ans["primitive_normals"].shape == (50, 60, 3)
    assert ans["primitive_normals"].dtype == np.float32
    miss = ans["primitive_ids"] == rayd.INVALID_ID
    assert miss.any() and (~miss).any()
    assert np.isinf(ans["t_hit"][miss]).all() and (ans["geometry_ids"][miss] == 4294967295).all()
    assert (ans["geometry_ids"][~miss] == 0).all()
    assert (ans["primitive_uvs"][miss] == 0).all() and (ans["primitive_normals"][miss] == 0).all()
    hits = fox.trace(origins, directions)
    assert np.array_equal(ans["t_hit"].reshape(-1), hits["t"])
    assert np.array_equal(ans["primitive_uvs"].reshape(-1, 2)[:, 1], hits["v"])


def test_cast_rays_answers_invalid_rays_as_misses_when_asked(fox, fox_rays):
    origins, directions = fox_rays[0][:50].copy(), fox_rays[1][:50].copy()
    origins[1, 0] = np.nan
    directions[2] = 0
    rays = np.concatenate([origins, directions], axis=1)
    with pytest.raises(rayd.ProblemError) as e:
        fox.cast_rays(rays)
    assert e.value.status == 422 and e.value.ray_index == 1
    ans = fox.cast_rays(rays, invalid="miss")
    assert np.isinf(ans["t_hit"][[1, 2]]).all()
    assert (ans["primitive_ids"][[1, 2]] == rayd.INVALID_ID).all()
    want = fox.trace(origins, directions, invalid="miss")
    assert np.array_equal(ans["t_hit"], want["t"]) and np.array_equal(ans["primitive_ids"],
                                                                      want["prim"])


def test_cast_rays_normals_are_the_traced_triangles_face_normals(fox, fox_rays):
    origins, directions = fox_rays
    ans = fox.cast_rays(np.concatenate([origins, directions], axis=1))
    hit = ans["primitive_ids"] != rayd.INVALID_ID
    n = ans["primitive_normals"][hit]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    tris = fox.triangles().astype(np.float64)[ans["primitive_ids"][hit]]
    cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    assert (np.einsum("ij,ij->i", cross, n) > 0).all(), "(v1-v0) x (v2-v0), as Embree's Ng"


def test_geometry_holds_the_positions_that_were_traced(client, fox, fox_rays):
    origins, directions = fox_rays
    hits = fox.trace(origins, directions)
    fresh = client.scene(fox.id)  # nothing cached: fetched from GET .../geometry
    tris = fresh.triangles(version=1)
    assert tris.shape == (fox.info["triangles"], 3, 3) and tris.dtype == np.float32
    hit = hits["prim"] != rayd.INVALID_ID
    along = origins[hit].astype(np.float64) + hits["t"][hit, None] * directions[hit]
    at = rayd.hit_points(hits, tris)[hit]
    scale = np.abs(along).max()
    np.testing.assert_allclose(at, along, atol=1e-4 * scale)
    posed = fresh.triangles(version=1, time=0.75)
    assert not np.array_equal(posed, tris)


# -- geometry versions --------------------------------------------------------------------


def test_update_geometry_makes_a_version_traced_like_rayd_trace_on_the_new_file(
    rayd_bin, client, tmp_path
):
    box = client.upload(SCENES / "Box.glb")
    base = box.triangles(version=1)
    origins, directions = rays_at(box.info, 2000, seed=3)
    before = box.trace(origins, directions, version=1)
    moved = base + np.float32(0.25)
    version = box.update_geometry(moved)
    assert version >= 2 and box.version == version
    tri = tmp_path / "moved.tri"
    tri.write_bytes(bytes(formats.encode_triangles(moved)))
    after = box.trace(origins, directions)
    want, _ = rayd_trace(rayd_bin, tri, formats.encode_rays(origins, directions), tmp_path)
    assert after.body == want
    assert after.body != before.body
    assert box.trace(origins, directions, version=1).body == before.body, "version 1 stays"
    assert np.array_equal(client.scene(box.id).triangles(version), moved)
    with pytest.raises(rayd.ProblemError) as e:
        box.update_geometry(moved[:-1])
    assert e.value.status == 422 and "triangles" in e.value.detail


def test_a_frame_is_an_update_and_a_trace_in_one_request(rayd_bin, client, tmp_path):
    box = client.upload(SCENES / "Box.glb")
    base = box.triangles(version=1)
    origins, directions = rays_at(box.info, 2000, seed=4)
    moved = base - np.float32(0.125)
    hits = box.frame(moved, origins, directions, accel="dacrt")
    assert hits.version >= 2 and box.version == hits.version
    assert hits.accel == "dacrt" and "trace" in hits.server_timing
    tri = tmp_path / "frame.tri"
    tri.write_bytes(bytes(formats.encode_triangles(moved)))
    want, _ = rayd_trace(rayd_bin, tri, formats.encode_rays(origins, directions), tmp_path)
    assert hits.body == want
    assert box.trace(origins, directions, version=hits.version).body == want
    assert np.array_equal(client.scene(box.id).triangles(hits.version), moved)
    with pytest.raises(rayd.ProblemError) as e:
        box.frame(moved[:-1], origins, directions)
    assert e.value.status == 422 and e.value.field == "count"
    assert client.scene(box.id).version == hits.version, "a refused frame made a version"


def test_a_tri1_upload_traces_like_rayd_trace_on_the_same_file(rayd_bin, client, tmp_path):
    rng = np.random.default_rng(5)
    tris = rng.uniform(-1, 1, size=(300, 3, 3)).astype(np.float32)
    path = tmp_path / "soup.tri"
    path.write_bytes(bytes(formats.encode_triangles(tris)))
    scene = client.upload(path)
    assert scene.info["content_type"] == "application/x-rayd-tri"
    assert np.array_equal(client.scene(scene.id).triangles(), tris), "GET geometry = upload"
    origins, directions = rays_at(scene.info, 1000, seed=6)
    want, _ = rayd_trace(rayd_bin, path, formats.encode_rays(origins, directions), tmp_path)
    assert scene.trace(origins, directions).body == want
    scene.delete()


def _tri1_scene(client, offset):
    """A TRI1 scene of two triangles at ``offset`` (its id differs from other tests')."""
    tris = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]],
                     [[0, 0, 1], [1, 0, 1], [0, 1, 1]]], np.float32) + np.float32(offset)
    body = bytes(formats.encode_triangles(tris))
    return client.upload(body), body, tris


def test_a_frame_loop_keeps_the_positions_of_a_few_versions_only(client):
    # The server keeps 16 versions; a client sending positions every frame must not keep
    # them all (client.CACHED_VERSIONS, 4, are kept; 10 leaves room to tune that).
    scene, _, tris = _tri1_scene(client, 21.5)
    o = np.array([[21.95, 21.95, 30]], np.float32)  # inside every frame's triangles
    d = np.array([[0, 0, -1]], np.float32)
    for k in range(24):
        moved = tris + np.float32(k / 64)
        hits = scene.frame(moved, o, d)
        ans = scene.cast_rays(np.concatenate([o, d], axis=1))
        assert len(scene._known) < 10, "every version was kept"
    assert np.array_equal(scene.triangles(hits.version), moved)
    made = [scene.update_geometry(tris - np.float32(k / 64)) for k in range(24)]
    assert len(scene._known) < 10, "every version was kept"
    # What is kept still answers right, and what was dropped is fetched again.
    assert np.array_equal(scene.triangles(), tris - np.float32(23 / 64))
    assert np.array_equal(scene.triangles(made[-10]), tris - np.float32(14 / 64))
    assert ans["primitive_ids"][0] == 1 and ans["primitive_normals"][0].tolist() == [0, 0, 1]
    scene.delete()


def test_a_scene_made_again_under_its_id_is_not_answered_from_the_old_ones_positions(client):
    scene, body, tris = _tri1_scene(client, 31.5)
    scene.update_geometry(tris * np.float32(2))  # version 2, known to `scene`
    assert scene.triangles(2) is not None and len(scene._known) > 0
    # Another client deletes it and uploads the same bytes: the same id, versions from 1.
    other = rayd.Client(client.url)
    other.delete(scene.id)
    again = other.upload(body)
    assert again.id == scene.id and again.version == 1
    flipped = tris[:, ::-1] * np.float32(3)  # the other winding: normals turn over
    assert again.update_geometry(flipped) == 2
    assert np.array_equal(scene.triangles(2), flipped), "version 2 of the deleted scene"
    assert np.array_equal(scene.triangles(), flipped)
    ray = np.array([[94.8, 94.8, 1000, 0, 0, -1]], np.float32)  # inside both at 3x
    ans = scene.cast_rays(ray, version=2)
    assert ans["primitive_ids"][0] != rayd.INVALID_ID
    want = rayd.face_normals(flipped, ans["primitive_ids"])
    assert np.array_equal(ans["primitive_normals"], want)
    # Its own delete() forgets everything it knew of the scene.
    scene.delete()
    assert len(scene._known) == 0
    third = client.upload(body)
    third.update_geometry(tris + np.float32(1))
    assert np.array_equal(scene.triangles(2), tris + np.float32(1))
    third.delete()


# -- secondary rays -----------------------------------------------------------------------


def _diffuse(normals, rng):
    """Cosine-weighted directions about ``normals`` (unnormalised sums are fine)."""
    d = rng.normal(size=normals.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return (normals + d).astype(np.float32)


def test_spawned_rays_never_hit_their_own_triangle_and_naive_ones_do(fox, fox_rays):
    origins, directions = np.tile(fox_rays[0], (4, 1)), np.tile(fox_rays[1], (4, 1))
    hits = fox.trace(origins, directions)
    tris = fox.triangles()
    rng = np.random.default_rng(7)
    facing = rayd.face_normals(tris, hits["prim"])
    # Leave on the side the primary ray came from (diffuse reflection).
    facing[np.einsum("ij,ij->i", facing, directions) > 0] *= -1
    out = _diffuse(facing, rng)
    rays = rayd.spawn_rays(hits, out, tris)
    assert rays.valid.sum() == (hits["prim"] != rayd.INVALID_ID).sum() > 0
    second = fox.trace(**rays)
    own = rays.valid & (second["prim"] == hits["prim"])
    assert not own.any(), f"{own.sum()} spawned rays hit their own triangle"
    assert np.isinf(second["t"][~rays.valid]).all(), "misses spawn empty intervals"
    # The same rays from the unmoved hit point: some find their own triangle at t ~ 0.
    naive_o = origins + hits["t"][:, None] * directions
    naive = fox.trace(naive_o[rays.valid], out[rays.valid])
    assert (naive["prim"] == hits["prim"][rays.valid]).any(), "the test can fail"


def test_rays_spawned_from_misses_miss_in_open3d_layout_too(client, fox, fox_rays):
    box = client.upload(SCENES / "Box.glb")  # the unit cube about the origin
    o = np.array([[0, 0, 5], [3, 3, 5]], np.float32)  # the first hits the top, the other misses
    d = np.array([[0, 0, -1], [0, 0, -1]], np.float32)
    up = rayd.spawn_rays(box.trace(o, d), np.array([0, 0, 1], np.float32), box.triangles())
    assert up.valid.tolist() == [True, False]
    assert (box.trace(**up)["prim"] == rayd.INVALID_ID).all()
    assert (box.cast_rays(up.as_open3d())["primitive_ids"] == rayd.INVALID_ID).all(), \
        "a ray of a miss hit the cube from inside"
    # Many rays, some of misses, leaving in every direction: both ways agree ray for ray.
    hits = fox.trace(*fox_rays)
    rng = np.random.default_rng(11)
    rays = rayd.spawn_rays(hits, rng.normal(size=(len(hits["t"]), 3)).astype(np.float32),
                           fox.triangles())
    assert (~rays.valid).any() and rays.valid.any()
    traced = fox.trace(**rays)
    ans = fox.cast_rays(rays.as_open3d())
    assert np.array_equal(ans["primitive_ids"], traced["prim"])
    assert np.array_equal(ans["t_hit"], traced["t"])
    # A finite tmax, which Open3D's layout cannot hold, goes with cast_rays' tmax.
    short = rayd.spawn_rays(hits, rng.normal(size=(len(hits["t"]), 3)).astype(np.float32),
                            fox.triangles(), tmax=2.0)
    ans = fox.cast_rays(short.as_open3d(), tmax=short["tmax"])
    assert np.array_equal(ans["primitive_ids"], fox.trace(**short)["prim"])


# -- rendering ----------------------------------------------------------------------------


def _result_304s(client) -> int:
    """How many result downloads the server has answered 304 Not Modified."""
    total = 0
    for line in client.metrics().splitlines():
        if (line.startswith("rayd_http_requests_total{") and 'status="304"' in line
                and 'route="/v1/jobs/{job}/result"' in line):
            total += int(float(line.rsplit(" ", 1)[1]))
    return total


def test_render_waits_with_a_progress_bar_and_decodes_the_png(client, fox, capsys):
    job = fox.render(width=64, height=48, spp=2, integrator="normals")
    assert job.state in ("queued", "running", "succeeded")
    final = job.wait(progress=True, timeout=120).info
    assert final["state"] == "succeeded" and final["progress"] == 1
    assert "100%" in capsys.readouterr().err, "tqdm drew the bar to the end"
    image = job.result()
    assert isinstance(image, np.ndarray) and image.dtype == np.uint8
    assert image.shape[:2] == (48, 64) and image.shape[2] in (3, 4)
    assert image.std() > 0, "not a blank image"
    # Asked again, the result comes from the client's copy after a 304: its ETag matched.
    import io

    from PIL import Image

    not_modified = _result_304s(client)
    png = job.result(raw=True)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert _result_304s(client) == not_modified + 1
    with Image.open(io.BytesIO(png)) as img:
        assert np.array_equal(np.asarray(img), image)
    assert job.cancel() is None, "an ended job is deleted"
    with pytest.raises(rayd.ProblemError) as e:
        job.refresh()
    assert e.value.status == 404


def test_cancel_stops_a_running_render(client, fox):
    job = fox.render(width=1024, height=1024, spp=4096, integrator="path", bounces=8)
    with pytest.raises(rayd.ProblemError) as e:
        job.result()
    assert e.value.status == 409 and e.value.type == "/problems/conflict"
    record = job.cancel()
    assert record["state"] == "cancelled"
    assert job.wait(progress=False, timeout=60, check=False).state == "cancelled"
    with pytest.raises(rayd.JobError, match="cancelled"):
        job.wait(progress=False)
    assert any(j.id == job.id for j in client.jobs())
    assert client.job(job.id).state == "cancelled"


def test_jobs_are_listed_oldest_first_as_the_docstring_says(client, fox):
    first = fox.render(width=8, height=8, seed=101)
    last = fox.render(width=8, height=8, seed=102)
    ids = [j.id for j in client.jobs()]
    assert ids.index(first.id) < ids.index(last.id)
    assert "oldest first" in rayd.Client.jobs.__doc__


def _busy_server(rayd_bin, tmp_path, *args):
    srv = Server(rayd_bin, tmp_path / "data", "--max-running", "1", "--threads", "1", *args)
    srv.wait_ready(rayd.Client(srv.url))
    return srv


def test_wait_with_a_timeout_raises_timeout_error_when_nothing_happens(rayd_bin, tmp_path):
    srv = _busy_server(rayd_bin, tmp_path)
    try:
        c = rayd.Client(srv.url)
        fox = c.upload(SCENES / "Fox.glb")
        busy = fox.render(width=1024, height=1024, spp=4096, integrator="path")
        queued = fox.render(width=8, height=8)  # waits for the only running slot
        start = time.monotonic()
        with pytest.raises(TimeoutError, match="still queued"):
            queued.wait(progress=False, timeout=1.0)
        assert time.monotonic() - start < 10
        busy.cancel()
        queued.cancel()
    finally:
        srv.stop()


def test_wait_outlives_a_restart_of_the_server(rayd_bin, tmp_path):
    srv = _busy_server(rayd_bin, tmp_path, "--grace", "1")
    c = rayd.Client(srv.url, timeout=60)
    fox = c.upload(SCENES / "Fox.glb")
    job = fox.render(width=512, height=512, spp=128, integrator="path")
    stopped = []

    def restart():
        nonlocal srv
        time.sleep(0.5)
        stopped.append(time.time() * 1000)
        srv.proc.send_signal(signal.SIGTERM)
        srv.proc.wait(timeout=30)
        srv.stop()
        srv = Server(rayd_bin, tmp_path / "data", "--max-running", "1", "--threads", "1",
                     port=srv.port)

    thread = threading.Thread(target=restart)
    thread.start()
    try:
        job.wait(progress=False, timeout=120, check=False)
        assert job.state == "succeeded", job.info
        assert job.info["finished_at"] > stopped[0], "the job ended before the restart"
    finally:
        thread.join()
        srv.stop()


# -- errors -------------------------------------------------------------------------------


def test_invalid_rays_raise_a_problem_with_its_members(fox, fox_rays):
    origins, directions = fox_rays[0][:10].copy(), fox_rays[1][:10].copy()
    origins[3, 1] = np.nan
    directions[8] = 0
    with pytest.raises(rayd.ProblemError) as e:
        fox.trace(origins, directions)
    err = e.value
    assert err.status == 422 and err.type == "/problems/unprocessable"
    assert err.ray_index == 3 and err.count == 2 and err.extras["field"] == "rays"
    assert err.instance and err.title and "ray 3" in err.detail
    answered = fox.trace(origins, directions, invalid="miss")
    assert np.isinf(answered["t"][[3, 8]]).all()


def _raise(err):
    raise err


def test_problems_and_job_errors_survive_pickling_and_a_process_pool(fox):
    with pytest.raises(rayd.ProblemError) as e:
        fox.trace([0, 0, 5], [0, 0, 0])  # a zero direction: 422
    err = e.value
    err.add_note("a note")
    back = pickle.loads(pickle.dumps(err))
    assert type(back) is rayd.ProblemError and str(back) == str(err)
    assert back.__dict__ == err.__dict__ and back.ray_index == 0 and back.__notes__ == ["a note"]
    job_err = rayd.JobError({"id": "x", "state": "failed", "error": "boom"})
    again = pickle.loads(pickle.dumps(job_err))
    assert again.job == job_err.job and str(again) == str(job_err)
    with concurrent.futures.ProcessPoolExecutor(1) as pool:
        with pytest.raises(rayd.ProblemError) as e:
            pool.submit(_raise, err).result()
        assert e.value.status == 422 and e.value.extras == err.extras
        assert e.value.instance == err.instance and e.value.url == err.url
        with pytest.raises(rayd.JobError, match="boom") as e:
            pool.submit(_raise, job_err).result()
        assert e.value.job == job_err.job


def test_a_bad_parameter_names_its_field(fox, fox_rays):
    with pytest.raises(rayd.ProblemError) as e:
        fox.trace(fox_rays[0][:4], fox_rays[1][:4], accel="no-such-core")
    assert e.value.status == 400 and e.value.field == "accel"
    with pytest.raises(rayd.ProblemError) as e:
        fox.trace(fox_rays[0][:4], fox_rays[1][:4], version=99)
    assert e.value.status == 404 and "version" in e.value.detail
    with pytest.raises(AttributeError):
        _ = e.value.no_such_member


# -- authentication -----------------------------------------------------------------------


def test_a_token_is_sent_and_its_absence_is_a_401(rayd_bin, tmp_path):
    tokens = tmp_path / "tokens"
    tokens.write_text("# the test's token\ns3cret-token\n")
    srv = Server(rayd_bin, tmp_path / "data", "--token-file", str(tokens))
    try:
        good = rayd.Client(srv.url, token="s3cret-token")
        srv.wait_ready(good)
        assert good.scenes() == []
        with pytest.raises(rayd.ProblemError) as e:
            rayd.Client(srv.url).scenes()
        assert e.value.status == 401 and e.value.type == "/problems/unauthorized"
        with pytest.raises(rayd.ProblemError) as e:
            rayd.Client(srv.url, token="wrong").scenes()
        assert e.value.status == 401
    finally:
        srv.stop()


def test_clients_sharing_a_session_keep_their_own_tokens(rayd_bin, tmp_path, server):
    tokens = tmp_path / "tokens"
    tokens.write_text("first-token\nsecond-token\n")
    srv = Server(rayd_bin, tmp_path / "data", "--token-file", str(tokens))
    try:
        shared = requests.Session()
        a = rayd.Client(srv.url, token="first-token", session=shared)
        srv.wait_ready(a)
        assert a.scenes() == []
        b = rayd.Client(server.url, token="for-another-server", session=shared)
        b.scenes()
        assert a.scenes() == [], "b's token replaced a's"
        assert "Authorization" not in shared.headers, "the caller's session was changed"
        with pytest.raises(rayd.ProblemError) as e:
            rayd.Client(srv.url, session=shared).scenes()
        assert e.value.status == 401
        # A session that carries its own header still works with no token given.
        own = requests.Session()
        own.headers["Authorization"] = "Bearer second-token"
        assert rayd.Client(srv.url, session=own).scenes() == []
    finally:
        srv.stop()


# -- metrics ------------------------------------------------------------------------------


def test_metrics_after_traffic_pass_promtool(client, fox, fox_rays):
    fox.trace(*fox_rays)
    text = client.metrics()
    assert "rayd_rays_traced_total" in text and "rayd_http_requests_total" in text
    promtool = shutil.which("promtool")
    if promtool is None:
        pytest.skip("promtool is not installed (apt-get install prometheus)")
    done = subprocess.run([promtool, "check", "metrics"], input=text, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, f"promtool check metrics: {done.stdout}{done.stderr}\n{text}"


# -- the README's example -----------------------------------------------------------------


def test_the_readme_example_runs(server, monkeypatch, capsys):
    from conftest import REPO

    text = (REPO / "README.md").read_text().split("## Python", 1)[1]
    code = text.split("```python\n", 1)[1].split("```", 1)[0]
    assert len(code.strip().splitlines()) <= 12
    monkeypatch.chdir(REPO)
    env = {}
    exec(compile(code.replace("http://127.0.0.1:8080", server.url), "README.md", "exec"), env)
    assert env["image"].shape == (240, 320, 3)
    assert set(env["hits"]) == {"t", "prim", "u", "v"} and "primitive_normals" in env["ans"]
    assert env["bounce"].valid.any()
