//! glTF loading: the shared real scenes, and small hand-built files for every rule and
//! every kind of malformed input.

use std::path::{Path, PathBuf};

use rayd::formats::gltf::{load, GltfError};
use rayd::formats::LoadOptions;
use rayd::scene::{Projection, Scene, SceneError};
use serde_json::{json, Value};

fn scenes_dir() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/scenes");
    if dir.is_dir() {
        Some(dir)
    } else {
        eprintln!("skipping: {} not found", dir.display());
        None
    }
}

fn load_shared(name: &str, time: Option<f64>) -> Option<Result<Scene, GltfError>> {
    let dir = scenes_dir()?;
    let bytes = std::fs::read(dir.join(name)).expect("read scene");
    Some(load(&bytes, None, &LoadOptions { time }))
}

/// Triangle counts of MANIFEST.md.
const MANIFEST: &[(&str, usize)] = &[
    ("2CylinderEngine.glb", 121_496),
    ("AlphaBlendModeTest.glb", 61),
    ("AnimatedCube.glb", 12),
    ("AnimatedMorphCube.glb", 12),
    ("AnimatedMorphSphere.glb", 960),
    ("AnimatedTriangle.glb", 1),
    ("Box.glb", 12),
    ("BoxAnimated.glb", 254),
    ("BoxInterleaved.glb", 12),
    ("BoxTextured.glb", 12),
    ("BoxTexturedNonPowerOfTwo.glb", 12),
    ("BoxVertexColors.glb", 12),
    ("BrainStem.glb", 61_666),
    ("Cameras.glb", 2),
    ("CesiumMan.glb", 4_672),
    ("CesiumMilkTruck.glb", 3_624),
    ("DamagedHelmet.glb", 15_452),
    ("dragon-100k.from-ply.glb", 100_000),
    ("Duck.glb", 4_212),
    ("Fox.glb", 576),
    ("horse.from-ply.glb", 96_966),
    ("InterpolationTest.glb", 110),
    ("lucy-100k.from-drc.glb", 100_000),
    ("MetalRoughSpheresNoTextures.glb", 1_040_409),
    ("Monster.glb", 884),
    ("MorphPrimitivesTest.glb", 32),
    ("MultipleScenes.glb", 2),
    ("MultiUVTest.glb", 12),
    ("nefertiti.from-obj.glb", 99_938),
    ("NormalTangentMirrorTest.glb", 5_240),
    ("NormalTangentTest.glb", 7_774),
    ("OrientationTest.glb", 524),
    ("ReciprocatingSaw.glb", 198_470),
    ("RiggedFigure.glb", 256),
    ("RiggedSimple.glb", 188),
    ("SimpleMeshes.glb", 2),
    ("SimpleMorph.glb", 1),
    ("SimpleSkin.glb", 8),
    ("SimpleSparseAccessor.glb", 12),
    ("stanford-bunny.from-obj.glb", 69_451),
    ("Suzanne.glb", 3_936),
    ("TextureCoordinateTest.glb", 10),
    ("TextureSettingsTest.glb", 72),
    ("TextureTransformTest.glb", 24),
    ("Triangle.glb", 1),
    ("TriangleWithoutIndices.glb", 1),
    ("TwoSidedPlane.glb", 2),
    ("UnlitTest.glb", 88),
    ("VC.glb", 8_383),
    ("VertexColorTest.glb", 36),
    ("VivaBalloon.glb", 35_698),
];

#[test]
fn shared_scenes_match_the_manifest() {
    let Some(_) = scenes_dir() else { return };
    let mut failures = Vec::new();
    for &(name, expected) in MANIFEST {
        for time in [None, Some(0.7)] {
            match load_shared(name, time).unwrap() {
                Ok(s) if s.triangles.len() == expected => {
                    let finite = s
                        .triangles
                        .iter()
                        .flat_map(|t| t.v)
                        .flatten()
                        .all(|x| x.is_finite());
                    assert!(finite, "{name}: non-finite position");
                }
                Ok(s) => failures.push(format!(
                    "{name} (t={time:?}): {} triangles, manifest says {expected}",
                    s.triangles.len()
                )),
                Err(e) => failures.push(format!("{name} (t={time:?}): {e}")),
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn shared_draco_files_are_refused_naming_the_extension() {
    for name in ["Box_Draco.glb", "BoxMetaDraco.glb"] {
        let Some(r) = load_shared(name, None) else {
            return;
        };
        match r {
            Err(e @ GltfError::UnsupportedExtension(_)) => {
                assert!(e.to_string().contains("KHR_draco_mesh_compression"), "{e}")
            }
            other => panic!("{name}: {other:?}"),
        }
    }
}

#[test]
fn shared_multiple_scenes_uses_the_default_scene() {
    let Some(r) = load_shared("MultipleScenes.glb", None) else {
        return;
    };
    let s = r.unwrap();
    // Scene 1 (the default) is the square: two triangles.
    assert_eq!(s.triangles.len(), 2);
}

#[test]
fn shared_sparse_accessor_substitution_is_visible() {
    let Some(r) = load_shared("SimpleSparseAccessor.glb", None) else {
        return;
    };
    let s = r.unwrap();
    assert_eq!(s.triangles.len(), 12);
    // The dense grid lies in y ∈ [0, 2]; the sparse values lift some vertices to y = 4.
    let max_y = s
        .triangles
        .iter()
        .flat_map(|t| t.v)
        .map(|p| p[1])
        .fold(f32::MIN, f32::max);
    assert_eq!(max_y, 4.0);
}

#[test]
fn shared_animated_scenes_differ_at_a_time() {
    for name in [
        "AnimatedTriangle.glb",
        "SimpleSkin.glb",
        "SimpleMorph.glb",
        "CesiumMan.glb",
    ] {
        let Some(a) = load_shared(name, None) else {
            return;
        };
        let b = load_shared(name, Some(0.5)).unwrap().unwrap();
        let a = a.unwrap();
        assert_eq!(a.triangles.len(), b.triangles.len());
        assert_ne!(
            a.triangles, b.triangles,
            "{name}: the pose at t=0.5 equals the static pose"
        );
        assert!(!a.animations.is_empty());
    }
}

#[test]
fn shared_cameras_and_animation_info() {
    let Some(r) = load_shared("Cameras.glb", None) else {
        return;
    };
    let s = r.unwrap();
    assert_eq!(s.cameras.len(), 2);
    assert!(matches!(
        s.cameras[0].as_ref().map(|c| c.projection),
        Some(Projection::Perspective { .. })
    ));
    assert!(matches!(
        s.cameras[1].as_ref().map(|c| c.projection),
        Some(Projection::Orthographic { .. })
    ));
    let fox = load_shared("Fox.glb", None).unwrap().unwrap();
    let names: Vec<&str> = fox.animations.iter().map(|a| a.name.as_str()).collect();
    assert_eq!(names, ["Survey", "Walk", "Run"]);
    assert!(fox.animations.iter().all(|a| a.duration > 0.0));
}

// ---------------------------------------------------------------------------------------
// Hand-built files.

/// Builds a glTF document with one binary buffer.
#[derive(Default)]
struct Builder {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

fn components(ty: &str) -> usize {
    match ty {
        "SCALAR" => 1,
        "VEC2" => 2,
        "VEC3" => 3,
        "VEC4" => 4,
        "MAT4" => 16,
        _ => panic!("type {ty}"),
    }
}

impl Builder {
    fn view(&mut self, bytes: &[u8]) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.views
            .push(json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len()}));
        self.views.len() - 1
    }

    fn accessor(&mut self, a: Value) -> usize {
        self.accessors.push(a);
        self.accessors.len() - 1
    }

    fn floats(&mut self, data: &[f32], ty: &str) -> usize {
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes);
        let count = data.len() / components(ty);
        self.accessor(
            json!({"bufferView": view, "componentType": 5126, "count": count, "type": ty}),
        )
    }

    fn positions(&mut self, p: &[[f32; 3]]) -> usize {
        self.floats(&p.concat(), "VEC3")
    }

    fn u16s(&mut self, data: &[u16], ty: &str) -> usize {
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes);
        let count = data.len() / components(ty);
        self.accessor(
            json!({"bufferView": view, "componentType": 5123, "count": count, "type": ty}),
        )
    }

    fn indices(&mut self, data: &[u32]) -> usize {
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes);
        self.accessor(json!({"bufferView": view, "componentType": 5125, "count": data.len(), "type": "SCALAR"}))
    }

    /// The whole document: `extra`'s keys plus asset, buffer, views and accessors.
    fn doc(&self, extra: Value) -> Value {
        let mut doc = json!({
            "asset": {"version": "2.0"},
            "buffers": [{"byteLength": self.bin.len()}],
            "bufferViews": self.views,
            "accessors": self.accessors,
        });
        for (k, v) in extra.as_object().unwrap() {
            doc[k] = v.clone();
        }
        doc
    }

    fn glb(&self, extra: Value) -> Vec<u8> {
        glb(&self.doc(extra), &self.bin)
    }

    fn gltf_embedded(&self, extra: Value) -> Vec<u8> {
        let mut doc = self.doc(extra);
        doc["buffers"][0]["uri"] = json!(format!(
            "data:application/octet-stream;base64,{}",
            base64(&self.bin)
        ));
        serde_json::to_vec_pretty(&doc).unwrap()
    }
}

