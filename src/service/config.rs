//! `rayd serve`'s options (`proto/service.md`, "Configuration"): one clap struct, every flag
//! with its `RAYD_*` environment variable and its default in the help text.
//!
//! Flags win over the environment because clap reads a flag first and only falls back to
//! the variable when the flag is absent. The struct is plain data: the service reads its
//! limits from it, the job engine and the store read theirs, and nothing here knows what a
//! ray is beyond the size limits it carries.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

/// How log lines are written to stderr.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LogFormat {
    /// Human-readable lines.
    #[default]
    Text,
    /// One JSON object a line, for log collectors.
    Json,
}

/// The options of `rayd serve`. Every one also has an environment variable; a flag wins.
#[derive(clap::Args, Debug, Clone)]
pub struct ServeArgs {
    /// Address and port to listen on.
    #[arg(long, env = "RAYD_ADDR", default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,

    /// Directory for everything that must survive a restart (scenes, results, the database).
    #[arg(long, env = "RAYD_DATA_DIR", default_value = "rayd-data")]
    pub data_dir: PathBuf,

    /// Threads for tracing and rendering; 0: all cores (at most 1024).
    #[arg(long, env = "RAYD_THREADS", default_value_t = 0,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new()
              .range(0..=crate::jobs::MAX_THREADS))]
    pub threads: usize,

    /// Jobs of every kind that may wait; past this, new work is answered 503.
    #[arg(long, env = "RAYD_MAX_QUEUED", default_value_t = 64)]
    pub max_queued: usize,

    /// Jobs (renders, asynchronous traces) that may have started and not finished at once,
    /// at least 1. A started render that yields to a higher-priority one between waves
    /// keeps its image in memory; past this bound a job waits for one to end, whatever its
    /// priority. Synchronous traces are not counted.
    #[arg(long, env = "RAYD_MAX_RUNNING", default_value_t = crate::jobs::DEFAULT_MAX_RUNNING)]
    pub max_running: usize,

    /// Bytes of one request body (1 GiB: a batch of 16M rays is 512 MiB).
    #[arg(long, env = "RAYD_MAX_BODY", default_value_t = 1 << 30)]
    pub max_body: u64,

    /// Rays in one trace batch.
    #[arg(long, env = "RAYD_MAX_RAYS", default_value_t = 1 << 24)]
    pub max_rays: u64,

    /// Pixels (width × height) of one image (4096 × 4096).
    #[arg(long, env = "RAYD_MAX_PIXELS", default_value_t = 1 << 24)]
    pub max_pixels: u64,

    /// Triangles of one uploaded scene, instancing included (2^26: 2.25 GiB of positions);
    /// counted from the document before any is placed. At most 2^28, the loader's bound.
    #[arg(long, env = "RAYD_MAX_TRIANGLES", default_value_t = 1 << 26)]
    pub max_triangles: u64,

    /// Samples per pixel of one render.
    #[arg(long, env = "RAYD_MAX_SPP", default_value_t = 4096)]
    pub max_spp: u32,

    /// Seconds that running requests and jobs get to finish after SIGTERM or SIGINT.
    #[arg(long, env = "RAYD_GRACE", default_value_t = 5.0, value_parser = parse_seconds)]
    pub grace: f64,

    /// File of bearer tokens, one a line (blank lines and `#` comments ignored); with it,
    /// every /v1 route needs `Authorization: Bearer TOKEN`. Re-read on SIGHUP. Default: none
    /// (no authentication).
    #[arg(long, env = "RAYD_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,

    /// Upload the repository's sample scenes at start (default: off). RAYD_DEMO takes
    /// 1/0, true/false, yes/no or on/off.
    #[arg(long, env = "RAYD_DEMO", value_parser = clap::builder::BoolishValueParser::new())]
    pub demo: bool,

    /// Seconds that a finished job's result is kept (1 day); 0 keeps results until they
    /// are deleted.
    #[arg(long, env = "RAYD_RESULT_TTL", default_value_t = 86_400)]
    pub result_ttl: u64,

    /// Newest geometry versions of a scene kept, the latest included (16). Version 1 (the
    /// upload) and versions a job names are kept as well; older ones are deleted as new
    /// ones arrive and then answer 404. 0: keep every version.
    #[arg(long, env = "RAYD_KEEP_VERSIONS", default_value_t = 16)]
    pub keep_versions: u32,

    /// Bytes of acceleration structures kept in memory for reuse (4 GiB).
    #[arg(long, env = "RAYD_CACHE_BYTES", default_value_t = 4 << 30)]
    pub cache_bytes: u64,

    /// Bytes of decoded textures (a scene's MIP pyramids) kept in memory for reuse by later
    /// render jobs of the same scene (1 GiB); the least recently used go first.
    #[arg(long, env = "RAYD_TEXTURE_BYTES", default_value_t = 1 << 30)]
    pub texture_bytes: u64,

    /// Bytes of parsed scenes and evaluated geometry (a scene's positions per version and
    /// animation time) kept in memory for reuse (1 GiB). Each upload, `PUT .../geometry`
    /// and new `time=` adds an entry; the least recently used go first and are read again
    /// from the data directory when next needed.
    #[arg(long, env = "RAYD_GEOMETRY_BYTES", default_value_t = 1 << 30)]
    pub geometry_bytes: u64,

    /// Bytes of request bodies held in memory at once, by all requests together (2 GiB);
    /// a request that cannot get its share in time is answered 503. At least --max-body.
    #[arg(long, env = "RAYD_MAX_INFLIGHT_BYTES", default_value_t = 2 << 30)]
    pub max_inflight_bytes: u64,

    /// Concurrent /v1 requests from one client IP address; past this, 503. 0: no bound.
    /// Behind a proxy every request comes from the proxy's address: raise it or use 0.
    #[arg(long, env = "RAYD_MAX_CLIENT_REQUESTS", default_value_t = 8)]
    pub max_client_requests: usize,

    /// Open connections at once; past this, new connections wait to be accepted.
    #[arg(long, env = "RAYD_MAX_CONNECTIONS", default_value_t = 10_000)]
    pub max_connections: usize,

    /// Seconds a client has to send a request's headers, and that an idle keep-alive
    /// connection stays open (closes slow or silent clients).
    #[arg(long, env = "RAYD_HEADER_TIMEOUT", default_value_t = 10.0, value_parser = parse_seconds)]
    pub header_timeout: f64,

    /// Seconds a request body may go without a byte arriving while the server waits for
    /// it; then the request is answered 408 and its memory freed (a body whose
    /// Content-Length lies, a chunked body that never ends).
    #[arg(long, env = "RAYD_BODY_TIMEOUT", default_value_t = 30.0, value_parser = parse_seconds)]
    pub body_timeout: f64,

    /// Bytes a second that a request body must average beyond the first --body-timeout
    /// seconds of waiting for it: the server waits for a body at most --body-timeout
    /// seconds plus a second for each this many bytes received, then answers 408. 0: no
    /// rate, only the idle timeout.
    #[arg(long, env = "RAYD_MIN_BODY_RATE", default_value_t = 4096)]
    pub min_body_rate: u64,

    /// Bytes that stored blobs (uploads, geometry versions, results) may occupy in the data
    /// directory; past it, a write fails as on a full disk (507) and nothing is half-stored.
    /// Default: none (only the disk limits).
    #[arg(long, env = "RAYD_MAX_STORE_BYTES")]
    pub max_store_bytes: Option<u64>,

    /// Hosts that render jobs' callbacks may be POSTed to: comma-separated `host` (port 80)
    /// or `host:port` entries. Default: none (a job with a callback is refused with 422).
    #[arg(long, env = "RAYD_CALLBACK_ALLOW", value_delimiter = ',')]
    pub callback_allow: Vec<String>,

    /// File holding the secret that signs every callback (HMAC-SHA256, at least 16 bytes;
    /// surrounding whitespace is trimmed). Needed with --callback-allow.
    #[arg(long, env = "RAYD_CALLBACK_SECRET_FILE")]
    pub callback_secret_file: Option<PathBuf>,

    /// POSTs a callback gets in all, the first included, with back-off between them.
    #[arg(long, env = "RAYD_CALLBACK_ATTEMPTS", default_value_t = 5)]
    pub callback_attempts: u32,

    /// Seconds one callback POST may take, connecting included.
    #[arg(long, env = "RAYD_CALLBACK_TIMEOUT", default_value_t = 10.0, value_parser = parse_seconds)]
    pub callback_timeout: f64,

    /// Log line format: text or json.
    #[arg(long, env = "RAYD_LOG_FORMAT", value_enum, default_value_t = LogFormat::Text)]
    pub log_format: LogFormat,
}

