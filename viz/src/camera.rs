//! The view camera: the renderers' pinhole camera as a projection matrix, so a rasterized layer
//! lines up with the ray-traced image pixel for pixel.
//!
//! Scene-space positions are drawn relative to an *anchor* (the centre of the scene's bounds),
//! subtracted in f64 on the CPU before anything becomes f32 on the GPU: a scene 1e6 units from
//! the origin keeps the precision of one at the origin.

use glam::{DMat4, DVec3, Mat4, Vec4};
use serde::{Deserialize, Serialize};
use store::scene::CameraAttrs;

/// A pinhole camera (same convention as `store::scene::CameraAttrs` and `renderers::Camera`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewCamera {
    pub position: [f64; 3],
    pub target: [f64; 3],
    pub up: [f64; 3],
    /// Vertical field of view in degrees.
    pub fov_y: f64,
}

impl ViewCamera {
    pub fn from_attrs(c: &CameraAttrs) -> ViewCamera {
        let d = |v: [f32; 3]| v.map(f64::from);
        ViewCamera { position: d(c.position), target: d(c.target), up: d(c.up), fov_y: f64::from(c.fov_y) }
    }

    /// A camera that frames the box `lo..hi`, looking down -z as the Cornell box camera does.
    pub fn framing(lo: [f64; 3], hi: [f64; 3], fov_y: f64) -> ViewCamera {
        let (lo, hi) = (DVec3::from_array(lo), DVec3::from_array(hi));
        let c = (lo + hi) * 0.5;
        let r = ((hi - lo).length() * 0.5).max(1e-9);
        let dist = r / (fov_y.to_radians() * 0.5).tan() * 1.05;
        ViewCamera { position: (c - DVec3::Z * dist).to_array(), target: c.to_array(), up: [0.0, 1.0, 0.0], fov_y }
    }

    /// Whether the camera can be used (finite, position ≠ target, up not along the view).
    pub fn validate(&self) -> Result<(), String> {
        let (p, t, u) = (DVec3::from_array(self.position), DVec3::from_array(self.target), DVec3::from_array(self.up));
        if !p.is_finite() || !t.is_finite() || !u.is_finite() || !self.fov_y.is_finite() {
            return Err("camera has NaN or infinite values".into());
        }
        let f = t - p;
        if f.length() == 0.0 {
            return Err("camera position equals its target".into());
        }
        if f.normalize().cross(u).length() < 1e-9 {
            return Err("camera up vector is parallel to the view direction".into());
        }
        if !(self.fov_y > 0.0 && self.fov_y < 180.0) {
            return Err(format!("camera field of view {} is outside (0, 180) degrees", self.fov_y));
        }
        Ok(())
    }

    /// View-projection matrix (clip space of wgpu: depth 0..1, y up) for a `width` × `height`
    /// viewport, of positions given relative to `anchor`. The near/far planes enclose `radius`
    /// around the anchor.
    pub fn view_proj(&self, anchor: [f64; 3], radius: f64, width: u32, height: u32) -> DMat4 {
        let a = DVec3::from_array(anchor);
        let eye = DVec3::from_array(self.position) - a;
        let target = DVec3::from_array(self.target) - a;
        let view = look_at_rh(eye, target, DVec3::from_array(self.up));
        let [near, far] = self.planes(anchor, radius);
        let aspect = f64::from(width) / f64::from(height.max(1));
        perspective_rh(self.fov_y.to_radians(), aspect, near, far) * view
    }

    /// Near and far plane distances that enclose `radius` around `anchor`.
    pub fn planes(&self, anchor: [f64; 3], radius: f64) -> [f64; 2] {
        let dist = (DVec3::from_array(self.position) - DVec3::from_array(anchor)).length();
        let radius = radius.max(1e-9);
        let far = (dist + radius) * 1.5;
        let near = (dist - radius * 1.5).max(far * 1e-5);
        [near, far]
    }

    /// The f32 matrix the shaders use.
    pub fn view_proj_f32(&self, anchor: [f64; 3], radius: f64, width: u32, height: u32) -> Mat4 {
        self.view_proj(anchor, radius, width, height).as_mat4()
    }

    /// Pixel coordinates (x right, y down, pixel (i, j) covers [i, i+1) × [j, j+1)) and depth of
    /// a scene-space point, or `None` behind the camera.
    pub fn project(&self, p: [f64; 3], anchor: [f64; 3], radius: f64, width: u32, height: u32) -> Option<[f64; 3]> {
        let m = self.view_proj(anchor, radius, width, height);
        let q = DVec3::from_array(p) - DVec3::from_array(anchor);
        let c = m * q.extend(1.0);
        if c.w <= 0.0 {
            return None;
        }
        let n = c / c.w;
        Some([(n.x + 1.0) * 0.5 * f64::from(width), (1.0 - n.y) * 0.5 * f64::from(height), n.z])
    }

    /// Orbits the camera about its target by `yaw` and `pitch` radians.
    pub fn orbit(&mut self, yaw: f64, pitch: f64) {
        let t = DVec3::from_array(self.target);
        let up = DVec3::from_array(self.up).normalize();
        let mut off = DVec3::from_array(self.position) - t;
        off = glam::DQuat::from_axis_angle(up, yaw) * off;
        let right = off.cross(up).normalize();
        let rotated = glam::DQuat::from_axis_angle(right, pitch) * off;
        if rotated.normalize().cross(up).length() > 1e-3 {
            off = rotated;
        }
        self.position = (t + off).to_array();
    }
}

