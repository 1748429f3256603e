//! `Scene::evaluate(t)` against the loader as it was before the scene could move, and what
//! each kind of load holds: rig only for animated files, no shading data or textures for a
//! geometry-only load, materials, textures and lights as the files give them.
//!
//! `OLD_POSES` was recorded from the loader that evaluated animation while parsing (commit
//! aca0c83, before the rig existed): per scene, an FNV-1a hash of every triangle's f32 bits
//! in id order followed by every camera's f64 `to_world` bits, for the static pose and then
//! for each of [`times`]. A changed rounding anywhere (a glam product summed in another
//! order, a reciprocal instead of a division) changes a hash. Session 30 re-recorded the
//! scenes whose rotation keyframes lie within 3.6° of each other (repo/Fox.glb, shared/BrainStem.glb, shared/CesiumMan.glb, shared/Fox.glb, shared/Monster.glb, shared/VC.glb): the old loader's
//! normalised lerp there was up to 8 f32 ULPs off slerp, which `rig::slerp` now computes
//! exactly (an independent numpy evaluator agrees with it to the bit on Fox and CesiumMan).

use std::path::{Path, PathBuf};

use rayd::formats::gltf::{load_with, GltfError};
use rayd::formats::{load_scene, load_scene_with, LoadOptions, Parts};
use rayd::scene::{
    AlphaMode, Compute, Filter, LightKind, Mipmap, Scene, SceneError, Shading, Wrap,
};
use serde_json::json;