fn glb(doc: &Value, bin: &[u8]) -> Vec<u8> {
    let mut json = serde_json::to_vec(doc).unwrap();
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let mut bin = bin.to_vec();
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(A[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

fn load_bytes(bytes: &[u8]) -> Result<Scene, GltfError> {
    load(bytes, None, &LoadOptions::default())
}

fn load_at(bytes: &[u8], t: f64) -> Result<Scene, GltfError> {
    load(bytes, None, &LoadOptions { time: Some(t) })
}

fn close(a: [f32; 3], b: [f32; 3]) -> bool {
    a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5)
}

fn assert_tri(s: &Scene, id: usize, expected: [[f32; 3]; 3]) {
    let t = s.triangles[id].v;
    assert!(
        (0..3).all(|k| close(t[k], expected[k])),
        "triangle {id}: {t:?} != {expected:?}"
    );
}

/// The x coordinates of each triangle's vertices, as integers (tests put vertex i at x=i).
fn xs(s: &Scene) -> Vec<[u32; 3]> {
    s.triangles
        .iter()
        .map(|t| t.v.map(|p| p[0] as u32))
        .collect()
}

/// One mesh (given primitives) on one node in the only scene.
fn single(b: &Builder, prims: Value) -> Vec<u8> {
    b.glb(json!({
        "meshes": [{"primitives": prims}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
    }))
}

const TRI: [[f32; 3]; 3] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];

/// Vertex i at (i, i², 0): recognisable by x.
fn numbered(n: usize) -> Vec<[f32; 3]> {
    (0..n).map(|i| [i as f32, (i * i) as f32, 0.0]).collect()
}

#[test]
fn modes_strip_fan_and_lines() {
    let mut b = Builder::default();
    let p = b.positions(&numbered(5));
    let rev = b.indices(&[4, 3, 2, 1, 0]);
    let bytes = single(
        &b,
        json!([
            {"attributes": {"POSITION": p}, "mode": 5},
            {"attributes": {"POSITION": p}, "mode": 6},
            {"attributes": {"POSITION": p}, "mode": 0},
            {"attributes": {"POSITION": p}, "mode": 1},
            {"attributes": {"POSITION": p}, "mode": 2},
            {"attributes": {"POSITION": p}, "mode": 3},
            {"attributes": {"POSITION": p}, "indices": rev, "mode": 5},
            {"attributes": {"POSITION": p}, "indices": rev, "mode": 6},
            {"attributes": {"POSITION": p}, "indices": rev},
            {"attributes": {"POSITION": p}},
        ]),
    );
    let s = load_bytes(&bytes).unwrap();
    assert_eq!(
        xs(&s),
        [
            // strip i: i, i+1+(i%2), i+2-(i%2)
            [0, 1, 2],
            [1, 3, 2],
            [2, 3, 4],
            // fan i: i+1, i+2, 0
            [1, 2, 0],
            [2, 3, 0],
            [3, 4, 0],
            // points and lines: nothing; indexed strip over 4,3,2,1,0
            [4, 3, 2],
            [3, 1, 2],
            [2, 1, 0],
            // indexed fan
            [3, 2, 4],
            [2, 1, 4],
            [1, 0, 4],
            // indexed triangles: the two left-over indices make no triangle
            [4, 3, 2],
            // non-indexed triangles: consecutive triples
            [0, 1, 2],
        ]
    );
}

#[test]
fn short_strips_and_primitives_without_positions_give_nothing() {
    let mut b = Builder::default();
    let p = b.positions(&numbered(2));
    let q = b.positions(&numbered(3));
    let bytes = single(
        &b,
        json!([
            {"attributes": {"POSITION": p}, "mode": 5},
            {"attributes": {"POSITION": p}, "mode": 6},
            {"attributes": {"NORMAL": q}},
            {"attributes": {"POSITION": q}},
        ]),
    );
    let s = load_bytes(&bytes).unwrap();
    assert_eq!(xs(&s), [[0, 1, 2]]);
}

#[test]
fn degenerate_triangles_keep_their_ids() {
    let mut b = Builder::default();
    let p = b.positions(&[
        [0.0; 3],
        [0.0; 3],
        [0.0; 3],
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
    ]);
    let s = load_bytes(&single(&b, json!([{"attributes": {"POSITION": p}}]))).unwrap();
    assert_eq!(s.triangles.len(), 2);
    assert!(s.triangles[0].is_degenerate());
    assert_tri(&s, 1, TRI);
}

#[test]
fn node_hierarchy_with_trs_and_matrix() {
    let mut b = Builder::default();
    let p = b.positions(&[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
    let h = std::f32::consts::FRAC_1_SQRT_2;
    let bytes = b.glb(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
        "nodes": [
            {"children": [1], "translation": [10.0, 0.0, 0.0], "rotation": [0.0, 0.0, h, h]},
            {"mesh": 0, "scale": [2.0, 2.0, 2.0]},
            {"mesh": 0, "matrix": [3.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 5.0, 0.0, 1.0]},
        ],
        "scenes": [{"nodes": [0, 2]}],
    }));
    let s = load_bytes(&bytes).unwrap();
    assert_eq!(s.triangles.len(), 2);
    // T(10,0,0) · R(90° about z) · S(2)
    assert_tri(&s, 0, [[10.0, 2.0, 0.0], [8.0, 0.0, 0.0], [10.0, 0.0, 2.0]]);
    assert_tri(&s, 1, [[3.0, 5.0, 0.0], [0.0, 6.0, 0.0], [0.0, 5.0, 1.0]]);
}

#[test]
fn instancing_follows_preorder_not_node_indices() {
    let mut b = Builder::default();
    let p0 = b.positions(&TRI);
    let p1 = b.positions(&[[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]);
    let bytes = b.glb(json!({
        "meshes": [
            {"primitives": [{"attributes": {"POSITION": p0}}, {"attributes": {"POSITION": p1}}]},
            {"primitives": [{"attributes": {"POSITION": p1}}]},
        ],
        "nodes": [
            {"mesh": 1, "translation": [0.0, 10.0, 0.0]},          // 0: child of 2
            {"mesh": 0, "translation": [200.0, 0.0, 0.0]},         // 1: second root
            {"mesh": 0, "translation": [100.0, 0.0, 0.0], "children": [0]}, // 2: first root
            {"mesh": 0, "translation": [300.0, 0.0, 0.0]},         // 3: not in the scene
        ],
        "scenes": [{"nodes": [2, 1]}],
    }));
    let s = load_bytes(&bytes).unwrap();
    assert_eq!(s.meshes, 2);
    let offsets: Vec<[f32; 3]> = s.triangles.iter().map(|t| t.v[0]).collect();
    assert_eq!(
        offsets,
        [
            [100.0, 0.0, 0.0],  // node 2, mesh 0 primitive 0
            [100.0, 0.0, 0.0],  // node 2, mesh 0 primitive 1
            [100.0, 10.0, 0.0], // node 0 (child of 2), mesh 1
            [200.0, 0.0, 0.0],  // node 1, mesh 0 primitive 0
            [200.0, 0.0, 0.0],  // node 1, mesh 0 primitive 1
        ]
    );
    assert_tri(
        &s,
        1,
        [[100.0, 0.0, 0.0], [100.0, 0.0, 1.0], [100.0, 1.0, 0.0]],
    );
}

#[test]
fn default_scene_else_scene_zero_and_no_scenes_refused() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let scenes = json!([{"nodes": [0]}, {"nodes": [1]}]);
    let base = json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
        "nodes": [{"mesh": 0}, {"mesh": 0, "translation": [5.0, 0.0, 0.0]}],
    });
    let mut with = base.clone();
    with["scenes"] = scenes.clone();
    with["scene"] = json!(1);
    assert_eq!(
        load_bytes(&b.glb(with)).unwrap().triangles[0].v[0],
        [5.0, 0.0, 0.0]
    );
    let mut without = base.clone();
    without["scenes"] = scenes;
    assert_eq!(
        load_bytes(&b.glb(without)).unwrap().triangles[0].v[0],
        [0.0, 0.0, 0.0]
    );
    assert!(matches!(
        load_bytes(&b.glb(base.clone())),
        Err(GltfError::NoScenes)
    ));
    let mut dangling = base;
    dangling["scenes"] = json!([{"nodes": [0]}]);
    dangling["scene"] = json!(3);
    assert!(matches!(
        load_bytes(&b.glb(dangling)),
        Err(GltfError::DanglingReference {
            kind: "scene",
            index: 3,
            ..
        })
    ));
}

