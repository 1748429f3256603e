//! Scenes: uploads, geometry versions, and the triangles a job traces.
//!
//! An upload is parsed before anything is stored: a body that does not load leaves nothing
//! behind. Parsed scenes and evaluated geometry are kept in memory (bounded) and rebuilt
//! lazily from the stored bytes after a restart. Only embedded buffers are accepted: the
//! loader is given no directory, so an uploaded document can never make the server open a
//! file it names.

use std::sync::{Arc, Mutex};

use serde::Serialize;
use serde_json::json;

use super::{App, AppError, TraceParams};
use crate::formats::binary::{read_tri, tri_count, write_tri};
use crate::formats::{LoadOptions, Parts};
use crate::geometry::{RaySegment, Triangle};
use crate::jobs::lru::Lru;
use crate::jobs::{sched, trace, Geometry, GeometryKey, HitBody, TraceReport};
use crate::scene::Scene;
use crate::store::StoreError;
use crate::store::{BlobId, NewScene, SceneRecord};

/// How many times a request that named no version takes the latest again when newer
/// versions deleted it (`--keep-versions`) before its file was read.
const LATEST_TRIES: u32 = 16;

/// What an upload is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UploadKind {
    /// `model/gltf-binary`.
    Glb,
    /// `model/gltf+json`, buffers embedded.
    Gltf,
    /// `application/x-rayd-tri`.
    Tri,
}

impl UploadKind {
    /// The MIME types accepted for uploads.
    pub const MEDIA_TYPES: [&'static str; 3] = [
        "model/gltf-binary",
        "model/gltf+json",
        "application/x-rayd-tri",
    ];

    /// The kind of a `Content-Type` (parameters ignored), if accepted.
    pub fn from_media_type(content_type: &str) -> Option<UploadKind> {
        let essence = content_type
            .split(';')
            .next()
            .unwrap_or("")
            .trim()
            .to_ascii_lowercase();
        match essence.as_str() {
            "model/gltf-binary" => Some(UploadKind::Glb),
            "model/gltf+json" => Some(UploadKind::Gltf),
            "application/x-rayd-tri" => Some(UploadKind::Tri),
            _ => None,
        }
    }

    fn media_type(self) -> &'static str {
        match self {
            UploadKind::Glb => Self::MEDIA_TYPES[0],
            UploadKind::Gltf => Self::MEDIA_TYPES[1],
            UploadKind::Tri => Self::MEDIA_TYPES[2],
        }
    }
}

/// A scene as the API shows it: its id, latest version and the fields of `rayd info`.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SceneView {
    /// Content hash of the uploaded bytes.
    pub id: String,
    /// Latest geometry version.
    pub version: i64,
    /// The upload's media type.
    pub content_type: String,
    /// The name given at upload, if any.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// Upload time, milliseconds since the epoch.
    pub created_at: i64,
    /// The fields of `rayd info`.
    #[serde(flatten)]
    pub info: serde_json::Map<String, serde_json::Value>,
}

impl SceneView {
    fn from_record(r: SceneRecord) -> SceneView {
        let info = serde_json::from_str(&r.summary).unwrap_or_default();
        SceneView {
            id: r.id,
            version: r.latest_version,
            content_type: r.content_type,
            name: r.name,
            created_at: r.created_at,
            info,
        }
    }
}

/// The fields of `rayd info` for `scene` (contract §4).
pub fn scene_info(scene: &Scene) -> serde_json::Value {
    json!({
        "triangles": scene.triangles.len(),
        "bounds": scene.bounds().map(|b| json!({"min": b.min, "max": b.max})),
        "meshes": scene.meshes,
        "animations": scene.animations.iter()
            .map(|a| json!({"name": a.name, "duration": a.duration}))
            .collect::<Vec<_>>(),
        "cameras": scene.cameras.len(),
        "bytes": scene.bytes(),
        "simd": crate::simd::selected().name(),
    })
}

/// Longest name an upload may give, bytes (the store's bound on labels).
const MAX_NAME: usize = 1024;

/// Checks an upload's `name` before any work: 1 to [`MAX_NAME`] bytes, no control
/// characters (it is shown in listings, and the store refuses anything else).
fn check_name(name: &str) -> Result<(), AppError> {
    if name.is_empty() || name.len() > MAX_NAME || name.chars().any(char::is_control) {
        return Err(AppError::BadParameter {
            field: "name",
            detail: format!("must be 1 to {MAX_NAME} bytes without control characters"),
        });
    }
    Ok(())
}

