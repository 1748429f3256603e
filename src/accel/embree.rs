//! Embree peer (placeholder).
