//! Tests of the store, one or more per public function, in temporary directories. The
//! end-to-end `kill -9` test is `tests/store_crash.rs`.

use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use super::*;

fn opts() -> StoreOptions {
    StoreOptions {
        gc_grace: Duration::ZERO,
        ..StoreOptions::default()
    }
}

async fn open(dir: &Path) -> Store {
    Store::open(dir, opts()).await.expect("open")
}

/// A store in `dir` that keeps `keep` versions of a scene, with the default GC grace (the
/// blobs of deleted versions go at `collect_pruned` all the same).
async fn open_keeping(dir: &Path, keep: u32) -> Store {
    let options = StoreOptions {
        keep_versions: Some(keep),
        ..StoreOptions::default()
    };
    Store::open(dir, options).await.expect("open")
}

/// Stores `bytes` and records a scene for them.
async fn scene(store: &Store, bytes: &[u8]) -> SceneRecord {
    let blob = store.put_blob(bytes.to_vec()).await.unwrap();
    let (s, _) = store
        .create_scene(NewScene {
            blob,
            content_type: "application/x-rayd-tri".into(),
            name: Some("test".into()),
            summary: r#"{"triangles": 1}"#.into(),
        })
        .await
        .unwrap();
    s
}

fn render_job(scene: &SceneRecord) -> NewJob {
    NewJob {
        kind: JobKind::Render,
        scene_id: scene.id.clone(),
        version: 1,
        request: r#"{"width": 4}"#.into(),
        priority: 50,
        idempotency_key: None,
        input_blob: None,
    }
}

/// Every file under `dir` whose name starts with `.tmp`, and everything in `blobs/tmp`.
fn temp_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.join("blobs")];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.file_name().unwrap().to_string_lossy().starts_with(".tmp")
                || p.parent().unwrap().ends_with("blobs/tmp")
            {
                out.push(p);
            }
        }
    }
    out
}

fn blob_files(dir: &Path) -> usize {
    std::fs::read_dir(dir.join("blobs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.file_name().unwrap().len() == 2)
        .map(|p| std::fs::read_dir(p).unwrap().count())
        .sum()
}

fn age(path: &Path, by: Duration) {
    let f = std::fs::File::options().write(true).open(path).unwrap();
    f.set_modified(SystemTime::now() - by).unwrap();
}

#[tokio::test]
async fn blobs_are_content_addressed_and_deduplicated() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    assert_eq!(store.dir(), tmp.path());
    let a = store.put_blob(b"hello".to_vec()).await.unwrap();
    assert_eq!(a.as_str(), blake3::hash(b"hello").to_hex().as_str());
    let again = store.put_blob(b"hello".to_vec()).await.unwrap();
    assert_eq!(a, again);
    let b = store.put_blob(b"world".to_vec()).await.unwrap();
    assert_ne!(a, b);
    assert_eq!(blob_files(tmp.path()), 2);
    assert_eq!(store.blob_bytes(), None, "counted only under a quota");
    let path = store.blob_path(a.as_str()).await.unwrap();
    assert_eq!(
        path,
        tmp.path()
            .join("blobs")
            .join(&a.as_str()[..2])
            .join(a.as_str())
    );
    assert_eq!(store.get_blob(a.as_str()).await.unwrap(), b"hello");
    let mut f = store.open_blob(b.as_str()).await.unwrap();
    let mut read = Vec::new();
    tokio::io::AsyncReadExt::read_to_end(&mut f, &mut read)
        .await
        .unwrap();
    assert_eq!(read, b"world");
    // The empty blob is a blob too.
    let e = store.put_blob(Vec::new()).await.unwrap();
    assert_eq!(store.get_blob(e.as_str()).await.unwrap(), b"");
    assert!(temp_files(tmp.path()).is_empty());
}

#[tokio::test]
async fn malformed_ids_name_nothing_and_never_reach_the_file_system() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let real = store.put_blob(b"x".to_vec()).await.unwrap();
    let upper = real.as_str().to_uppercase();
    for bad in [
        "",
        "../lock",
        "ab/../../lock",
        upper.as_str(),
        &real.as_str()[..63],
    ] {
        for r in [
            store.get_blob(bad).await.map(|_| ()),
            store.blob_path(bad).await.map(|_| ()),
            store.get_scene(bad).await.map(|_| ()),
            store.get_job(bad).await.map(|_| ()),
            store.delete_scene(bad).await.map(|_| ()),
        ] {
            assert!(
                matches!(r, Err(StoreError::NotFound { .. })),
                "{bad:?}: {r:?}"
            );
        }
    }
    let missing = "0".repeat(64);
    assert!(matches!(
        store.get_blob(&missing).await,
        Err(StoreError::NotFound { what: "blob", .. })
    ));
    assert!(matches!(
        store.get_job(&"0".repeat(32)).await,
        Err(StoreError::NotFound { what: "job", .. })
    ));
}

#[tokio::test]
async fn a_corrupt_blob_is_detected_never_served_and_repaired_by_a_new_upload() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let id = store.put_blob(b"precious bytes".to_vec()).await.unwrap();
    let path = store.blob_path(id.as_str()).await.unwrap();
    std::fs::write(&path, b"precious bytez").unwrap();
    match store.get_blob(id.as_str()).await {
        Err(StoreError::Corrupt { blob, .. }) => assert_eq!(blob, id.as_str()),
        other => panic!("expected Corrupt, got {other:?}"),
    }
    // Moved aside: not served again, kept for inspection.
    assert!(!path.exists());
    assert_eq!(
        std::fs::read_dir(tmp.path().join("quarantine"))
            .unwrap()
            .count(),
        1
    );
    assert!(matches!(
        store.open_blob(id.as_str()).await,
        Err(StoreError::NotFound { .. })
    ));
    // The same bytes again write a good copy.
    assert_eq!(
        store.put_blob(b"precious bytes".to_vec()).await.unwrap(),
        id
    );
    assert_eq!(
        store.get_blob(id.as_str()).await.unwrap(),
        b"precious bytes"
    );

    // A same-size corruption is caught by open_blob too, before a byte is handed out.
    std::fs::write(&path, b"PRECIOUS BYTES").unwrap();
    assert!(matches!(
        store.open_blob(id.as_str()).await,
        Err(StoreError::Corrupt { .. })
    ));
    // A truncated copy is replaced by the next upload of the bytes (its size is wrong).
    std::fs::write(&path, b"prec").unwrap();
    store.put_blob(b"precious bytes".to_vec()).await.unwrap();
    assert_eq!(
        store.get_blob(id.as_str()).await.unwrap(),
        b"precious bytes"
    );
}

#[tokio::test]
async fn streamed_writes_hash_while_writing_and_leave_nothing_when_dropped() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let data: Vec<u8> = (0..3_000_000u32).map(|i| (i * 7 % 251) as u8).collect();
    let mut w = store.blob_writer().await.unwrap();
    assert!(w.is_empty());
    for chunk in data.chunks(65_536) {
        w.write(chunk).await.unwrap();
    }
    assert_eq!(w.len(), data.len() as u64);
    let id = w.commit().await.unwrap();
    assert_eq!(id, BlobId::of(&data));
    assert_eq!(store.get_blob(id.as_str()).await.unwrap(), data);

    // A duplicate stream keeps the one file.
    let mut w = store.blob_writer().await.unwrap();
    w.write(&data).await.unwrap();
    assert_eq!(w.commit().await.unwrap(), id);
    assert_eq!(blob_files(tmp.path()), 1);

    // An abandoned upload leaves no temporary file.
    let mut w = store.blob_writer().await.unwrap();
    w.write(b"half an upl").await.unwrap();
    assert_eq!(temp_files(tmp.path()).len(), 1);
    drop(w);
    assert!(temp_files(tmp.path()).is_empty());
    assert_eq!(blob_files(tmp.path()), 1);

    // put_blob_file streams a file in and leaves it in place.
    let src = tmp.path().join("upload.bin");
    std::fs::write(&src, &data[..1_234_567]).unwrap();
    let f = store.put_blob_file(&src).await.unwrap();
    assert_eq!(f, BlobId::of(&data[..1_234_567]));
    assert!(src.exists());
    assert!(matches!(
        store.put_blob_file(tmp.path().join("missing")).await,
        Err(StoreError::Io { .. })
    ));
}

#[tokio::test]
async fn the_lock_refuses_a_second_open_until_the_first_is_dropped() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let clone = store.clone();
    match Store::open(tmp.path(), opts()).await {
        Err(StoreError::Locked { dir }) => assert_eq!(dir, tmp.path()),
        other => panic!("expected Locked, got {other:?}"),
    }
    drop(store);
    // A clone still holds it.
    assert!(matches!(
        Store::open(tmp.path(), opts()).await,
        Err(StoreError::Locked { .. })
    ));
    clone.close().await;
    let again = open(tmp.path()).await;
    again.put_blob(b"works".to_vec()).await.unwrap();
}