/// Right-handed view matrix (camera looks down -z), as the renderers' camera: right = f × up.
fn look_at_rh(eye: DVec3, target: DVec3, up: DVec3) -> DMat4 {
    let f = (target - eye).normalize();
    let s = f.cross(up).normalize();
    let u = s.cross(f);
    DMat4::from_cols(
        glam::DVec4::new(s.x, u.x, -f.x, 0.0),
        glam::DVec4::new(s.y, u.y, -f.y, 0.0),
        glam::DVec4::new(s.z, u.z, -f.z, 0.0),
        glam::DVec4::new(-s.dot(eye), -u.dot(eye), f.dot(eye), 1.0),
    )
}

/// Right-handed perspective projection to wgpu's clip space (depth 0 at `near`, 1 at `far`).
fn perspective_rh(fov_y: f64, aspect: f64, near: f64, far: f64) -> DMat4 {
    let h = 1.0 / (0.5 * fov_y).tan();
    let w = h / aspect;
    let r = far / (near - far);
    DMat4::from_cols(
        glam::DVec4::new(w, 0.0, 0.0, 0.0),
        glam::DVec4::new(0.0, h, 0.0, 0.0),
        glam::DVec4::new(0.0, 0.0, r, -1.0),
        glam::DVec4::new(0.0, 0.0, r * near, 0.0),
    )
}

/// The uniform block every scene-space shader reads (`View` in the WGSL sources).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct ViewUniform {
    pub view_proj: [[f32; 4]; 4],
    /// width, height, line width in pixels, opacity.
    pub viewport: [f32; 4],
    /// Light direction (xyz) for surface shading and a mode word (w).
    pub params: [f32; 4],
}

impl ViewUniform {
    pub fn new(m: Mat4, width: u32, height: u32, line_width: f32, opacity: f32, mode: f32) -> ViewUniform {
        let light = Vec4::new(0.3, 0.8, -0.5, mode);
        ViewUniform {
            view_proj: m.to_cols_array_2d(),
            viewport: [width as f32, height as f32, line_width, opacity],
            params: light.to_array(),
        }
    }
}

/// Where the scene sits: positions on the GPU are relative to `anchor`; `radius` bounds the
/// scene around it (for the depth range).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    pub anchor: [f64; 3],
    pub radius: f64,
}

impl Frame {
    /// A scene-space point as the f32 the GPU draws (subtracted in f64).
    pub fn local(&self, p: [f64; 3]) -> [f32; 3] {
        [(p[0] - self.anchor[0]) as f32, (p[1] - self.anchor[1]) as f32, (p[2] - self.anchor[2]) as f32]
    }
}

/// The one conversion from the view's camera (f64) to a tracer's (f32).
impl From<&ViewCamera> for renderers::Camera {
    fn from(c: &ViewCamera) -> renderers::Camera {
        let v = |a: [f64; 3]| glam::DVec3::from_array(a).as_vec3a();
        renderers::Camera { position: v(c.position), target: v(c.target), up: v(c.up), fov_y: c.fov_y as f32 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cornell() -> ViewCamera {
        ViewCamera {
            position: [278.0, 273.0, -800.0],
            target: [278.0, 273.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y: 2.0 * (12.5f64 / 35.0).atan().to_degrees(),
        }
    }

    #[test]
    fn target_projects_to_the_image_centre_and_validation_names_problems() {
        let c = cornell();
        let p = c.project(c.target, [278.0, 274.0, 280.0], 600.0, 64, 48).unwrap();
        assert!((p[0] - 32.0).abs() < 1e-6 && (p[1] - 24.0).abs() < 1e-6, "{p:?}");
        assert!(c.project([278.0, 273.0, -900.0], [0.0; 3], 600.0, 64, 48).is_none());
        assert!(c.validate().is_ok());
        let mut bad = c;
        bad.up = [0.0, 0.0, 1.0];
        assert!(bad.validate().unwrap_err().contains("parallel"));
        bad = c;
        bad.position[1] = f64::NAN;
        assert!(bad.validate().unwrap_err().contains("NaN"));
    }

    #[test]
    fn depth_converts_back_to_the_distance_along_the_view_axis() {
        // The compositor linearizes depth with the planes; check it against the matrix.
        let c = cornell();
        let (anchor, radius) = ([278.0, 274.0, 280.0], 480.0);
        let [n, f] = c.planes(anchor, radius);
        for d in [n * 1.01, 700.0, 1000.0, 1500.0, f * 0.99] {
            let p = c.project([278.0, 273.0, -800.0 + d], anchor, radius, 64, 48).unwrap();
            let lin = f * n / (f - p[2] * (f - n));
            assert!((lin - d).abs() < 1e-6 * d, "distance {d}: depth {} gives {lin}", p[2]);
        }
    }

    #[test]
    fn orbit_keeps_the_distance_to_the_target() {
        let mut c = cornell();
        let d0 = (DVec3::from_array(c.position) - DVec3::from_array(c.target)).length();
        c.orbit(0.7, 0.3);
        let d1 = (DVec3::from_array(c.position) - DVec3::from_array(c.target)).length();
        assert!((d0 - d1).abs() < 1e-9 * d0);
        assert!(c.validate().is_ok());
    }
}