/// (directory, file, triangles, hashes: static pose, then one per entry of `times`).
#[rustfmt::skip]
const OLD_POSES: &[(&str, &str, usize, [u64; 13])] = &[
    ("repo", "AnimatedMorphCube.glb", 12, [0x7ef761891136a9e9, 0x7ef761891136a9e9, 0x7ef761891136a9e9, 0x8daa3ebc6e46462a, 0x1488f68eee542bf3, 0x91f72221a603b225, 0xf299df1ac84a7518, 0xfd22ab8da2e6a908, 0x642628b28c48d90f, 0x7c6aab50f5012840, 0x9eb85ba7cbba80ca, 0x9eb85ba7cbba80ca, 0x9eb85ba7cbba80ca]),
    ("repo", "AnimatedTriangle.glb", 1, [0x1d3535e07c06fa35, 0x1d3535e07c06fa35, 0x1d3535e07c06fa35, 0xf60398eaea4f4901, 0xa25635e9bf41d3d5, 0xfa51b8b25e0483d5, 0x345adb213b61f2dd, 0xc914233836a7f635, 0x881d603db019257d, 0x58cd8355dde203d5, 0x1d3535e07c06fa35, 0x1d3535e07c06fa35, 0x1d3535e07c06fa35]),
    ("repo", "BoxAnimated.glb", 254, [0x42531334968b5553, 0x42531334968b5553, 0x42531334968b5553, 0x665398ab3e1a2f16, 0x47ddd78685d50985, 0xa48f6a56a19d88d5, 0x40b13bd24da0b76f, 0x690dd114efcb6171, 0x6c7239dab9a0da65, 0x119c11cc3d7f9b5f, 0x921e336547454853, 0x921e336547454853, 0x921e336547454853]),
    ("repo", "Fox.glb", 576, [0xe226ace5fc650ac6, 0x4103761874ea1eab, 0x4103761874ea1eab, 0x339628f2227109b6, 0x3854f36bc5727d2a, 0x3342903bef0a0b3b, 0x9c812239103c41f4, 0x4103761874ea1eab, 0x4103761874ea1eab, 0x4103761874ea1eab, 0x4103761874ea1eab, 0x4103761874ea1eab, 0x4103761874ea1eab]),
    ("repo", "InterpolationTest.glb", 110, [0xd328c2e4585ef850, 0x299f1590889db560, 0x299f1590889db560, 0x058cf312de5ddaa4, 0x93b67ab46ac6fd62, 0x8a590e0dd0481c91, 0x9a8efda600dd8933, 0x3dea38b303120d11, 0x0726059b5b18d1f6, 0x0ca710bfeb83313b, 0xd57a848942867f7e, 0xd57a848942867f7e, 0xd57a848942867f7e]),
    ("repo", "RiggedSimple.glb", 188, [0xe14d6327ce191691, 0xe14d6327ce191691, 0xe14d6327ce191691, 0xe14d6327ce191691, 0xb3b26a411e04c7d5, 0xe54e9d85b4224fc0, 0x45d824ab6ed5a396, 0xd860970638e9df1e, 0x33c6d0147b70cf57, 0x6e790be45954daf8, 0xe14d6327ce191691, 0xe14d6327ce191691, 0xe14d6327ce191691]),
    ("repo", "SimpleMorph.glb", 1, [0xbb35e4f573347c98, 0x4a6abec2fddfd1d8, 0x4a6abec2fddfd1d8, 0x27af51cf2152e1b4, 0x3045e256ec46d230, 0x994c0c5f4e59f258, 0x932c725f32490c1c, 0x3772b7d195162ba5, 0x3814ad7459b3185a, 0x44f921cc4cc32849, 0x4a6abec2fddfd1d8, 0x4a6abec2fddfd1d8, 0x4a6abec2fddfd1d8]),
    ("repo", "SimpleSkin.glb", 8, [0xe8ef1146c0e6ba75, 0xe8ef1146c0e6ba75, 0xe8ef1146c0e6ba75, 0xd44de68193d13507, 0x36f84ca0f9d6f36b, 0x9827b06299eeefe8, 0x464a61b1d2f7b821, 0xe8ef1146c0e6ba75, 0x33c6ea4a660d4a16, 0x8aca23b75e15d0b8, 0xe8ef1146c0e6ba75, 0xe8ef1146c0e6ba75, 0xe8ef1146c0e6ba75]),
    ("shared", "AnimatedCube.glb", 12, [0xba58e379d8963264, 0xff439ba8de6f4264, 0xff439ba8de6f4264, 0xcf30cf82dec24e0e, 0x2d033d6ade017042, 0xe7982e2013e531f6, 0xa23dca078536f7a9, 0x1c6540722487c198, 0x35a9adc46d18fa53, 0xc3129c4d2051a783, 0x6ca99f1b393cab48, 0x6ca99f1b393cab48, 0x6ca99f1b393cab48]),
    ("shared", "AnimatedMorphCube.glb", 12, [0x7ef761891136a9e9, 0x7ef761891136a9e9, 0x7ef761891136a9e9, 0x8daa3ebc6e46462a, 0x1488f68eee542bf3, 0x91f72221a603b225, 0xf299df1ac84a7518, 0xfd22ab8da2e6a908, 0x642628b28c48d90f, 0x7c6aab50f5012840, 0x9eb85ba7cbba80ca, 0x9eb85ba7cbba80ca, 0x9eb85ba7cbba80ca]),
    ("shared", "AnimatedMorphSphere.glb", 960, [0x2063f7e9d55330f8, 0x2063f7e9d55330f8, 0x2063f7e9d55330f8, 0x7c72fc254d792b52, 0xb188cbb791d68467, 0xfb80207a4a97d3c4, 0x0c167d40c3fa15b4, 0xde11209a8c51d034, 0x09088cc1c03080e8, 0x4893d6c857885063, 0xc58b5a5401fc3c94, 0xc58b5a5401fc3c94, 0xc58b5a5401fc3c94]),
    ("shared", "AnimatedTriangle.glb", 1, [0x1d3535e07c06fa35, 0x1d3535e07c06fa35, 0x1d3535e07c06fa35, 0xf60398eaea4f4901, 0xa25635e9bf41d3d5, 0xfa51b8b25e0483d5, 0x345adb213b61f2dd, 0xc914233836a7f635, 0x881d603db019257d, 0x58cd8355dde203d5, 0x1d3535e07c06fa35, 0x1d3535e07c06fa35, 0x1d3535e07c06fa35]),
    ("shared", "BoxAnimated.glb", 254, [0x42531334968b5553, 0x42531334968b5553, 0x42531334968b5553, 0x665398ab3e1a2f16, 0x47ddd78685d50985, 0xa48f6a56a19d88d5, 0x40b13bd24da0b76f, 0x690dd114efcb6171, 0x6c7239dab9a0da65, 0x119c11cc3d7f9b5f, 0x921e336547454853, 0x921e336547454853, 0x921e336547454853]),
    ("shared", "BrainStem.glb", 61666, [0xf2b7959fa66d5880, 0x87415300f513a597, 0x87415300f513a597, 0x8148396365f6d1e8, 0x94fde78bd9e47331, 0x66252d9f96deb2c8, 0xf1b02af6817daa14, 0xb2e491e02badafa4, 0xc700fe7a73d413a1, 0xd7a3656d692513fd, 0xe5b29e0f6dd14882, 0xe5b29e0f6dd14882, 0xe5b29e0f6dd14882]),
    ("shared", "CesiumMan.glb", 4672, [0x2bdf5f7575d63a8c, 0x6d39cef1e1182004, 0x6d39cef1e1182004, 0x4cb42159060eab43, 0x5d18a0ac7adfce72, 0x805ffa08a1ba6ab6, 0x16d48cdd9f4a16e3, 0x42080d114976bdd9, 0x548c5fd8038e3caa, 0x6714b1cae8817ff1, 0x6d39cef1e1182004, 0x6d39cef1e1182004, 0x6d39cef1e1182004]),
    ("shared", "CesiumMilkTruck.glb", 3624, [0xcfa7a52ddc62814a, 0xc1c9d9e40e32de0e, 0xc1c9d9e40e32de0e, 0xc8a7b8cb4f291466, 0x96f96d99fd9e020a, 0x9d57fad4e316d63e, 0x75dcbd7e15ea7e4e, 0xb0ff40c71f78ce26, 0x3c58d2cc720eafde, 0x7c3607e9c0143736, 0x07f4f1b06177ebf6, 0x07f4f1b06177ebf6, 0x07f4f1b06177ebf6]),
    ("shared", "Fox.glb", 576, [0xe226ace5fc650ac6, 0x4103761874ea1eab, 0x4103761874ea1eab, 0x339628f2227109b6, 0x3854f36bc5727d2a, 0x3342903bef0a0b3b, 0x9c812239103c41f4, 0x4103761874ea1eab, 0x4103761874ea1eab, 0x4103761874ea1eab, 0x4103761874ea1eab, 0x4103761874ea1eab, 0x4103761874ea1eab]),
    ("shared", "InterpolationTest.glb", 110, [0xd328c2e4585ef850, 0x299f1590889db560, 0x299f1590889db560, 0x058cf312de5ddaa4, 0x93b67ab46ac6fd62, 0x8a590e0dd0481c91, 0x9a8efda600dd8933, 0x3dea38b303120d11, 0x0726059b5b18d1f6, 0x0ca710bfeb83313b, 0xd57a848942867f7e, 0xd57a848942867f7e, 0xd57a848942867f7e]),
    ("shared", "Monster.glb", 884, [0xb9c2201496ef0637, 0xab0662cd77534d44, 0xab0662cd77534d44, 0xf5f5f5b1b318a6bd, 0x0141af142f18c92f, 0x1b07792a57cc125b, 0xee9d8f883508297c, 0x3b1482a98aa1ad21, 0x6d8d174930d7921b, 0x9077f79e84c72b99, 0x0bc219addb53cd65, 0x0bc219addb53cd65, 0x0bc219addb53cd65]),
    ("shared", "RiggedFigure.glb", 256, [0xba5c6cc03afe07ad, 0xeb868d19cd9e274c, 0xeb868d19cd9e274c, 0x1dd10f4839d6801a, 0x807e936cf8febc47, 0xf64c3ec0793c8f71, 0x1c28017cb89f12d7, 0x8e3c0f4b9d2b6d12, 0xc656ea4239ea732e, 0x56c2d9fcd71bd5f9, 0x76f230a894d61186, 0x76f230a894d61186, 0x76f230a894d61186]),
    ("shared", "RiggedSimple.glb", 188, [0xe14d6327ce191691, 0xe14d6327ce191691, 0xe14d6327ce191691, 0xe14d6327ce191691, 0xb3b26a411e04c7d5, 0xe54e9d85b4224fc0, 0x45d824ab6ed5a396, 0xd860970638e9df1e, 0x33c6d0147b70cf57, 0x6e790be45954daf8, 0xe14d6327ce191691, 0xe14d6327ce191691, 0xe14d6327ce191691]),
    ("shared", "SimpleMorph.glb", 1, [0xbb35e4f573347c98, 0x4a6abec2fddfd1d8, 0x4a6abec2fddfd1d8, 0x27af51cf2152e1b4, 0x3045e256ec46d230, 0x994c0c5f4e59f258, 0x932c725f32490c1c, 0x3772b7d195162ba5, 0x3814ad7459b3185a, 0x44f921cc4cc32849, 0x4a6abec2fddfd1d8, 0x4a6abec2fddfd1d8, 0x4a6abec2fddfd1d8]),
    ("shared", "SimpleSkin.glb", 8, [0xe8ef1146c0e6ba75, 0xe8ef1146c0e6ba75, 0xe8ef1146c0e6ba75, 0xd44de68193d13507, 0x36f84ca0f9d6f36b, 0x9827b06299eeefe8, 0x464a61b1d2f7b821, 0xe8ef1146c0e6ba75, 0x33c6ea4a660d4a16, 0x8aca23b75e15d0b8, 0xe8ef1146c0e6ba75, 0xe8ef1146c0e6ba75, 0xe8ef1146c0e6ba75]),
    ("shared", "VC.glb", 8383, [0x89940f81b99eccdd, 0x1c2e69b8341ecaed, 0x1c2e69b8341ecaed, 0xd8f878d49cf08dc9, 0xa3523af71a672c12, 0x4348f99d1061edf2, 0x9c3111b50c219f6a, 0x85c8cdcf32d6d735, 0x328b0565cbb28636, 0x4a3165ca07c4319e, 0x3afcdc632e766e45, 0x3afcdc632e766e45, 0x3afcdc632e766e45]),
];

