//! The hit record every accelerator fills in.

/// What a ray hit: `t` along the ray, the triangle id, and barycentrics such that the hit
/// point is `(1-u-v)·v0 + u·v1 + v·v2`. A miss is [`Hit::MISS`].
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Hit {
    /// Ray parameter of the hit, `+inf` for a miss.
    pub t: f32,
    /// Triangle id (contract §1), `u32::MAX` for a miss.
    pub prim: u32,
    /// Barycentric weight of `v1`.
    pub u: f32,
    /// Barycentric weight of `v2`.
    pub v: f32,
}

const _: () = assert!(std::mem::size_of::<Hit>() == 16);

impl Hit {
    /// The contract's miss: `t = +inf`, `prim = 0xFFFFFFFF`, `u = v = 0`.
    pub const MISS: Hit = Hit {
        t: f32::INFINITY,
        prim: u32::MAX,
        u: 0.0,
        v: 0.0,
    };

    /// Whether this record is a hit.
    #[inline]
    pub fn is_hit(&self) -> bool {
        self.prim != u32::MAX
    }
}

impl Default for Hit {
    fn default() -> Self {
        Hit::MISS
    }
}