#[test]
fn node_graph_errors() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let file = |nodes: Value, roots: Value| {
        b.glb(json!({
            "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
            "nodes": nodes,
            "scenes": [{"nodes": roots}],
        }))
    };
    // 0 → 1 → 2 → 1: a cycle below a root.
    let e = load_bytes(&file(
        json!([{"children": [1]}, {"children": [2]}, {"children": [1], "mesh": 0}]),
        json!([0]),
    ))
    .unwrap_err();
    match &e {
        GltfError::NodeMultipleParents {
            node: 1,
            first: 0,
            second: 2,
        } => {}
        other => panic!("{other:?}"),
    }
    // A pure cycle, unreachable from any root.
    let e = load_bytes(&file(
        json!([{"mesh": 0}, {"children": [2]}, {"children": [3]}, {"children": [1]}]),
        json!([0]),
    ))
    .unwrap_err();
    match &e {
        GltfError::NodeCycle { nodes } => assert_eq!(nodes, &[1, 2, 3, 1]),
        other => panic!("{other:?}"),
    }
    assert!(e.to_string().contains("1 -> 2 -> 3 -> 1"), "{e}");
    // A node that is its own child.
    let e = load_bytes(&file(json!([{"children": [0], "mesh": 0}]), json!([0]))).unwrap_err();
    assert!(
        matches!(e, GltfError::NodeCycle { ref nodes } if nodes == &[0, 0]),
        "{e:?}"
    );
    // Listed twice as a child of one parent.
    let e = load_bytes(&file(
        json!([{"children": [1, 1]}, {"mesh": 0}]),
        json!([0]),
    ))
    .unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::NodeMultipleParents {
                node: 1,
                first: 0,
                second: 0
            }
        ),
        "{e:?}"
    );
    // A scene root that is someone's child, and a root listed twice.
    let e = load_bytes(&file(
        json!([{"children": [1]}, {"mesh": 0}]),
        json!([0, 1]),
    ))
    .unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::BadSceneRoot {
                scene: 0,
                node: 1,
                ..
            }
        ),
        "{e:?}"
    );
    let e = load_bytes(&file(json!([{"mesh": 0}]), json!([0, 0]))).unwrap_err();
    assert!(
        matches!(e, GltfError::BadSceneRoot { node: 0, .. }),
        "{e:?}"
    );
    // Dangling references.
    let e = load_bytes(&file(json!([{"mesh": 4}]), json!([0]))).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::DanglingReference {
                kind: "mesh",
                index: 4,
                count: 1,
                ..
            }
        ),
        "{e:?}"
    );
    let e = load_bytes(&file(json!([{"children": [9]}]), json!([0]))).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::DanglingReference {
                kind: "node",
                index: 9,
                ..
            }
        ),
        "{e:?}"
    );
    let e = load_bytes(&file(json!([{"mesh": 0}]), json!([7]))).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::DanglingReference {
                kind: "node",
                index: 7,
                ..
            }
        ),
        "{e:?}"
    );
}

#[test]
fn deep_hierarchy_does_not_overflow_the_stack() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let n = 100_000;
    let nodes: Vec<Value> = (0..n)
        .map(|i| {
            if i + 1 < n {
                json!({"children": [i + 1], "translation": [1.0, 0.0, 0.0]})
            } else {
                json!({"mesh": 0})
            }
        })
        .collect();
    let bytes = b.glb(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
        "nodes": nodes,
        "scenes": [{"nodes": [0]}],
    }));
    let s = load_bytes(&bytes).unwrap();
    assert_eq!(s.triangles[0].v[0], [(n - 1) as f32, 0.0, 0.0]);
}

#[test]
fn sparse_accessors_dense_and_viewless() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let idx = b.view(&2u16.to_le_bytes());
    let val = b.view(
        &[0.0f32, 5.0, 0.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<_>>(),
    );
    let idx1 = b.view(&[1u8]);
    let val1 = b.view(
        &[7.0f32, 0.0, 0.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<_>>(),
    );
    let base_view = b.accessors[p]["bufferView"].clone();
    let dense = b.accessor(json!({
        "bufferView": base_view, "componentType": 5126, "count": 3, "type": "VEC3",
        "sparse": {"count": 1, "indices": {"bufferView": idx, "componentType": 5123}, "values": {"bufferView": val}},
    }));
    let viewless = b.accessor(json!({
        "componentType": 5126, "count": 3, "type": "VEC3",
        "sparse": {"count": 1, "indices": {"bufferView": idx1, "componentType": 5121}, "values": {"bufferView": val1}},
    }));
    let bytes = single(
        &b,
        json!([{"attributes": {"POSITION": dense}}, {"attributes": {"POSITION": viewless}}]),
    );
    let s = load_bytes(&bytes).unwrap();
    assert_tri(&s, 0, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 5.0, 0.0]]);
    assert_tri(&s, 1, [[0.0, 0.0, 0.0], [7.0, 0.0, 0.0], [0.0, 0.0, 0.0]]);
}

