#!/usr/bin/env python3
"""rayd's `path` integrator against Mitsuba 3 (issue 9 item 8) on scenes both renderers
read the same way: purely diffuse glTF materials (`KHR_materials_specular` with
`specularFactor` 0) in several colours, flat-shaded triangles, a constant environment, one
look-at camera, a box filter.

Each scene is a small glTF committed under `scenes/` (`--write-scenes` makes them again from
the definitions below). Mitsuba gets the very same triangles: the script reads the .glb's
buffers itself and hands each primitive to Mitsuba as a PLY file with face normals, with a
`twosided` `diffuse` BSDF of the primitive's base colour (rayd's surfaces are two-sided and
Mitsuba's diffuse BSDF is not). Conventions, matched on purpose:

- camera: vertical field of view (`fov_axis` y), Mitsuba's `look_at` with rayd's eye, target
  and up; the image's aspect sets the horizontal extent on both sides;
- pixels: each sample uniform in its pixel, a pixel the plain mean (Mitsuba `box` filter of
  radius 0.5, rayd `proto/rendering.md` "Pixels and samples");
- bounces: Mitsuba's `max_depth` counts path vertices, rayd's `bounces` scatterings, so
  `max_depth = bounces + 1`; Russian roulette is kept off on Mitsuba's side (`rr_depth` past
  `max_depth`) so that both are plain unbiased path tracers of the same truncated sum;
- radiance: both images are linear scene-referred RGB (rayd's EXR, Mitsuba's film tensor),
  compared as they are, never through sRGB.

Reported per scene: over the pixels that see geometry (rayd's coverage `A` > 0), the mean
absolute difference of the two images as a fraction of Mitsuba's mean there, and both means.
The goal (issue 9): MAD <= 2 % and the means within 1 % at 1024 spp on both sides.

Usage: python3 scripts/mitsuba_compare.py [--spp 1024] [--rayd target/release/rayd]
Needs: pip install mitsuba OpenEXR numpy (the scalar_rgb variant ships in the wheel).
"""

import argparse
import json
import os
import struct
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# ---------------------------------------------------------------------------------------
# The scenes: boxes, walls and a sphere in linear-RGB colours.