/// The lock holds when its file is unlinked by hand: the data directory itself is
/// locked, so a second store cannot open it by making a new lock file.
#[tokio::test]
async fn the_lock_holds_when_its_file_is_removed() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    std::fs::remove_file(tmp.path().join("lock")).unwrap();
    assert!(matches!(
        Store::open(tmp.path(), opts()).await,
        Err(StoreError::Locked { .. })
    ));
    store.close().await;
}

/// Stored files without their database are refused, not opened as an empty store whose
/// GC would then delete them all; an empty `blobs/` (or none) opens.
#[tokio::test]
async fn blobs_without_their_database_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let s = scene(&store, b"kept").await;
    store.close().await;
    for f in ["rayd.db", "rayd.db-wal", "rayd.db-shm"] {
        let _ = std::fs::remove_file(tmp.path().join(f));
    }
    match Store::open(tmp.path(), opts()).await {
        Err(e @ StoreError::Invalid { .. }) => {
            assert!(e.to_string().contains("no rayd.db"), "{e}");
        }
        other => panic!("expected Invalid, got {:?}", other.map(|_| ())),
    }
    let blob = tmp.path().join("blobs").join(&s.id[..2]).join(&s.id);
    assert_eq!(std::fs::read(&blob).unwrap(), b"kept");
    std::fs::remove_file(&blob).unwrap();
    open(tmp.path()).await.close().await;
}

/// A deleted scene's files (its upload and versions) go at the next `collect_pruned`,
/// not after GC's grace, so that a store bounded by `max_bytes` is not full of deleted
/// scenes; bytes another scene also stored stay.
#[tokio::test]
async fn a_deleted_scenes_files_go_at_the_next_collection() {
    let tmp = tempfile::tempdir().unwrap();
    let options = StoreOptions {
        gc_grace: Duration::from_secs(900),
        ..StoreOptions::default()
    };
    let store = Store::open(tmp.path(), options).await.unwrap();
    let s = scene(&store, b"doomed").await;
    let moved = store.put_blob(vec![7u8; 36]).await.unwrap();
    store.add_version(&s.id, &moved).await.unwrap();
    let other = scene(&store, b"other").await;
    store.add_version(&other.id, &moved).await.unwrap();
    store.delete_scene(&s.id).await.unwrap();
    let report = store.collect_pruned(true).await.unwrap();
    assert_eq!((report.deleted, report.referenced), (1, 1));
    assert!(matches!(
        store.get_blob(&s.id).await,
        Err(StoreError::NotFound { .. })
    ));
    assert_eq!(store.get_blob(moved.as_str()).await.unwrap(), vec![7u8; 36]);
    store.close().await;
}

/// A deleted or expired job's files (its result, a sequence's frames, an async trace's
/// rays) go at the next `collect_pruned`, not after GC's grace, so that deleting results
/// frees `max_bytes` at once; the same bytes stored again by a running job, not yet
/// recorded, stay until it ends and names them.
#[tokio::test]
async fn a_deleted_jobs_files_go_at_the_next_collection_unless_a_running_job_stored_them() {
    let tmp = tempfile::tempdir().unwrap();
    let options = StoreOptions {
        gc_grace: Duration::from_secs(900),
        result_ttl: Some(Duration::from_secs(3600)),
        ..StoreOptions::default()
    };
    let store = Store::open(tmp.path(), options).await.unwrap();
    let s = scene(&store, b"scene").await;
    let finish = |id: String, result: BlobId, frames: Vec<BlobId>| {
        let store = store.clone();
        async move {
            store
                .finish_job(
                    &id,
                    JobOutcome::Succeeded {
                        stats: None,
                        result: Some((result, "image/png".into())),
                        frames: frames
                            .into_iter()
                            .map(|b| (b, "image/png".into()))
                            .collect(),
                    },
                )
                .await
                .unwrap()
        }
    };
    // A finished job with a result and frames, and an async trace's rays.
    let mut with_rays = render_job(&s);
    let rays = store.put_blob(b"rays".to_vec()).await.unwrap();
    with_rays.input_blob = Some(rays.clone());
    let (a, _) = store.create_job(with_rays).await.unwrap();
    store.start_job(&a.id).await.unwrap();
    let result = store.put_blob(b"result a".to_vec()).await.unwrap();
    let frame = store.put_blob(b"frame a".to_vec()).await.unwrap();
    finish(a.id.clone(), result.clone(), vec![frame.clone()]).await;
    // Written an hour ago: a running job keeps what was written or renewed since it
    // started (less a second), as GC does.
    let hour_ago = SystemTime::now() - Duration::from_secs(3600);
    for id in [&rays, &result, &frame] {
        let path = tmp
            .path()
            .join("blobs")
            .join(&id.as_str()[..2])
            .join(id.as_str());
        let f = std::fs::File::options().write(true).open(&path).unwrap();
        f.set_modified(hour_ago).unwrap();
    }
    // Job b is running and has stored the same frame again, not yet recorded.
    let (b, _) = store.create_job(render_job(&s)).await.unwrap();
    store.start_job(&b.id).await.unwrap();
    assert_eq!(store.put_blob(b"frame a".to_vec()).await.unwrap(), frame);
    store.delete_job(&a.id).await.unwrap();
    let report = store.collect_pruned(true).await.unwrap();
    assert_eq!((report.deleted, report.kept_recent), (2, 1), "{report:?}");
    for gone in [&result, &rays] {
        assert!(matches!(
            store.get_blob(gone.as_str()).await,
            Err(StoreError::NotFound { .. })
        ));
    }
    // The kept one is tried again: while b runs it stays; once b names it, it is
    // referenced.
    assert_eq!(store.collect_pruned(true).await.unwrap().kept_recent, 1);
    let b_result = store.put_blob(b"result b".to_vec()).await.unwrap();
    let done = finish(b.id.clone(), b_result.clone(), vec![frame.clone()]).await;
    assert_eq!(store.collect_pruned(true).await.unwrap().referenced, 1);
    assert_eq!(store.get_blob(frame.as_str()).await.unwrap(), b"frame a");
    // Expired, b's files go at the next collection too, without waiting for GC's grace.
    let expires = done.expires_at.unwrap();
    assert_eq!(store.expire(expires).await.unwrap(), 1);
    let report = store.collect_pruned(true).await.unwrap();
    assert_eq!(report.deleted, 2, "{report:?}");
    assert_eq!(store.get_blob(&s.id).await.unwrap(), b"scene");
    store.close().await;
}

#[tokio::test]
async fn migrations_are_recorded_and_run_once() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let first: Vec<(i64, i64)> = sqlx::query_as(
        "SELECT version, CAST(strftime('%s', installed_on) AS INTEGER) FROM _sqlx_migrations",
    )
    .fetch_all(&store.inner.reader)
    .await
    .unwrap();
    assert_eq!(
        first.iter().map(|m| m.0).collect::<Vec<_>>(),
        [1, 2, 3],
        "every migration once, in order"
    );
    let s = scene(&store, b"kept across reopen").await;
    store.close().await;

    let store = open(tmp.path()).await;
    let second: Vec<(i64, i64)> = sqlx::query_as(
        "SELECT version, CAST(strftime('%s', installed_on) AS INTEGER) FROM _sqlx_migrations",
    )
    .fetch_all(&store.inner.reader)
    .await
    .unwrap();
    assert_eq!(first, second, "reopening ran a migration again");
    assert_eq!(store.get_scene(&s.id).await.unwrap(), s);
    // The pragmas the crash guarantees rest on.
    let mut conn = store.inner.writer.acquire().await.unwrap();
    let mode: String = sqlx::query_scalar("PRAGMA journal_mode")
        .fetch_one(&mut *conn)
        .await
        .unwrap();
    let sync: i64 = sqlx::query_scalar("PRAGMA synchronous")
        .fetch_one(&mut *conn)
        .await
        .unwrap();
    let fk: i64 = sqlx::query_scalar("PRAGMA foreign_keys")
        .fetch_one(&mut *conn)
        .await
        .unwrap();
    assert_eq!((mode.as_str(), sync, fk), ("wal", 2, 1));
}

#[tokio::test]
async fn a_database_from_a_newer_rayd_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    sqlx::query(
        "INSERT INTO _sqlx_migrations (version, description, success, checksum, execution_time) \
         VALUES (99, 'from the future', TRUE, X'00', 0)",
    )
    .execute(&store.inner.writer)
    .await
    .unwrap();
    store.close().await;
    assert!(matches!(
        Store::open(tmp.path(), opts()).await,
        Err(StoreError::Migrate(_))
    ));
}

