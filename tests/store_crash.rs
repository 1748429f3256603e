//! End to end: a child process writes to a store in a loop and is killed with SIGKILL at
//! random moments, ten times. After each kill the store must open at once (the lock dies
//! with the process), hold every write the child acknowledged, intact, and show nothing
//! half-written. The child is this test binary run again on its ignored `crash_child` test.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant, SystemTime};

use rayd::store::{
    BlobId, JobKind, JobOutcome, JobState, NewJob, NewScene, Store, StoreError, StoreOptions,
};

/// Set (to the data directory) only in the child.
const CHILD_ENV: &str = "RAYD_STORE_CRASH_CHILD";
const KILLS: usize = 10;

/// xorshift64*: enough randomness for sizes and delays, reproducible from a printed seed.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
    fn bytes(&mut self, n: usize) -> Vec<u8> {
        (0..n).map(|_| self.next() as u8).collect()
    }
}

fn seed() -> u64 {
    let t = SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64;
    (t ^ (u64::from(std::process::id()) << 32)) | 1
}

fn options() -> StoreOptions {
    // A GC in the child must not collect the parent's evidence: the default grace holds.
    StoreOptions::default()
}

/// What the child acknowledged: each line is printed only after the call returned Ok, and
/// ends with " ." so a line cut short by the kill is never mistaken for a whole one.
#[derive(Debug)]
enum Ack {
    Scene {
        id: String,
        len: usize,
    },
    Version {
        scene: String,
        version: i64,
        blob: String,
    },
    Job {
        id: String,
    },
    Done {
        id: String,
        blob: String,
    },
    /// A delete is about to be sent: until `Deleted` is seen, the job may be gone
    /// (the kill can land after the commit and before the acknowledgement).
    Deleting {
        id: String,
    },
    Deleted {
        id: String,
    },
}

fn parse(line: &str) -> Option<Ack> {
    let words: Vec<&str> = line.split(' ').collect();
    if words.first() != Some(&"ACK") || words.last() != Some(&".") {
        return None;
    }
    Some(match &words[1..words.len() - 1] {
        ["scene", id, len] => Ack::Scene {
            id: id.to_string(),
            len: len.parse().ok()?,
        },
        ["version", scene, v, blob] => Ack::Version {
            scene: scene.to_string(),
            version: v.parse().ok()?,
            blob: blob.to_string(),
        },
        ["job", id] => Ack::Job { id: id.to_string() },
        ["done", id, blob] => Ack::Done {
            id: id.to_string(),
            blob: blob.to_string(),
        },
        ["deleting", id] => Ack::Deleting { id: id.to_string() },
        ["deleted", id] => Ack::Deleted { id: id.to_string() },
        _ => return None,
    })
}

#[test]
#[ignore = "the writer half of kill_9_at_random_moments_loses_no_acknowledged_write, which runs it"]
fn crash_child() {
    let dir = std::env::var(CHILD_ENV)
        .expect("crash_child is run by kill_9_at_random_moments_loses_no_acknowledged_write");
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(child(Path::new(&dir)));
}