/// A problem with the options that clap cannot see on its own.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The in-flight budget could never hold one largest body.
    #[error(
        "--max-inflight-bytes {inflight} is smaller than --max-body {body}: a body of the \
         largest allowed size could never be accepted"
    )]
    BudgetBelowBody {
        /// `--max-inflight-bytes`.
        inflight: u64,
        /// `--max-body`.
        body: u64,
    },
    /// A limit that must be positive is 0.
    #[error("--{0} must be at least 1")]
    Zero(&'static str),
}

impl ServeArgs {
    /// Checks the relations between options that single flags cannot express.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.max_inflight_bytes < self.max_body {
            return Err(ConfigError::BudgetBelowBody {
                inflight: self.max_inflight_bytes,
                body: self.max_body,
            });
        }
        for (name, v) in [
            ("max-body", self.max_body),
            ("max-rays", self.max_rays),
            ("max-pixels", self.max_pixels),
            ("max-spp", u64::from(self.max_spp)),
            ("max-triangles", self.max_triangles),
            ("max-connections", self.max_connections as u64),
            ("max-running", self.max_running as u64),
            ("max-store-bytes", self.max_store_bytes.unwrap_or(1)),
            ("callback-attempts", u64::from(self.callback_attempts)),
        ] {
            if v == 0 {
                return Err(ConfigError::Zero(name));
            }
        }
        Ok(())
    }

    /// `--grace` as a duration.
    pub fn grace(&self) -> Duration {
        Duration::from_secs_f64(self.grace)
    }

    /// `--callback-timeout` as a duration.
    pub fn callback_timeout(&self) -> Duration {
        Duration::from_secs_f64(self.callback_timeout)
    }

    /// `--body-timeout` as a duration.
    pub fn body_timeout(&self) -> Duration {
        Duration::from_secs_f64(self.body_timeout)
    }

    /// How long request bodies may take: `--body-timeout` and `--min-body-rate`.
    pub fn body_pace(&self) -> crate::service::body::BodyPace {
        crate::service::body::BodyPace {
            idle: self.body_timeout(),
            min_rate: self.min_body_rate,
        }
    }

    /// `--header-timeout` as a duration.
    pub fn header_timeout(&self) -> Duration {
        Duration::from_secs_f64(self.header_timeout)
    }

    /// Parses `rayd serve`'s arguments (without the program and subcommand names), the
    /// `RAYD_*` environment filling in what they leave out: for tests and embedders.
    pub fn try_parse_from<I, T>(args: I) -> Result<Self, clap::Error>
    where
        I: IntoIterator<Item = T>,
        T: Into<std::ffi::OsString> + Clone,
    {
        use clap::Parser;
        #[derive(clap::Parser)]
        #[command(name = "rayd serve", no_binary_name = true)]
        struct Standalone {
            #[command(flatten)]
            args: ServeArgs,
        }
        Ok(Standalone::try_parse_from(args)?.args)
    }
}

/// Parses a non-negative, finite number of seconds.
fn parse_seconds(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(x) if (0.0..1e9).contains(&x) => Ok(x),
        _ => Err(format!(
            "'{s}' is not a number of seconds (a finite number from 0 up)"
        )),
    }
}
