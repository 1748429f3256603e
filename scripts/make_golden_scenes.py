#!/usr/bin/env python3
"""Writes scenes/golden-lights.gltf: a tiny scene for the renderer's golden images.

A floor with a bumpy normal texture (no TANGENT: tangents come from its UVs), a red
diffuse back wall (specularFactor 0), an emissive square light (emissive strength), a
standing quad cut out by a checker alpha texture (MASK), a half-transparent blue quad
(BLEND), a point light and a camera. Everything is generated here; run it from the
repository root to regenerate the file byte for byte.
"""

import base64
import json
import math
import struct
import zlib


def png(width, height, rows):
    """An 8-bit RGBA PNG from rows of (r, g, b, a) tuples."""
    raw = b"".join(b"\x00" + bytes(c for px in row for c in px) for row in rows)

    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    header = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
            + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))


def bumps(n=16):
    """Tangent-space normals of a sine bump field, encoded as glTF expects."""
    rows = []
    for j in range(n):
        row = []
        for i in range(n):
            dx = 0.5 * math.cos(2 * math.pi * i / n)
            dy = 0.5 * math.cos(2 * math.pi * j / n)
            length = math.sqrt(dx * dx + dy * dy + 1.0)
            v = (dx / length, dy / length, 1.0 / length)
            row.append(tuple(round(255 * (0.5 * c + 0.5)) for c in v) + (255,))
        rows.append(row)
    return png(n, n, rows)


def checker(n=4):
    """Green texels, alternately opaque and clear."""
    return png(n, n, [[(40, 180, 60, 255 if (i + j) % 2 == 0 else 0)
                       for i in range(n)] for j in range(n)])


class Builder:
    def __init__(self):
        self.bin = bytearray()
        self.views = []
        self.accessors = []

    def add(self, fmt, items, kind, component, target, bounds=False):
        while len(self.bin) % 4:
            self.bin.append(0)
        offset = len(self.bin)
        for it in items:
            self.bin += struct.pack(fmt, *(it if isinstance(it, tuple) else (it,)))
        self.views.append({"buffer": 0, "byteOffset": offset,
                           "byteLength": len(self.bin) - offset, "target": target})
        acc = {"bufferView": len(self.views) - 1, "componentType": component,
               "count": len(items), "type": kind}
        if bounds:
            acc["min"] = [min(p[k] for p in items) for k in range(3)]
            acc["max"] = [max(p[k] for p in items) for k in range(3)]
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def quad(self, corners, normal, material):
        """A primitive of two triangles over four corners (counter-clockwise seen from
        the side `normal` points to), with UVs (0,0) at the first corner."""
        uvs = [(0.0, 1.0), (1.0, 1.0), (1.0, 0.0), (0.0, 0.0)]
        pos = self.add("<3f", corners, "VEC3", 5126, 34962, bounds=True)
        nrm = self.add("<3f", [normal] * 4, "VEC3", 5126, 34962)
        uv = self.add("<2f", uvs, "VEC2", 5126, 34962)
        idx = self.add("<H", [0, 1, 2, 0, 2, 3], "SCALAR", 5123, 34963)
        return {"attributes": {"POSITION": pos, "NORMAL": nrm, "TEXCOORD_0": uv},
                "indices": idx, "material": material}


def main():
    b = Builder()
    prims = [
        b.quad([(-2, 0, 2), (2, 0, 2), (2, 0, -2), (-2, 0, -2)], (0, 1, 0), 0),
        b.quad([(-2, 0, -2), (2, 0, -2), (2, 2.5, -2), (-2, 2.5, -2)], (0, 0, 1), 1),
        b.quad([(-0.5, 2.2, 0.5), (-0.5, 2.2, -0.5), (0.5, 2.2, -0.5), (0.5, 2.2, 0.5)],
               (0, -1, 0), 2),
        b.quad([(-1.6, 0, -0.5), (-0.4, 0, -0.5), (-0.4, 1.2, -0.5), (-1.6, 1.2, -0.5)],
               (0, 0, 1), 3),
        b.quad([(0.4, 0, 0.3), (1.6, 0, 0.3), (1.6, 1.2, 0.3), (0.4, 1.2, 0.3)],
               (0, 0, 1), 4),
    ]
    diffuse = {"KHR_materials_specular": {"specularFactor": 0.0}}
    images = [bumps(), checker()]
    gltf = {
        "asset": {"version": "2.0", "generator": "rayd scripts/make_golden_scenes.py"},
        "extensionsUsed": ["KHR_materials_specular", "KHR_materials_emissive_strength",
                           "KHR_lights_punctual"],
        "extensions": {"KHR_lights_punctual": {"lights": [
            {"type": "point", "color": [1.0, 0.9, 0.8], "intensity": 6.0}]}},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [
            {"mesh": 0},
            {"camera": 0, "translation": [0.3, 1.3, 4.2],
             "rotation": [-0.0998, 0.0, 0.0, 0.995]},
            {"translation": [1.2, 1.8, 1.2], "extensions": {"KHR_lights_punctual": {"light": 0}}},
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.05}}],
        "meshes": [{"primitives": prims}],
        "materials": [
            {"name": "floor", "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1],
                                                        "metallicFactor": 0.0,
                                                        "roughnessFactor": 0.6},
             "normalTexture": {"index": 0, "scale": 1.0}},
            {"name": "red wall", "pbrMetallicRoughness": {"baseColorFactor": [0.7, 0.1, 0.1, 1],
                                                          "metallicFactor": 0.0},
             "extensions": diffuse},
            {"name": "lamp", "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1],
                                                      "metallicFactor": 0.0},
             "emissiveFactor": [1.0, 0.95, 0.9],
             "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 6.0}}},
            {"name": "leaf", "pbrMetallicRoughness": {"baseColorTexture": {"index": 1},
                                                      "metallicFactor": 0.0},
             "alphaMode": "MASK", "alphaCutoff": 0.5, "doubleSided": True,
             "extensions": diffuse},
            {"name": "glass", "pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.3, 0.9, 0.5],
                                                       "metallicFactor": 0.0},
             "alphaMode": "BLEND", "doubleSided": True, "extensions": diffuse},
        ],
        "samplers": [{"magFilter": 9729, "minFilter": 9729},
                     {"magFilter": 9728, "minFilter": 9728}],
        "textures": [{"source": 0, "sampler": 0}, {"source": 1, "sampler": 1}],
        "images": [{"uri": "data:image/png;base64," + base64.b64encode(i).decode()}
                   for i in images],
        "buffers": [],
        "bufferViews": b.views,
        "accessors": b.accessors,
    }
    gltf["buffers"] = [{"byteLength": len(b.bin),
                        "uri": "data:application/octet-stream;base64,"
                               + base64.b64encode(bytes(b.bin)).decode()}]
    with open("scenes/golden-lights.gltf", "w") as f:
        json.dump(gltf, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()