#[tokio::test]
async fn scenes_are_created_once_per_content_and_listed_in_pages() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let blob = store.put_blob(b"scene 0".to_vec()).await.unwrap();
    let new = NewScene {
        blob: blob.clone(),
        content_type: "model/gltf-binary".into(),
        name: None,
        summary: r#"{"triangles": 12}"#.into(),
    };
    let (s, created) = store.create_scene(new.clone()).await.unwrap();
    assert!(created);
    assert_eq!(s.id, blob.as_str());
    assert_eq!(s.latest_version, 1);
    assert_eq!(s.name, None);
    let (again, created) = store.create_scene(new.clone()).await.unwrap();
    assert!(!created);
    assert_eq!(again, s);
    assert_eq!(store.get_scene(&s.id).await.unwrap(), s);
    let v1 = store.get_version(&s.id, 1).await.unwrap();
    assert_eq!(v1.blob, s.id);

    // Refusals, each saying which field.
    let bad = |f: fn(&mut NewScene)| {
        let mut n = new.clone();
        f(&mut n);
        n
    };
    for (n, field) in [
        (bad(|n| n.summary = "{not json".into()), "summary"),
        (bad(|n| n.content_type = String::new()), "content_type"),
        (bad(|n| n.name = Some("a\nb".into())), "name"),
    ] {
        match store.create_scene(n).await {
            Err(StoreError::Invalid { field: f, .. }) => assert_eq!(f, field),
            other => panic!("expected Invalid {field}, got {other:?}"),
        }
    }
    // A scene can only name a stored blob.
    let ghost = BlobId::of(b"never stored");
    assert!(matches!(
        store
            .create_scene(NewScene {
                blob: ghost,
                ..new.clone()
            })
            .await,
        Err(StoreError::NotFound { what: "blob", .. })
    ));

    let mut made = vec![(s.created_at, s.id.clone())];
    for i in 1..7 {
        let s = scene(&store, format!("scene {i}").as_bytes()).await;
        made.push((s.created_at, s.id));
    }
    // Creation order; within one millisecond, by id (a stable total order).
    made.sort();
    let ids: Vec<String> = made.into_iter().map(|(_, id)| id).collect();
    let mut seen = Vec::new();
    let mut token: Option<String> = None;
    let mut pages = 0;
    loop {
        let (page, next) = store.list_scenes(3, token.as_deref()).await.unwrap();
        assert!(page.len() <= 3);
        seen.extend(page.into_iter().map(|s| s.id));
        pages += 1;
        match next {
            Some(t) => token = Some(t),
            None => break,
        }
    }
    assert_eq!(pages, 3);
    assert_eq!(seen, ids, "pages in creation order, each scene once");
    let (all, next) = store.list_scenes(0, None).await.unwrap();
    assert_eq!((all.len(), next), (7, None));

    // Hex of `s1:1:a` and of `s1:1:' OR 1=1 --`: well-formed tokens whose id is no
    // scene id.
    let hex = |t: &str| t.bytes().map(|b| format!("{b:02x}")).collect::<String>();
    let forged = [
        hex("s1:1:a"),
        hex("s1:1:' OR 1=1 --"),
        hex(&format!("s1:-5:{}", ids[0])),
    ];
    for bad in ["zz", "00", "7331", &"ab".repeat(300)]
        .into_iter()
        .chain(forged.iter().map(String::as_str))
    {
        assert!(matches!(
            store.list_scenes(3, Some(bad)).await,
            Err(StoreError::BadPageToken)
        ));
    }
    // AIP-158: an empty token is the first page.
    let (first, _) = store.list_scenes(3, Some("")).await.unwrap();
    assert_eq!(first[0].id, ids[0]);
    // A job list's token is not a scene list's.
    let j = store.create_job(render_job(&s)).await.unwrap().0;
    store.create_job(render_job(&s)).await.unwrap();
    let (_, jt) = store.list_jobs(1, None).await.unwrap();
    assert!(matches!(
        store.list_scenes(3, jt.as_deref()).await,
        Err(StoreError::BadPageToken)
    ));
    assert_eq!(store.get_job(&j.id).await.unwrap().id, j.id);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_versions_get_consecutive_numbers() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let s = scene(&store, b"base").await;
    let mut tasks = Vec::new();
    for i in 0..8u8 {
        let store = store.clone();
        let id = s.id.clone();
        tasks.push(tokio::spawn(async move {
            let blob = store.put_blob(vec![i; 36]).await.unwrap();
            store.add_version(&id, &blob).await.unwrap().0
        }));
    }
    let mut versions = Vec::new();
    for t in tasks {
        versions.push(t.await.unwrap());
    }
    let mut numbers: Vec<i64> = versions.iter().map(|v| v.version).collect();
    numbers.sort();
    assert_eq!(numbers, (2..=9).collect::<Vec<_>>());
    assert_eq!(store.get_scene(&s.id).await.unwrap().latest_version, 9);
    for v in &versions {
        let got = store.get_version(&s.id, v.version).await.unwrap();
        assert_eq!(&got, v);
        assert_eq!(store.get_blob(&got.blob).await.unwrap().len(), 36);
    }
    assert_eq!(store.list_versions(&s.id).await.unwrap().len(), 9);
    assert!(matches!(
        store.get_version(&s.id, 10).await,
        Err(StoreError::NotFound {
            what: "version",
            ..
        })
    ));
    let ghost = "1".repeat(64);
    assert!(matches!(
        store.get_version(&ghost, 1).await,
        Err(StoreError::NotFound { what: "scene", .. })
    ));
    let blob = store.put_blob(b"x".to_vec()).await.unwrap();
    assert!(matches!(
        store.add_version(&ghost, &blob).await,
        Err(StoreError::NotFound { what: "scene", .. })
    ));
    assert!(matches!(
        store.add_version(&s.id, &BlobId::of(b"not stored")).await,
        Err(StoreError::NotFound { what: "blob", .. })
    ));
    assert_eq!(store.get_scene(&s.id).await.unwrap().latest_version, 9);
}

/// With `keep_versions`, each new version deletes those older than the newest `keep`,
/// except version 1 and versions a job names; those go at the upkeep's `prune_versions`
/// once their jobs are gone, and GC then frees their blobs.
#[tokio::test]
async fn old_versions_go_unless_a_job_names_them() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open_keeping(tmp.path(), 2).await;
    let s = scene(&store, b"moving").await;
    let numbers = |vs: Vec<VersionRecord>| vs.iter().map(|v| v.version).collect::<Vec<_>>();
    let mut blobs = Vec::new();
    let mut pruned = Vec::new();
    for i in 2..=7u8 {
        // Version 7 repeats version 2's positions: the same blob.
        let blob = store
            .put_blob(vec![if i == 7 { 2 } else { i }; 36])
            .await
            .unwrap();
        blobs.push(blob.clone());
        let (v, p) = store.add_version(&s.id, &blob).await.unwrap();
        assert_eq!(v.version, i64::from(i));
        pruned.push(p);
        if i == 3 {
            // A job on version 3 keeps it past its turn.
            store
                .create_job(NewJob {
                    version: 3,
                    ..render_job(&s)
                })
                .await
                .unwrap();
        }
    }
    // Version 4 deleted 2; 5 would have deleted 3 (named by the job); 6 deleted 4, 7 5.
    assert_eq!(
        pruned,
        vec![vec![], vec![], vec![2], vec![], vec![4], vec![5]]
    );
    assert_eq!(
        numbers(store.list_versions(&s.id).await.unwrap()),
        [1, 3, 6, 7]
    );
    assert!(matches!(
        store.get_version(&s.id, 2).await,
        Err(StoreError::NotFound {
            what: "version",
            ..
        })
    ));
    // Nothing to prune while the job exists.
    assert_eq!(store.prune_versions().await.unwrap(), vec![]);
    let collected = store.collect_pruned(true).await.unwrap();
    assert_eq!(
        (collected.deleted, collected.referenced),
        (2, 1),
        "the blobs of versions 4 and 5; 2's is 7's too: {collected:?}"
    );
    let blob_of = |i: usize| store.get_blob(blobs[i].as_str());
    assert!(blob_of(2).await.is_err());
    assert!(blob_of(3).await.is_err());
    for i in [0, 1, 4] {
        assert_eq!(blob_of(i).await.unwrap().len(), 36, "blob {i}");
    }
    assert_eq!(
        store.collect_pruned(true).await.unwrap(),
        GcReport::default()
    );

    // Once the job has gone, the upkeep deletes version 3.
    let jobs = store.list_jobs(10, None).await.unwrap().0;
    assert_eq!(jobs.len(), 1);
    store.cancel_job(&jobs[0].id).await.unwrap();
    assert_eq!(
        store.prune_versions().await.unwrap(),
        vec![],
        "a cancelled job's record keeps it"
    );
    store.delete_job(&jobs[0].id).await.unwrap();
    assert_eq!(
        store.prune_versions().await.unwrap(),
        vec![(s.id.clone(), 3)]
    );
    assert_eq!(
        numbers(store.list_versions(&s.id).await.unwrap()),
        [1, 6, 7]
    );
    assert_eq!(store.collect_pruned(true).await.unwrap().deleted, 1);
    assert!(blob_of(1).await.is_err());
}