/// A mesh with two morph targets (one sparse and view-less), instanced by a node with its
/// own weights and by one without; `anim` adds a weights animation on node 0.
fn morph_file(anim: bool) -> Vec<u8> {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let idx = b.view(&[2u8]);
    let val = b.view(
        &[0.0f32, 0.0, 1.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<_>>(),
    );
    let t0 = b.accessor(json!({
        "componentType": 5126, "count": 3, "type": "VEC3",
        "sparse": {"count": 1, "indices": {"bufferView": idx, "componentType": 5121}, "values": {"bufferView": val}},
    }));
    let t1 = b.positions(&[[1.0, 0.0, 0.0]; 3]);
    let times = b.floats(&[0.0, 1.0], "SCALAR");
    let weights = b.floats(&[0.0, 0.0, 1.0, 1.0], "SCALAR");
    let mut extra = json!({
        "meshes": [{
            "primitives": [{"attributes": {"POSITION": p}, "targets": [{"POSITION": t0}, {"POSITION": t1}]}],
            "weights": [0.5, 0.0],
        }],
        "nodes": [{"mesh": 0, "weights": [1.0, 2.0]}, {"mesh": 0}],
        "scenes": [{"nodes": [0, 1]}],
    });
    if anim {
        extra["animations"] = json!([{
            "name": "blend",
            "samplers": [{"input": times, "output": weights}],
            "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
        }]);
    }
    b.glb(extra)
}

#[test]
fn morph_weights_static_and_animated() {
    let s = load_bytes(&morph_file(false)).unwrap();
    // Node 0: its own weights (1, 2).
    assert_tri(&s, 0, [[2.0, 0.0, 0.0], [3.0, 0.0, 0.0], [2.0, 1.0, 1.0]]);
    // Node 1: the mesh's weights (0.5, 0).
    assert_tri(&s, 1, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.5]]);
    let s = load_at(&morph_file(true), 0.25).unwrap();
    // Animated weights (0.25, 0.25) replace node 0's; node 1 is not animated.
    assert_tri(
        &s,
        0,
        [[0.25, 0.0, 0.0], [1.25, 0.0, 0.0], [0.25, 1.0, 0.25]],
    );
    assert_tri(&s, 1, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.5]]);
    assert_eq!(s.animations.len(), 1);
    assert_eq!(s.animations[0].name, "blend");
    assert_eq!(s.animations[0].duration, 1.0);
}

/// Mesh node 0 (translated far away: ignored) skinned to joints 1 and 2.
fn skin_file(with_ibm: bool) -> Vec<u8> {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let joints = b.u16s(&[0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0], "VEC4");
    let weights = b.floats(
        &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0],
        "VEC4",
    );
    let mut ibm = vec![
        1.0f32, 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1.,
    ];
    ibm.extend([
        1.0f32, 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., -10., 0., 0., 1.,
    ]);
    let ibm = b.floats(&ibm, "MAT4");
    let times = b.floats(&[0.0, 1.0], "SCALAR");
    let moves = b.floats(&[10.0, 0.0, 0.0, 10.0, 4.0, 0.0], "VEC3");
    let mut skin = json!({"joints": [1, 2]});
    if with_ibm {
        skin["inverseBindMatrices"] = json!(ibm);
    }
    b.glb(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": p, "JOINTS_0": joints, "WEIGHTS_0": weights}}]}],
        "skins": [skin],
        "nodes": [
            {"mesh": 0, "skin": 0, "translation": [1000.0, 0.0, 0.0]},
            {"translation": [0.0, 0.0, 5.0]},
            {"translation": [10.0, 0.0, 0.0]},
        ],
        "scenes": [{"nodes": [0, 1, 2]}],
        "animations": [{
            "samplers": [{"input": times, "output": moves}],
            "channels": [{"sampler": 0, "target": {"node": 2, "path": "translation"}}],
        }],
    }))
}

#[test]
fn simple_skin_static_animated_and_without_inverse_bind_matrices() {
    let s = load_bytes(&skin_file(true)).unwrap();
    assert_tri(&s, 0, [[0.0, 0.0, 5.0], [1.0, 0.0, 0.0], [0.0, 1.0, 2.5]]);
    let s = load_at(&skin_file(true), 0.5).unwrap();
    assert_tri(&s, 0, [[0.0, 0.0, 5.0], [1.0, 2.0, 0.0], [0.0, 2.0, 2.5]]);
    assert_eq!(s.animations[0].name, "");
    // Without inverse bind matrices they are identities: joint 1 moves vertices by +10 x.
    let s = load_bytes(&skin_file(false)).unwrap();
    assert_tri(&s, 0, [[0.0, 0.0, 5.0], [11.0, 0.0, 0.0], [5.0, 1.0, 2.5]]);
}

#[test]
fn joint_out_of_range_is_an_error() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let joints = b.u16s(&[0, 0, 0, 0, 5, 0, 0, 0, 0, 0, 0, 0], "VEC4");
    let weights = b.floats(
        &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        "VEC4",
    );
    let bytes = b.glb(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": p, "JOINTS_0": joints, "WEIGHTS_0": weights}}]}],
        "skins": [{"joints": [1]}],
        "nodes": [{"mesh": 0, "skin": 0}, {}],
        "scenes": [{"nodes": [0, 1]}],
    }));
    let e = load_bytes(&bytes).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::Scene(SceneError::JointOutOfRange {
                vertex: 1,
                joint: 5,
                joints: 1,
                skin: 0,
                ..
            })
        ),
        "{e:?}"
    );
}

/// A triangle on node 0 whose translation is animated with `interp` through keyframes
/// at 0, 1, 3; node 1 has a matrix and an (ignored) animation.
fn translation_file(interp: &str) -> Vec<u8> {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let times = b.floats(&[0.0, 1.0, 3.0], "SCALAR");
    let values: Vec<f32> = if interp == "CUBICSPLINE" {
        // (in-tangent, value, out-tangent) per keyframe.
        vec![
            0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0, 0.0, 0.0, //
            1.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0, //
            0.0, 0.0, 0.0, 2.0, 4.0, 0.0, 0.0, 0.0, 0.0,
        ]
    } else {
        vec![0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 2.0, 4.0, 0.0]
    };
    let out = b.floats(&values, "VEC3");
    b.glb(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
        "nodes": [
            {"mesh": 0},
            {"mesh": 0, "matrix": [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 9.0, 1.0]},
        ],
        "scenes": [{"nodes": [0, 1]}],
        "animations": [{
            "name": "move",
            "samplers": [{"input": times, "output": out, "interpolation": interp}],
            "channels": [
                {"sampler": 0, "target": {"node": 0, "path": "translation"}},
                {"sampler": 0, "target": {"node": 1, "path": "translation"}},
            ],
        }],
    }))
}

fn origin_at(bytes: &[u8], t: Option<f64>) -> [f32; 3] {
    let s = load(bytes, None, &LoadOptions { time: t }).unwrap();
    // The matrix node ignores its animation.
    assert_eq!(s.triangles[1].v[0], [0.0, 0.0, 9.0]);
    assert_eq!(s.animations[0].duration, 3.0);
    s.triangles[0].v[0]
}

