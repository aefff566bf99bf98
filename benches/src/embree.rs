//! A minimal binding to Embree 3 (Debian's `libembree-dev`), only for `rtvtk bench trace`
//! (`cargo build --release --features embree`). Not part of CI.

use std::ffi::c_void;

#[repr(C)]
struct RTCIntersectContext {
    flags: u32,
    filter: *const c_void,
    inst_id: [u32; 1],
}

#[repr(C, align(16))]
#[derive(Clone, Copy)]
struct RTCRay {
    org: [f32; 3],
    tnear: f32,
    dir: [f32; 3],
    time: f32,
    tfar: f32,
    mask: u32,
    id: u32,
    flags: u32,
}

#[repr(C, align(16))]
#[derive(Clone, Copy)]
struct RTCHit {
    ng: [f32; 3],
    u: f32,
    v: f32,
    prim_id: u32,
    geom_id: u32,
    inst_id: [u32; 1],
}

#[repr(C, align(16))]
struct RTCRayHit {
    ray: RTCRay,
    hit: RTCHit,
}

#[link(name = "embree3")]
unsafe extern "C" {
    fn rtcNewDevice(config: *const i8) -> *mut c_void;
    fn rtcReleaseDevice(device: *mut c_void);
    fn rtcNewScene(device: *mut c_void) -> *mut c_void;
    fn rtcReleaseScene(scene: *mut c_void);
    fn rtcNewGeometry(device: *mut c_void, kind: u32) -> *mut c_void;
    fn rtcSetNewGeometryBuffer(
        geom: *mut c_void,
        kind: u32,
        slot: u32,
        format: u32,
        stride: usize,
        count: usize,
    ) -> *mut c_void;
    fn rtcCommitGeometry(geom: *mut c_void);
    fn rtcAttachGeometry(scene: *mut c_void, geom: *mut c_void) -> u32;
    fn rtcReleaseGeometry(geom: *mut c_void);
    fn rtcCommitScene(scene: *mut c_void);
    fn rtcIntersect1(scene: *mut c_void, ctx: *mut RTCIntersectContext, rayhit: *mut RTCRayHit);
    fn rtcOccluded1(scene: *mut c_void, ctx: *mut RTCIntersectContext, ray: *mut RTCRay);
}

const RTC_GEOMETRY_TYPE_TRIANGLE: u32 = 0;
const RTC_BUFFER_TYPE_INDEX: u32 = 0;
const RTC_BUFFER_TYPE_VERTEX: u32 = 1;
const RTC_FORMAT_UINT3: u32 = 0x5003;
const RTC_FORMAT_FLOAT3: u32 = 0x9003;
const INVALID: u32 = u32::MAX;

/// An Embree scene over triangles.
pub struct EmbreeScene {
    device: *mut c_void,
    scene: *mut c_void,
}

impl EmbreeScene {
    pub fn new(tris: &[[glam::Vec3A; 3]]) -> Option<EmbreeScene> {
        // SAFETY: plain C API use; buffers are sized as declared before being written.
        unsafe {
            let device = rtcNewDevice(std::ptr::null());
            if device.is_null() {
                return None;
            }
            let scene = rtcNewScene(device);
            let geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
            let v = rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 12, tris.len() * 3)
                as *mut f32;
            let ix =
                rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 12, tris.len()) as *mut u32;
            if v.is_null() || ix.is_null() {
                return None;
            }
            for (i, t) in tris.iter().enumerate() {
                for k in 0..3 {
                    for c in 0..3 {
                        *v.add((i * 3 + k) * 3 + c) = t[k][c];
                    }
                    *ix.add(i * 3 + k) = (i * 3 + k) as u32;
                }
            }
            rtcCommitGeometry(geom);
            rtcAttachGeometry(scene, geom);
            rtcReleaseGeometry(geom);
            rtcCommitScene(scene);
            Some(EmbreeScene { device, scene })
        }
    }

    fn ray(o: glam::Vec3A, d: glam::Vec3A, tfar: f32) -> RTCRay {
        RTCRay { org: o.to_array(), tnear: 0.0, dir: d.to_array(), time: 0.0, tfar, mask: u32::MAX, id: 0, flags: 0 }
    }

    /// Closest hit distance (rtcIntersect1).
    pub fn intersect(&self, o: glam::Vec3A, d: glam::Vec3A, tfar: f32) -> Option<f32> {
        let mut ctx = RTCIntersectContext { flags: 0, filter: std::ptr::null(), inst_id: [INVALID] };
        let mut rh = RTCRayHit {
            ray: Self::ray(o, d, tfar),
            hit: RTCHit { ng: [0.0; 3], u: 0.0, v: 0.0, prim_id: INVALID, geom_id: INVALID, inst_id: [INVALID] },
        };
        // SAFETY: valid scene, context and ray-hit structures laid out as Embree 3 declares them.
        unsafe { rtcIntersect1(self.scene, &mut ctx, &mut rh) };
        (rh.hit.geom_id != INVALID).then_some(rh.ray.tfar)
    }

    /// Whether anything lies on the segment (rtcOccluded1).
    pub fn occluded(&self, o: glam::Vec3A, d: glam::Vec3A, tfar: f32) -> bool {
        let mut ctx = RTCIntersectContext { flags: 0, filter: std::ptr::null(), inst_id: [INVALID] };
        let mut r = Self::ray(o, d, tfar);
        // SAFETY: as above.
        unsafe { rtcOccluded1(self.scene, &mut ctx, &mut r) };
        r.tfar == f32::NEG_INFINITY
    }
}

impl Drop for EmbreeScene {
    fn drop(&mut self) {
        // SAFETY: created by new(), released once.
        unsafe {
            rtcReleaseScene(self.scene);
            rtcReleaseDevice(self.device);
        }
    }
}