/// A blob stored again while its deleted version's copy awaits `collect_pruned`, but not
/// yet recorded, is collected all the same: recording it then fails with `NotFound`, never
/// naming a missing file, and storing it again works (what the service's retry does).
#[tokio::test]
async fn a_pruned_blob_stored_again_before_its_record_must_be_stored_once_more() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open_keeping(tmp.path(), 1).await;
    let s = scene(&store, b"frames").await;
    let first = store.put_blob(vec![1u8; 36]).await.unwrap();
    store.add_version(&s.id, &first).await.unwrap();
    let second = store.put_blob(vec![2u8; 36]).await.unwrap();
    assert_eq!(store.add_version(&s.id, &second).await.unwrap().1, vec![2]);
    // Version 2's bytes arrive again and are stored; the collection runs before the record.
    let again = store.put_blob(vec![1u8; 36]).await.unwrap();
    assert_eq!(store.collect_pruned(true).await.unwrap().deleted, 1);
    assert!(matches!(
        store.add_version(&s.id, &again).await,
        Err(StoreError::NotFound { what: "blob", .. })
    ));
    let again = store.put_blob(vec![1u8; 36]).await.unwrap();
    let (v, pruned) = store.add_version(&s.id, &again).await.unwrap();
    assert_eq!((v.version, pruned), (4, vec![3]));
    assert_eq!(store.get_blob(again.as_str()).await.unwrap(), vec![1u8; 36]);
}

#[tokio::test]
async fn jobs_move_through_their_states_once() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let s = scene(&store, b"scene").await;
    let (job, created) = store.create_job(render_job(&s)).await.unwrap();
    assert!(created);
    assert_eq!(job.id.len(), 32);
    assert_eq!(job.state, JobState::Queued);
    assert_eq!(
        (job.progress, job.started_at, job.result.clone()),
        (0.0, None, None)
    );

    let started = store.start_job(&job.id).await.unwrap();
    assert_eq!(started.state, JobState::Running);
    assert!(started.started_at.is_some());
    assert!(matches!(
        store.start_job(&job.id).await,
        Err(StoreError::Conflict(_))
    ));
    store.set_progress(&job.id, 0.5).await.unwrap();
    assert_eq!(store.get_job(&job.id).await.unwrap().progress, 0.5);
    assert!(matches!(
        store.set_progress(&job.id, 1.5).await,
        Err(StoreError::Invalid {
            field: "progress",
            ..
        })
    ));
    assert!(matches!(
        store.set_progress(&job.id, f64::NAN).await,
        Err(StoreError::Invalid { .. })
    ));
    assert!(matches!(
        store.delete_job(&job.id).await,
        Err(StoreError::Conflict(_))
    ));

    let png = store.put_blob(b"\x89PNG frame".to_vec()).await.unwrap();
    let f0 = store.put_blob(b"frame 0".to_vec()).await.unwrap();
    let f1 = store.put_blob(b"frame 1".to_vec()).await.unwrap();
    let done = store
        .finish_job(
            &job.id,
            JobOutcome::Succeeded {
                stats: Some(r#"{"rays": 16}"#.into()),
                result: Some((png.clone(), "image/png".into())),
                frames: vec![
                    (f0.clone(), "image/png".into()),
                    (f1.clone(), "image/png".into()),
                ],
            },
        )
        .await
        .unwrap();
    assert_eq!(done.state, JobState::Succeeded);
    assert_eq!(done.progress, 1.0);
    assert_eq!(done.result.as_ref().unwrap().blob, png.as_str());
    let frames: Vec<&str> = done.result_frames.iter().map(|f| f.blob.as_str()).collect();
    assert_eq!(frames, [f0.as_str(), f1.as_str()]);
    let ttl = store.options().result_ttl.unwrap().as_millis() as i64;
    assert_eq!(done.expires_at, Some(done.finished_at.unwrap() + ttl));
    assert_eq!(store.get_job(&job.id).await.unwrap(), done);
    assert!(matches!(
        store.cancel_job(&job.id).await,
        Err(StoreError::Conflict(_))
    ));
    assert!(matches!(
        store
            .finish_job(
                &job.id,
                JobOutcome::Failed {
                    error: "late".into(),
                    stats: None
                }
            )
            .await,
        Err(StoreError::Conflict(_))
    ));

    // Failure, cancellation of a queued and of a running job.
    let (a, _) = store.create_job(render_job(&s)).await.unwrap();
    store.start_job(&a.id).await.unwrap();
    let failed = store
        .finish_job(
            &a.id,
            JobOutcome::Failed {
                error: "boom".into(),
                stats: None,
            },
        )
        .await
        .unwrap();
    assert_eq!(
        (failed.state, failed.error.as_deref()),
        (JobState::Failed, Some("boom"))
    );
    let (b, _) = store.create_job(render_job(&s)).await.unwrap();
    assert_eq!(
        store.cancel_job(&b.id).await.unwrap().state,
        JobState::Cancelled
    );
    assert!(matches!(
        store.start_job(&b.id).await,
        Err(StoreError::Conflict(_))
    ));
    let (c, _) = store.create_job(render_job(&s)).await.unwrap();
    store.start_job(&c.id).await.unwrap();
    let cancelled = store.cancel_job(&c.id).await.unwrap();
    assert_eq!(cancelled.state, JobState::Cancelled);
    assert!(cancelled.expires_at.is_some());
    // A result can only name stored blobs.
    let (d, _) = store.create_job(render_job(&s)).await.unwrap();
    store.start_job(&d.id).await.unwrap();
    let ghost = BlobId::of(b"not stored");
    assert!(matches!(
        store
            .finish_job(
                &d.id,
                JobOutcome::Succeeded {
                    stats: None,
                    result: Some((ghost, "image/png".into())),
                    frames: vec![]
                }
            )
            .await,
        Err(StoreError::NotFound { what: "blob", .. })
    ));
    assert_eq!(store.get_job(&d.id).await.unwrap().state, JobState::Running);

    store.delete_job(&job.id).await.unwrap();
    assert!(matches!(
        store.get_job(&job.id).await,
        Err(StoreError::NotFound { .. })
    ));
    assert!(matches!(
        store.delete_job(&job.id).await,
        Err(StoreError::NotFound { .. })
    ));
    let rows: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM job_results")
        .fetch_one(&store.inner.reader)
        .await
        .unwrap();
    assert_eq!(rows, 0, "frame results go with their job");
}

#[tokio::test]
async fn job_submissions_are_checked_and_idempotent() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let s = scene(&store, b"scene").await;
    let keyed = NewJob {
        idempotency_key: Some("retry-me".into()),
        input_blob: None,
        ..render_job(&s)
    };
    let (first, created) = store.create_job(keyed.clone()).await.unwrap();
    assert!(created);
    let (second, created) = store.create_job(keyed.clone()).await.unwrap();
    assert!(!created);
    assert_eq!(first, second);
    assert!(matches!(
        store
            .create_job(NewJob {
                request: r#"{"width": 8}"#.into(),
                ..keyed.clone()
            })
            .await,
        Err(StoreError::Conflict(_))
    ));
    assert!(matches!(
        store
            .create_job(NewJob {
                priority: 101,
                ..render_job(&s)
            })
            .await,
        Err(StoreError::Invalid {
            field: "priority",
            ..
        })
    ));
    assert!(matches!(
        store
            .create_job(NewJob {
                request: "nope".into(),
                ..render_job(&s)
            })
            .await,
        Err(StoreError::Invalid {
            field: "request",
            ..
        })
    ));
    assert!(matches!(
        store
            .create_job(NewJob {
                version: 2,
                ..render_job(&s)
            })
            .await,
        Err(StoreError::NotFound {
            what: "version",
            ..
        })
    ));
    assert!(matches!(
        store
            .create_job(NewJob {
                scene_id: "2".repeat(64),
                ..render_job(&s)
            })
            .await,
        Err(StoreError::NotFound { what: "scene", .. })
    ));
    assert!(matches!(
        store
            .create_job(NewJob {
                scene_id: "../x".into(),
                ..render_job(&s)
            })
            .await,
        Err(StoreError::NotFound { what: "scene", .. })
    ));

    // Pages of jobs, and the scheduler's order.
    let mut made = vec![(first.created_at, first.id.clone())];
    for p in [10u8, 90, 50, 90] {
        let (j, _) = store
            .create_job(NewJob {
                priority: p,
                kind: JobKind::Trace,
                ..render_job(&s)
            })
            .await
            .unwrap();
        made.push((j.created_at, j.id));
    }
    made.sort();
    let ids: Vec<String> = made.into_iter().map(|(_, id)| id).collect();
    let (p1, t1) = store.list_jobs(2, None).await.unwrap();
    let (p2, t2) = store.list_jobs(2, t1.as_deref()).await.unwrap();
    let (p3, t3) = store.list_jobs(2, t2.as_deref()).await.unwrap();
    assert_eq!(t3, None);
    let listed: Vec<String> = p1
        .iter()
        .chain(&p2)
        .chain(&p3)
        .map(|j| j.id.clone())
        .collect();
    assert_eq!(listed, ids);
    assert!(matches!(
        store.list_jobs(2, Some("abc")).await,
        Err(StoreError::BadPageToken)
    ));
    let queued: Vec<u8> = store
        .queued_jobs()
        .await
        .unwrap()
        .iter()
        .map(|j| j.priority)
        .collect();
    assert_eq!(queued, [90, 90, 50, 50, 10]);
}