/// The bound on reloading a stored scene: it passed `--max-triangles` when it was uploaded,
/// and lowering the option later must not make it unreadable.
const STORED_MAX: u64 = crate::formats::gltf::MAX_TRIANGLES;

/// Parses an upload of at most `max` triangles (CPU work: call on the pool).
fn parse(kind: UploadKind, bytes: &[u8], max: u64) -> Result<Scene, AppError> {
    parse_with(kind, bytes, Parts::Geometry, max)
}

/// [`parse`] keeping `parts` (a TRI1 upload has geometry only).
fn parse_with(kind: UploadKind, bytes: &[u8], parts: Parts, max: u64) -> Result<Scene, AppError> {
    let upload = |detail: String, byte_offset: Option<u64>| AppError::BadUpload {
        detail,
        byte_offset,
    };
    let binary = |e: crate::formats::binary::BinaryError| upload(e.to_string(), e.byte_offset());
    match kind {
        UploadKind::Tri => {
            let count = tri_count(bytes).map_err(binary)?;
            if count as u64 > max {
                return Err(upload(too_many_triangles(count as u64, max), Some(8)));
            }
            read_tri(bytes).map(Scene::from_triangles).map_err(binary)
        }
        UploadKind::Glb | UploadKind::Gltf => {
            crate::formats::gltf::load_limited(bytes, None, &LoadOptions { time: None }, parts, max)
                .map_err(|e| upload(e.to_string(), e.byte_offset()))
        }
    }
}

/// Refuses a glTF upload that is not what its `Content-Type` says (the record keeps the
/// type). Only uploads: a scene stored before this check reloads as it always did.
fn check_kind(kind: UploadKind, bytes: &[u8]) -> Result<(), AppError> {
    let glb = bytes.starts_with(b"glTF");
    let declared = match kind {
        UploadKind::Glb if !glb => "model/gltf-binary but is not a GLB (no glTF magic at byte 0)",
        UploadKind::Gltf if glb => "model/gltf+json but is a GLB (it starts with the glTF magic)",
        _ => return Ok(()),
    };
    Err(AppError::BadUpload {
        detail: format!("the body is declared {declared}"),
        byte_offset: Some(0),
    })
}

/// The refusal of a TRI1 body over `--max-triangles`, worded as the glTF loader's.
fn too_many_triangles(count: u64, max: u64) -> String {
    format!(
        "the scene would have {count} triangles, more than the limit of {max} (--max-triangles)"
    )
}

/// A scene's cameras at one pose.
type Cameras = Arc<Vec<Option<crate::scene::Camera>>>;

/// A parsed scene: its static pose, and the rig that poses it at other times.
struct Loaded {
    /// The scene without its positions, which are `static_pose` (one copy for the parse
    /// and for version 1's geometry).
    scene: Arc<Scene>,
    /// Version 1's positions at the static pose.
    static_pose: Arc<Vec<Triangle>>,
    /// The same file with shading data, materials and lights, parsed on first use by a
    /// render that shades (`path`, or the `albedo`/`normal` AOVs).
    shaded: std::sync::OnceLock<Arc<Scene>>,
}

impl Loaded {
    fn new(mut scene: Scene) -> Loaded {
        let static_pose = Arc::new(std::mem::take(&mut scene.triangles));
        Loaded {
            scene: Arc::new(scene),
            static_pose,
            shaded: std::sync::OnceLock::new(),
        }
    }

    /// Bytes held: both parses, every part.
    fn bytes(&self) -> usize {
        let total = |s: &Scene| {
            let p = s.bytes_by_part();
            p.positions + p.attributes + p.textures + p.animation
        };
        std::mem::size_of_val(&self.static_pose[..])
            + total(&self.scene)
            + self.shaded.get().map_or(0, |s| total(s))
    }
}

/// What the scene cache holds: a parsed scene, or positions evaluated for a key.
#[derive(Clone, PartialEq, Eq, Hash)]
enum CacheKey {
    Scene(Arc<str>),
    Geometry(GeometryKey),
}

impl CacheKey {
    fn scene(&self) -> &str {
        match self {
            CacheKey::Scene(id) => id,
            CacheKey::Geometry(k) => &k.scene,
        }
    }
}

#[derive(Clone)]
enum Held {
    Scene(Arc<Loaded>),
    Geometry(Arc<Vec<Triangle>>, Cameras),
}

