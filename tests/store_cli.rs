//! `rayd backup --data-dir DIR --out DEST`, run as a process.

use std::process::Command;

use rayd::store::{NewScene, Store, StoreOptions};

#[test]
fn rayd_backup_writes_a_copy_that_opens_as_a_store() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let out = tmp.path().join("copy");
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let id = rt.block_on(async {
        let store = Store::open(&data, StoreOptions::default()).await.unwrap();
        let blob = store.put_blob(b"a scene".to_vec()).await.unwrap();
        let (s, _) = store
            .create_scene(NewScene {
                blob,
                content_type: "model/gltf-binary".into(),
                name: None,
                summary: "{}".into(),
            })
            .await
            .unwrap();
        store.close().await;
        s.id
    });
    let run = Command::new(env!("CARGO_BIN_EXE_rayd"))
        .arg("backup")
        .arg("--data-dir")
        .arg(&data)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(report["blobs"], 1);
    assert_eq!(report["bytes"], 7);
    rt.block_on(async {
        let copy = Store::open(&out, StoreOptions::default()).await.unwrap();
        assert_eq!(copy.get_blob(&id).await.unwrap(), b"a scene");
    });

    // A second run refuses to overwrite the copy, with a message that says why.
    let again = Command::new(env!("CARGO_BIN_EXE_rayd"))
        .arg("backup")
        .arg("--data-dir")
        .arg(&data)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!again.status.success());
    let err = String::from_utf8_lossy(&again.stderr);
    assert!(err.contains("not empty"), "{err}");

    let backup = |out: &std::path::Path| {
        Command::new(env!("CARGO_BIN_EXE_rayd"))
            .arg("backup")
            .arg("--data-dir")
            .arg(&data)
            .arg("--out")
            .arg(out)
            .output()
            .unwrap()
    };
    // A copy inside the data directory is refused.
    let inner = backup(&data.join("inner"));
    let err = String::from_utf8_lossy(&inner.stderr);
    assert!(
        !inner.status.success() && err.contains("inside the data directory"),
        "{err}"
    );
    assert!(!data.join("inner").exists());
    // The staging directory a killed backup left (its process gone) goes with the next
    // backup to the same place; another destination's is left alone.
    #[cfg(target_os = "linux")]
    {
        let dead = u32::MAX - 7; // no process has this id (pid_max is at most 2^22)
        let left = tmp.path().join(format!(".second.rayd-backup-{dead}.tmp"));
        let other = tmp.path().join(format!(".third.rayd-backup-{dead}.tmp"));
        for d in [&left, &other] {
            std::fs::create_dir_all(d.join("blobs")).unwrap();
        }
        let run = backup(&tmp.path().join("second"));
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        assert!(!left.exists() && other.exists());
    }
}