#[tokio::test]
async fn recover_requeues_jobs_a_crash_left_running() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let s = scene(&store, b"scene").await;
    let (running, _) = store.create_job(render_job(&s)).await.unwrap();
    store.start_job(&running.id).await.unwrap();
    store.set_progress(&running.id, 0.7).await.unwrap();
    let (queued, _) = store
        .create_job(NewJob {
            priority: 10,
            ..render_job(&s)
        })
        .await
        .unwrap();
    let (done, _) = store.create_job(render_job(&s)).await.unwrap();
    store.start_job(&done.id).await.unwrap();
    store
        .finish_job(
            &done.id,
            JobOutcome::Failed {
                error: "x".into(),
                stats: None,
            },
        )
        .await
        .unwrap();
    drop(store); // the "crash": no clean shutdown of the running job

    let store = open(tmp.path()).await;
    let back = store.recover().await.unwrap();
    let ids: Vec<&str> = back.iter().map(|j| j.id.as_str()).collect();
    assert_eq!(ids, [running.id.as_str(), queued.id.as_str()]);
    let r = store.get_job(&running.id).await.unwrap();
    assert_eq!(
        (r.state, r.progress, r.started_at),
        (JobState::Queued, 0.0, None)
    );
    assert_eq!(
        store.get_job(&done.id).await.unwrap().state,
        JobState::Failed
    );
    // It runs again normally.
    store.start_job(&running.id).await.unwrap();
}

/// Past its `expires_at` a job is gone to every reader at once, before the cleanup pass
/// (once a minute) deletes its rows: not answered, not listed, its result not served.
#[tokio::test]
async fn an_expired_job_is_gone_before_cleanup_deletes_it() {
    let tmp = tempfile::tempdir().unwrap();
    let options = StoreOptions {
        result_ttl: Some(Duration::from_millis(1)),
        ..opts()
    };
    let store = Store::open(tmp.path(), options).await.unwrap();
    let s = scene(&store, b"scene").await;
    let (job, _) = store.create_job(render_job(&s)).await.unwrap();
    let (queued, _) = store.create_job(render_job(&s)).await.unwrap();
    store.start_job(&job.id).await.unwrap();
    store
        .finish_job(
            &job.id,
            JobOutcome::Succeeded {
                stats: None,
                result: None,
                frames: vec![],
            },
        )
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(20)).await;
    assert!(matches!(
        store.get_job(&job.id).await,
        Err(StoreError::NotFound { .. })
    ));
    let (listed, next) = store.list_jobs(10, None).await.unwrap();
    let ids: Vec<&str> = listed.iter().map(|j| j.id.as_str()).collect();
    assert_eq!((ids, next), (vec![queued.id.as_str()], None));
    // Its rows are still there until the cleanup pass.
    assert_eq!(store.expire(super::records::now_millis()).await.unwrap(), 1);
}

#[tokio::test]
async fn finished_jobs_expire_after_their_ttl_and_their_blobs_are_collected() {
    let tmp = tempfile::tempdir().unwrap();
    let options = StoreOptions {
        result_ttl: Some(Duration::from_secs(3600)),
        ..opts()
    };
    let store = Store::open(tmp.path(), options).await.unwrap();
    let s = scene(&store, b"scene").await;
    let (job, _) = store.create_job(render_job(&s)).await.unwrap();
    let (open_job, _) = store.create_job(render_job(&s)).await.unwrap();
    store.start_job(&job.id).await.unwrap();
    let result = store.put_blob(b"result".to_vec()).await.unwrap();
    let done = store
        .finish_job(
            &job.id,
            JobOutcome::Succeeded {
                stats: None,
                result: Some((result.clone(), "application/octet-stream".into())),
                frames: vec![],
            },
        )
        .await
        .unwrap();
    let expires = done.expires_at.unwrap();
    assert_eq!(expires, done.finished_at.unwrap() + 3_600_000);
    assert_eq!(
        store.gc().await.unwrap().deleted,
        0,
        "a result is referenced"
    );
    assert_eq!(store.expire(expires - 1).await.unwrap(), 0);
    assert_eq!(
        store.get_job(&job.id).await.unwrap().state,
        JobState::Succeeded
    );
    // Far in the future: only the finished job goes; a queued one never expires.
    assert_eq!(store.expire(expires + 1_000_000_000).await.unwrap(), 1);
    assert!(matches!(
        store.get_job(&job.id).await,
        Err(StoreError::NotFound { .. })
    ));
    assert_eq!(
        store.get_job(&open_job.id).await.unwrap().state,
        JobState::Queued
    );
    let report = store.gc().await.unwrap();
    assert_eq!(report.deleted, 1);
    assert_eq!(report.freed_bytes, 6);
    assert!(matches!(
        store.get_blob(result.as_str()).await,
        Err(StoreError::NotFound { .. })
    ));
    assert_eq!(store.get_blob(&s.id).await.unwrap(), b"scene");

    // Without a TTL, results stay until deleted.
    drop(store);
    let store = Store::open(
        tmp.path(),
        StoreOptions {
            result_ttl: None,
            ..opts()
        },
    )
    .await
    .unwrap();
    store.start_job(&open_job.id).await.unwrap();
    let f = store
        .finish_job(
            &open_job.id,
            JobOutcome::Failed {
                error: "e".into(),
                stats: None,
            },
        )
        .await
        .unwrap();
    assert_eq!(f.expires_at, None);
    assert_eq!(store.expire(i64::MAX).await.unwrap(), 0);
}

#[tokio::test]
async fn deleting_a_scene_takes_its_versions_and_jobs_in_one_transaction() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let s = scene(&store, b"doomed").await;
    let keep = scene(&store, b"kept").await;
    let v2 = store.put_blob(vec![1u8; 36]).await.unwrap();
    store.add_version(&s.id, &v2).await.unwrap();
    let (queued, _) = store.create_job(render_job(&s)).await.unwrap();
    let (running, _) = store
        .create_job(NewJob {
            version: 2,
            ..render_job(&s)
        })
        .await
        .unwrap();
    store.start_job(&running.id).await.unwrap();
    let (other, _) = store.create_job(render_job(&keep)).await.unwrap();

    let stopped = store.delete_scene(&s.id).await.unwrap();
    let mut expected = vec![queued.id.clone(), running.id.clone()];
    expected.sort();
    let mut got = stopped.clone();
    got.sort();
    assert_eq!(got, expected);
    assert!(matches!(
        store.get_scene(&s.id).await,
        Err(StoreError::NotFound { .. })
    ));
    assert!(matches!(
        store.get_job(&queued.id).await,
        Err(StoreError::NotFound { .. })
    ));
    assert!(matches!(
        store
            .finish_job(
                &running.id,
                JobOutcome::Failed {
                    error: "x".into(),
                    stats: None
                }
            )
            .await,
        Err(StoreError::NotFound { what: "job", .. })
    ));
    assert!(matches!(
        store.delete_scene(&s.id).await,
        Err(StoreError::NotFound { .. })
    ));
    assert_eq!(
        store.get_job(&other.id).await.unwrap().state,
        JobState::Queued
    );
    let report = store.gc().await.unwrap();
    assert_eq!(report.deleted, 2, "the upload and version 2");
    assert_eq!(blob_files(tmp.path()), 1);
    assert_eq!(store.get_blob(&keep.id).await.unwrap(), b"kept");
}

