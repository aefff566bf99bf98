//! Scattering: evaluating and sampling the materials.

use glam::Vec3A;

use crate::sampling::{Rng, cosine_hemisphere, phong_lobe};
use crate::scene::{Material, MaterialKind};
use std::f32::consts::PI;

/// Which lobe a sampled direction came from (decides the recorded ray kind).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lobe {
    Diffuse,
    Specular,
    Transmission,
}

/// A sampled direction and its weight f·|cos|/pdf.
#[derive(Clone, Copy, Debug)]
pub struct Sample {
    pub dir: Vec3A,
    pub weight: Vec3A,
    pub lobe: Lobe,
    /// A delta lobe (mirror, glass): emission seen along it is counted directly.
    pub delta: bool,
}

pub fn reflect(d: Vec3A, n: Vec3A) -> Vec3A {
    d - n * (2.0 * d.dot(n))
}

fn luminance(c: Vec3A) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// f(wo, wi) for the non-delta materials; `n` faces `wo`.
pub fn eval(m: &Material, n: Vec3A, wo: Vec3A, wi: Vec3A) -> Vec3A {
    if n.dot(wi) <= 0.0 {
        return Vec3A::ZERO;
    }
    match m.kind {
        MaterialKind::Diffuse => m.diffuse / PI,
        MaterialKind::Glossy => {
            let r = reflect(-wo, n);
            let c = r.dot(wi).max(0.0);
            m.diffuse / PI + m.specular * ((m.exponent + 2.0) / (2.0 * PI) * c.powf(m.exponent))
        }
        MaterialKind::Mirror | MaterialKind::Dielectric => Vec3A::ZERO,
    }
}

/// Unpolarized Fresnel reflectance of a smooth dielectric.
pub fn fresnel(cos_i: f32, eta_i: f32, eta_t: f32) -> (f32, f32) {
    let eta = eta_i / eta_t;
    let sin2_t = eta * eta * (1.0 - cos_i * cos_i).max(0.0);
    if sin2_t >= 1.0 {
        return (1.0, 0.0);
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    let rs = (eta_i * cos_i - eta_t * cos_t) / (eta_i * cos_i + eta_t * cos_t);
    let rp = (eta_t * cos_i - eta_i * cos_t) / (eta_t * cos_i + eta_i * cos_t);
    (0.5 * (rs * rs + rp * rp), cos_t)
}

/// Samples a direction. `ng` is the geometric normal (any side), `d` the incoming ray direction.
/// `None` ends the path (direction below the surface).
pub fn sample(m: &Material, ng: Vec3A, d: Vec3A, rng: &mut Rng) -> Option<Sample> {
    let wo = -d;
    let front = ng.dot(wo) >= 0.0;
    let n = if front { ng } else { -ng };
    match m.kind {
        MaterialKind::Diffuse => {
            let wi = cosine_hemisphere(n, rng.next_f32(), rng.next_f32());
            // f·cos/pdf = (ρ/π)·cos / (cos/π) = ρ.
            (n.dot(wi) > 0.0).then_some(Sample { dir: wi, weight: m.diffuse, lobe: Lobe::Diffuse, delta: false })
        }
        MaterialKind::Glossy => {
            let (ld, ls) = (luminance(m.diffuse), luminance(m.specular));
            let pd = if ld + ls > 0.0 { ld / (ld + ls) } else { 1.0 };
            let r = reflect(d, n);
            let (wi, lobe) = if rng.next_f32() < pd {
                (cosine_hemisphere(n, rng.next_f32(), rng.next_f32()), Lobe::Diffuse)
            } else {
                (phong_lobe(r, m.exponent, rng.next_f32(), rng.next_f32()), Lobe::Specular)
            };
            let cos = n.dot(wi);
            if cos <= 0.0 {
                return None;
            }
            let c = r.dot(wi).max(0.0);
            let pdf = pd * cos / PI + (1.0 - pd) * (m.exponent + 1.0) / (2.0 * PI) * c.powf(m.exponent);
            if pdf <= 0.0 {
                return None;
            }
            let f = eval(m, n, wo, wi);
            Some(Sample { dir: wi, weight: f * cos / pdf, lobe, delta: false })
        }
        MaterialKind::Mirror => {
            Some(Sample { dir: reflect(d, n), weight: m.specular, lobe: Lobe::Specular, delta: true })
        }
        MaterialKind::Dielectric => {
            let (eta_i, eta_t) = if front { (1.0, m.ior) } else { (m.ior, 1.0) };
            let cos_i = n.dot(wo).clamp(0.0, 1.0);
            let (f, cos_t) = fresnel(cos_i, eta_i, eta_t);
            if rng.next_f32() < f {
                Some(Sample { dir: reflect(d, n), weight: m.specular, lobe: Lobe::Specular, delta: true })
            } else {
                let eta = eta_i / eta_t;
                let wi = (d * eta + n * (eta * cos_i - cos_t)).normalize();
                // Radiance is scaled by (η_i/η_t)² crossing the interface.
                Some(Sample { dir: wi, weight: m.specular * (eta * eta), lobe: Lobe::Transmission, delta: true })
            }
        }
    }
}
