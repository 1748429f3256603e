//! Plain data shared by every layer: rays, hits, triangles and boxes, in the exact memory
//! layouts of the contract's binary records so that files map onto them without copies.

mod aabb;
mod hit;
mod ray;
mod triangle;

pub use aabb::Aabb;
pub use hit::Hit;
pub use ray::{InvalidRays, Ray, RayError, RaySegment};
pub use triangle::Triangle;

/// `a - b` for 3-vectors.
#[inline(always)]
pub fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// Cross product of two 3-vectors.
#[inline(always)]
pub fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Dot product of two 3-vectors.
#[inline(always)]
pub fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