/// Times around a scene's longest animation `d`: before the first key, at it, between
/// keys, at and after the last. (0.7071 is just a fraction, as recorded.)
#[allow(clippy::approx_constant)]
fn times(d: f64) -> [f64; 12] {
    [
        -1.0,
        0.0,
        1e-3,
        d * 0.1,
        d * 0.25,
        d / 3.0,
        d * 0.5,
        d * 0.7071,
        d * 0.9,
        d,
        d + 0.5,
        100.0,
    ]
}

fn fnv(h: &mut u64, bytes: &[u8]) {
    for &b in bytes {
        *h ^= u64::from(b);
        *h = h.wrapping_mul(0x0100_0000_01b3);
    }
}

/// A hash of a pose's triangles and cameras, the cameras in the order the scene's
/// pre-order first places them (as the old loader listed them; they are now kept by their
/// index in the file).
fn pose_hash(
    triangles: &[rayd::geometry::Triangle],
    cameras: &[Option<rayd::scene::Camera>],
    rig: Option<&rayd::scene::rig::Rig>,
) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    for t in triangles {
        for c in t.v.iter().flatten() {
            fnv(&mut h, &c.to_bits().to_le_bytes());
        }
    }
    let mut order: Vec<usize> = Vec::new();
    for item in rig.map_or(&[][..], |r| r.items.as_slice()) {
        if let rayd::scene::rig::Item::Camera { index, .. } = item {
            if !order.contains(index) {
                order.push(*index);
            }
        }
    }
    for c in order.iter().filter_map(|&i| cameras[i].as_ref()) {
        for x in c.to_world.iter().flatten() {
            fnv(&mut h, &x.to_bits().to_le_bytes());
        }
    }
    h
}

fn dir(which: &str) -> Option<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let d = match which {
        "repo" => root.join("scenes"),
        _ => root.join("../shared/scenes"),
    };
    d.is_dir().then_some(d)
}

fn shared(name: &str) -> Option<PathBuf> {
    let p = dir("shared")?.join(name);
    if p.is_file() {
        Some(p)
    } else {
        eprintln!("skipping: {} not found", p.display());
        None
    }
}

fn duration(s: &Scene) -> f64 {
    s.animations.iter().map(|a| a.duration).fold(0.0, f64::max)
}