/// Parsed scenes and evaluated geometry, in memory, within one budget
/// (`--geometry-bytes`): the least recently used go first, and come back from the stored
/// bytes when asked for again. The one in use is kept even when it alone is larger.
pub(super) struct SceneCache(Mutex<Lru<CacheKey, Held>>);

impl SceneCache {
    pub(super) fn new(budget: usize) -> SceneCache {
        SceneCache(Mutex::new(Lru::keeping_one(budget)))
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Lru<CacheKey, Held>> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn loaded(&self, id: &str) -> Option<Arc<Loaded>> {
        match self.lock().get(&CacheKey::Scene(Arc::from(id)))? {
            Held::Scene(l) => Some(Arc::clone(l)),
            Held::Geometry(..) => None,
        }
    }

    /// Keeps `loaded` as scene `id` (again, after its shaded parse: its size grew).
    fn keep_loaded(&self, id: &str, loaded: Arc<Loaded>) {
        let bytes = loaded.bytes();
        self.lock()
            .insert(CacheKey::Scene(Arc::from(id)), Held::Scene(loaded), bytes);
    }

    fn geometry(&self, key: &GeometryKey) -> Option<(Arc<Vec<Triangle>>, Cameras)> {
        match self.lock().get(&CacheKey::Geometry(key.clone()))? {
            Held::Geometry(g, c) => Some((Arc::clone(g), Arc::clone(c))),
            Held::Scene(_) => None,
        }
    }

    fn keep_geometry(&self, key: GeometryKey, tris: Arc<Vec<Triangle>>, cameras: Cameras) {
        let bytes = std::mem::size_of_val(&tris[..]);
        self.lock().insert(
            CacheKey::Geometry(key),
            Held::Geometry(tris, cameras),
            bytes,
        );
    }

    fn forget(&self, scene: &str) {
        self.lock().remove_where(|k| k.scene() == scene);
    }

    /// Drops the positions of versions the store has deleted, so that they answer `404`
    /// from memory as they do from the store.
    fn forget_versions(&self, scene: &str, versions: &[i64]) {
        if versions.is_empty() {
            return;
        }
        self.lock().remove_where(|k| match k {
            CacheKey::Geometry(g) => &*g.scene == scene && versions.contains(&i64::from(g.version)),
            CacheKey::Scene(_) => false,
        });
    }
}

/// A TRI1 body of a scene's positions ([`App::triangles_tri1`]).
#[derive(Debug)]
pub enum Tri1Body {
    /// A stored version's file, verified, at offset 0, and its length.
    Stored {
        /// The open file.
        file: tokio::fs::File,
        /// Its length in bytes.
        len: u64,
    },
    /// Positions encoded for this request.
    Encoded(Vec<u8>),
}

/// Stores `bytes` as a blob, then commits the record `record` makes of it. If the blob
/// vanished in between (the blob of a deleted version with the same bytes, collected at
/// once by [`crate::store::Store::collect_pruned`]), stores it again: three tries in all,
/// since each loss needs a version deleted and collected within milliseconds; then 503.
async fn stored_then_recorded<T, F, Fut>(
    store: &crate::store::Store,
    bytes: bytes::Bytes,
    record: F,
) -> Result<T, AppError>
where
    F: Fn(crate::store::Store, BlobId) -> Fut,
    Fut: std::future::Future<Output = Result<T, StoreError>>,
{
    for _ in 0..3 {
        let blob = store.put_blob(bytes.clone()).await?;
        match record(store.clone(), blob).await {
            Err(StoreError::NotFound { what: "blob", .. }) => {}
            r => return Ok(r?),
        }
    }
    Err(AppError::Busy(
        "the same bytes were being deleted (an old version's) while they were stored; \
         send them again"
            .into(),
    ))
}

impl App {
    /// Stores an upload as a scene: parses it first (a body that does not load leaves
    /// nothing behind), then stores the bytes and the record. The same bytes again give the
    /// same scene and `false`.
    pub async fn upload(
        &self,
        kind: UploadKind,
        bytes: bytes::Bytes,
        name: Option<String>,
    ) -> Result<(SceneView, bool), AppError> {
        if let Some(name) = &name {
            check_name(name)?;
        }
        check_kind(kind, &bytes)?;
        let id = BlobId::of(&bytes);
        if let Ok(existing) = self.store().get_scene(id.as_str()).await {
            // The same bytes declared as what they were stored as are the same scene.
            // Declared as another type they are parsed as that type below, and refused as
            // they would be on a server that had never seen them: a stored GLB sent as
            // TRI1 does not load as TRI1.
            if existing.content_type == kind.media_type() {
                // The stored copy is written again where it is missing or damaged:
                // uploading the same bytes is how a damaged scene is mended
                // (proto/store.md). It is hashed first, so that a copy damaged in place
                // (same size, a flipped byte) is found and moved to quarantine, which a
                // size check alone would take for whole; a whole copy only has its time
                // renewed.
                if let Err(e) = self.store().open_blob(&existing.id).await {
                    tracing::warn!(scene = %existing.id, "stored copy unreadable, written again: {e}");
                }
                self.store().put_blob(bytes).await?;
                // Uploading the bytes again is also how a failed thumbnail is tried again.
                self.queue_thumbnail(&existing.id);
                return Ok((SceneView::from_record(existing), false));
            }
        }
        let b = bytes.clone();
        let max = self.inner.max_triangles;
        // Checked as a render would read it, so that nothing is stored that no render
        // could load; kept as geometry only.
        let scene = self
            .cpu(move || parse_with(kind, &b, Parts::CheckedGeometry, max))
            .await??;
        let summary = scene_info(&scene).to_string();
        let new = |blob| NewScene {
            blob,
            content_type: kind.media_type().to_string(),
            name: name.clone(),
            summary: summary.clone(),
        };
        let (record, created) = stored_then_recorded(self.store(), bytes, |store, blob| {
            let new = new(blob);
            async move { store.create_scene(new).await }
        })
        .await?;
        self.inner
            .scenes
            .keep_loaded(&record.id, Arc::new(Loaded::new(scene)));
        // In the background, at the lowest priority: the answer does not wait for it.
        self.queue_thumbnail(&record.id);
        Ok((SceneView::from_record(record), created))
    }