#[test]
fn animated_translation_linear_step_cubic() {
    let f = translation_file("LINEAR");
    assert_eq!(origin_at(&f, None), [0.0, 0.0, 0.0]);
    assert_eq!(origin_at(&f, Some(0.5)), [1.0, 0.0, 0.0]);
    assert_eq!(origin_at(&f, Some(2.0)), [2.0, 2.0, 0.0]);
    assert_eq!(origin_at(&f, Some(-1.0)), [0.0, 0.0, 0.0]);
    assert_eq!(origin_at(&f, Some(10.0)), [2.0, 4.0, 0.0]);
    let f = translation_file("STEP");
    assert_eq!(origin_at(&f, Some(0.5)), [0.0, 0.0, 0.0]);
    assert_eq!(origin_at(&f, Some(1.0)), [2.0, 0.0, 0.0]);
    assert_eq!(origin_at(&f, Some(2.9)), [2.0, 0.0, 0.0]);
    assert_eq!(origin_at(&f, Some(3.0)), [2.0, 4.0, 0.0]);
    let f = translation_file("CUBICSPLINE");
    // s = 0.5 on [0, 1]: h00·0 + h10·1·3 + h01·2 + h11·1·1 = 0.375 + 1 − 0.125.
    assert_eq!(origin_at(&f, Some(0.5)), [1.25, 0.0, 0.0]);
    assert_eq!(origin_at(&f, Some(1.0)), [2.0, 0.0, 0.0]);
    assert_eq!(origin_at(&f, Some(5.0)), [2.0, 4.0, 0.0]);
}

#[test]
fn animated_rotation_is_slerped() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let times = b.floats(&[0.0, 1.0], "SCALAR");
    let h = std::f32::consts::FRAC_1_SQRT_2;
    // The second key is −q: the same rotation; slerp must take the short arc.
    let rots = b.floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, -h, -h], "VEC4");
    let bytes = b.glb(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "animations": [{
            "samplers": [{"input": times, "output": rots}],
            "channels": [{"sampler": 0, "target": {"node": 0, "path": "rotation"}}],
        }],
    }));
    let s = load_at(&bytes, 0.5).unwrap();
    let c = std::f32::consts::FRAC_PI_4.cos();
    assert_tri(&s, 0, [[0.0, 0.0, 0.0], [c, c, 0.0], [-c, c, 0.0]]);
}

/// Cameras go by their index in the file's `cameras` (contract §6: "a glTF camera by
/// index"), each where the first node in the scene's pre-order that places it puts it; a
/// camera no node of the scene places is there, unplaced.
#[test]
fn cameras_by_their_index_in_the_file() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let bytes = b.glb(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
        "cameras": [
            {"type": "perspective", "perspective": {"yfov": 0.8, "aspectRatio": 1.5, "znear": 0.1}},
            {"type": "orthographic", "orthographic": {"xmag": 2.0, "ymag": 3.0, "znear": 0.1, "zfar": 10.0}},
            {"type": "perspective", "perspective": {"yfov": 0.5, "znear": 0.1}},
        ],
        "nodes": [
            {"camera": 0, "translation": [0.0, 0.0, 5.0]},
            {"camera": 1, "children": [0]},
            {"mesh": 0, "camera": 0},
        ],
        "scenes": [{"nodes": [1, 2]}],
    }));
    let s = load_bytes(&bytes).unwrap();
    assert_eq!(s.cameras.len(), 3);
    let [Some(persp), Some(ortho), None] = &s.cameras[..] else {
        panic!("{:?}", s.cameras);
    };
    assert_eq!(
        ortho.projection,
        Projection::Orthographic {
            xmag: 2.0,
            ymag: 3.0
        }
    );
    assert_eq!(ortho.to_world[3], [0.0, 0.0, 0.0, 1.0]);
    assert_eq!(
        persp.projection,
        Projection::Perspective {
            yfov: 0.8f32 as f64,
            aspect: Some(1.5)
        }
    );
    // Node 0 (under node 1) comes before node 2 in the pre-order.
    assert_eq!(persp.to_world[3], [0.0, 0.0, 5.0, 1.0]);
    // The clipping planes: a perspective camera without zfar sees to infinity.
    assert_eq!(persp.clip, [f64::from(0.1f32), f64::INFINITY]);
    assert_eq!(ortho.clip, [f64::from(0.1f32), 10.0]);
}

#[test]
fn embedded_gltf_and_external_buffers() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let extra = json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
    });
    let s = load_bytes(&b.gltf_embedded(extra.clone())).unwrap();
    assert_tri(&s, 0, TRI);

    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("my data.bin"), &b.bin).unwrap();
    let mut doc = b.doc(extra);
    doc["buffers"][0]["uri"] = json!("my%20data.bin");
    let text = serde_json::to_vec(&doc).unwrap();
    let s = load(&text, Some(dir.path()), &LoadOptions::default()).unwrap();
    assert_tri(&s, 0, TRI);
    // Without a base directory, external files are refused.
    let e = load_bytes(&text).unwrap_err();
    assert!(
        matches!(e, GltfError::ExternalBufferNotAllowed { buffer: 0, .. }),
        "{e:?}"
    );
    assert!(e.to_string().contains("my%20data.bin"));
    // A missing file.
    doc["buffers"][0]["uri"] = json!("absent.bin");
    let e = load(
        &serde_json::to_vec(&doc).unwrap(),
        Some(dir.path()),
        &LoadOptions::default(),
    )
    .unwrap_err();
    assert!(
        matches!(e, GltfError::MissingBuffer { buffer: 0, .. }),
        "{e:?}"
    );
    assert!(e.to_string().contains("absent.bin"), "{e}");
    // Schemes and absolute paths.
    for uri in [
        "http://example.com/a.bin",
        "/etc/passwd",
        "file:///tmp/a.bin",
    ] {
        doc["buffers"][0]["uri"] = json!(uri);
        let e = load(
            &serde_json::to_vec(&doc).unwrap(),
            Some(dir.path()),
            &LoadOptions::default(),
        )
        .unwrap_err();
        assert!(
            matches!(e, GltfError::UnsupportedUri { .. }),
            "{uri}: {e:?}"
        );
    }
    // A malformed data URI, and a buffer with no data at all.
    doc["buffers"][0]["uri"] = json!("data:application/octet-stream;base64,AAA*");
    let e = load_bytes(&serde_json::to_vec(&doc).unwrap()).unwrap_err();
    assert!(
        matches!(e, GltfError::BadDataUri { buffer: 0, .. }),
        "{e:?}"
    );
    doc["buffers"][0].as_object_mut().unwrap().remove("uri");
    let e = load_bytes(&serde_json::to_vec(&doc).unwrap()).unwrap_err();
    assert!(matches!(e, GltfError::NoBufferData { buffer: 0 }), "{e:?}");
}

#[test]
fn required_extensions() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let file = |ext: &str| {
        b.glb(json!({
            "extensionsUsed": [ext],
            "extensionsRequired": [ext],
            "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
            "nodes": [{"mesh": 0}],
            "scenes": [{"nodes": [0]}],
        }))
    };
    for ext in [
        "KHR_draco_mesh_compression",
        "EXT_meshopt_compression",
        "EXT_mesh_gpu_instancing",
    ] {
        let e = load_bytes(&file(ext)).unwrap_err();
        assert!(
            matches!(&e, GltfError::UnsupportedExtension(x) if x == ext),
            "{e:?}"
        );
        assert!(e.to_string().contains(ext));
    }
    for ext in [
        "KHR_materials_unlit",
        "KHR_texture_basisu",
        "KHR_lights_punctual",
        "VENDOR_unknown",
    ] {
        assert_eq!(load_bytes(&file(ext)).unwrap().triangles.len(), 1, "{ext}");
    }
}