def box(lo, hi):
    """The 12 triangles of an axis-aligned box, outward-facing."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    v = np.array(
        [
            [x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
            [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1],
        ],
        dtype=np.float32,
    )
    f = np.array(
        [
            [0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7],  # -z, +z
            [0, 1, 5], [0, 5, 4], [3, 6, 2], [3, 7, 6],  # -y, +y
            [0, 4, 7], [0, 7, 3], [1, 2, 6], [1, 6, 5],  # -x, +x
        ],
        dtype=np.uint32,
    )
    return v, f


def quad(a, b, c, d):
    """Two triangles a-b-c, a-c-d."""
    return np.array([a, b, c, d], dtype=np.float32), np.array([[0, 1, 2], [0, 2, 3]], np.uint32)


def icosphere(centre, radius, subdivisions):
    """A sphere of subdivided icosahedron faces."""
    t = (1.0 + 5 ** 0.5) / 2.0
    verts = [
        [-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0],
        [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
        [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1],
    ]
    faces = [
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
        [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
        [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
        [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
    ]
    verts = [np.array(v, float) / np.linalg.norm(v) for v in verts]
    for _ in range(subdivisions):
        mid = {}

        def m(i, j):
            key = (min(i, j), max(i, j))
            if key not in mid:
                p = verts[i] + verts[j]
                verts.append(p / np.linalg.norm(p))
                mid[key] = len(verts) - 1
            return mid[key]

        out = []
        for a, b, c in faces:
            ab, bc, ca = m(a, b), m(b, c), m(c, a)
            out += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = out
    v = np.array(verts) * radius + np.array(centre)
    return v.astype(np.float32), np.array(faces, dtype=np.uint32)


SCENES = {
    "diffuse-boxes": {
        "parts": [
            ("floor", [0.7, 0.7, 0.7], quad([-3, 0, -2], [-3, 0, 3], [3, 0, 3], [3, 0, -2])),
            ("wall", [0.8, 0.75, 0.5], quad([-3, 0, -2], [3, 0, -2], [3, 2.5, -2], [-3, 2.5, -2])),
            ("red", [0.8, 0.1, 0.1], box([-1.5, 0, -0.4], [-0.7, 0.8, 0.4])),
            ("green", [0.1, 0.7, 0.2], box([0.5, 0, 0.0], [1.4, 1.0, 0.9])),
            ("blue", [0.15, 0.25, 0.8], box([-0.3, 0, -1.5], [0.3, 1.5, -0.9])),
        ],
        "camera": {"eye": [0.4, 2.4, 5.0], "target": [0.0, 0.6, -0.3], "up": [0, 1, 0], "fov": 40.0},
        "sky": [1.0, 1.0, 1.0],
        "bounces": 3,
    },
    "diffuse-corner": {
        "parts": [
            ("floor", [0.75, 0.75, 0.75], quad([-2, 0, -2], [-2, 0, 2], [2, 0, 2], [2, 0, -2])),
            ("left", [0.7, 0.2, 0.2], quad([-2, 0, -2], [-2, 2, -2], [-2, 2, 2], [-2, 0, 2])),
            ("back", [0.2, 0.3, 0.7], quad([-2, 0, -2], [2, 0, -2], [2, 2, -2], [-2, 2, -2])),
            ("ball", [0.9, 0.8, 0.3], icosphere([-0.6, 0.7, -0.8], 0.7, 2)),
            ("block", [0.5, 0.9, 0.9], box([0.4, 0, -0.3], [1.2, 0.5, 0.5])),
        ],
        "camera": {"eye": [2.6, 2.0, 4.2], "target": [-0.4, 0.5, -0.8], "up": [0, 1, 0], "fov": 45.0},
        "sky": [0.9, 0.95, 1.1],
        "bounces": 5,
    },
}

# ---------------------------------------------------------------------------------------
# glTF out and in (the subset these scenes use: one node per primitive, no transforms).


def write_glb(path, parts):
    """Writes `parts` (name, colour, (vertices, faces)) as a .glb: one mesh of one primitive
    each, positions and indices only (so both renderers use face normals), a purely diffuse
    material each."""
    blob = bytearray()
    views, accessors, meshes, nodes, materials = [], [], [], [], []
    for name, colour, (v, f) in parts:
        for data, target in ((v.astype("<f4").tobytes(), 34962), (f.astype("<u4").tobytes(), 34963)):
            while len(blob) % 4:
                blob.append(0)
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data), "target": target})
            blob += data
        accessors.append({
            "bufferView": len(views) - 2, "componentType": 5126, "count": len(v), "type": "VEC3",
            "min": v.min(axis=0).tolist(), "max": v.max(axis=0).tolist(),
        })
        accessors.append({
            "bufferView": len(views) - 1, "componentType": 5125, "count": f.size, "type": "SCALAR",
        })
        materials.append({
            "name": name,
            "pbrMetallicRoughness": {
                "baseColorFactor": list(colour) + [1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0,
            },
            "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}},
        })
        meshes.append({
            "name": name,
            "primitives": [{
                "attributes": {"POSITION": len(accessors) - 2},
                "indices": len(accessors) - 1,
                "material": len(materials) - 1,
            }],
        })
        nodes.append({"name": name, "mesh": len(meshes) - 1})
    gltf = {
        "asset": {"version": "2.0", "generator": "rayd scripts/mitsuba_compare.py"},
        "extensionsUsed": ["KHR_materials_specular"],
        "scene": 0,
        "scenes": [{"nodes": list(range(len(nodes)))}],
        "nodes": nodes, "meshes": meshes, "materials": materials,
        "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": len(blob)}],
    }
    js = json.dumps(gltf, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    with open(path, "wb") as out:
        out.write(struct.pack("<4sII", b"glTF", 2, total))
        out.write(struct.pack("<I4s", len(js), b"JSON") + js)
        out.write(struct.pack("<I4s", len(blob), b"BIN\0") + bytes(blob))


def read_glb(path):
    """The primitives of a .glb written by `write_glb`: (name, colour, vertices, faces)."""
    with open(path, "rb") as f:
        data = f.read()
    magic, version, _ = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2:
        raise SystemExit(f"{path}: not a glTF 2.0 binary")
    jlen, _ = struct.unpack_from("<I4s", data, 12)
    gltf = json.loads(data[20:20 + jlen])
    blen, _ = struct.unpack_from("<I4s", data, 20 + jlen)
    blob = data[28 + jlen:28 + jlen + blen]

    def accessor(i, dtype, width):
        a = gltf["accessors"][i]
        view = gltf["bufferViews"][a["bufferView"]]
        start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
        arr = np.frombuffer(blob, dtype=dtype, count=a["count"] * width, offset=start)
        return arr.reshape(-1, width)

    out = []
    for node in gltf["nodes"]:
        if any(k in node for k in ("matrix", "translation", "rotation", "scale", "children")):
            raise SystemExit(f"{path}: node {node.get('name')} has a transform; this reader has none")
        for prim in gltf["meshes"][node["mesh"]]["primitives"]:
            mat = gltf["materials"][prim["material"]]
            spec = mat.get("extensions", {}).get("KHR_materials_specular", {}).get("specularFactor", 1.0)
            pbr = mat["pbrMetallicRoughness"]
            if spec != 0.0 or pbr.get("metallicFactor", 1.0) != 0.0:
                raise SystemExit(f"{path}: material {mat.get('name')} is not purely diffuse")
            v = accessor(prim["attributes"]["POSITION"], "<f4", 3)
            f = accessor(prim["indices"], "<u4", 1).reshape(-1, 3)
            out.append((mat.get("name", "?"), pbr["baseColorFactor"][:3], v, f))
    return out


def write_ply(path, v, f):
    """A binary PLY of one triangle mesh, without normals."""
    with open(path, "wb") as out:
        out.write(
            (
                "ply\nformat binary_little_endian 1.0\n"
                f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
                f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
            ).encode()
        )
        out.write(np.ascontiguousarray(v, dtype="<f4").tobytes())
        rec = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", 3)])
        rec["n"] = 3
        rec["i"] = f
        out.write(rec.tobytes())


# ---------------------------------------------------------------------------------------
# The two renders.


def render_rayd(rayd, glb, spec, width, height, spp, out):
    cam = spec["camera"]
    vec = lambda v: ",".join(repr(float(x)) for x in v)  # noqa: E731
    cmd = [
        rayd, "render", glb, "-o", out, "--integrator", "path", "--spp", str(spp),
        "--bounces", str(spec["bounces"]), "--width", str(width), "--height", str(height),
        "--eye", vec(cam["eye"]), "--target", vec(cam["target"]), "--up", vec(cam["up"]),
        "--fov", repr(cam["fov"]), "--sky", vec(spec["sky"]), "--accel", "mbvh8", "--seed", "1",
    ]
    t0 = time.time()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    seconds = time.time() - t0
    import OpenEXR

    with OpenEXR.File(out, separate_channels=True) as f:
        ch = f.channels()
        rgb = np.stack([np.asarray(ch[c].pixels, dtype=np.float64) for c in "RGB"], axis=-1)
        alpha = np.asarray(ch["A"].pixels, dtype=np.float64)
    return rgb, alpha, seconds


def render_mitsuba(glb, spec, width, height, spp, tmp):
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    cam = spec["camera"]
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": spec["bounces"] + 1, "rr_depth": spec["bounces"] + 100},
        "sensor": {
            "type": "perspective",
            "fov_axis": "y",
            "fov": cam["fov"],
            "to_world": mi.ScalarTransform4f().look_at(origin=cam["eye"], target=cam["target"], up=cam["up"]),
            "film": {
                "type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                "rfilter": {"type": "box"},
            },
            "sampler": {"type": "independent", "sample_count": spp, "seed": 7},
        },
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": spec["sky"]}},
    }
    for k, (name, colour, v, f) in enumerate(read_glb(glb)):
        ply = os.path.join(tmp, f"{k}-{name}.ply")
        write_ply(ply, v, f)
        scene[f"shape{k}"] = {
            "type": "ply", "filename": ply, "face_normals": True,
            "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": colour}}},
        }
    t0 = time.time()
    img = np.array(mi.render(mi.load_dict(scene), spp=spp), dtype=np.float64)
    return img[..., :3], time.time() - t0


def compare(name, spec, args, tmp):
    glb = os.path.join(ROOT, "scenes", f"{name}.glb")
    ours, alpha, t_ours = render_rayd(args.rayd, glb, spec, args.width, args.height, args.spp,
                                      os.path.join(tmp, f"{name}.exr"))
    theirs, t_theirs = render_mitsuba(glb, spec, args.width, args.height, args.spp, tmp)
    if ours.shape != theirs.shape:
        raise SystemExit(f"{name}: image shapes differ: rayd {ours.shape}, Mitsuba {theirs.shape}")
    mask = alpha > 0
    if not mask.any():
        raise SystemExit(f"{name}: no pixel sees geometry")
    o, t = ours[mask], theirs[mask]
    mean_o, mean_t = float(o.mean()), float(t.mean())
    result = {
        "scene": name,
        "pixels": int(mask.sum()),
        "mad_fraction": float(np.abs(o - t).mean() / mean_t),
        "mean_rayd": mean_o,
        "mean_mitsuba": mean_t,
        "mean_ratio": mean_o / mean_t,
        "per_channel_ratio": (o.mean(axis=0) / t.mean(axis=0)).tolist(),
        "rayd_seconds": t_ours,
        "mitsuba_seconds": t_theirs,
    }
    if args.keep:
        np.save(os.path.join(args.keep, f"{name}-rayd.npy"), ours)
        np.save(os.path.join(args.keep, f"{name}-mitsuba.npy"), theirs)
    return result


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--spp", type=int, default=1024)
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--rayd", default=os.path.join(ROOT, "target", "release", "rayd"))
    p.add_argument("--scenes", default=",".join(SCENES), help="comma-separated names")
    p.add_argument("--write-scenes", action="store_true", help="write scenes/*.glb anew and stop")
    p.add_argument("--keep", help="a directory for both images as .npy")
    args = p.parse_args()
    if args.write_scenes:
        for name, spec in SCENES.items():
            write_glb(os.path.join(ROOT, "scenes", f"{name}.glb"), spec["parts"])
        return 0
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes.split(","):
            if name not in SCENES:
                raise SystemExit(f"unknown scene {name!r} (one of {', '.join(SCENES)})")
            results.append(compare(name, SCENES[name], args, tmp))
    print(json.dumps(results, indent=2))
    print(f"\n| scene | pixels | spp | bounces | MAD / Mitsuba mean | rayd mean | Mitsuba mean | ratio | goal |",
          file=sys.stderr)
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|", file=sys.stderr)
    ok = True
    for r in results:
        met = r["mad_fraction"] <= 0.02 and abs(r["mean_ratio"] - 1) <= 0.01
        ok &= met
        print(
            f"| {r['scene']} | {r['pixels']} | {args.spp} | {SCENES[r['scene']]['bounces']} | "
            f"{100 * r['mad_fraction']:.2f} % | {r['mean_rayd']:.4f} | {r['mean_mitsuba']:.4f} | "
            f"{r['mean_ratio']:.4f} | {'met' if met else 'NOT met'} |",
            file=sys.stderr,
        )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
