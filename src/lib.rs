//! rayd: a ray-tracing service that traces triangle scenes on the CPU.
//!
//! Data flows one way: `formats` turns files into a plain [`scene::Scene`]; `accel` builds
//! the cores that answer "what does this ray hit?" from the scene's triangles; `render` and
//! `bench` drive those cores; `cli` (and later the service) is the thin edge. `geometry` and
//! `simd` are leaves that everything may use.
//!
//! `unsafe` is denied everywhere except the SIMD layer and the FFI of the Embree peer.
#![deny(unsafe_code)]
#![warn(missing_docs)]
// Geometry code walks the three axes of several arrays at once; an index loop says that
// more plainly than zipped iterators.
#![allow(clippy::needless_range_loop)]

/// `eprintln!` for notes to the user that ignores a failed write: a closed stderr (a pipe
/// whose reader has gone, as in `rayd bench … 2>&1 >/dev/null | head -1`) must not turn a
/// run into a panic and exit code 101 (session 31's review).
#[macro_export]
macro_rules! note {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), $($arg)*);
    }};
}

pub mod accel;
pub mod app;
pub mod bench;
pub mod cli;
pub mod formats;
pub mod geometry;
pub mod jobs;
pub mod names;
pub mod render;
pub mod scene;
pub mod service;
pub mod simd;
pub mod store;
pub mod tradeoff;