    /// A scene's record.
    pub async fn scene(&self, id: &str) -> Result<SceneView, AppError> {
        Ok(SceneView::from_record(self.store().get_scene(id).await?))
    }

    /// A page of scenes and the next page's token.
    pub async fn scenes(
        &self,
        limit: u32,
        page_token: Option<&str>,
    ) -> Result<(Vec<SceneView>, Option<String>), AppError> {
        let (records, next) = self.store().list_scenes(limit, page_token).await?;
        Ok((
            records.into_iter().map(SceneView::from_record).collect(),
            next,
        ))
    }

    /// Deletes a scene, its versions, its jobs (stopping those that are queued or
    /// running), its cached structures and its decoded textures.
    pub async fn delete_scene(&self, id: &str) -> Result<(), AppError> {
        let unfinished = self.store().delete_scene(id).await?;
        self.stop_deleted(&unfinished);
        self.inner.scenes.forget(id);
        self.engine().forget_scene(id);
        self.inner.thumbnails.forget(id);
        Ok(())
    }

    /// Scene `id`'s stored bytes and what they are.
    async fn stored(&self, id: &str) -> Result<(UploadKind, Vec<u8>), AppError> {
        let record = self.store().get_scene(id).await?;
        let kind = UploadKind::from_media_type(&record.content_type).ok_or_else(|| {
            AppError::Internal(format!(
                "scene {id} has an unknown stored type {}",
                record.content_type
            ))
        })?;
        Ok((kind, self.store().get_blob(id).await?))
    }

    /// The parsed static pose of scene `id`, parsing the stored bytes after a restart.
    async fn loaded(&self, id: &str) -> Result<Arc<Loaded>, AppError> {
        if let Some(l) = self.inner.scenes.loaded(id) {
            return Ok(l);
        }
        let (kind, bytes) = self.stored(id).await?;
        let scene = self.cpu(move || parse(kind, &bytes, STORED_MAX)).await??;
        let loaded = Arc::new(Loaded::new(scene));
        self.inner.scenes.keep_loaded(id, Arc::clone(&loaded));
        Ok(loaded)
    }

    /// Scene `id` with its shading data, materials and lights, parsed once on first use.
    pub async fn shaded_scene(&self, id: &str) -> Result<Arc<Scene>, AppError> {
        let loaded = self.loaded(id).await?;
        if let Some(s) = loaded.shaded.get() {
            return Ok(Arc::clone(s));
        }
        let (kind, bytes) = self.stored(id).await?;
        let scene = self
            .cpu(move || parse_with(kind, &bytes, Parts::Shading, STORED_MAX))
            .await??;
        let shaded = Arc::clone(loaded.shaded.get_or_init(|| Arc::new(scene)));
        // Counted again with its shaded parse.
        self.inner.scenes.keep_loaded(id, loaded);
        Ok(shaded)
    }