#[tokio::test]
async fn gc_keeps_young_and_referenced_blobs() {
    let tmp = tempfile::tempdir().unwrap();
    let options = StoreOptions {
        gc_grace: Duration::from_secs(3600),
        ..opts()
    };
    let store = Store::open(tmp.path(), options).await.unwrap();
    let s = scene(&store, b"referenced").await;
    let young = store.put_blob(b"young".to_vec()).await.unwrap();
    let old = store.put_blob(b"old".to_vec()).await.unwrap();
    age(
        &store.blob_path(old.as_str()).await.unwrap(),
        Duration::from_secs(7200),
    );
    age(
        &store.blob_path(&s.id).await.unwrap(),
        Duration::from_secs(7200),
    );
    let report = store.gc().await.unwrap();
    assert_eq!(
        report,
        GcReport {
            deleted: 1,
            freed_bytes: 3,
            kept_recent: 1,
            referenced: 1
        }
    );
    assert!(store.get_blob(young.as_str()).await.is_ok());
    assert!(store.get_blob(&s.id).await.is_ok());
    assert!(matches!(
        store.get_blob(old.as_str()).await,
        Err(StoreError::NotFound { .. })
    ));

    // Putting bytes again renews an old unreferenced blob, so GC keeps it.
    let again = store.put_blob(b"young".to_vec()).await.unwrap();
    age(
        &store.blob_path(again.as_str()).await.unwrap(),
        Duration::from_secs(7200),
    );
    store.put_blob(b"young".to_vec()).await.unwrap();
    assert_eq!(store.gc().await.unwrap().deleted, 0);
}

/// A sequence's frames are stored as they are rendered and named by the job's record
/// only at its end: blobs written since the oldest running job started are kept past the
/// grace, so a render longer than the grace keeps its first frames; older ones still go.
#[tokio::test]
async fn gc_keeps_what_a_running_job_has_written_however_old() {
    let tmp = tempfile::tempdir().unwrap();
    let options = StoreOptions {
        gc_grace: Duration::from_secs(900),
        ..opts()
    };
    let store = Store::open(tmp.path(), options).await.unwrap();
    let s = scene(&store, b"scene").await;
    let (job, _) = store.create_job(render_job(&s)).await.unwrap();
    store.start_job(&job.id).await.unwrap();
    // Started three hours ago; its first frame written two hours ago.
    let hours_ago = |h: u64| {
        (SystemTime::now() - Duration::from_secs(3600 * h))
            .duration_since(SystemTime::UNIX_EPOCH)
            .unwrap()
            .as_millis() as i64
    };
    sqlx::query("UPDATE jobs SET started_at = ? WHERE id = ?")
        .bind(hours_ago(3))
        .bind(&job.id)
        .execute(&store.inner.writer)
        .await
        .unwrap();
    let frame = store.put_blob(b"frame 0".to_vec()).await.unwrap();
    age(
        &store.blob_path(frame.as_str()).await.unwrap(),
        Duration::from_secs(7200),
    );
    let stale = store
        .put_blob(b"from before the job".to_vec())
        .await
        .unwrap();
    age(
        &store.blob_path(stale.as_str()).await.unwrap(),
        Duration::from_secs(4 * 3600),
    );
    assert_eq!(store.gc().await.unwrap().deleted, 1);
    assert!(store.get_blob(stale.as_str()).await.is_err());
    let end = JobOutcome::Succeeded {
        stats: None,
        result: None,
        frames: vec![(frame.clone(), "image/png".into())],
    };
    let ended = store.finish_job(&job.id, end).await.unwrap();
    assert_eq!(ended.state, JobState::Succeeded);
    assert_eq!(store.get_blob(frame.as_str()).await.unwrap(), b"frame 0");
}

/// A job's input blob (an async trace's rays) is kept for as long as the job's record
/// is, however long it waits in the queue, and collected once the job is deleted.
#[tokio::test]
async fn gc_keeps_a_jobs_input_while_the_job_exists() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let s = scene(&store, b"scene").await;
    let rays = store.put_blob(b"rays".to_vec()).await.unwrap();
    let (job, _) = store
        .create_job(NewJob {
            kind: JobKind::Trace,
            input_blob: Some(rays.clone()),
            ..render_job(&s)
        })
        .await
        .unwrap();
    // Grace 0: only the reference keeps it, queued, running and ended alike.
    assert_eq!(store.gc().await.unwrap().deleted, 0);
    store.start_job(&job.id).await.unwrap();
    assert_eq!(store.gc().await.unwrap().deleted, 0);
    store.cancel_job(&job.id).await.unwrap();
    assert_eq!(store.gc().await.unwrap().deleted, 0);
    assert_eq!(store.get_blob(rays.as_str()).await.unwrap(), b"rays");
    store.delete_job(&job.id).await.unwrap();
    assert_eq!(store.gc().await.unwrap().deleted, 1);
    assert!(store.get_blob(rays.as_str()).await.is_err());
}

/// Uploads of the same bytes race GC (grace 0, the worst case) from several tasks: a record
/// may fail to commit (its blob was collected between put and record, reported as
/// `NotFound { what: "blob" }`), but no committed record ever names a missing blob.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn gc_never_races_an_upload_of_the_same_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let gc = {
        let (store, stop) = (store.clone(), stop.clone());
        tokio::spawn(async move {
            let mut runs = 0u32;
            let mut deleted = 0;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                deleted += store.gc().await.unwrap().deleted;
                runs += 1;
                tokio::time::sleep(Duration::from_micros(200 * (runs % 5) as u64)).await;
            }
            (runs, deleted)
        })
    };
    let mut uploaders = Vec::new();
    for t in 0..3u8 {
        let store = store.clone();
        uploaders.push(tokio::spawn(async move {
            let mut collected = 0;
            for round in 0..40u8 {
                // The same four byte strings again and again: each upload meets the garbage
                // its predecessor left (its scene deleted below), which GC is after.
                let bytes = vec![t * 4 + round % 4; 1000];
                loop {
                    let blob = store.put_blob(bytes.clone()).await.unwrap();
                    match store
                        .create_scene(NewScene {
                            blob: blob.clone(),
                            content_type: "application/x-rayd-tri".into(),
                            name: None,
                            summary: "{}".into(),
                        })
                        .await
                    {
                        Ok((scene, _)) => {
                            // Referenced now: GC must keep it.
                            assert_eq!(store.get_blob(&scene.id).await.unwrap(), bytes);
                            store.delete_scene(&scene.id).await.unwrap();
                            break;
                        }
                        // Collected between put and record: refused, never dangling.
                        Err(StoreError::NotFound { what: "blob", .. }) => collected += 1,
                        Err(e) => panic!("unexpected {e}"),
                    }
                    assert!(collected < 10_000, "uploads starved by GC");
                }
            }
            collected
        }));
    }
    let mut collected = 0;
    for u in uploaders {
        collected += u.await.unwrap();
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let (runs, deleted) = gc.await.unwrap();
    assert!(
        runs > 0 && deleted > 0,
        "GC ran ({runs}) and collected ({deleted}; {collected} uploads refused)"
    );
    // Every record left names a blob that is there and intact.
    for blob in sqlx::query_scalar::<_, String>("SELECT blob FROM scene_versions")
        .fetch_all(&store.inner.reader)
        .await
        .unwrap()
    {
        store.get_blob(&blob).await.unwrap();
    }

    // With a grace period, uploads always win.
    drop(store);
    let store = Store::open(
        tmp.path(),
        StoreOptions {
            gc_grace: Duration::from_secs(60),
            ..opts()
        },
    )
    .await
    .unwrap();
    let gc = {
        let store = store.clone();
        tokio::spawn(async move {
            for _ in 0..50 {
                store.gc().await.unwrap();
                tokio::task::yield_now().await;
            }
        })
    };
    for round in 0..30u8 {
        let blob = store.put_blob(vec![round; 64]).await.unwrap();
        store
            .create_scene(NewScene {
                blob,
                content_type: "application/x-rayd-tri".into(),
                name: None,
                summary: "{}".into(),
            })
            .await
            .unwrap();
    }
    gc.await.unwrap();
}