#[test]
fn out_of_range_index_and_non_finite_positions() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let bad_idx = b.indices(&[0, 1, 5]);
    let e = load_bytes(&single(
        &b,
        json!([{"attributes": {"POSITION": p}, "indices": bad_idx}]),
    ))
    .unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::IndexOutOfRange {
                mesh: 0,
                primitive: 0,
                slot: 2,
                index: 5,
                vertices: 3,
                ..
            }
        ),
        "{e:?}"
    );
    let nan = b.positions(&[[0.0; 3], [f32::NAN, 0.0, 0.0], [0.0, 1.0, 0.0]]);
    let e = load_bytes(&single(&b, json!([{"attributes": {"POSITION": nan}}]))).unwrap_err();
    assert!(
        matches!(e, GltfError::NonFinitePosition { element: 1, .. }),
        "{e:?}"
    );
    let inf = b.positions(&[[0.0; 3], [0.0, f32::INFINITY, 0.0], [0.0, 1.0, 0.0]]);
    let e = load_bytes(&single(&b, json!([{"attributes": {"POSITION": inf}}]))).unwrap_err();
    assert!(
        matches!(e, GltfError::NonFinitePosition { element: 1, .. }),
        "{e:?}"
    );
    // Finite in the file, infinite in f32 world space.
    let big = b.positions(&[[0.0; 3], [3.0e38, 0.0, 0.0], [0.0, 1.0, 0.0]]);
    let bytes = b.glb(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": big}}]}],
        "nodes": [{"mesh": 0, "scale": [10.0, 1.0, 1.0]}],
        "scenes": [{"nodes": [0]}],
    }));
    let e = load_bytes(&bytes).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::Scene(SceneError::NonFiniteWorldPosition {
                node: 0,
                vertex: 1,
                ..
            })
        ),
        "{e:?}"
    );
}

fn triangle_doc() -> (Builder, Value) {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let extra = json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
    });
    (b, extra)
}

#[test]
fn malformed_glb_containers() {
    let (b, extra) = triangle_doc();
    let good = b.glb(extra);
    assert!(load_bytes(&good).is_ok());
    // Truncated: the header's length no longer matches.
    let e = load_bytes(&good[..good.len() - 10]).unwrap_err();
    assert!(matches!(e, GltfError::GlbLength { .. }), "{e:?}");
    let e = load_bytes(&good[..7]).unwrap_err();
    assert!(matches!(e, GltfError::GlbHeader(_)), "{e:?}");
    // Version 1.
    let mut v1 = good.clone();
    v1[4] = 1;
    assert!(matches!(load_bytes(&v1), Err(GltfError::GlbHeader(_))));
    // The BIN chunk's length runs past the end of the file.
    let json_len = u32::from_le_bytes(good[12..16].try_into().unwrap()) as usize;
    let bin_header = 20 + json_len;
    let mut long = good.clone();
    long[bin_header..bin_header + 4].copy_from_slice(&10_000u32.to_le_bytes());
    let e = load_bytes(&long).unwrap_err();
    assert!(
        matches!(e, GltfError::GlbChunk { index: 1, offset, .. } if offset == bin_header),
        "{e:?}"
    );
    // The first chunk is not JSON.
    let mut first = good.clone();
    first[16..20].copy_from_slice(b"BIN\0");
    assert!(matches!(
        load_bytes(&first),
        Err(GltfError::GlbChunk { index: 0, .. })
    ));
}

#[test]
fn invalid_json_reports_its_location() {
    let text = b"{\n  \"asset\": {\"version\": \"2.0\"},\n  \"scenes\": [}\n}";
    match load_bytes(text).unwrap_err() {
        GltfError::Json {
            line,
            column,
            detail,
        } => {
            assert_eq!(line, 3);
            assert!(column > 0);
            assert!(detail.contains("line 3"), "{detail}");
        }
        other => panic!("{other:?}"),
    }
    // Well-formed JSON without glTF's shape.
    let e = load_bytes(b"{\"scenes\": []}").unwrap_err();
    assert!(matches!(e, GltfError::Json { .. }), "{e:?}");
    let e = load_bytes(b"").unwrap_err();
    assert!(matches!(e, GltfError::Json { .. }), "{e:?}");
}

#[test]
fn byte_ranges_are_checked() {
    let (b, extra) = triangle_doc();
    let mut doc = b.doc(extra.clone());
    // A view past its buffer.
    doc["bufferViews"][0]["byteLength"] = json!(1000);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::BufferViewOutOfRange {
                view: 0,
                buffer: 0,
                end: 1000,
                ..
            }
        ),
        "{e:?}"
    );
    // An offset near u64::MAX must not overflow.
    let mut doc = b.doc(extra.clone());
    doc["bufferViews"][0]["byteOffset"] = json!(u64::MAX - 3);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(matches!(e, GltfError::BufferViewOutOfRange { .. }), "{e:?}");
    // An accessor past its view (count and offset).
    let mut doc = b.doc(extra.clone());
    doc["accessors"][0]["count"] = json!(4);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::AccessorOutOfRange {
                accessor: 0,
                view: 0,
                end: 48,
                view_length: 36,
                ..
            }
        ),
        "{e:?}"
    );
    let mut doc = b.doc(extra.clone());
    doc["accessors"][0]["byteOffset"] = json!(4);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(e, GltfError::AccessorOutOfRange { offset: 4, .. }),
        "{e:?}"
    );
    let mut doc = b.doc(extra.clone());
    doc["accessors"][0]["count"] = json!(u64::MAX);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(matches!(e, GltfError::AccessorOutOfRange { .. }), "{e:?}");
    // A stride smaller than the element.
    let mut doc = b.doc(extra.clone());
    doc["bufferViews"][0]["byteStride"] = json!(8);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(e, GltfError::BadAccessor { accessor: 0, .. }),
        "{e:?}"
    );
    let mut doc = b.doc(extra.clone());
    doc["bufferViews"][0]["byteStride"] = json!(6);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(e, GltfError::BadBufferView { view: 0, .. }),
        "{e:?}"
    );
    // The buffer claims more bytes than the BIN chunk has.
    let mut doc = b.doc(extra.clone());
    doc["buffers"][0]["byteLength"] = json!(4000);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::BufferTooShort {
                buffer: 0,
                declared: 4000,
                actual: 36
            }
        ),
        "{e:?}"
    );
    // A view into a buffer that does not exist.
    let mut doc = b.doc(extra.clone());
    doc["bufferViews"][0]["buffer"] = json!(3);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::DanglingReference {
                kind: "buffer",
                index: 3,
                ..
            }
        ),
        "{e:?}"
    );
    // The wrong type for POSITION.
    let mut doc = b.doc(extra);
    doc["accessors"][0]["type"] = json!("VEC2");
    doc["accessors"][0]["count"] = json!(4);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(e, GltfError::BadAccessor { accessor: 0, .. }),
        "{e:?}"
    );
    assert!(e.to_string().contains("POSITION"), "{e}");
}