    /// Stores new positions for every triangle of scene `id` as its next version.
    pub async fn update_geometry(&self, id: &str, body: bytes::Bytes) -> Result<i64, AppError> {
        let loaded = self.loaded(id).await?;
        let expected = loaded.static_pose.len();
        // Header and length first, reading no record: a malformed body, or one for
        // another scene, is refused before any work.
        let count = tri_count(&body).map_err(bad_positions)?;
        if count != expected {
            return Err(wrong_count(id, count as u64, expected));
        }
        // Parsing (on the pool) and the durable write (on a blocking thread) run at once:
        // a frame's update costs the longer of the two, not their sum. A body that turns
        // out not to parse (a NaN) leaves an unnamed blob, which GC collects.
        let b = body.clone();
        let (tris, blob) = tokio::join!(
            self.cpu(move || read_tri(&b)),
            self.store().put_blob(body.clone())
        );
        let tris = tris?.map_err(bad_positions)?;
        let (record, pruned) = match self.store().add_version(id, &blob?).await {
            Err(StoreError::NotFound { what: "blob", .. }) => {
                stored_then_recorded(self.store(), body, |store, blob| async move {
                    store.add_version(id, &blob).await
                })
                .await?
            }
            r => r?,
        };
        let version = record.version;
        self.inner.scenes.forget_versions(id, &pruned);
        self.inner.scenes.keep_geometry(
            GeometryKey::new(id, version as u32, None),
            Arc::new(tris),
            Arc::new(loaded.scene.cameras.clone()),
        );
        Ok(version)
    }

    /// The triangle count of scene `id`: what a geometry update must give.
    pub async fn triangle_count(&self, id: &str) -> Result<usize, AppError> {
        Ok(self.loaded(id).await?.static_pose.len())
    }

    /// Checks the header (first 16 bytes) of a geometry update for scene `id` before its
    /// records arrive, as [`App::update_geometry`] checks a whole body: malformed is 400,
    /// another triangle count 422.
    pub async fn check_positions_header(&self, id: &str, header: &[u8]) -> Result<(), AppError> {
        let count = crate::formats::binary::tri_header_count(header).map_err(bad_positions)?;
        let expected = self.triangle_count(id).await?;
        if count != expected {
            return Err(wrong_count(id, count as u64, expected));
        }
        Ok(())
    }

    /// Deletes the old versions that jobs kept until they ended (see
    /// [`crate::store::Store::prune_versions`]); returns how many. For the periodic upkeep.
    pub async fn prune_versions(&self) -> Result<usize, AppError> {
        let pruned = self.store().prune_versions().await?;
        for (scene, version) in &pruned {
            self.inner.scenes.forget_versions(scene, &[*version]);
        }
        Ok(pruned.len())
    }

    /// The triangles of scene `id` at `version` (default: the latest) and `time` (version
    /// 1 only), and the scene's cameras at that time.
    ///
    /// The latest, when no version is named, is taken again if newer versions deleted it
    /// (`--keep-versions`) while it was read: a client that names no version asked for
    /// whatever is latest, and must not get a 404 for a version it never named.
    pub(super) async fn geometry(
        &self,
        id: &str,
        version: Option<u32>,
        time: Option<f64>,
    ) -> Result<(Geometry, Cameras), AppError> {
        let mut tries = 1;
        loop {
            match self.geometry_once(id, version, time).await {
                Err(AppError::Store(StoreError::NotFound {
                    what: "version" | "blob",
                    ..
                })) if version.is_none() && tries < LATEST_TRIES => tries += 1,
                r => return r,
            }
        }
    }