#[tokio::test]
async fn leftovers_of_a_crash_are_invisible_and_cleaned() {
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let s = scene(&store, b"committed").await;
    // What a writer killed mid-way leaves: a blob written but never recorded, temporary
    // files of a put and of a stream.
    let orphan = store.put_blob(b"orphan".to_vec()).await.unwrap();
    drop(store);
    let shard = tmp.path().join("blobs").join(&s.id[..2]);
    std::fs::write(shard.join(".tmpCRASH"), b"half").unwrap();
    std::fs::write(tmp.path().join("blobs/tmp/.tmpSTREAM"), b"half a stream").unwrap();

    let store = open(tmp.path()).await;
    assert!(
        temp_files(tmp.path()).is_empty(),
        "open removes temporary files"
    );
    let (scenes, _) = store.list_scenes(0, None).await.unwrap();
    assert_eq!(scenes.len(), 1);
    assert_eq!(store.get_blob(&s.id).await.unwrap(), b"committed");
    let report = store.gc().await.unwrap();
    assert_eq!((report.deleted, report.referenced), (1, 1));
    assert!(matches!(
        store.get_blob(orphan.as_str()).await,
        Err(StoreError::NotFound { .. })
    ));
}

#[tokio::test]
async fn a_full_store_fails_cleanly_and_works_again_once_space_returns() {
    let tmp = tempfile::tempdir().unwrap();
    let options = StoreOptions {
        max_bytes: Some(1000),
        ..opts()
    };
    let store = Store::open(tmp.path(), options.clone()).await.unwrap();
    let big = scene(&store, &[7u8; 600]).await;
    assert_eq!(store.blob_bytes(), Some(600));
    match store.put_blob(vec![8u8; 600]).await {
        Err(StoreError::Full { path, detail }) => {
            assert!(path.starts_with(tmp.path().join("blobs")), "{path:?}");
            assert!(detail.contains("1000"), "{detail}");
        }
        other => panic!("expected Full, got {other:?}"),
    }
    // A stream that runs out of space mid-way leaves nothing.
    let mut w = store.blob_writer().await.unwrap();
    w.write(&[9u8; 300]).await.unwrap();
    assert!(matches!(
        w.write(&[9u8; 300]).await,
        Err(StoreError::Full { .. })
    ));
    assert!(matches!(
        w.write(b"more").await,
        Err(StoreError::Conflict(_))
    ));
    drop(w);
    assert!(temp_files(tmp.path()).is_empty());
    assert_eq!(blob_files(tmp.path()), 1);
    assert_eq!(store.blob_bytes(), Some(600));
    // Re-putting what is already there needs no space.
    assert_eq!(
        store.put_blob(vec![7u8; 600]).await.unwrap().as_str(),
        big.id
    );
    // Small writes still fit; then free space and the big one fits.
    scene(&store, &[1u8; 100]).await;
    store.delete_scene(&big.id).await.unwrap();
    assert_eq!(store.gc().await.unwrap().freed_bytes, 600);
    let s = scene(&store, &[8u8; 600]).await;
    assert_eq!(store.get_blob(&s.id).await.unwrap(), vec![8u8; 600]);
    // The count survives a reopen.
    drop(store);
    let store = Store::open(tmp.path(), options).await.unwrap();
    assert_eq!(store.blob_bytes(), Some(700));
}

#[tokio::test]
async fn a_full_database_rolls_back_and_recovers() {
    let tmp = tempfile::tempdir().unwrap();
    let options = StoreOptions {
        max_db_bytes: Some(256 * 1024),
        ..opts()
    };
    let store = Store::open(tmp.path(), options).await.unwrap();
    let blob = store.put_blob(b"scene".to_vec()).await.unwrap();
    let huge = format!("{{\"pad\": \"{}\"}}", "x".repeat(400 * 1024));
    match store
        .create_scene(NewScene {
            blob: blob.clone(),
            content_type: "model/gltf-binary".into(),
            name: None,
            summary: huge,
        })
        .await
    {
        Err(StoreError::Full { .. }) => {}
        other => panic!("expected Full, got {other:?}"),
    }
    // Nothing half-written: no scene, no version 1.
    assert!(matches!(
        store.get_scene(blob.as_str()).await,
        Err(StoreError::NotFound { .. })
    ));
    let versions: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM scene_versions")
        .fetch_one(&store.inner.reader)
        .await
        .unwrap();
    assert_eq!(versions, 0);
    let (s, created) = store
        .create_scene(NewScene {
            blob,
            content_type: "model/gltf-binary".into(),
            name: None,
            summary: "{}".into(),
        })
        .await
        .unwrap();
    assert!(created);
    assert_eq!(s.latest_version, 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_backup_taken_while_writing_opens_as_a_store() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    // A grace period, as in service: the writer's blobs wait for their records.
    let options = StoreOptions {
        gc_grace: Duration::from_secs(60),
        ..opts()
    };
    let store = Store::open(&data, options).await.unwrap();
    for i in 0..5u32 {
        scene(&store, format!("before {i}").as_bytes()).await;
    }
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let writer = {
        let (store, stop) = (store.clone(), stop.clone());
        tokio::spawn(async move {
            let mut i = 0u32;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                let s = scene(&store, format!("during {i}").as_bytes()).await;
                let (job, _) = store.create_job(render_job(&s)).await.unwrap();
                store.start_job(&job.id).await.unwrap();
                let r = store
                    .put_blob(format!("result {i}").into_bytes())
                    .await
                    .unwrap();
                store
                    .finish_job(
                        &job.id,
                        JobOutcome::Succeeded {
                            stats: None,
                            result: Some((r, "image/png".into())),
                            frames: vec![],
                        },
                    )
                    .await
                    .unwrap();
                // Churn: old garbage for a GC that runs beside the backup.
                let g = store
                    .put_blob(format!("garbage {i}").into_bytes())
                    .await
                    .unwrap();
                age(
                    &store.blob_path(g.as_str()).await.unwrap(),
                    Duration::from_secs(120),
                );
                i += 1;
            }
            i
        })
    };
    tokio::time::sleep(Duration::from_millis(100)).await;
    let backup_dir = tmp.path().join("backup");
    let gc = {
        let store = store.clone();
        tokio::spawn(async move { store.gc().await.unwrap() })
    };
    let report = store.backup(&backup_dir).await.unwrap();
    gc.await.unwrap();
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let written = writer.await.unwrap();
    assert!(written > 0);
    assert!(report.blobs >= 5);

    let copy = open(&backup_dir).await;
    let (scenes, _) = copy.list_scenes(MAX_PAGE_SIZE, None).await.unwrap();
    assert!(scenes.len() >= 5);
    for s in &scenes {
        assert_eq!(
            copy.get_blob(&s.id).await.unwrap(),
            store.get_blob(&s.id).await.unwrap()
        );
    }
    let (jobs, _) = copy.list_jobs(MAX_PAGE_SIZE, None).await.unwrap();
    for j in jobs.iter().filter(|j| j.state == JobState::Succeeded) {
        copy.get_blob(&j.result.as_ref().unwrap().blob)
            .await
            .unwrap();
    }
    assert_eq!(blob_files(&backup_dir) as u64, report.blobs);
    // Both stores keep working.
    scene(&copy, b"after, in the copy").await;
    scene(&store, b"after, in the original").await;

    // A backup never overwrites anything.
    assert!(matches!(
        store.backup(&backup_dir).await,
        Err(StoreError::Invalid { .. })
    ));
}

#[tokio::test]
async fn backup_dir_copies_a_store_held_by_another_handle_or_by_none() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let store = open(&data).await;
    let s = scene(&store, b"live").await;
    // Held: the copy is taken beside the holder, through a read-only connection.
    let live = tmp.path().join("live");
    let report = Store::backup_dir(&data, &live).await.unwrap();
    assert_eq!((report.blobs, report.bytes), (1, 4));
    // The holder's streams in progress are left alone.
    let mut w = store.blob_writer().await.unwrap();
    w.write(b"in flight").await.unwrap();
    Store::backup_dir(&data, tmp.path().join("again"))
        .await
        .unwrap();
    assert_eq!(temp_files(&data).len(), 1);
    drop(w);
    store.close().await;
    // Not held: through the store.
    let cold = tmp.path().join("cold");
    Store::backup_dir(&data, &cold).await.unwrap();
    for dir in [&live, &cold] {
        let copy = open(dir).await;
        assert_eq!(copy.get_scene(&s.id).await.unwrap(), s);
        assert_eq!(copy.get_blob(&s.id).await.unwrap(), b"live");
    }
    assert!(matches!(
        Store::backup_dir(tmp.path().join("nothing"), tmp.path().join("x")).await,
        Err(StoreError::NotFound { what: "store", .. })
    ));
}