#[test]
fn sparse_ranges_are_checked() {
    let mut b = Builder::default();
    let idx = b.view(&[1u8, 0, 0, 0]);
    let val = b.view(
        &[7.0f32, 0.0, 0.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<_>>(),
    );
    let acc = b.accessor(json!({
        "componentType": 5126, "count": 3, "type": "VEC3",
        "sparse": {"count": 1, "indices": {"bufferView": idx, "componentType": 5121}, "values": {"bufferView": val}},
    }));
    let extra = json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": acc}}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
    });
    assert!(load_bytes(&b.glb(extra.clone())).is_ok());
    let mut doc = b.doc(extra.clone());
    doc["accessors"][0]["sparse"]["values"]["byteOffset"] = json!(4);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::SparseOutOfRange {
                accessor: 0,
                part: "values",
                ..
            }
        ),
        "{e:?}"
    );
    let mut doc = b.doc(extra.clone());
    doc["accessors"][0]["sparse"]["indices"]["byteOffset"] = json!(4);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::SparseOutOfRange {
                part: "indices",
                ..
            }
        ),
        "{e:?}"
    );
    let mut doc = b.doc(extra.clone());
    doc["accessors"][0]["count"] = json!(1);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::SparseIndexOutOfRange {
                accessor: 0,
                entry: 0,
                index: 1,
                count: 1
            }
        ),
        "{e:?}"
    );
    // View-less accessors are zeros that cost no file bytes: bounded.
    let mut doc = b.doc(extra);
    doc["accessors"][0]["count"] = json!(1u64 << 40);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(e, GltfError::TooLarge { accessor: 0, .. }),
        "{e:?}"
    );
}

#[test]
fn instancing_amplification_is_bounded() {
    let mut b = Builder::default();
    // 2^22 view-less vertices: 1,398,101 triangles per instance, 200 instances > 2^28.
    let acc = b.accessor(json!({"componentType": 5126, "count": 1 << 22, "type": "VEC3"}));
    let nodes: Vec<Value> = (0..200).map(|_| json!({"mesh": 0})).collect();
    let roots: Vec<usize> = (0..200).collect();
    let bytes = b.glb(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": acc}}]}],
        "nodes": nodes,
        "scenes": [{"nodes": roots}],
    }));
    let e = load_bytes(&bytes).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::TooManyTriangles {
                count: 279_620_200,
                ..
            }
        ),
        "{e:?}"
    );
}

#[test]
fn other_structural_errors() {
    let (b, extra) = triangle_doc();
    let mut doc = b.doc(extra.clone());
    doc["meshes"][0]["primitives"][0]["mode"] = json!(9);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::BadPrimitive {
                mesh: 0,
                primitive: 0,
                ..
            }
        ),
        "{e:?}"
    );
    let mut doc = b.doc(extra.clone());
    doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = json!(8);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::DanglingReference {
                kind: "accessor",
                index: 8,
                ..
            }
        ),
        "{e:?}"
    );
    let mut doc = b.doc(extra.clone());
    doc["nodes"][0]["rotation"] = json!([0.0, 0.0, 0.0, 0.0]);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(
        matches!(e, GltfError::Scene(SceneError::BadNode { node: 0, .. })),
        "{e:?}"
    );
    let mut doc = b.doc(extra.clone());
    doc["nodes"][0]["camera"] = json!(0);
    doc["cameras"] = json!([{"type": "perspective"}]);
    let e = load_bytes(&glb(&doc, &b.bin)).unwrap_err();
    assert!(matches!(e, GltfError::BadCamera { camera: 0, .. }), "{e:?}");
    let e = load(
        &b.glb(extra),
        None,
        &LoadOptions {
            time: Some(f64::NAN),
        },
    )
    .unwrap_err();
    assert!(
        matches!(e, GltfError::Scene(SceneError::BadTime(_))),
        "{e:?}"
    );
}

#[test]
fn animation_errors() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let times = b.floats(&[0.0, 2.0, 1.0], "SCALAR");
    let out = b.floats(&[0.0; 9], "VEC3");
    let short = b.floats(&[0.0; 6], "VEC3");
    let file = |input: usize, output: usize| {
        b.glb(json!({
            "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
            "nodes": [{"mesh": 0}],
            "scenes": [{"nodes": [0]}],
            "animations": [{
                "samplers": [{"input": input, "output": output}],
                "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}],
            }],
        }))
    };
    // Decreasing keyframe times.
    let e = load_bytes(&file(times, out)).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::Scene(SceneError::BadAnimation { animation: 0, .. })
        ),
        "{e:?}"
    );
    // Too few output values (checked with or without a time).
    let e = load_bytes(&file(out, short)).unwrap_err();
    assert!(
        matches!(
            e,
            GltfError::BadAccessor { .. } | GltfError::Scene(SceneError::BadAnimation { .. })
        ),
        "{e:?}"
    );
}

// ---------------------------------------------------------------------------------------
// Robustness: damaged files are errors, never panics.

/// Loads `bytes` statically and at a time; either may fail, neither may panic.
fn load_both(bytes: &[u8]) {
    let _ = load_bytes(bytes);
    let _ = load_at(bytes, 0.37);
}

/// Damages a file every way a deterministic loop can afford: every truncation, every byte
/// set to 0x00/0xFF or bit-flipped, and every ASCII digit in the JSON replaced by 0 and 9
/// (which turns counts, offsets and indices into out-of-range ones).
fn damage_everywhere(name: &str, bytes: &[u8]) {
    for len in 0..bytes.len() {
        load_both(&bytes[..len]);
    }
    let mut copy = bytes.to_vec();
    for i in 0..bytes.len() {
        let original = copy[i];
        let mut variants = vec![0x00, 0xFF, original ^ 0x01, original ^ 0x80];
        if original.is_ascii_digit() {
            variants.extend([b'0', b'9']);
        }
        for v in variants {
            copy[i] = v;
            load_both(&copy);
        }
        copy[i] = original;
    }
    eprintln!("{name}: {} bytes damaged without a panic", bytes.len());
}

#[test]
fn damaged_real_files_never_panic() {
    let Some(dir) = scenes_dir() else { return };
    for name in [
        "Box.glb",
        "TriangleWithoutIndices.glb",
        "SimpleSparseAccessor.glb",
        "SimpleSkin.glb",
        "SimpleMorph.glb",
        "AnimatedTriangle.glb",
        "Cameras.glb",
        "MultipleScenes.glb",
        "SimpleMeshes.glb",
        "Box_Draco.glb",
    ] {
        let bytes = std::fs::read(dir.join(name)).unwrap();
        damage_everywhere(name, &bytes);
    }
}

#[test]
fn damaged_hand_built_files_never_panic() {
    damage_everywhere("skin", &skin_file(true));
    damage_everywhere("morph", &morph_file(true));
    damage_everywhere("cubic", &translation_file("CUBICSPLINE"));
}

mod fuzz {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]

        /// Random multi-byte damage to a small skinned, animated, sparse file.
        #[test]
        fn random_damage_never_panics(
            edits in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..12),
            cut in any::<prop::sample::Index>(),
            truncate in any::<bool>(),
        ) {
            let mut bytes = skin_file(true);
            for (at, v) in edits {
                let i = at.index(bytes.len());
                bytes[i] = v;
            }
            if truncate {
                let n = cut.index(bytes.len());
                bytes.truncate(n);
            }
            load_both(&bytes);
        }
    }
}