    /// [`App::geometry`], taking the latest once.
    async fn geometry_once(
        &self,
        id: &str,
        version: Option<u32>,
        time: Option<f64>,
    ) -> Result<(Geometry, Cameras), AppError> {
        // Before anything is read: see `Geometry::forgets`.
        let forgets = self.engine().forgets();
        let latest = self.store().get_scene(id).await?.latest_version as u32;
        let named = version.is_some();
        let version = version.unwrap_or(latest);
        if version == 0 || version > latest {
            return Err(crate::store::StoreError::NotFound {
                what: "version",
                id: format!("{id} version {version}"),
            }
            .into());
        }
        if let Some(t) = time {
            animated(version, "time")?;
            if !t.is_finite() {
                return Err(AppError::BadParameter {
                    field: "time",
                    detail: "must be a finite number of seconds".into(),
                });
            }
        }
        let answer = |key, triangles, cameras| {
            let geometry = Geometry {
                key,
                triangles,
                forgets,
            };
            Ok((geometry, cameras))
        };
        let key = GeometryKey::new(id, version, time);
        if let Some((triangles, cameras)) = self.inner.scenes.geometry(&key) {
            return answer(key, triangles, cameras);
        }
        let loaded = self.loaded(id).await?;
        let mut cameras = Arc::new(loaded.scene.cameras.clone());
        // Version 1 at rest (or at any time, without a rig) is the parse's own positions:
        // no copy, and no entry of its own beside the scene's. Without a rig every time
        // is the static pose, under its key: one structure serves them all.
        if version == 1 && (time.is_none() || loaded.scene.rig.is_none()) {
            let triangles = Arc::clone(&loaded.static_pose);
            return answer(GeometryKey::new(id, 1, None), triangles, cameras);
        }
        let tris: Arc<Vec<Triangle>> = if let (1, Some(t)) = (version, time) {
            // The scene's rig re-poses it: no second parse of the file.
            let l = Arc::clone(&loaded);
            let pose = self
                .cpu(move || l.scene.evaluate(t, crate::scene::Compute::Positions))
                .await?
                .map_err(|e| AppError::BadParameter {
                    field: "time",
                    detail: format!("at {t}: {e}"),
                })?;
            cameras = Arc::new(pose.cameras);
            Arc::new(pose.triangles)
        } else {
            let v = self.store().get_version(id, version as i64).await?;
            let bytes = self.store().get_blob(&v.blob).await?;
            let tris = self.cpu(move || read_tri(&bytes)).await?.map_err(|e| {
                AppError::Internal(format!("stored version {version} of {id}: {e}"))
            })?;
            Arc::new(tris)
        };
        self.inner
            .scenes
            .keep_geometry(key.clone(), Arc::clone(&tris), Arc::clone(&cameras));
        if version >= 2 {
            // A newer version may have deleted this one while it was read: then it must
            // not stay in memory, answering there as it no longer does from the store. A
            // request for the latest is still answered with it: it was the latest when the
            // request came (a request that waited for the pool behind a render while
            // versions arrived would otherwise never find one that stayed).
            if let Err(e) = self.store().get_version(id, i64::from(version)).await {
                self.inner.scenes.forget_versions(id, &[i64::from(version)]);
                if named {
                    return Err(e.into());
                }
            }
        }
        answer(key, tris, cameras)
    }

    /// The world-space triangles of scene `id` at `version` (default: the latest) and `time`
    /// (version 1 only) as a TRI1 body, in id order: what `GET /v1/scenes/{id}/geometry`
    /// answers, so that a client can shade its own hits (normals, hit points) with the
    /// positions that were traced. A version from 2 on is the TRI1 body its `PUT` stored,
    /// byte for byte what encoding its triangles gives, so it is sent from its file (checked
    /// against its hash) instead of being encoded again; other positions are encoded on the
    /// pool, never on the async runtime.
    pub async fn triangles_tri1(
        &self,
        id: &str,
        version: Option<u32>,
        time: Option<f64>,
    ) -> Result<Tri1Body, AppError> {
        let latest = self.store().get_scene(id).await?.latest_version as u32;
        let v = version.unwrap_or(latest);
        if v >= 2 && time.is_none() {
            if let Ok(record) = self.store().get_version(id, i64::from(v)).await {
                let file = self.store().open_blob(&record.blob).await?;
                let len = file
                    .metadata()
                    .await
                    .map_err(|e| AppError::Internal(format!("version {v} of {id}: {e}")))?
                    .len();
                return Ok(Tri1Body::Stored { file, len });
            }
        }
        // Version 1, a `time`, or a version that does not exist: `geometry` says which.
        let tris = self.geometry(id, version, time).await?.0.triangles;
        Ok(Tri1Body::Encoded(self.cpu(move || write_tri(&tris)).await?))
    }

    /// Refuses a synchronous trace before its body is read when the queue is full (or the
    /// service is shutting down), so that a client does not upload a batch to hear 503.
    /// The place itself is taken when the trace can start ([`App::begin_trace`]): a body
    /// still on its way holds none, so slow uploads cannot fill the queue (a frame's
    /// rays excepted: [`App::reserve_trace`]).
    pub fn trace_has_room(&self) -> Result<(), AppError> {
        Ok(self.engine().scheduler().has_room()?)
    }

