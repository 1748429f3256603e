//! Every SIMD backend against the scalar twin, operation by operation.
//!
//! Inputs mix uniformly random bit patterns (every class of float, NaN payloads included),
//! "nice" values, and the edge cases NaN, ±inf, ±0, denormals, ±f32::MAX. Results must be
//! bit-identical, except:
//! - NaN results: only NaN-ness is compared (payloads are unspecified);
//! - `mul_add` on AVX2 is fused, so it is compared with `f32::mul_add` (correctly rounded
//!   fused multiply-add) bit for bit, while SSE and scalar must equal `a*b + c`;
//! - `recip_fast` is checked against `1/x` with relative error ≤ 2^-21 for inputs whose
//!   reciprocal is a normal float (hardware `rcpps` flushes denormals), and must be exact on
//!   scalar.
//!
//! Backends the CPU lacks are skipped (and say so on stderr).

use rayd::simd::{dispatch, Backend, FloatV, IntV, Kernel, MaskV, Select, Simd};

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn f32(&mut self) -> f32 {
        const SPECIAL: [f32; 16] = [
            0.0,
            -0.0,
            1.0,
            -1.0,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            1e-45,
            -1e-40,
            f32::MAX,
            f32::MIN,
            0.5,
            2.0,
            3.0e9,
        ];
        match self.next() % 4 {
            0 => SPECIAL[(self.next() % 16) as usize],
            1 => f32::from_bits(self.next() as u32),
            _ => ((self.next() % 2_000_001) as f32 - 1_000_000.0) / 1000.0,
        }
    }
    fn i32(&mut self) -> i32 {
        match self.next() % 3 {
            0 => (self.next() % 17) as i32 - 8,
            1 => [0, -1, 1, i32::MIN, i32::MAX][(self.next() % 5) as usize],
            _ => self.next() as i32,
        }
    }
}

#[derive(Clone, Copy)]
struct Inputs {
    a: [f32; 8],
    b: [f32; 8],
    c: [f32; 8],
    i: [i32; 8],
    j: [i32; 8],
    m: u32,
}