#[test]
fn evaluate_is_bit_identical_to_the_old_loader() {
    let mut failures = Vec::new();
    let mut checked = 0;
    for &(which, name, triangles, hashes) in OLD_POSES {
        let Some(d) = dir(which) else {
            eprintln!("skipping {which}/{name}: directory not found");
            continue;
        };
        let path = d.join(name);
        let geometry = load_scene(&path, &LoadOptions::default()).unwrap();
        let shading = load_scene_with(&path, &LoadOptions::default(), Parts::Shading).unwrap();
        assert_eq!(geometry.triangles.len(), triangles, "{name}");
        assert!(geometry.rig.is_some(), "{name} animates but keeps no rig");
        if pose_hash(
            &geometry.triangles,
            &geometry.cameras,
            geometry.rig.as_deref(),
        ) != hashes[0]
        {
            failures.push(format!("{which}/{name}: static pose"));
        }
        for (i, t) in times(duration(&geometry)).into_iter().enumerate() {
            let want = hashes[i + 1];
            for (what, scene) in [("geometry", &geometry), ("shading", &shading)] {
                let pose = scene.evaluate(t, Compute::Positions).unwrap();
                if pose_hash(&pose.triangles, &pose.cameras, scene.rig.as_deref()) != want {
                    failures.push(format!("{which}/{name} t={t}: evaluate ({what} load)"));
                }
            }
            let loaded = load_scene(&path, &LoadOptions { time: Some(t) }).unwrap();
            if pose_hash(&loaded.triangles, &loaded.cameras, loaded.rig.as_deref()) != want {
                failures.push(format!("{which}/{name} t={t}: load at the time"));
            }
            checked += 1;
        }
    }
    assert!(checked >= 8 * 12, "only {checked} poses checked");
    assert!(
        failures.is_empty(),
        "{} poses differ:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

#[test]
fn every_animated_shared_scene_is_recorded() {
    let Some(d) = dir("shared") else { return };
    let mut names: Vec<String> = std::fs::read_dir(&d)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n.ends_with(".glb"))
        .collect();
    names.sort();
    for name in names {
        // Some files are refused on purpose (Draco); they are not scenes to evaluate.
        let Ok(s) = load_scene(&d.join(&name), &LoadOptions::default()) else {
            continue;
        };
        let recorded = OLD_POSES.iter().any(|r| r.0 == "shared" && r.1 == name);
        assert_eq!(!s.animations.is_empty(), recorded, "{name}");
        assert_eq!(
            s.rig.is_some(),
            recorded,
            "{name}: a rig exactly when the file animates"
        );
    }
}

#[test]
fn static_scenes_keep_no_animation_data() {
    for which in ["repo", "shared"] {
        let Some(d) = dir(which) else { continue };
        for name in [
            "Box.glb",
            "SimpleMeshes.glb",
            "OrientationTest.glb",
            "Cameras.glb",
        ] {
            let s =
                load_scene_with(&d.join(name), &LoadOptions::default(), Parts::Shading).unwrap();
            assert!(s.rig.is_none(), "{name}");
            assert!(s.animations.is_empty(), "{name}");
            assert_eq!(s.bytes_by_part().animation, 0, "{name}");
            // A static scene is its own pose at every time.
            let p = s.evaluate(3.0, Compute::PositionsAndNormals).unwrap();
            assert_eq!(p.triangles, s.triangles, "{name}");
            assert_eq!(p.normals, s.shading.as_ref().unwrap().normals, "{name}");
        }
    }
    let Some(d) = dir("repo") else { return };
    let fox = load_scene(&d.join("Fox.glb"), &LoadOptions::default()).unwrap();
    assert!(fox.bytes_by_part().animation > 0);
}

#[test]
fn evaluate_refuses_a_non_finite_time() {
    let d = dir("repo").unwrap();
    for name in ["Fox.glb", "Box.glb"] {
        let s = load_scene(&d.join(name), &LoadOptions::default()).unwrap();
        for t in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let e = s.evaluate(t, Compute::Positions).unwrap_err();
            assert!(matches!(e, SceneError::BadTime(_)), "{name}: {e}");
            assert!(e.to_string().contains("not a finite number"), "{e}");
        }
    }
}

#[test]
fn evaluate_into_reuses_its_buffers() {
    let d = dir("repo").unwrap();
    let s = load_scene(&d.join("Fox.glb"), &LoadOptions::default()).unwrap();
    let mut pose = rayd::scene::Pose::default();
    for t in [0.1, 0.5, 0.1] {
        s.evaluate_into(t, Compute::Positions, &mut pose).unwrap();
        assert_eq!(pose.triangles.len(), s.triangles.len());
    }
    assert_eq!(pose, s.evaluate(0.1, Compute::Positions).unwrap());
    assert_ne!(
        pose.triangles,
        s.evaluate(0.5, Compute::Positions).unwrap().triangles
    );
    // `at` is the scene posed at the time, like a load at that time.
    let at = s.at(0.5).unwrap();
    let loaded = load_scene(&d.join("Fox.glb"), &LoadOptions { time: Some(0.5) }).unwrap();
    assert_eq!(at.triangles, loaded.triangles);
}

/// Unit normal of a triangle from its positions.
fn face_normal(t: &rayd::geometry::Triangle) -> glam::Vec3 {
    let [a, b, c] = t.v.map(glam::Vec3::from);
    (b - a).cross(c - a).normalize_or_zero()
}

