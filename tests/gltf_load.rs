//! glTF loading: the shared real scenes, and small hand-built files for every rule and
//! every kind of malformed input.

use std::path::{Path, PathBuf};

use rayd::formats::gltf::{load, GltfError};
use rayd::formats::LoadOptions;
use rayd::scene::Scene;

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
