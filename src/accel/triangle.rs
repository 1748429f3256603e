//! Ray/triangle tests (placeholder until the module lands).