#[test]
fn shading_normals_follow_the_pose() {
    // BoxAnimated's boxes are flat-shaded: every vertex normal is its face's normal, in
    // every pose of the rigid animation, and they must turn with the triangles.
    let d = dir("repo").unwrap();
    let path = d.join("BoxAnimated.glb");
    let s = load_scene_with(&path, &LoadOptions::default(), Parts::Shading).unwrap();
    let shading = s.shading.as_ref().unwrap();
    for t in [0.0, 0.4, 1.3, 2.9] {
        let pose = s.evaluate(t, Compute::PositionsAndNormals).unwrap();
        assert_eq!(pose.normals.len(), shading.normals.len());
        let mut aligned = 0;
        for (id, tri) in pose.triangles.iter().enumerate() {
            let f = face_normal(tri);
            if f == glam::Vec3::ZERO {
                continue;
            }
            for &v in &shading.corners[id] {
                let n = pose.normals[v as usize];
                assert!((n.length() - 1.0).abs() < 1e-5, "t={t} id={id}: {n}");
                if n.dot(f) > 0.999 {
                    aligned += 1;
                }
            }
        }
        // The inner box's normals point inwards, so count agreement with either side.
        let flipped: usize = pose
            .triangles
            .iter()
            .enumerate()
            .map(|(id, tri)| {
                let f = face_normal(tri);
                shading.corners[id]
                    .iter()
                    .filter(|&&v| pose.normals[v as usize].dot(f) < -0.999)
                    .count()
            })
            .sum();
        assert_eq!(aligned + flipped, 3 * pose.triangles.len(), "t={t}");
        // Positions-only evaluation computes no normals.
        assert!(s
            .evaluate(t, Compute::Positions)
            .unwrap()
            .normals
            .is_empty());
    }
    // The static shading normals are the static pose's.
    let p0 = s.evaluate(0.0, Compute::PositionsAndNormals).unwrap();
    let at0 = load_scene_with(&path, &LoadOptions { time: Some(0.0) }, Parts::Shading).unwrap();
    assert_eq!(p0.normals, at0.shading.unwrap().normals);
}

#[test]
fn geometry_only_loads_hold_no_textures_or_attributes() {
    let Some(path) = shared("DamagedHelmet.glb") else {
        return;
    };
    let s = load_scene(&path, &LoadOptions::default()).unwrap();
    assert!(s.shading.is_none());
    assert!(s.materials.is_empty() && s.textures.is_empty() && s.images.is_empty());
    let b = s.bytes_by_part();
    assert_eq!((b.attributes, b.textures, b.animation), (0, 0, 0));
    assert_eq!(b.positions, s.bytes());
    let full = load_scene_with(&path, &LoadOptions::default(), Parts::Shading).unwrap();
    assert_eq!(full.triangles, s.triangles);
    let b = full.bytes_by_part();
    assert!(b.attributes > 0 && b.textures > 0, "{b:?}");
}

#[test]
fn damaged_helmet_material_and_encoded_textures() {
    let Some(path) = shared("DamagedHelmet.glb") else {
        return;
    };
    let s = load_scene_with(&path, &LoadOptions::default(), Parts::Shading).unwrap();
    assert_eq!(s.materials.len(), 1);
    let m = &s.materials[0];
    assert_eq!(m.name, "Material_MR");
    assert_eq!(m.base_color_texture.unwrap().texture, 0);
    assert_eq!(m.metallic_roughness_texture.unwrap().texture, 1);
    assert_eq!(m.emissive_texture.unwrap().texture, 2);
    assert_eq!(m.occlusion_texture.unwrap().texture, 3);
    assert_eq!(m.normal_texture.unwrap().texture, 4);
    assert_eq!(m.emissive_factor, [1.0; 3]);
    assert_eq!((m.metallic_factor, m.roughness_factor), (1.0, 1.0));
    assert_eq!(m.alpha_mode, AlphaMode::Opaque);
    assert_eq!(s.textures.len(), 5);
    assert_eq!(s.images.len(), 5);
    for im in &s.images {
        assert_eq!(im.mime_type, "image/jpeg");
        // Encoded, not decoded: a JPEG's start-of-image marker.
        assert_eq!(&im.bytes[..3], &[0xFF, 0xD8, 0xFF]);
    }
    let sh = s.shading.as_ref().unwrap();
    assert_eq!(sh.corners.len(), s.triangles.len());
    assert!(sh.materials.iter().all(|&m| m == 0));
    assert_eq!(sh.uv0.len(), sh.normals.len());
    assert!(sh.uv1.is_empty() && sh.colors.is_empty() && sh.tangents.is_empty());
    // The corners name the vertices the triangles were placed from.
    let n = sh.normals.len() as u32;
    assert!(sh.corners.iter().flatten().all(|&v| v < n));
}

#[test]
fn metal_rough_spheres_factors_per_triangle() {
    let Some(path) = shared("MetalRoughSpheresNoTextures.glb") else {
        return;
    };
    let s = load_scene_with(&path, &LoadOptions::default(), Parts::Shading).unwrap();
    assert_eq!(s.materials.len(), 98);
    let m1 = &s.materials[1];
    assert_eq!(m1.name, "mat_1");
    assert_eq!(m1.base_color_factor, [0.603_827, 0.603_827, 0.603_827, 1.0]);
    assert_eq!(m1.metallic_factor, 0.0);
    assert_eq!(m1.roughness_factor, 0.166_666_67);
    assert!(m1.double_sided);
    assert!(s.textures.is_empty() && s.images.is_empty());
    let sh = s.shading.as_ref().unwrap();
    assert_eq!(sh.materials.len(), 1_040_409);
    // Every material is used; the triangles of primitives without one use the default.
    let mut used = [false; 98];
    let mut default = 0;
    for &m in &sh.materials {
        match used.get_mut(m as usize) {
            Some(u) => *u = true,
            None => {
                assert_eq!(m, Shading::DEFAULT_MATERIAL);
                default += 1;
            }
        }
    }
    assert!(default < sh.materials.len() / 2, "{default}");
    assert!(used.iter().all(|&u| u));
}

