//! Camera controls of the render window: orbit about the target, pan, zoom (dolly), and fly
//! (move the eye, look around). All in f64, so far-from-origin scenes move smoothly.

use glam::DVec3;
use serde::{Deserialize, Serialize};
use viz::ViewCamera;

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum Mode {
    /// Drag orbits about the target; scroll dollies towards it.
    #[default]
    Orbit,
    /// Drag turns the view about the eye; W/A/S/D/Q/E move the eye.
    Fly,
}

fn v(a: [f64; 3]) -> DVec3 {
    DVec3::from_array(a)
}

/// The camera's basis: forward (unit), right, up (unit), and the eye-target distance.
fn basis(c: &ViewCamera) -> Option<(DVec3, DVec3, DVec3, f64)> {
    let d = v(c.target) - v(c.position);
    let dist = d.length();
    let f = d.try_normalize()?;
    let r = f.cross(v(c.up)).try_normalize()?;
    let u = r.cross(f);
    Some((f, r, u, dist))
}

/// Rotates about the target (orbit) or the eye (fly) by a drag of `dx`, `dy` pixels.
pub fn rotate(c: &mut ViewCamera, mode: Mode, dx: f64, dy: f64) {
    if !(dx.is_finite() && dy.is_finite()) {
        return;
    }
    let (yaw, pitch) = (-dx * 0.008, -dy * 0.008);
    match mode {
        Mode::Orbit => c.orbit(yaw, pitch),
        Mode::Fly => {
            let Some((f, r, u, dist)) = basis(c) else { return };
            let q = glam::DQuat::from_axis_angle(v(c.up).normalize_or(u), yaw) * glam::DQuat::from_axis_angle(r, pitch);
            let nf = q * f;
            // Never look straight along `up`.
            if nf.dot(v(c.up).normalize_or(u)).abs() < 0.995 {
                c.target = (v(c.position) + nf * dist).to_array();
            }
        }
    }
}

/// Moves eye and target in the view plane by a drag of `dx`, `dy` pixels of a view `height`
/// pixels high (the point under the cursor at the target's depth follows the cursor).
pub fn pan(c: &mut ViewCamera, dx: f64, dy: f64, height: f64) {
    if !(dx.is_finite() && dy.is_finite() && height.is_finite()) {
        return;
    }
    let Some((_, r, u, dist)) = basis(c) else { return };
    let per_px = 2.0 * dist * (c.fov_y.to_radians() * 0.5).tan() / height.max(1.0);
    let off = (-r * dx + u * dy) * per_px;
    c.position = (v(c.position) + off).to_array();
    c.target = (v(c.target) + off).to_array();
}

/// Dollies towards the target by `steps` (positive: closer), never through it.
pub fn zoom(c: &mut ViewCamera, steps: f64) {
    if !steps.is_finite() {
        return;
    }
    let Some((f, _, _, dist)) = basis(c) else { return };
    // Never closer than f64 can tell eye from target at these coordinates.
    let floor = v(c.target).abs().max_element().max(1.0) * 1e-9;
    let nd = (dist * 0.9f64.powf(steps)).max(floor);
    c.position = (v(c.target) - f * nd).to_array();
}

/// Flies the eye (and target) along forward/right/up by `amount` of the eye-target distance.
pub fn fly(c: &mut ViewCamera, forward: f64, right: f64, up: f64, amount: f64) {
    if ![forward, right, up, amount].iter().all(|x| x.is_finite()) {
        return;
    }
    let Some((f, r, u, dist)) = basis(c) else { return };
    let off = (f * forward + r * right + u * up) * dist * amount;
    c.position = (v(c.position) + off).to_array();
    c.target = (v(c.target) + off).to_array();
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(scale: f64, at: f64) -> ViewCamera {
        ViewCamera { position: [at, at, at - 10.0 * scale], target: [at, at, at], up: [0.0, 1.0, 0.0], fov_y: 40.0 }
    }

    #[test]
    fn orbit_keeps_distance_and_zoom_never_passes_the_target() {
        for (scale, at) in [(1.0, 0.0), (1e-6, 0.0), (1e6, 0.0), (1.0, 1e7)] {
            let mut c = cam(scale, at);
            let d0 = (v(c.target) - v(c.position)).length();
            rotate(&mut c, Mode::Orbit, 120.0, 40.0);
            let d1 = (v(c.target) - v(c.position)).length();
            assert!((d1 - d0).abs() <= d0 * 1e-9, "orbit changed the distance {d0} -> {d1}");
            c.validate().expect("valid after orbit");
            for _ in 0..500 {
                zoom(&mut c, 10.0);
            }
            let d2 = (v(c.target) - v(c.position)).length();
            assert!(d2 > 0.0 && d2 < d0, "zoom went to {d2}");
            c.validate().expect("valid after zoom");
        }
    }

    #[test]
    fn pan_moves_eye_and_target_together_and_fly_moves_forward() {
        let mut c = cam(1.0, 1e7);
        let before = v(c.target) - v(c.position);
        pan(&mut c, 30.0, -12.0, 600.0);
        let after = v(c.target) - v(c.position);
        assert!((before - after).length() < 1e-6);
        assert!(c.target[0] != 1e7, "pan moved sideways");
        let z0 = c.position[2];
        fly(&mut c, 1.0, 0.0, 0.0, 0.1);
        assert!(c.position[2] > z0, "fly moved forward along +z");
        let t0 = c.target;
        rotate(&mut c, Mode::Fly, 50.0, 0.0);
        assert_ne!(c.target, t0, "fly rotation turns the view");
        c.validate().expect("valid after fly");
    }

    #[test]
    fn degenerate_cameras_are_left_alone() {
        let mut c = ViewCamera { position: [0.0; 3], target: [0.0; 3], up: [0.0, 1.0, 0.0], fov_y: 40.0 };
        let before = c;
        pan(&mut c, 10.0, 10.0, 100.0);
        zoom(&mut c, 3.0);
        fly(&mut c, 1.0, 1.0, 1.0, 1.0);
        rotate(&mut c, Mode::Fly, 10.0, 10.0);
        assert_eq!(c, before);
        let mut n = cam(1.0, 0.0);
        pan(&mut n, f64::NAN, 0.0, 100.0);
        zoom(&mut n, f64::INFINITY);
        rotate(&mut n, Mode::Orbit, f64::NAN, 1.0);
        fly(&mut n, 1.0, 0.0, 0.0, f64::NAN);
        assert_eq!(n, cam(1.0, 0.0), "non-finite input moves nothing");
    }
}
