//! Deterministic random numbers per (seed, pixel, sample), and sampling helpers.

use glam::Vec3A;

/// PCG32 (O'Neill): small, fast, and good enough for Monte Carlo sampling.
#[derive(Clone, Debug)]
pub struct Rng {
    state: u64,
    inc: u64,
}

fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl Rng {
    /// The stream of one pixel sample: depends only on the seed, the pixel and the sample index,
    /// so any sample can be traced again identically.
    pub fn for_sample(seed: u64, x: u32, y: u32, sample: u32) -> Rng {
        let a = splitmix(seed ^ splitmix(u64::from(x) | (u64::from(y) << 32)));
        let b = splitmix(a ^ u64::from(sample).wrapping_mul(0xD6E8_FEB8_6659_FD93));
        let mut r = Rng { state: 0, inc: (b << 1) | 1 };
        r.next_u32();
        r.state = r.state.wrapping_add(a);
        r.next_u32();
        r
    }

    #[inline]
    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform in [0, 1).
    #[inline]
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / 16_777_216.0)
    }
}

/// An orthonormal basis around `n` (Duff et al. 2017).
pub fn basis(n: Vec3A) -> (Vec3A, Vec3A) {
    let sign = 1.0f32.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    (Vec3A::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x), Vec3A::new(b, sign + n.y * n.y * a, -n.y))
}

/// Cosine-weighted direction around `n`; pdf = cos / π.
pub fn cosine_hemisphere(n: Vec3A, u1: f32, u2: f32) -> Vec3A {
    let r = u1.sqrt();
    let phi = 2.0 * std::f32::consts::PI * u2;
    let (t, b) = basis(n);
    let z = (1.0 - u1).max(0.0).sqrt();
    (t * (r * phi.cos()) + b * (r * phi.sin()) + n * z).normalize()
}

/// A direction around `axis` distributed as cos^exponent (Phong lobe); pdf = (e+1)/(2π) cos^e.
pub fn phong_lobe(axis: Vec3A, exponent: f32, u1: f32, u2: f32) -> Vec3A {
    let cos_t = u1.powf(1.0 / (exponent + 1.0));
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    let phi = 2.0 * std::f32::consts::PI * u2;
    let (t, b) = basis(axis);
    (t * (sin_t * phi.cos()) + b * (sin_t * phi.sin()) + axis * cos_t).normalize()
}

/// Uniform point on a triangle: barycentric (b1, b2).
pub fn triangle_point(u1: f32, u2: f32) -> (f32, f32) {
    let s = u1.sqrt();
    (1.0 - s, u2 * s)
}