#[test]
fn texture_transforms_and_samplers() {
    let Some(path) = shared("TextureTransformTest.glb") else {
        return;
    };
    let s = load_scene_with(&path, &LoadOptions::default(), Parts::Shading).unwrap();
    let by_name = |n: &str| s.materials.iter().find(|m| m.name == n).unwrap();
    let t = by_name("Offset U")
        .base_color_texture
        .unwrap()
        .transform
        .unwrap();
    assert_eq!(
        (t.offset, t.rotation, t.scale),
        ([0.5, 0.0], 0.0, [1.0, 1.0])
    );
    let t = by_name("Rotation")
        .base_color_texture
        .unwrap()
        .transform
        .unwrap();
    assert_eq!(t.rotation, std::f32::consts::FRAC_PI_8);
    let all = by_name("All").base_color_texture.unwrap();
    let t = all.transform.unwrap();
    assert_eq!(
        (t.offset, t.rotation, t.scale),
        ([-0.2, -0.1], 0.3, [1.5, 1.5])
    );
    assert_eq!(all.tex_coord, 0);
    // The extension's matrix: scale, then rotate, then offset.
    let uv = t.apply(glam::Vec2::new(1.0, 0.0));
    let (sn, cs) = 0.3f32.sin_cos();
    assert!(
        (uv - glam::Vec2::new(-0.2 + 1.5 * cs, -0.1 - 1.5 * sn)).length() < 1e-6,
        "{uv}"
    );
    assert!(by_name("Correct")
        .base_color_texture
        .unwrap()
        .transform
        .is_none());
    let sampler = s.textures[0].sampler;
    assert_eq!(
        (sampler.wrap_s, sampler.wrap_t),
        (Wrap::ClampToEdge, Wrap::ClampToEdge)
    );
    assert_eq!(
        (sampler.mag_filter, sampler.min_filter),
        (Some(Filter::Linear), Some(Filter::Linear))
    );
    // A texture without a sampler gets the default one.
    assert_eq!(s.textures[2].sampler, rayd::scene::Sampler::default());
    assert!(s
        .images
        .iter()
        .all(|i| i.mime_type == "image/png" && i.bytes.starts_with(b"\x89PNG")));

    let Some(path) = shared("TextureSettingsTest.glb") else {
        return;
    };
    let s = load_scene_with(&path, &LoadOptions::default(), Parts::Shading).unwrap();
    let wraps: Vec<(Wrap, Wrap)> = s
        .textures
        .iter()
        .take(4)
        .map(|t| (t.sampler.wrap_s, t.sampler.wrap_t))
        .collect();
    assert_eq!(
        wraps,
        [
            (Wrap::Repeat, Wrap::MirroredRepeat),
            (Wrap::MirroredRepeat, Wrap::Repeat),
            (Wrap::ClampToEdge, Wrap::Repeat),
            (Wrap::Repeat, Wrap::ClampToEdge),
        ]
    );
    assert_eq!(s.textures[0].sampler.mipmap, Mipmap::Linear);
    assert_eq!(s.textures[0].sampler.min_filter, Some(Filter::Nearest));
}

#[test]
fn alpha_modes_and_vertex_colours() {
    let Some(path) = shared("AlphaBlendModeTest.glb") else {
        return;
    };
    let s = load_scene_with(&path, &LoadOptions::default(), Parts::Shading).unwrap();
    let modes: Vec<(&str, AlphaMode, bool)> = s
        .materials
        .iter()
        .map(|m| (m.name.as_str(), m.alpha_mode, m.double_sided))
        .collect();
    assert_eq!(
        modes,
        [
            ("MatBed", AlphaMode::Opaque, false),
            ("MatBlend", AlphaMode::Blend, true),
            ("MatCutoff25", AlphaMode::Mask { cutoff: 0.25 }, true),
            ("MatCutoff75", AlphaMode::Mask { cutoff: 0.75 }, true),
            ("MatCutoffDefault", AlphaMode::Mask { cutoff: 0.5 }, true),
            ("MatOpaque", AlphaMode::Opaque, true),
        ]
    );
    let sh = s.shading.as_ref().unwrap();
    assert_eq!(sh.tangents.len(), sh.normals.len());
    assert!(sh.tangents.iter().all(|t| t.w == 1.0 || t.w == -1.0));

    let Some(path) = shared("VertexColorTest.glb") else {
        return;
    };
    let s = load_scene_with(&path, &LoadOptions::default(), Parts::Shading).unwrap();
    let sh = s.shading.as_ref().unwrap();
    assert_eq!(sh.colors.len(), sh.normals.len());
    // The label primitive has no COLOR_0 (white); the checks primitive has some colour
    // that is not white.
    let first = &sh.corners[0];
    assert_eq!(sh.colors[first[0] as usize], glam::Vec4::ONE);
    assert_eq!(sh.materials[0], 0);
    let last = sh.corners.len() - 1;
    assert_eq!(sh.materials[last], 1);
    assert!(sh.colors.iter().any(|c| c.x < 0.5 && c.w == 1.0));
}

/// A glTF with one triangle, two punctual lights (one used twice) and a spot, as JSON text.
fn lights_file(extra_light: serde_json::Value) -> Vec<u8> {
    use base64::Engine as _;
    let positions: Vec<u8> = [0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let uri = format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&positions)
    );
    serde_json::to_vec(&json!({
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_lights_punctual"],
        "extensions": {"KHR_lights_punctual": {"lights": [
            {"type": "point", "color": [1.0, 0.5, 0.25], "intensity": 20.0, "range": 5.0, "name": "bulb"},
            {"type": "spot", "spot": {"innerConeAngle": 0.1, "outerConeAngle": 0.5}},
            extra_light,
        ]}},
        "buffers": [{"byteLength": 36, "uri": uri}],
        "bufferViews": [{"buffer": 0, "byteLength": 36}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 0]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [
            {"mesh": 0, "children": [1, 2]},
            {"translation": [0, 3, 0], "extensions": {"KHR_lights_punctual": {"light": 0}}},
            {"rotation": [0, std::f32::consts::FRAC_1_SQRT_2, 0, std::f32::consts::FRAC_1_SQRT_2], "extensions": {"KHR_lights_punctual": {"light": 1}}},
            {"translation": [9, 0, 0], "extensions": {"KHR_lights_punctual": {"light": 2}}}
        ],
        "scenes": [{"nodes": [0, 3]}]
    }))
    .unwrap()
}

