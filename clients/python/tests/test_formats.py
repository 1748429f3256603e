"""RAY1/HIT1/TRI1 as the repository's ``proto/binary-formats.md`` lays them out, without a server."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from rayd import FormatError, formats


def test_ray1_records_are_origin_tmin_direction_tmax():
    o = np.array([[1, 2, 3], [4, 5, 6]], np.float64)
    d = np.array([[0, 0, 1], [0, 1, 0]], np.float32)
    body = formats.encode_rays(o, d, tmin=[0.5, 0.25], tmax=9.0)
    assert isinstance(body, bytearray) and len(body) == 16 + 2 * 32
    assert struct.unpack_from("<IHHQ", body) == (0x31594152, 1, 0, 2)
    assert body[:4] == b"RAY1"
    assert struct.unpack_from("<8f", body, 16) == (1, 2, 3, 0.5, 0, 0, 1, 9)
    assert struct.unpack_from("<8f", body, 48) == (4, 5, 6, 0.25, 0, 1, 0, 9)
    back = formats.decode_rays(bytes(body))
    assert np.array_equal(back["origin"], o) and np.array_equal(back["direction"], d)


def test_one_origin_is_broadcast_to_every_direction():
    body = formats.encode_rays([1, 1, 1], np.eye(3))
    recs = formats.decode_rays(body)
    assert recs.shape == (3,) and (recs["origin"] == 1).all()
    assert np.isinf(recs["tmax"]).all() and (recs["tmin"] == 0).all()


@pytest.mark.parametrize(
    "origins,directions,match",
    [
        (np.zeros((4, 2)), np.zeros((4, 3)), "origins must have shape"),
        (np.zeros((4, 3)), np.zeros((5, 3)), "ray counts disagree"),
    ],
)
def test_bad_ray_shapes_are_refused(origins, directions, match):
    with pytest.raises(ValueError, match=match):
        formats.encode_rays(origins, directions)


def _hit1(fmt, records: bytes, count):
    return struct.pack("<IHHQ", 0x31544948, 1, fmt, count) + records


@pytest.mark.parametrize("n, segment", [(0, 4), (1, 4), (10, 3), (1000, 64), (64, 64)])
def test_segmented_encoding_sends_the_same_bytes(n, segment):
    rng = np.random.default_rng(n)
    o, d = rng.random((n, 3)), rng.random((n, 3))
    lo, hi = rng.random(n), np.full(n, np.inf)
    for args in ((o, d, lo, hi), (o[0] if n else [0, 0, 0], d, 0.0, 5.0)):
        whole = bytes(formats.encode_rays(*args))
        parts = formats.RaySegments(*args, segment=segment)
        assert len(parts) == len(whole) and parts.count == n
        # Iterating twice (a retried request) sends the same bytes again.
        for _ in range(2):
            assert b"".join(bytes(p) for p in parts) == whole


@pytest.mark.parametrize("n", [0, 1, 7, 1000])
def test_every_input_layout_encodes_the_same_bytes(n):
    # Rows of three adjacent float32 (packed, the halves of an (N, 6) array, or float64
    # rows once a segment is converted) are copied as 12-byte values; components a row
    # apart (Fortran order, transposed) and one broadcast vector go field by field. All
    # must agree, and the fast path must be the one packed rows take.
    rng = np.random.default_rng(7 + n)
    o64, d64 = rng.standard_normal((n, 3)), rng.standard_normal((n, 3))
    o32, d32 = o64.astype(np.float32), d64.astype(np.float32)
    want = bytes(formats.encode_rays(o64, d64, 0.5, 7.0))
    layouts = [
        (o32, d32),
        (np.asfortranarray(o32), d32),
        (o32, np.ascontiguousarray(d32.T).T),
        (np.repeat(o32, 2, axis=0)[::2], np.repeat(d32, 2, axis=0)[::2]),
        (np.pad(o32, ((0, 0), (0, 1)))[:, :3], d32),
        (np.concatenate([o32, d32], axis=1)[:, :3], np.concatenate([o32, d32], axis=1)[:, 3:]),
        (np.ascontiguousarray(o32[::-1])[::-1], d32.astype(">f4")),
    ]
    for o, d in layouts:
        assert bytes(formats.encode_rays(o, d, 0.5, 7.0)) == want
        assert b"".join(bytes(p) for p in formats.RaySegments(o, d, 0.5, 7.0, segment=3)) == want
    if n:
        one = bytes(formats.encode_rays(o32[0], d32, 0.5, 7.0))
        assert one == bytes(formats.encode_rays(np.broadcast_to(o64[0], (n, 3)), d64, 0.5, 7.0))
        # One ray's worth as (1, 3) and (1,) is one value for all rays, in every segment.
        for args in ((o32[:1], d32, [0.5], [7.0]), (o64[:1], d64, np.float32(0.5), 7.0)):
            assert bytes(formats.encode_rays(*args)) == one
            assert b"".join(bytes(p) for p in formats.RaySegments(*args, segment=3)) == one
        assert formats._rows(o32) is not None
        assert formats._rows(np.concatenate([o32, d32], axis=1)[:, 3:]) is not None
        assert formats._rows(np.asfortranarray(o32)) is None or n == 1


def test_segmented_encoding_checks_shapes_before_anything_is_sent():
    with pytest.raises(ValueError, match="ray counts disagree"):
        formats.RaySegments(np.zeros((3, 3)), np.zeros((4, 3)))


def test_hit1_formats_decode_to_their_fields():
    rec = struct.pack("<fIff", 2.5, 7, 0.25, 0.5) + struct.pack("<fIff", np.inf, 0xFFFFFFFF, 0, 0)
    hits = formats.hit_arrays(formats.decode_hits(_hit1(0, rec, 2), 0, 2))
    assert hits["t"].tolist() == [2.5, np.inf] and hits["prim"].tolist() == [7, 0xFFFFFFFF]
    assert hits["u"].tolist() == [0.25, 0] and hits["v"].tolist() == [0.5, 0]
    occ = formats.hit_arrays(formats.decode_hits(_hit1(3, b"\x01\x00\x01", 3)))
    assert occ["occluded"].dtype == np.bool_ and occ["occluded"].tolist() == [True, False, True]
    assert formats.decode_hits(_hit1(1, struct.pack("<fI", 1, 2), 1)).dtype.names == ("t", "prim")
    assert formats.decode_hits(_hit1(2, struct.pack("<f", 1), 1)).dtype.names == ("t",)


@pytest.mark.parametrize(
    "body,match",
    [
        (b"HIT1", "shorter than the 16-byte header"),
        (struct.pack("<IHHQ", 0x31594152, 1, 0, 0), "magic at byte 0 is RAY1, not HIT1"),
        (struct.pack("<IHHQ", 0x31544948, 2, 0, 0), "version at byte 4 is 2"),
        (struct.pack("<IHHQ", 0x31544948, 1, 4, 0), "format at byte 6 is 4"),
        (_hit1(2, b"\0" * 7, 2), "is 23 bytes but its header's count 2 needs 24"),
        (_hit1(2, b"\0" * 4, 2**64 - 1), "needs"),
    ],
)
def test_hit1_readers_check_in_the_order_of_the_format(body, match):
    with pytest.raises(FormatError, match=match):
        formats.decode_hits(body)


def test_an_answer_of_another_format_or_count_is_refused():
    body = _hit1(2, struct.pack("<f", 1), 1)
    with pytest.raises(FormatError, match="format 2 answered where 0 was asked for"):
        formats.decode_hits(body, 0, 1)
    with pytest.raises(FormatError, match="1 records answered for 2 rays"):
        formats.decode_hits(body, 2, 2)


def test_tri1_round_trips_and_refuses_non_finite_coordinates():
    tris = np.arange(18, dtype=np.float32).reshape(2, 3, 3)
    body = formats.encode_triangles(tris.reshape(2, 9))
    assert struct.unpack_from("<IHHQ", body) == (0x31495254, 1, 0, 2)
    assert struct.unpack_from("<9f", body, 16 + 36) == tuple(range(9, 18))
    assert np.array_equal(formats.decode_triangles(body), tris)
    tris[1, 2, 0] = np.inf
    with pytest.raises(ValueError, match="triangle 1 has a NaN or infinite"):
        formats.encode_triangles(tris)
    with pytest.raises(FormatError, match="TRI1: magic at byte 0 is HIT1"):
        formats.decode_triangles(_hit1(0, b"", 0))
