//! The command line (contract §4): `info`, `trace`, `render`, `bench`, `serve`,
//! `healthcheck`, `backup` and `tradeoff`.
//!
//! Each command prints one JSON object on stdout and exits 0, or prints a clear message on
//! stderr and exits non-zero. Parsing happens here; the work happens in the library.

mod backup;
mod bench;
mod info;
mod render;
mod serve;
mod trace;
mod tradeoff;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

use crate::accel::{AccelKind, BuildQuality, Precision};

/// Errors of the command line: every layer's error, converted at this edge.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// A scene, ray or hit file problem.
    #[error(transparent)]
    Format(#[from] crate::formats::FormatError),
    /// A binary body problem.
    #[error(transparent)]
    Binary(#[from] crate::formats::BinaryError),
    /// An accelerator could not be built.
    #[error(transparent)]
    Accel(#[from] crate::accel::AccelError),
    /// The ray batch has invalid rays and `--invalid error` is in force.
    #[error(
        "{path}: {detail}; no output was written (use --invalid miss to answer them as misses)"
    )]
    InvalidRays {
        /// The ray file.
        path: String,
        /// Which rays.
        detail: crate::geometry::InvalidRays,
    },
    /// A camera description is unusable.
    #[error(transparent)]
    Camera(#[from] crate::render::camera::CameraError),
    /// An image could not be encoded.
    #[error(transparent)]
    Image(#[from] crate::render::image::ImageError),
    /// The SIMD backend request cannot be met.
    #[error(transparent)]
    Simd(#[from] crate::simd::SimdError),
    /// A benchmark failed.
    #[error(transparent)]
    Bench(#[from] crate::bench::BenchError),
    /// An option's value is unusable in a way the parser cannot see.
    #[error("{0}")]
    Usage(String),
    /// The HTTP service could not start or failed.
    #[error(transparent)]
    Service(#[from] crate::service::ServiceError),
    /// A thread pool could not be made.
    #[error("cannot start the thread pool: {0}")]
    Pool(#[from] rayon::ThreadPoolBuildError),
    /// A job failed.
    #[error(transparent)]
    Job(#[from] crate::jobs::JobError),
    /// The store failed.
    #[error(transparent)]
    Store(#[from] crate::store::StoreError),
    /// A trade-off run failed.
    #[error(transparent)]
    Tradeoff(#[from] crate::tradeoff::TradeoffError),
    /// A signal stopped the command; it exits 128 + the signal's number, as shells expect.
    #[error("stopped by {name}; {detail}")]
    Stopped {
        /// `SIGINT` or `SIGTERM`.
        name: &'static str,
        /// The signal's number.
        number: u8,
        /// What was left behind (or not).
        detail: &'static str,
    },
}

#[derive(Parser, Debug)]
#[command(
    name = "rayd",
    version,
    about = "Ray-traces triangle scenes on the CPU."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Describe a scene: triangles, bounds, meshes, animations, cameras, memory, SIMD backend.
    Info(info::InfoArgs),
    /// Trace a RAY1 file against a scene and write HIT1.
    Trace(trace::TraceArgs),
    /// Render a scene to PNG or OpenEXR.
    Render(render::RenderArgs),
    /// Measure the accelerators on identical ray sets.
    Bench(bench::BenchArgs),
    /// Run the HTTP service.
    Serve(crate::service::ServeArgs),
    /// Probe a running service; exit 0 when it answers 200.
    Healthcheck(serve::HealthcheckArgs),
    /// Copy a data directory (live or not) to a new directory that opens as a store.
    Backup(backup::BackupArgs),
    /// Render a ladder of settings and measure each one's time and error against a reference.
    Tradeoff(tradeoff::TradeoffArgs),
}

/// Runs the command line and turns the outcome into an exit code.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = crate::simd::from_env()
        .map_err(CliError::from)
        .and_then(|_| match cli.command {
            Command::Info(a) => info::run(a),
            Command::Trace(a) => trace::run(a),
            Command::Render(a) => render::run(a),
            Command::Bench(a) => bench::run(a),
            Command::Serve(a) => serve::run(a),
            Command::Healthcheck(a) => serve::healthcheck(a),
            Command::Backup(a) => backup::run(a),
            Command::Tradeoff(a) => tradeoff::run(a),
        });
    match result {
        Ok(json) => {
            // `bench --format table|csv` has already printed its result.
            if !json.is_null() {
                println!("{json}");
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            crate::note!("rayd: error: {e}");
            match e {
                CliError::Stopped { number, .. } => ExitCode::from(128u8.saturating_add(number)),
                _ => ExitCode::FAILURE,
            }
        }
    }
}

/// Options every tracing command shares: which core, how it is built, how many threads.
#[derive(clap::Args, Debug, Clone)]
struct CoreArgs {
    /// Accelerator.
    #[arg(long, value_enum, default_value_t = AccelKind::Auto)]
    accel: AccelKind,
    /// Build quality of the BVH accelerators.
    #[arg(long, value_enum, default_value_t = BuildQuality::Sah)]
    build: BuildQuality,
    /// Ray/triangle test: fast (Möller–Trumbore) or watertight.
    #[arg(long, value_enum, default_value_t = Precision::Watertight)]
    precision: Precision,
    /// Threads for every phase; 0 or absent: all cores (at most 1024).
    #[arg(long, default_value_t = 0, value_parser = threads_arg())]
    threads: usize,
    /// Animation time in seconds (absent: the file's static pose).
    #[arg(long, allow_negative_numbers = true)]
    time: Option<f64>,
}

impl CoreArgs {
    /// The engine of one command: a pool of the requested size, the environment's DACRT
    /// settings, and limits wide enough for anything a file can hold.
    fn engine(&self) -> Result<crate::jobs::Engine, CliError> {
        Ok(crate::jobs::Engine::new(crate::jobs::EngineOptions {
            threads: self.threads,
            tuning: crate::accel::dacrt::DacrtTuning::from_env(),
            limits: crate::jobs::Limits {
                max_rays: usize::MAX,
                ..crate::jobs::Limits::default()
            },
            ..crate::jobs::EngineOptions::default()
        })?)
    }

    fn load_options(&self) -> Result<crate::formats::LoadOptions, CliError> {
        load_options(self.time)
    }
}

/// Load options for `--time`, refusing a time that is not a finite number.
fn load_options(time: Option<f64>) -> Result<crate::formats::LoadOptions, CliError> {
    if let Some(t) = time {
        if !t.is_finite() {
            return Err(CliError::Usage(format!(
                "--time {t} is not a finite number"
            )));
        }
    }
    Ok(crate::formats::LoadOptions { time })
}

/// How a command picks its camera.
#[derive(clap::Args, Debug, Clone)]
struct CameraArgs {
    /// Use the scene's camera with this index (default: a view framing the scene's bounds;
    /// `bench`: the scene's camera 0 where a node places it, else that view).
    #[arg(long, conflicts_with_all = ["eye", "target"])]
    camera: Option<usize>,
    /// Eye position x,y,z of a look-at camera (with --target).
    #[arg(long, value_parser = parse_vec3, requires = "target", allow_hyphen_values = true)]
    eye: Option<[f64; 3]>,
    /// Point looked at x,y,z (with --eye).
    #[arg(long, value_parser = parse_vec3, requires = "eye", allow_hyphen_values = true)]
    target: Option<[f64; 3]>,
    /// Up vector x,y,z of a look-at camera (with --eye and --target).
    #[arg(long, value_parser = parse_vec3, default_value = "0,1,0", allow_hyphen_values = true,
          requires = "eye")]
    up: [f64; 3],
    /// Vertical field of view of a look-at camera, degrees (with --eye and --target).
    #[arg(
        long,
        default_value_t = 45.0,
        allow_negative_numbers = true,
        requires = "eye"
    )]
    fov: f64,
}

impl CameraArgs {
    fn choice(&self) -> crate::render::camera::CameraChoice {
        use crate::render::camera::CameraChoice;
        match (self.camera, self.eye, self.target) {
            (Some(i), _, _) => CameraChoice::Scene(i),
            (None, Some(eye), Some(target)) => CameraChoice::LookAt {
                eye,
                target,
                up: self.up,
                fov: self.fov,
            },
            _ => CameraChoice::Auto,
        }
    }
}

fn parse_vec3(s: &str) -> Result<[f64; 3], String> {
    let parts: Vec<&str> = s.split(',').collect();
    if parts.len() != 3 {
        return Err(format!("'{s}' is not three comma-separated numbers"));
    }
    let mut v = [0.0; 3];
    for (x, p) in v.iter_mut().zip(parts) {
        *x = p
            .trim()
            .parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| format!("'{p}' in '{s}' is not a finite number"))?;
    }
    Ok(v)
}

/// A path argument.
type PathArg = PathBuf;

/// `--threads`' parser: 0 (all cores) to [`crate::jobs::MAX_THREADS`].
fn threads_arg() -> clap::builder::RangedU64ValueParser<usize> {
    clap::builder::RangedU64ValueParser::<usize>::new().range(0..=crate::jobs::MAX_THREADS)
}

/// Refuses an output path that is one of the command's inputs, through whatever path
/// (a link, `./`, another spelling): writing it would destroy the input.
fn refuse_overwriting(out: &std::path::Path, inputs: &[&std::path::Path]) -> Result<(), CliError> {
    let Ok(o) = std::fs::metadata(out) else {
        return Ok(()); // not there yet: nothing to destroy
    };
    for input in inputs {
        let Ok(i) = std::fs::metadata(input) else {
            continue;
        };
        #[cfg(unix)]
        let same = {
            use std::os::unix::fs::MetadataExt;
            (o.dev(), o.ino()) == (i.dev(), i.ino())
        };
        #[cfg(not(unix))]
        let same = std::fs::canonicalize(out).ok() == std::fs::canonicalize(input).ok();
        if same && o.is_file() && i.is_file() {
            return Err(CliError::Usage(format!(
                "the output {} is the input {}: writing it would destroy the input",
                out.display(),
                input.display()
            )));
        }
    }
    Ok(())
}

/// Writes `bytes` to `path` whole or not at all: into a temporary file beside it, renamed
/// over it once written, so that a failed or interrupted write leaves the old file (or
/// none) and never a part of the new one. A path that is not a regular file (a pipe,
/// `/dev/stdout`) is written in place.
fn write_whole(path: &std::path::Path, bytes: &[u8]) -> std::io::Result<()> {
    if std::fs::metadata(path).is_ok_and(|m| !m.is_file()) {
        return std::fs::write(path, bytes);
    }
    let mut staged = Staged::default();
    staged.write(path, bytes)?;
    staged.commit()
}

/// SIGINT and SIGTERM turned into a job's cancellation, for a command that must clean up
/// after itself (a render sequence's staged frames): the first one cancels `token`, so the
/// work stops at its next step and the command unwinds; a second one ends the process at
/// once, as a user who presses Ctrl-C twice means.
struct StopOnSignal {
    /// The signal that came, by name and number (none yet: `None`).
    came: std::sync::Arc<std::sync::OnceLock<(&'static str, u8)>>,
}

impl StopOnSignal {
    /// Installs the handlers (from then on the signals no longer end the process) and
    /// starts the thread that waits for them.
    fn install(token: crate::jobs::CancelToken) -> Result<StopOnSignal, CliError> {
        let failed = |source| CliError::Usage(format!("cannot install a signal handler: {source}"));
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(failed)?;
        let mut signals = rt
            .block_on(async { crate::service::health::Signals::new() })
            .map_err(failed)?;
        let came = std::sync::Arc::new(std::sync::OnceLock::new());
        let seen = std::sync::Arc::clone(&came);
        std::thread::Builder::new()
            .name("rayd-signals".into())
            .spawn(move || {
                rt.block_on(async move {
                    let first = signals.next().await;
                    let _ = seen.set(first);
                    crate::note!("rayd: {}: stopping (again to stop at once)", first.0);
                    token.cancel();
                    let (_, number) = signals.next().await;
                    std::process::exit(128 + i32::from(number));
                })
            })
            .map_err(failed)?;
        Ok(StopOnSignal { came })
    }

    /// The signal that came, if one did.
    fn came(&self) -> Option<(&'static str, u8)> {
        self.came.get().copied()
    }
}

/// Outputs of one command written all or none: each into a temporary file beside its
/// path, all renamed over their paths only when the command has written every one
/// ([`Staged::commit`]); dropped uncommitted (an error on the way), the temporary files
/// are removed and no path has changed. A sequence of frames whose tenth fails leaves none
/// of the first nine, and old files of those names stay as they were.
#[derive(Default)]
struct Staged {
    /// (temporary file, final path), in the order written.
    files: Vec<(std::path::PathBuf, std::path::PathBuf)>,
}

impl Staged {
    /// Refuses, before any work, a path that exists and is not a regular file (a
    /// directory): a rename over it would fail only after everything was made.
    fn check(path: &std::path::Path) -> Result<(), CliError> {
        match std::fs::metadata(path) {
            Ok(m) if !m.is_file() => Err(CliError::Usage(format!(
                "{}: the output exists and is not a regular file",
                path.display()
            ))),
            _ => Ok(()),
        }
    }

    /// Writes `bytes` into a temporary file for `path`.
    fn write(&mut self, path: &std::path::Path, bytes: &[u8]) -> std::io::Result<()> {
        let name = path
            .file_name()
            .ok_or_else(|| std::io::Error::other("the path names no file"))?;
        let suffix = format!(".rayd-{}-{}.tmp", std::process::id(), self.files.len());
        // `.NAME` + suffix, unless that would pass the 255 bytes a file name may have
        // (a name the user could create would fail here): then the suffix alone.
        let mut tmp_name = std::ffi::OsString::new();
        if 1 + name.len() + suffix.len() <= 255 {
            tmp_name.push(".");
            tmp_name.push(name);
        }
        tmp_name.push(&suffix);
        let tmp = path.with_file_name(tmp_name);
        if let Err(e) = std::fs::write(&tmp, bytes) {
            let _ = std::fs::remove_file(&tmp);
            return Err(e);
        }
        self.files.push((tmp, path.to_owned()));
        Ok(())
    }

    /// Renames every temporary file over its path, in order, after checking that no path
    /// became something a rename cannot replace (a directory) since [`Staged::check`].
    fn commit(mut self) -> std::io::Result<()> {
        for (_, path) in &self.files {
            if std::fs::metadata(path).is_ok_and(|m| m.is_dir()) {
                return Err(std::io::Error::other(format!(
                    "{} is a directory",
                    path.display()
                )));
            }
        }
        let files = std::mem::take(&mut self.files);
        let mut left = files.iter();
        for (tmp, path) in left.by_ref() {
            if let Err(e) = std::fs::rename(tmp, path) {
                let _ = std::fs::remove_file(tmp);
                for (tmp, _) in left {
                    let _ = std::fs::remove_file(tmp);
                }
                return Err(e);
            }
        }
        Ok(())
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        for (tmp, _) in &self.files {
            let _ = std::fs::remove_file(tmp);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Staged;

    fn names(dir: &std::path::Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn staged_outputs_appear_together_or_not_at_all() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.png"), dir.path().join("b.png"));
        std::fs::write(&a, b"old").unwrap();
        {
            let mut s = Staged::default();
            s.write(&a, b"new a").unwrap();
            s.write(&b, b"new b").unwrap();
            // Dropped uncommitted, as on an error after these frames.
        }
        assert_eq!(names(dir.path()), ["a.png"]);
        assert_eq!(std::fs::read(&a).unwrap(), b"old");
        let mut s = Staged::default();
        s.write(&a, b"new a").unwrap();
        s.write(&b, b"new b").unwrap();
        s.commit().unwrap();
        assert_eq!(names(dir.path()), ["a.png", "b.png"]);
        assert_eq!(std::fs::read(&b).unwrap(), b"new b");
        std::fs::create_dir(dir.path().join("c.png")).unwrap();
        assert!(Staged::check(&dir.path().join("c.png")).is_err());
        assert!(Staged::check(&a).is_ok() && Staged::check(&dir.path().join("d.png")).is_ok());
    }
}