/// Everything each backend computes from one input set.
#[derive(Debug, Default)]
struct Outputs {
    f: Vec<(&'static str, Vec<f32>)>,
    i: Vec<(&'static str, Vec<i32>)>,
    masks: Vec<(&'static str, u32)>,
    fused: Vec<f32>,
    recip_fast: Vec<f32>,
}

struct Ops(Inputs);

/// 4-wide results of lanes 0–3 and 4–7 concatenated, so they compare like 8-wide ones.
fn cat<T: Copy>(lo: &[T], hi: &[T]) -> Vec<T> {
    lo.iter().chain(hi).copied().collect()
}

impl Kernel for Ops {
    type Output = Outputs;
    #[inline(always)]
    fn run<S: Simd>(self, s: S) -> Outputs {
        let x = self.0;
        let mut o = Outputs::default();
        let (a, b, c) = (s.load_f8(&x.a), s.load_f8(&x.b), s.load_f8(&x.c));
        let (i, j) = (s.load_i8(&x.i), s.load_i8(&x.j));
        let m = s.mask8(x.m);
        let cmp = b.lt(a);
        let f = |v: S::F8| v.to_array().to_vec();
        let n = |v: S::I8| v.to_array().to_vec();
        o.f.push(("splat", f(s.splat_f8(x.a[3]))));
        o.f.push(("add", f(a + b)));
        o.f.push(("sub", f(a - b)));
        o.f.push(("mul", f(a * b)));
        o.f.push(("div", f(a / b)));
        o.f.push(("neg", f(-a)));
        o.f.push(("min", f(a.min(b))));
        o.f.push(("max", f(a.max(b))));
        o.f.push(("abs", f(a.abs())));
        o.f.push(("sqrt", f(a.sqrt())));
        o.f.push(("recip", f(a.recip())));
        o.f.push(("select", f(m.select(a, b))));
        o.f.push(("select_cmp", f(cmp.select(a, c))));
        o.f.push(("hmin", vec![a.hmin()]));
        o.f.push(("hmax", vec![a.hmax()]));
        o.f.push(("permute", f(a.permute(i))));
        o.f.push(("compress", f(a.compress(m))));
        o.f.push(("from_bits", f(i.to_float_bits())));
        o.f.push(("to_float", f(i.to_float())));
        o.i.push(("to_bits", n(a.to_bits())));
        o.i.push(("trunc", n(a.to_int_trunc())));
        o.i.push(("splat", n(s.splat_i8(x.i[5]))));
        o.i.push(("add", n(i + j)));
        o.i.push(("sub", n(i - j)));
        o.i.push(("mul", n(i * j)));
        o.i.push(("and", n(i & j)));
        o.i.push(("or", n(i | j)));
        o.i.push(("xor", n(i ^ j)));
        o.i.push(("not", n(!i)));
        o.i.push(("andnot", n(i.andnot(j))));
        o.i.push(("shl3", n(i.shl::<3>())));
        o.i.push(("shl31", n(i.shl::<31>())));
        o.i.push(("shr5", n(i.shr::<5>())));
        o.i.push(("sar7", n(i.sar::<7>())));
        o.i.push(("sar31", n(i.sar::<31>())));
        o.i.push(("min", n(i.min(j))));
        o.i.push(("max", n(i.max(j))));
        o.i.push(("hmin", vec![i.hmin()]));
        o.i.push(("select", n(m.select(i, j))));
        o.i.push(("permute", n(i.permute(j))));
        o.i.push(("compress", n(i.compress(cmp))));
        for (name, mk) in [
            ("lt", a.lt(b)),
            ("le", a.le(b)),
            ("gt", a.gt(b)),
            ("ge", a.ge(b)),
            ("eq", FloatV::eq(a, b)),
            ("ne", FloatV::ne(a, b)),
            ("ieq", IntV::eq(i, j)),
            ("igt", IntV::gt(i, j)),
            ("ilt", IntV::lt(i, j)),
            ("and", m & cmp),
            ("or", m | cmp),
            ("xor", m ^ cmp),
            ("not", !m),
            ("andnot", m.andnot(cmp)),
        ] {
            o.masks.push((name, mk.bitmask()));
        }
        o.masks.push(("any", u32::from(m.any())));
        o.masks.push(("all", u32::from(m.all())));
        o.masks.push(("none", u32::from(m.none())));
        o.fused = f(a.mul_add(b, c));
        o.recip_fast = f(a.recip_fast());

        // 4-wide, on both halves.
        let h = |k: usize| {
            let a4 = s.load_f4(x.a[4 * k..4 * k + 4].try_into().unwrap());
            let b4 = s.load_f4(x.b[4 * k..4 * k + 4].try_into().unwrap());
            let c4 = s.load_f4(x.c[4 * k..4 * k + 4].try_into().unwrap());
            let i4 = s.load_i4(x.i[4 * k..4 * k + 4].try_into().unwrap());
            let j4 = s.load_i4(x.j[4 * k..4 * k + 4].try_into().unwrap());
            let m4 = s.mask4(x.m >> (4 * k));
            let cmp4 = b4.lt(a4);
            let fl = vec![
                (a4 + b4).to_array(),
                (a4 - b4).to_array(),
                (a4 * b4).to_array(),
                (a4 / b4).to_array(),
                (-a4).to_array(),
                a4.min(b4).to_array(),
                a4.max(b4).to_array(),
                a4.abs().to_array(),
                a4.sqrt().to_array(),
                a4.recip().to_array(),
                m4.select(a4, c4).to_array(),
                [a4.hmin(), a4.hmax(), s.splat_f4(x.c[1]).hmin(), 0.0],
                a4.permute(i4).to_array(),
                a4.compress(m4).to_array(),
                i4.to_float().to_array(),
                i4.to_float_bits().to_array(),
            ];
            let il = vec![
                a4.to_bits().to_array(),
                a4.to_int_trunc().to_array(),
                (i4 + j4).to_array(),
                (i4 - j4).to_array(),
                (i4 * j4).to_array(),
                (i4 & j4).to_array(),
                (i4 | j4).to_array(),
                (i4 ^ j4).to_array(),
                (!i4).to_array(),
                i4.andnot(j4).to_array(),
                i4.shl::<4>().to_array(),
                i4.shr::<9>().to_array(),
                i4.sar::<2>().to_array(),
                i4.min(j4).to_array(),
                i4.max(j4).to_array(),
                [i4.hmin(), 0, 0, 0],
                m4.select(i4, j4).to_array(),
                i4.permute(j4).to_array(),
                i4.compress(cmp4).to_array(),
                s.splat_i4(x.j[2]).to_array(),
            ];
            let ml = vec![
                a4.lt(b4).bitmask(),
                a4.le(b4).bitmask(),
                a4.gt(b4).bitmask(),
                a4.ge(b4).bitmask(),
                FloatV::eq(a4, b4).bitmask(),
                FloatV::ne(a4, b4).bitmask(),
                IntV::eq(i4, j4).bitmask(),
                IntV::gt(i4, j4).bitmask(),
                IntV::lt(i4, j4).bitmask(),
                (m4 & cmp4).bitmask(),
                (m4 | cmp4).bitmask(),
                (m4 ^ cmp4).bitmask(),
                (!m4).bitmask(),
                m4.andnot(cmp4).bitmask(),
                u32::from(m4.any()) | u32::from(m4.all()) << 1 | u32::from(m4.none()) << 2,
            ];
            (
                fl,
                il,
                ml,
                a4.mul_add(b4, c4).to_array(),
                a4.recip_fast().to_array(),
            )
        };
        let (lo, hi) = (h(0), h(1));
        for (k, (l, r)) in lo.0.iter().zip(&hi.0).enumerate() {
            o.f.push((F4_NAMES[k], cat(l, r)));
        }
        for (k, (l, r)) in lo.1.iter().zip(&hi.1).enumerate() {
            o.i.push((I4_NAMES[k], cat(l, r)));
        }
        for (k, (l, r)) in lo.2.iter().zip(&hi.2).enumerate() {
            o.masks.push((M4_NAMES[k], l | r << 4));
        }
        o.fused.extend(cat(&lo.3, &hi.3));
        o.recip_fast.extend(cat(&lo.4, &hi.4));
        o
    }
}

const F4_NAMES: [&str; 16] = [
    "add4",
    "sub4",
    "mul4",
    "div4",
    "neg4",
    "min4",
    "max4",
    "abs4",
    "sqrt4",
    "recip4",
    "select4",
    "hminmax4",
    "permute4",
    "compress4",
    "to_float4",
    "from_bits4",
];
const I4_NAMES: [&str; 20] = [
    "to_bits4",
    "trunc4",
    "add4",
    "sub4",
    "mul4",
    "and4",
    "or4",
    "xor4",
    "not4",
    "andnot4",
    "shl4",
    "shr4",
    "sar4",
    "min4",
    "max4",
    "hmin4",
    "select4",
    "permute4",
    "compress4",
    "splat4",
];
const M4_NAMES: [&str; 15] = [
    "lt4",
    "le4",
    "gt4",
    "ge4",
    "eq4",
    "ne4",
    "ieq4",
    "igt4",
    "ilt4",
    "and4",
    "or4",
    "xor4",
    "not4",
    "andnot4",
    "any_all_none4",
];

fn same(x: f32, y: f32) -> bool {
    (x.is_nan() && y.is_nan()) || x.to_bits() == y.to_bits()
}

fn inputs(rng: &mut Rng) -> Inputs {
    let mut v = || std::array::from_fn(|_| rng.f32());
    let (a, b, c) = (v(), v(), v());
    let mut w = || std::array::from_fn(|_| rng.i32());
    let (i, j) = (w(), w());
    let m = (rng.next() & 0xff) as u32;
    Inputs { a, b, c, i, j, m }
}

fn check(backend: Backend, x: Inputs) {
    let got = dispatch(backend, Ops(x));
    let want = dispatch(Backend::Scalar, Ops(x));
    for ((name, g), (_, w)) in got.f.iter().zip(&want.f) {
        assert!(
            g.iter().zip(w).all(|(&g, &w)| same(g, w)),
            "{backend} f32 {name}: {g:?} vs scalar {w:?}\n a={:?}\n b={:?}\n i={:?} m={:08b}",
            x.a,
            x.b,
            x.i,
            x.m
        );
    }
    for ((name, g), (_, w)) in got.i.iter().zip(&want.i) {
        assert_eq!(
            g, w,
            "{backend} i32 {name}\n a={:?}\n i={:?}\n j={:?}",
            x.a, x.i, x.j
        );
    }
    for ((name, g), (_, w)) in got.masks.iter().zip(&want.masks) {
        assert_eq!(g, w, "{backend} mask {name}\n a={:?}\n b={:?}", x.a, x.b);
    }
    for k in 0..16 {
        let (a, b, c) = (x.a[k % 8], x.b[k % 8], x.c[k % 8]);
        let r = if backend == Backend::Avx2 && k < 8 {
            // 8-wide FMA; the 4-wide (SSE) half is never fused.
            a.mul_add(b, c)
        } else {
            a * b + c
        };
        assert!(
            same(got.fused[k], r),
            "{backend} mul_add({a}, {b}, {c}) lane {k}: {} vs {r}",
            got.fused[k]
        );
        let exact = 1.0 / a;
        if backend == Backend::Scalar {
            assert!(same(got.recip_fast[k], exact));
        } else if exact.is_normal() && a.is_normal() {
            let rel = ((got.recip_fast[k] as f64 - exact as f64) / exact as f64).abs();
            assert!(
                rel <= 2f64.powi(-21),
                "{backend} recip_fast({a}) = {} (rel err {rel:e})",
                got.recip_fast[k]
            );
        }
    }
}

fn hardware_backends() -> Vec<Backend> {
    let all = [Backend::Avx2, Backend::Sse];
    for b in all {
        if !b.is_supported() {
            eprintln!("skipping {b}: not supported on this CPU");
        }
    }
    all.into_iter().filter(|b| b.is_supported()).collect()
}

#[test]
fn every_backend_matches_scalar_on_random_and_special_inputs() {
    let mut rng = Rng(0x5eed);
    for backend in hardware_backends() {
        for _ in 0..20_000 {
            check(backend, inputs(&mut rng));
        }
    }
}

#[test]
fn every_backend_matches_scalar_on_special_value_grid() {
    let specials = [
        0.0f32,
        -0.0,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::NAN,
        -f32::NAN,
        1e-45,
        -1e-45,
        f32::MIN_POSITIVE,
        f32::MAX,
        -1.0,
        1.0,
    ];
    for backend in hardware_backends() {
        for (k, &x) in specials.iter().enumerate() {
            let mut a = [x; 8];
            let b: [f32; 8] = std::array::from_fn(|l| specials[(k + l) % specials.len()]);
            let c: [f32; 8] = std::array::from_fn(|l| specials[(3 * k + l) % specials.len()]);
            for (l, &y) in b.iter().enumerate() {
                check(
                    backend,
                    Inputs {
                        a,
                        b,
                        c,
                        i: std::array::from_fn(|q| (q + l) as i32),
                        j: std::array::from_fn(|q| (7 * q + l) as i32 - 20),
                        m: (k * 37 + l) as u32 & 0xff,
                    },
                );
                a[l] = y;
            }
        }
    }
}

#[test]
fn scalar_follows_the_documented_rules() {
    let mut rng = Rng(7);
    for _ in 0..10_000 {
        let x = inputs(&mut rng);
        let o = dispatch(Backend::Scalar, Ops(x));
        let get = |name: &str| o.f.iter().find(|(n, _)| *n == name).unwrap().1.clone();
        let (min, max) = (get("min"), get("max"));
        for l in 0..8 {
            let (a, b) = (x.a[l], x.b[l]);
            assert!(same(min[l], if a < b { a } else { b }));
            assert!(same(max[l], if a > b { a } else { b }));
        }
        // hmin: lanes (i, i+4), then (i, i+2), then (0, 1), each with the minps rule.
        let m = |a: f32, b: f32| if a < b { a } else { b };
        let a = x.a;
        let t: Vec<f32> = (0..4).map(|i| m(a[i], a[i + 4])).collect();
        let want = m(m(t[0], t[2]), m(t[1], t[3]));
        assert!(same(get("hmin")[0], want));
    }
    // The rules on ±0 and NaN, spelled out.
    let x = Inputs {
        a: [0.0, -0.0, f32::NAN, 1.0, f32::NAN, 2.0, -0.0, 0.0],
        b: [-0.0, 0.0, 1.0, f32::NAN, f32::NAN, 2.0, -0.0, 0.0],
        c: [0.0; 8],
        i: [0; 8],
        j: [0; 8],
        m: 0,
    };
    let o = dispatch(Backend::Scalar, Ops(x));
    let min = &o.f.iter().find(|(n, _)| *n == "min").unwrap().1;
    assert_eq!(min[0].to_bits(), (-0.0f32).to_bits());
    assert_eq!(min[1].to_bits(), 0.0f32.to_bits());
    assert_eq!(min[2], 1.0);
    assert!(min[3].is_nan());
}