/// A backup beside a server that deletes old versions as new ones arrive can find a
/// version's blob gone (deleted after the snapshot): that version is left out of the copy,
/// which still opens. Any other missing blob (here version 1's, the upload) still fails.
#[tokio::test]
async fn a_backup_leaves_out_versions_whose_blobs_went_after_its_snapshot() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let store = open(&data).await;
    let s = scene(&store, b"moving").await;
    let mut blobs = Vec::new();
    for i in 2..=3u8 {
        let blob = store.put_blob(vec![i; 36]).await.unwrap();
        store.add_version(&s.id, &blob).await.unwrap();
        blobs.push(blob);
    }
    store.close().await;
    let file = |id: &str| data.join("blobs").join(&id[..2]).join(id);
    std::fs::remove_file(file(blobs[0].as_str())).unwrap();
    let copy = tmp.path().join("copy");
    let report = Store::backup_dir(&data, &copy).await.unwrap();
    assert_eq!((report.blobs, report.dropped_versions), (2, 1));
    let c = open(&copy).await;
    let versions: Vec<i64> = c
        .list_versions(&s.id)
        .await
        .unwrap()
        .iter()
        .map(|v| v.version)
        .collect();
    assert_eq!(versions, [1, 3]);
    c.close().await;
    // The newest version's file gone: the copy would report version 3 without holding
    // it, so the backup fails (after starting again from new snapshots) and leaves
    // nothing, neither `again` nor its staging directory.
    let newest = std::fs::read(file(blobs[1].as_str())).unwrap();
    std::fs::remove_file(file(blobs[1].as_str())).unwrap();
    let again = tmp.path().join("again");
    match Store::backup_dir(&data, &again).await {
        Err(e @ StoreError::MissingBlob { .. }) => {
            let m = e.to_string();
            assert!(m.contains(blobs[1].as_str()), "{m}");
            assert!(m.contains(&format!("version 3 of scene {}", s.id)), "{m}");
        }
        other => panic!("{other:?}"),
    }
    let left = |dir: &Path| {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    };
    assert_eq!(left(tmp.path()), ["copy", "data"]);
    std::fs::write(file(blobs[1].as_str()), newest).unwrap();
    std::fs::remove_file(file(&s.id)).unwrap();
    match Store::backup_dir(&data, &again).await {
        Err(e @ StoreError::MissingBlob { .. }) => {
            assert!(
                e.to_string()
                    .contains(&format!("version 1 of scene {}", s.id)),
                "{e}"
            );
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(left(tmp.path()), ["copy", "data"]);
    // Mended, it runs again into the same (now empty) destination.
    std::fs::write(file(&s.id), b"moving").unwrap();
    std::fs::create_dir(&again).unwrap();
    let report = Store::backup_dir(&data, &again).await.unwrap();
    assert_eq!((report.blobs, report.dropped_versions), (2, 1));
    assert_eq!(left(tmp.path()), ["again", "copy", "data"]);
}

/// A real full disk: a 4 MiB tmpfs, where mounting works (as root with the capability; the
/// test says so and returns elsewhere). Fills it until a write fails, which must be `Full`
/// and leave nothing half-written, then frees space and writes again.
#[cfg(target_os = "linux")]
#[tokio::test]
async fn a_real_full_tmpfs_reports_full_and_recovers() {
    struct Mount(PathBuf);
    impl Drop for Mount {
        fn drop(&mut self) {
            let _ = std::process::Command::new("umount")
                .arg("-l")
                .arg(&self.0)
                .status();
        }
    }
    let tmp = tempfile::tempdir().unwrap();
    let point = tmp.path().join("small");
    std::fs::create_dir(&point).unwrap();
    let mounted = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=4m", "tmpfs"])
        .arg(&point)
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !mounted {
        eprintln!("skipped: cannot mount a tmpfs here (needs root)");
        return;
    }
    let _mount = Mount(point.clone());
    // Someone else's file, removed later to make space "return".
    let ballast = point.join("ballast");
    std::fs::write(&ballast, vec![1u8; 1 << 20]).unwrap();
    let dir = point.join("data");
    let store = open(&dir).await;
    let mut made = Vec::new();
    let mut seed = 1u32;
    let failure = loop {
        // Incompressible bytes, 256 KiB a scene.
        let bytes: Vec<u8> = (0..256 * 1024)
            .map(|_| {
                seed ^= seed << 13;
                seed ^= seed >> 17;
                seed ^= seed << 5;
                seed as u8
            })
            .collect();
        let blob = match store.put_blob(bytes).await {
            Ok(b) => b,
            Err(e) => break e,
        };
        match store
            .create_scene(NewScene {
                blob,
                content_type: "application/x-rayd-tri".into(),
                name: None,
                summary: "{}".into(),
            })
            .await
        {
            Ok((s, _)) => made.push(s),
            Err(e) => break e,
        }
        assert!(made.len() < 100, "a 4 MiB file system never filled");
    };
    assert!(matches!(failure, StoreError::Full { .. }), "{failure:?}");
    assert!(made.len() >= 2, "only {} scenes fitted", made.len());
    assert!(temp_files(&dir).is_empty(), "{:?}", temp_files(&dir));
    for s in &made {
        store.get_blob(&s.id).await.unwrap();
    }
    // Space returns: writes work again, deletes and GC free more, and everything reopens.
    std::fs::remove_file(&ballast).unwrap();
    let again = scene(&store, b"space returned").await;
    let half = made.len() / 2;
    for s in &made[..half] {
        store.delete_scene(&s.id).await.unwrap();
    }
    assert_eq!(store.gc().await.unwrap().deleted, half as u64);
    scene(&store, &vec![5u8; 256 * 1024]).await;
    store.close().await;
    let store = open(&dir).await;
    assert_eq!(store.get_blob(&again.id).await.unwrap(), b"space returned");
    for s in &made[half..] {
        store.get_blob(&s.id).await.unwrap();
    }
    store.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_puts_of_the_same_new_bytes_make_one_file_counted_once() {
    let tmp = tempfile::tempdir().unwrap();
    let options = StoreOptions {
        max_bytes: Some(1 << 20),
        ..opts()
    };
    let store = Store::open(tmp.path(), options).await.unwrap();
    for round in 0..5u8 {
        let mut tasks = Vec::new();
        for t in 0..6 {
            let store = store.clone();
            tasks.push(tokio::spawn(async move {
                if t % 2 == 0 {
                    store.put_blob(vec![round; 1000]).await.unwrap()
                } else {
                    let mut w = store.blob_writer().await.unwrap();
                    w.write(&[round; 1000]).await.unwrap();
                    w.commit().await.unwrap()
                }
            }));
        }
        let mut ids = Vec::new();
        for t in tasks {
            ids.push(t.await.unwrap());
        }
        ids.dedup();
        assert_eq!(ids.len(), 1);
    }
    assert_eq!(blob_files(tmp.path()), 5);
    assert_eq!(store.blob_bytes(), Some(5000));
    assert!(temp_files(tmp.path()).is_empty());
}

#[tokio::test]
async fn callbacks_are_owed_only_for_ended_jobs_and_go_with_their_job() {
    use super::CallbackState::{Delivered, Pending};
    let tmp = tempfile::tempdir().unwrap();
    let store = open(tmp.path()).await;
    let s = scene(&store, b"callback scene").await;
    let (a, _) = store.create_job(render_job(&s)).await.unwrap();
    let (b, _) = store.create_job(render_job(&s)).await.unwrap();
    let url = "http://127.0.0.1:9/hook";
    for j in [&a, &b] {
        let r = store
            .put_callback(&j.id, url, Pending, 0, None)
            .await
            .unwrap();
        assert_eq!((r.state, r.attempts), (Pending, 0));
    }
    // Nothing is owed while the jobs are queued.
    assert!(store.pending_callbacks().await.unwrap().is_empty());
    store.cancel_job(&a.id).await.unwrap();
    let owed = store.pending_callbacks().await.unwrap();
    assert_eq!(
        owed.iter().map(|c| c.job_id.as_str()).collect::<Vec<_>>(),
        [a.id.as_str()]
    );
    // A later write replaces the row.
    store
        .put_callback(&a.id, url, Delivered, 2, Some("first try: refused"))
        .await
        .unwrap();
    let got = store.get_callback(&a.id).await.unwrap().unwrap();
    assert_eq!((got.state, got.attempts), (Delivered, 2));
    assert!(store.pending_callbacks().await.unwrap().is_empty());
    // Deleting the job deletes its row; a row for a job that is gone cannot be written.
    store.delete_job(&a.id).await.unwrap();
    assert!(matches!(
        store.put_callback(&a.id, url, Pending, 0, None).await,
        Err(StoreError::NotFound { .. })
    ));
    assert!(matches!(
        store.get_callback(&a.id).await,
        Ok(None) | Err(StoreError::NotFound { .. })
    ));
    assert!(store.get_callback(&b.id).await.unwrap().is_some());
}