async fn child(dir: &Path) {
    let store = Store::open(dir, options()).await.expect("child open");
    store.recover().await.unwrap();
    let mut rng = Rng(seed());
    // A new line first: libtest has printed "test crash_child ... " without one.
    println!("\nACK ready .");
    // Bounded, in case the parent is gone and no kill comes.
    for i in 0..100_000u64 {
        let scene = if i % 4 == 3 {
            // A streamed upload of up to 2 MiB, so kills also land mid-stream.
            let len = 1 + rng.below(2 << 20) as usize;
            let data = rng.bytes(len);
            let mut w = store.blob_writer().await.unwrap();
            for chunk in data.chunks(256 * 1024) {
                w.write(chunk).await.unwrap();
            }
            let blob = w.commit().await.unwrap();
            (blob, len)
        } else {
            let len = 1 + rng.below(64 * 1024) as usize;
            (store.put_blob(rng.bytes(len)).await.unwrap(), len)
        };
        let (rec, _) = store
            .create_scene(NewScene {
                blob: scene.0.clone(),
                content_type: "application/x-rayd-tri".into(),
                name: Some(format!("scene {i}")),
                summary: format!("{{\"i\": {i}}}"),
            })
            .await
            .unwrap();
        println!("ACK scene {} {} .", rec.id, scene.1);
        let tri = store
            .put_blob({
                let n = 36 * (1 + rng.below(100) as usize);
                rng.bytes(n)
            })
            .await
            .unwrap();
        let (v, _) = store.add_version(&rec.id, &tri).await.unwrap();
        println!("ACK version {} {} {} .", rec.id, v.version, v.blob);
        let (job, _) = store
            .create_job(NewJob {
                kind: JobKind::Render,
                scene_id: rec.id.clone(),
                version: v.version,
                request: "{}".into(),
                priority: (i % 101) as u8,
                idempotency_key: Some(format!("key-{}", rng.next())),
                input_blob: None,
            })
            .await
            .unwrap();
        println!("ACK job {} .", job.id);
        store.start_job(&job.id).await.unwrap();
        store.set_progress(&job.id, 0.5).await.unwrap();
        if i % 3 == 0 {
            // Left running: recovery must requeue it.
            continue;
        }
        let result = store
            .put_blob({
                let n = 1 + rng.below(32 * 1024) as usize;
                rng.bytes(n)
            })
            .await
            .unwrap();
        store
            .finish_job(
                &job.id,
                JobOutcome::Succeeded {
                    stats: Some("{}".into()),
                    result: Some((result.clone(), "image/png".into())),
                    frames: vec![(result.clone(), "image/png".into())],
                },
            )
            .await
            .unwrap();
        println!("ACK done {} {} .", job.id, result);
        if i % 5 == 4 {
            println!("ACK deleting {} .", job.id);
            store.delete_job(&job.id).await.unwrap();
            println!("ACK deleted {} .", job.id);
        }
    }
}

#[test]
fn kill_9_at_random_moments_loses_no_acknowledged_write() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("data");
    let exe = std::env::current_exe().unwrap();
    let s = seed();
    eprintln!("store_crash seed {s}");
    let mut rng = Rng(s);
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let mut acks = Vec::new();
    let started = Instant::now();
    for round in 0..KILLS {
        let mut child = Command::new(&exe)
            .args([
                "crash_child",
                "--exact",
                "--ignored",
                "--nocapture",
                "--test-threads=1",
            ])
            .env(CHILD_ENV, &dir)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        let reader = std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        // Wait for the child to be up, so the kill lands among writes.
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let line = rx
                .recv_timeout(deadline.saturating_duration_since(Instant::now()))
                .expect("the child never said it was ready");
            if line == "ACK ready ." {
                break;
            }
        }
        if round == 0 {
            // Another process holds the lock while the child lives.
            match rt.block_on(Store::open(&dir, options())) {
                Err(StoreError::Locked { .. }) => {}
                other => panic!("expected Locked while the child runs, got {other:?}"),
            }
        }
        std::thread::sleep(Duration::from_millis(50 + rng.below(1200)));
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        reader.join().unwrap();
        acks.extend(rx.try_iter().filter_map(|l| parse(&l)));
        rt.block_on(verify(&dir, &acks));
    }
    let scenes = acks
        .iter()
        .filter(|a| matches!(a, Ack::Scene { .. }))
        .count();
    let done = acks
        .iter()
        .filter(|a| matches!(a, Ack::Done { .. }))
        .count();
    eprintln!(
        "store_crash: {KILLS} kills in {:.1} s, {} acks ({scenes} scenes, {done} results)",
        started.elapsed().as_secs_f64(),
        acks.len()
    );
    assert!(
        scenes >= KILLS,
        "the child wrote too little to test anything ({scenes} scenes)"
    );
}