    /// Takes a synchronous trace's place in the queue now, before its rays are in, for a
    /// request that makes something durable before its trace: a frame records its version
    /// only once its trace has a place, so that a queue that filled while the positions
    /// arrived refuses the frame whole (503, no version made) instead of after the version
    /// is made. The place is held while the rays arrive (a frame's rays follow its
    /// positions at once); [`App::begin_trace`] takes it.
    pub fn reserve_trace(&self) -> Result<TracePlace, AppError> {
        Ok(TracePlace(self.engine().scheduler().reserve()?))
    }

    /// Notes that a trace body of `bytes` (after its first piece) took `seconds` to arrive,
    /// for `auto`'s estimate of the next one's arrival.
    pub fn note_upload(&self, bytes: u64, seconds: f64) {
        self.engine().note_upload(bytes, seconds);
    }

    /// Starts a synchronous trace of scene `id` whose rays are still to arrive; `rays` is
    /// the count the request's length announces, if it does. Where the accelerator answers
    /// each ray on its own and the batch is large, the trace takes its place in the queue
    /// now and starts on the rays that have arrived while the rest uploads (the structure
    /// is prepared first, during the upload); otherwise it takes its place, and starts,
    /// when all have arrived. A `place` taken before ([`App::reserve_trace`]) is used
    /// instead of a new one.
    pub async fn begin_trace(
        &self,
        id: &str,
        params: &TraceParams,
        rays: Option<usize>,
        place: Option<TracePlace>,
    ) -> Result<TraceIntake, AppError> {
        let (geometry, _) = self.geometry(id, params.version, params.time).await?;
        let request = params.request();
        let engine = Arc::clone(self.engine());
        // How long the body will take to arrive, as recent bodies did: `auto` weighs it.
        let arrival = rays.map_or(0.0, |n| engine.arrival(n));
        let streamed = rays.filter(|&n| engine.streams(&geometry, &request, n, arrival));
        let Some(count) = streamed else {
            return Ok(TraceIntake::Whole {
                geometry,
                request,
                engine,
                place,
            });
        };
        let ticket = match place {
            Some(p) => p.taken(),
            None => admit_sync_trace(&engine)?,
        };
        let (arrive, arrivals) = std::sync::mpsc::channel();
        let abandon = Abandon::new(&engine);
        let cancel = abandon.token.clone();
        let done = on_trace_thread(move || {
            let control = engine.control(cancel, None, ticket);
            engine.trace_stream(&geometry, &request, count, arrival, arrivals, &control)
        })?;
        Ok(TraceIntake::Streamed {
            arrive,
            done,
            abandon,
        })
    }
}

/// Cancels a synchronous trace whose request is dropped before its answer (the client
/// went away): a trace nobody waits for then gives up its place in the queue, or stops
/// at its next step, instead of holding a place and the pool for nobody (session 31's
/// review: four clients that sent 1K rays and hung up filled `--max-queued 4` behind a
/// long trace, and renders got 503). Cancelling a trace that has answered changes nothing.
pub struct Abandon {
    token: crate::jobs::CancelToken,
    sched: Arc<sched::Scheduler>,
}

impl Abandon {
    fn new(engine: &crate::jobs::Engine) -> Abandon {
        Abandon {
            token: crate::jobs::CancelToken::new(),
            sched: Arc::clone(engine.scheduler()),
        }
    }
}

impl Drop for Abandon {
    fn drop(&mut self) {
        self.token.cancel();
        // A trace waiting for the pool notices at once.
        self.sched.nudge();
    }
}

/// A synchronous trace's place in the queue taken ahead of its rays
/// ([`App::reserve_trace`]); dropping it gives the place up.
pub struct TracePlace(sched::Ticket);

impl TracePlace {
    /// The ticket, for a trace about to ask for the pool ([`sched::Ticket::arrive`]).
    fn taken(self) -> sched::Ticket {
        self.0.arrive();
        self.0
    }
}

/// A synchronous trace's place in the queue, ahead of every job, taken when it can start
/// (see [`App::trace_has_room`]).
fn admit_sync_trace(engine: &crate::jobs::Engine) -> Result<sched::Ticket, AppError> {
    Ok(engine.scheduler().admit(sched::SYNC_PRIORITY, true)?)
}

/// What a synchronous trace answers, when its thread is done.
type TraceDone =
    tokio::sync::oneshot::Receiver<Result<(HitBody, TraceReport), crate::jobs::JobError>>;

/// Runs a synchronous trace on a thread of its own, which waits for the scheduler's lease
/// (and, streamed, for its rays) so that no runtime thread does; its work runs on the pool.
fn on_trace_thread(
    trace: impl FnOnce() -> Result<(HitBody, TraceReport), crate::jobs::JobError> + Send + 'static,
) -> Result<TraceDone, AppError> {
    let (tx, done) = tokio::sync::oneshot::channel();
    std::thread::Builder::new()
        .name("rayd-trace".into())
        .spawn(move || {
            let _ = tx.send(trace());
        })
        .map_err(|e| AppError::Internal(format!("cannot start a trace thread: {e}")))?;
    Ok(done)
}

/// Refuses animation times (`field`: a render's `time` or `frames`) for a `version` from 2
/// on, which holds positions only: times evaluate version 1's animation (400).
pub(super) fn animated(version: u32, field: &'static str) -> Result<(), AppError> {
    if version == 1 {
        return Ok(());
    }
    Err(AppError::BadParameter {
        field,
        detail: format!(
            "version {version} holds positions only; {field} evaluates version 1's animation"
        ),
    })
}

/// A geometry update's TRI1 body that does not read (400, naming its byte).
fn bad_positions(e: crate::formats::binary::BinaryError) -> AppError {
    AppError::BadUpload {
        detail: e.to_string(),
        byte_offset: e.byte_offset(),
    }
}

fn wrong_count(id: &str, got: u64, expected: usize) -> AppError {
    AppError::Unprocessable {
        field: "count",
        detail: format!(
            "the body has {got} triangles but scene {id} has {expected}: a geometry update gives new positions for every triangle, same ids"
        ),
    }
}

/// A synchronous trace waiting for its rays (see [`App::begin_trace`]). Dropping it before
/// [`TraceIntake::finish`] abandons the trace.
pub enum TraceIntake {
    /// The trace starts when the whole batch is in.
    Whole {
        /// The triangles.
        geometry: Geometry,
        /// The options.
        request: trace::TraceRequest,
        /// The engine.
        engine: Arc<crate::jobs::Engine>,
        /// Its place in the queue, if taken before the rays ([`App::reserve_trace`]).
        place: Option<TracePlace>,
    },
    /// The trace runs as the rays arrive.
    Streamed {
        /// Where the rays go.
        arrive: std::sync::mpsc::Sender<trace::Arrival>,
        /// The answer.
        done: TraceDone,
        /// Cancels the trace if the request is dropped first.
        abandon: Abandon,
    },
}

impl TraceIntake {
    /// Rays per piece the trace takes as they arrive (`None`: it wants the whole batch).
    pub fn segment_rays(&self) -> Option<usize> {
        match self {
            TraceIntake::Whole { .. } => None,
            TraceIntake::Streamed { .. } => Some(trace::STREAM_SEGMENT_RAYS),
        }
    }