#[test]
fn punctual_lights_with_their_nodes() {
    let bytes = lights_file(json!({"type": "directional", "intensity": 3.0}));
    let s = load_with(&bytes, None, &LoadOptions::default(), Parts::Shading).unwrap();
    assert_eq!(s.lights.len(), 3);
    let [bulb, spot, sun] = [&s.lights[0], &s.lights[1], &s.lights[2]];
    assert_eq!(
        (bulb.name.as_str(), bulb.node, bulb.kind),
        ("bulb", 1, LightKind::Point)
    );
    assert_eq!(
        (bulb.color, bulb.intensity, bulb.range),
        ([1.0, 0.5, 0.25], 20.0, Some(5.0))
    );
    assert_eq!(
        bulb.to_world.w_axis.truncate(),
        glam::DVec3::new(0.0, 3.0, 0.0)
    );
    assert_eq!(
        spot.kind,
        LightKind::Spot {
            inner_cone_angle: 0.1,
            outer_cone_angle: 0.5
        }
    );
    // The spot's node turns −Z towards −X.
    let dir = spot.to_world.transform_vector3(glam::DVec3::NEG_Z);
    assert!((dir - glam::DVec3::NEG_X).length() < 1e-6, "{dir}");
    assert_eq!(
        (sun.kind, sun.intensity, sun.color, sun.range),
        (LightKind::Directional, 3.0, [1.0; 3], None)
    );
    assert_eq!(sun.light, 2);
    // A geometry-only load keeps no lights.
    let g = load_with(&bytes, None, &LoadOptions::default(), Parts::Geometry).unwrap();
    assert!(g.lights.is_empty());
    assert_eq!(g.triangles, s.triangles);
    let sh = s.shading.unwrap();
    assert_eq!(sh.materials, [Shading::DEFAULT_MATERIAL]);
    assert!(sh.normals.is_empty(), "no primitive has normals");
}

#[test]
fn malformed_appearance_is_an_error_only_when_asked_for() {
    let cases = [
        (
            json!({"type": "spot", "spot": {"innerConeAngle": 0.6, "outerConeAngle": 0.5}}),
            "light 2: spot cone angles",
        ),
        (
            json!({"type": "point", "intensity": -1.0}),
            "light 2: intensity must be finite and non-negative",
        ),
        (
            json!({"type": "point", "range": 0.0}),
            "light 2: range must be a positive finite number",
        ),
    ];
    for (light, message) in cases {
        let bytes = lights_file(light);
        let e = load_with(&bytes, None, &LoadOptions::default(), Parts::Shading).unwrap_err();
        assert!(e.to_string().starts_with(message), "{e}");
        assert!(matches!(e, GltfError::BadLight { .. }));
        load_with(&bytes, None, &LoadOptions::default(), Parts::Geometry).unwrap();
    }
    // A material pointing past the textures, a factor out of range.
    let mut doc: serde_json::Value =
        serde_json::from_slice(&lights_file(json!({"type": "point"}))).unwrap();
    doc["materials"] = json!([{"pbrMetallicRoughness": {"baseColorTexture": {"index": 3}}}]);
    doc["meshes"][0]["primitives"][0]["material"] = json!(0);
    let bytes = serde_json::to_vec(&doc).unwrap();
    let e = load_with(&bytes, None, &LoadOptions::default(), Parts::Shading).unwrap_err();
    assert_eq!(
        e.to_string(),
        "material 0 baseColorTexture refers to texture 3, but the file has 0"
    );
    load_with(&bytes, None, &LoadOptions::default(), Parts::Geometry).unwrap();
    doc["materials"] = json!([{"pbrMetallicRoughness": {"roughnessFactor": 1.5}}]);
    let bytes = serde_json::to_vec(&doc).unwrap();
    let e = load_with(&bytes, None, &LoadOptions::default(), Parts::Shading).unwrap_err();
    assert_eq!(
        e.to_string(),
        "material 0: roughnessFactor must be in [0, 1]"
    );
    // A primitive pointing past the materials.
    doc["materials"] = json!([{}]);
    doc["meshes"][0]["primitives"][0]["material"] = json!(3);
    let bytes = serde_json::to_vec(&doc).unwrap();
    let e = load_with(&bytes, None, &LoadOptions::default(), Parts::Shading).unwrap_err();
    assert_eq!(
        e.to_string(),
        "mesh 0 primitive 0: refers to material 3, but the file has 1"
    );
    load_with(&bytes, None, &LoadOptions::default(), Parts::Geometry).unwrap();
    // An image stored beside a file that was uploaded alone.
    doc["materials"] = json!([]);
    doc["meshes"][0]["primitives"][0]
        .as_object_mut()
        .unwrap()
        .remove("material");
    doc["images"] = json!([{"uri": "texture.png"}]);
    let bytes = serde_json::to_vec(&doc).unwrap();
    let e = load_with(&bytes, None, &LoadOptions::default(), Parts::Shading).unwrap_err();
    assert!(matches!(e, GltfError::BadImage { image: 0, .. }), "{e}");
    assert!(
        e.to_string().contains("only embedded images are allowed"),
        "{e}"
    );
}