/// Reopens right after a kill and checks every acknowledged write and the absence of
/// half-written state.
async fn verify(dir: &Path, acks: &[Ack]) {
    let store = Store::open(dir, options())
        .await
        .expect("open right after kill -9");
    let deleted: std::collections::HashSet<&str> = acks
        .iter()
        .filter_map(|a| match a {
            Ack::Deleted { id } | Ack::Deleting { id } => Some(id.as_str()),
            _ => None,
        })
        .collect();
    for ack in acks {
        match ack {
            Ack::Scene { id, len } => {
                store.get_scene(id).await.unwrap();
                assert_eq!(store.get_blob(id).await.unwrap().len(), *len);
            }
            Ack::Version {
                scene,
                version,
                blob,
            } => {
                let v = store.get_version(scene, *version).await.unwrap();
                assert_eq!(&v.blob, blob);
                store.get_blob(blob).await.unwrap();
            }
            Ack::Job { id } if !deleted.contains(id.as_str()) => {
                store.get_job(id).await.unwrap();
            }
            Ack::Done { id, blob } if !deleted.contains(id.as_str()) => {
                let j = store.get_job(id).await.unwrap();
                assert_eq!(j.state, JobState::Succeeded);
                assert_eq!(&j.result.unwrap().blob, blob);
                assert_eq!(j.result_frames.len(), 1);
                store.get_blob(blob).await.unwrap();
            }
            Ack::Deleted { id } => {
                assert!(matches!(
                    store.get_job(id).await,
                    Err(StoreError::NotFound { .. })
                ));
            }
            Ack::Job { .. } | Ack::Done { .. } | Ack::Deleting { .. } => {}
        }
    }
    // Nothing half-written: every scene has all its versions and their blobs, every
    // finished job its results; after recovery nothing is running.
    let requeued = store.recover().await.unwrap();
    assert!(requeued.iter().all(|j| j.state == JobState::Queued));
    let mut token = None;
    loop {
        let (page, next) = store.list_scenes(100, token.as_deref()).await.unwrap();
        for s in &page {
            let versions = store.list_versions(&s.id).await.unwrap();
            let numbers: Vec<i64> = versions.iter().map(|v| v.version).collect();
            assert_eq!(
                numbers,
                (1..=s.latest_version).collect::<Vec<_>>(),
                "scene {}",
                s.id
            );
            assert_eq!(versions[0].blob, s.id);
            for v in &versions {
                store.get_blob(&v.blob).await.unwrap();
            }
        }
        match next {
            Some(t) => token = Some(t),
            None => break,
        }
    }
    let mut token = None;
    loop {
        let (page, next) = store.list_jobs(100, token.as_deref()).await.unwrap();
        for j in &page {
            assert_ne!(j.state, JobState::Running);
            if j.state == JobState::Succeeded {
                let r = j.result.as_ref().expect("a succeeded job has its result");
                store.get_blob(&r.blob).await.unwrap();
                for f in &j.result_frames {
                    store.get_blob(&f.blob).await.unwrap();
                }
            }
        }
        match next {
            Some(t) => token = Some(t),
            None => break,
        }
    }
    // No temporary file survives an open.
    let staging: Vec<_> = std::fs::read_dir(dir.join("blobs/tmp")).unwrap().collect();
    assert!(staging.is_empty(), "{staging:?}");
    for shard in std::fs::read_dir(dir.join("blobs")).unwrap() {
        let shard = shard.unwrap().path();
        for f in std::fs::read_dir(&shard).unwrap() {
            let name = f.unwrap().file_name().to_string_lossy().into_owned();
            assert!(
                shard.ends_with("tmp") || BlobId::parse(&name).is_some(),
                "stray file {name} in {}",
                shard.display()
            );
        }
    }
    store.close().await;
}