    /// Hands over the next rays of the batch, in order.
    pub fn send(&mut self, rays: RaySegment) {
        if let TraceIntake::Streamed { arrive, .. } = self {
            // A trace that already stopped (bad rays, say) answers at `finish`.
            let _ = arrive.send(trace::Arrival::Rays(rays));
        }
    }

    /// Hands over the last rays of a complete, well-formed body and waits for the answer.
    pub async fn finish(self, mut rays: RaySegment) -> Result<(HitBody, TraceReport), AppError> {
        let (done, _abandon) = match self {
            TraceIntake::Streamed {
                arrive,
                done,
                abandon,
            } => {
                let _ = arrive.send(trace::Arrival::Rays(rays));
                let _ = arrive.send(trace::Arrival::End);
                (done, abandon)
            }
            TraceIntake::Whole {
                geometry,
                request,
                engine,
                place,
            } => {
                // Its place in the queue, now that the whole batch is here (unless taken
                // before).
                let ticket = match place {
                    Some(p) => p.taken(),
                    None => admit_sync_trace(&engine)?,
                };
                let abandon = Abandon::new(&engine);
                let cancel = abandon.token.clone();
                let done = on_trace_thread(move || {
                    let invalid = trace::validate_read(&mut rays, request.invalid)?;
                    let control = engine.control(cancel, None, ticket);
                    engine.trace(&geometry, &rays.rays, &request, invalid, &control)
                })?;
                (done, abandon)
            }
        };
        Ok(done
            .await
            .map_err(|_| AppError::Internal("the trace thread died".into()))??)
    }
}