#[test]
fn quantized_positions_need_khr_mesh_quantization() {
    let mut b = Builder::default();
    // SHORT normalized, padded to a stride of 8: 32767 → 1.0, −32768 → −1.0.
    let raw: Vec<u8> = [0i16, 0, 0, 0, 32767, 0, 0, 0, 0, -32768, 0, 0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let view = b.view(&raw);
    b.views[view]["byteStride"] = json!(8);
    let acc = b.accessor(json!({"bufferView": view, "componentType": 5122, "normalized": true, "count": 3, "type": "VEC3"}));
    let mut extra = json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": acc}}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
    });
    let e = load_bytes(&b.glb(extra.clone())).unwrap_err();
    assert!(
        matches!(e, GltfError::BadAccessor { accessor: 0, .. }),
        "{e:?}"
    );
    assert!(
        e.to_string().contains("KHR_mesh_quantization") || e.to_string().contains("FLOAT"),
        "{e}"
    );
    extra["extensionsUsed"] = json!(["KHR_mesh_quantization"]);
    extra["extensionsRequired"] = json!(["KHR_mesh_quantization"]);
    let s = load_bytes(&b.glb(extra)).unwrap();
    assert_tri(&s, 0, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]);
}

#[test]
fn glb_json_chunk_padded_with_nuls_is_accepted() {
    let (b, extra) = triangle_doc();
    let mut json = serde_json::to_vec(&b.doc(extra)).unwrap();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    json.extend_from_slice(&[0; 4]);
    let mut bytes = b"glTF".to_vec();
    let total = 12 + 8 + json.len() + 8 + b.bin.len();
    bytes.extend_from_slice(&2u32.to_le_bytes());
    bytes.extend_from_slice(&(total as u32).to_le_bytes());
    bytes.extend_from_slice(&(json.len() as u32).to_le_bytes());
    bytes.extend_from_slice(b"JSON");
    bytes.extend_from_slice(&json);
    bytes.extend_from_slice(&(b.bin.len() as u32).to_le_bytes());
    bytes.extend_from_slice(b"BIN\0");
    bytes.extend_from_slice(&b.bin);
    assert_tri(&load_bytes(&bytes).unwrap(), 0, TRI);
    // A top-level value that is not an object.
    let e = load_bytes(b"[1, 2]").unwrap_err();
    assert!(e.to_string().contains("glTF"), "{e}");
}

/// A scene's `nodes` is optional in glTF 2.0: a scene without it is an empty scene, not a
/// JSON error, in a `.gltf` as in a GLB.
#[test]
fn a_scene_without_nodes_is_empty() {
    let doc = json!({"asset": {"version": "2.0"}, "scenes": [{}], "scene": 0});
    let scene = load_bytes(&serde_json::to_vec(&doc).unwrap()).unwrap();
    assert!(scene.triangles.is_empty());
    let scene = load_bytes(&glb(&doc, &[])).unwrap();
    assert!(scene.triangles.is_empty());
    // Beside a scene that has nodes, which still counts.
    let mut b = Builder::default();
    let pos = b.positions(&[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]);
    let extra = json!({
        "scenes": [{"name": "empty"}, {"nodes": [0]}],
        "scene": 1,
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": pos}}]}],
    });
    let scene = load_bytes(&b.glb(extra)).unwrap();
    assert_eq!(scene.triangles.len(), 1);
}

/// A channel without `target.node` (`KHR_animation_pointer`'s, or any: glTF says it is then
/// ignored) is ignored; the other channels keep their numbers and still move the scene.
#[test]
fn a_channel_without_a_node_is_ignored() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let times = b.floats(&[0.0, 1.0], "SCALAR");
    let moves = b.floats(&[0.0, 0.0, 0.0, 10.0, 0.0, 0.0], "VEC3");
    let colours = b.floats(&[1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0], "VEC4");
    let bytes = b.glb(json!({
        "extensionsUsed": ["KHR_animation_pointer"],
        "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "animations": [{
            "samplers": [{"input": times, "output": colours}, {"input": times, "output": moves}],
            "channels": [
                {"sampler": 0, "target": {"path": "pointer", "extensions": {"KHR_animation_pointer": {"pointer": "/materials/0/pbrMetallicRoughness/baseColorFactor"}}}},
                {"sampler": 1, "target": {"node": 0, "path": "translation"}},
            ],
        }],
    }));
    let s = load_at(&bytes, 0.5).unwrap();
    assert_eq!(s.triangles[0].v[0], [5.0, 0.0, 0.0]);
    assert_eq!(s.triangles.len(), 1);
}

/// glTF gives a mesh's primitives equal numbers of morph targets, and mesh, node and
/// animation weights one per target; other counts read weights from the wrong targets'
/// places and are refused, naming what disagrees.
#[test]
fn morph_weight_counts_must_match_the_targets() {
    let build = |targets: [usize; 2],
                 mesh_w: Option<usize>,
                 node_w: Option<usize>,
                 outputs: usize| {
        let mut b = Builder::default();
        let p = b.positions(&TRI);
        let d = b.positions(&[[0.0, 0.0, 1.0]; 3]);
        let times = b.floats(&[0.0, 1.0], "SCALAR");
        let w = b.floats(&vec![0.5; outputs], "SCALAR");
        let prim = |n: usize| json!({"attributes": {"POSITION": p}, "targets": vec![json!({"POSITION": d}); n]});
        let mut mesh = json!({"primitives": [prim(targets[0]), prim(targets[1])]});
        if let Some(n) = mesh_w {
            mesh["weights"] = json!(vec![0.0; n]);
        }
        let mut node = json!({"mesh": 0});
        if let Some(n) = node_w {
            node["weights"] = json!(vec![0.0; n]);
        }
        b.glb(json!({
            "meshes": [mesh],
            "nodes": [node],
            "scenes": [{"nodes": [0]}],
            "animations": [{
                "samplers": [{"input": times, "output": w}],
                "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
            }],
        }))
    };
    let ok = load_at(&build([2, 2], Some(2), Some(2), 4), 1.0).unwrap();
    // Both targets at 0.5 on both primitives: z = 0.5 + 0.5.
    assert_eq!(ok.triangles[0].v[0], [0.0, 0.0, 1.0]);
    for (bytes, want) in [
        (build([2, 2], None, None, 8), "animation 0: channel 0: weights output accessor 3 has 8 values, expected 4 (2 morph targets"),
        (build([2, 2], None, None, 2), "has 2 values, expected 4"),
        (build([2, 2], None, Some(1), 4), "node 0: has 1 weights, but its mesh 0 has 2 morph targets"),
        (build([2, 2], Some(3), None, 4), "mesh 0: has 3 weights for 2 morph targets"),
        (build([2, 1], None, None, 4), "mesh 0 primitive 1: has 1 morph targets, but primitive 0 has 2"),
    ] {
        let e = load_bytes(&bytes).unwrap_err().to_string();
        assert!(e.contains(want), "{e}");
    }
}

/// A stored rotation of no length is refused whether or not an animation replaces it, so
/// that whether a file loads does not depend on the time (proto/scenes.md).
#[test]
fn a_zero_stored_rotation_is_refused_at_every_time() {
    let mut b = Builder::default();
    let p = b.positions(&TRI);
    let times = b.floats(&[0.0, 1.0], "SCALAR");
    let turns = b.floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0], "VEC4");
    let bytes = b.glb(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": p}}]}],
        "nodes": [{"mesh": 0, "rotation": [0.0, 0.0, 0.0, 0.0]}],
        "scenes": [{"nodes": [0]}],
        "animations": [{
            "samplers": [{"input": times, "output": turns}],
            "channels": [{"sampler": 0, "target": {"node": 0, "path": "rotation"}}],
        }],
    }));
    for e in [
        load_bytes(&bytes).unwrap_err(),
        load_at(&bytes, 0.5).unwrap_err(),
    ] {
        assert_eq!(
            e.to_string(),
            "node 0: rotation is a zero or non-finite quaternion"
        );
    }
}
