//! Tests of the ray/triangle tests.