#[test]
fn every_shared_scene_loads_with_shading_data() {
    let Some(d) = dir("shared") else { return };
    let mut names: Vec<String> = std::fs::read_dir(&d)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n.ends_with(".glb"))
        .collect();
    names.sort();
    let mut failures = Vec::new();
    for name in names {
        let path = d.join(&name);
        let Ok(g) = load_scene(&path, &LoadOptions::default()) else {
            continue;
        };
        match load_scene_with(&path, &LoadOptions::default(), Parts::Shading) {
            Err(e) => failures.push(format!("{name}: {e}")),
            Ok(s) => {
                let sh = s.shading.as_ref().unwrap();
                let vertices = [
                    sh.normals.len(),
                    sh.tangents.len(),
                    sh.uv0.len(),
                    sh.uv1.len(),
                    sh.colors.len(),
                ];
                let n = vertices.iter().copied().max().unwrap_or(0);
                if s.triangles != g.triangles
                    || sh.corners.len() != s.triangles.len()
                    || sh.materials.len() != s.triangles.len()
                    || vertices.iter().any(|&v| v != 0 && v != n)
                    || sh
                        .corners
                        .iter()
                        .flatten()
                        .any(|&v| v as usize >= n.max(1) && n > 0)
                    || sh
                        .materials
                        .iter()
                        .any(|&m| m != Shading::DEFAULT_MATERIAL && m as usize >= s.materials.len())
                    || sh
                        .normals
                        .iter()
                        .any(|v| !(v.length() == 0.0 || (v.length() - 1.0).abs() < 1e-5))
                {
                    failures.push(format!("{name}: inconsistent shading data"));
                }
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// A 1 × 1 RGBA PNG of `rgba`, as a data URI.
fn png_uri(rgba: [u8; 4]) -> String {
    use base64::Engine as _;
    let mut png = Vec::new();
    {
        let mut e = png::Encoder::new(&mut png, 1, 1);
        e.set_color(png::ColorType::Rgba);
        e.write_header().unwrap().write_image_data(&rgba).unwrap();
    }
    format!(
        "data:image/png;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&png)
    )
}

/// `KHR_materials_specular`'s two textures, from a glTF file to the BRDF a hit shades
/// with: the strength texture's alpha scales `specularFactor`, the colour texture's RGB
/// (sRGB-decoded) scales `specularColorFactor`.
#[test]
fn specular_textures_reach_the_brdf() {
    use base64::Engine as _;
    let mut bin: Vec<u8> = [0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    bin.extend(
        [0f32, 0.0, 1.0, 0.0, 0.0, 1.0]
            .iter()
            .flat_map(|v| v.to_le_bytes()),
    );
    let buffer = format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&bin)
    );
    let file = |specular: serde_json::Value| {
        serde_json::to_vec(&json!({
            "asset": {"version": "2.0"},
            "extensionsUsed": ["KHR_materials_specular"],
            "buffers": [{"byteLength": 60, "uri": buffer}],
            "bufferViews": [
                {"buffer": 0, "byteLength": 36},
                {"buffer": 0, "byteOffset": 36, "byteLength": 24}
            ],
            "accessors": [
                {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                 "min": [0, 0, 0], "max": [1, 1, 0]},
                {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC2"}
            ],
            "images": [
                {"uri": png_uri([255, 255, 255, 64])},
                {"uri": png_uri([255, 128, 0, 255])}
            ],
            "textures": [{"source": 0}, {"source": 1}],
            "materials": [{"extensions": {"KHR_materials_specular": specular}}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1},
                                        "material": 0}]}],
            "nodes": [{"mesh": 0}],
            "scenes": [{"nodes": [0]}]
        }))
        .unwrap()
    };
    let bsdf = |specular: serde_json::Value| {
        let s = load_with(
            &file(specular),
            None,
            &LoadOptions::default(),
            Parts::Shading,
        )
        .unwrap();
        let surfaces = rayd::render::surface::Surfaces::of(&s).unwrap();
        let hit = rayd::geometry::Hit {
            t: 1.0,
            u: 0.25,
            v: 0.25,
            prim: 0,
        };
        surfaces
            .at(&s.triangles[0], &hit, glam::Vec3::NEG_Z, 0.01)
            .bsdf
    };
    let factors = json!({"specularFactor": 0.8, "specularColorFactor": [1.0, 0.5, 0.25]});
    let plain = bsdf(factors.clone());
    assert_eq!(plain.specular, 0.8);
    let mut with = factors.clone();
    with["specularTexture"] = json!({"index": 0});
    let strength = bsdf(with).specular;
    assert!((strength - 0.8 * 64.0 / 255.0).abs() < 1e-6, "{strength}");
    let mut with = factors;
    with["specularColorTexture"] = json!({"index": 1});
    let f0 = bsdf(with.clone()).f0_dielectric;
    // sRGB code 128 is 0.2158 in linear light.
    let want = 0.04 * glam::Vec3::new(1.0, 0.5 * 0.2158, 0.0);
    assert!(
        (f0 - want).abs().max_element() < 1e-5,
        "{f0} against {want}"
    );
    // A texture reading a third coordinate set is refused, naming it: only two are loaded.
    with["specularColorTexture"] = json!({"index": 1, "texCoord": 2});
    let e = load_with(&file(with), None, &LoadOptions::default(), Parts::Shading).unwrap_err();
    assert!(
        e.to_string()
            .contains("specularColorTexture reads TEXCOORD_2"),
        "{e}"
    );
}
