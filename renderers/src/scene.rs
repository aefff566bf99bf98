//! Scenes: triangles with materials, emitters, and a camera. Built-in Cornell boxes or OBJ/MTL.

use glam::Vec3A;
use std::path::Path;

use crate::geometry::{is_degenerate, triangle_normal};
use crate::{Error, Result};

/// How a surface scatters light.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum MaterialKind {
    /// Lambertian with albedo `diffuse`.
    Diffuse,
    /// Lambertian `diffuse` plus a normalized Phong lobe `specular` with `exponent`.
    Glossy,
    /// Perfect mirror with reflectance `specular`.
    Mirror,
    /// Smooth dielectric (glass) with index of refraction `ior`, Fresnel reflection/refraction.
    Dielectric,
}

/// A material, as read from MTL or built in.
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    pub name: String,
    pub kind: MaterialKind,
    pub diffuse: Vec3A,
    pub specular: Vec3A,
    pub exponent: f32,
    pub ior: f32,
    pub emission: Vec3A,
}

impl Material {
    pub fn diffuse(name: &str, albedo: [f32; 3]) -> Material {
        Material {
            name: name.into(),
            kind: MaterialKind::Diffuse,
            diffuse: Vec3A::from_array(albedo),
            specular: Vec3A::ZERO,
            exponent: 0.0,
            ior: 1.0,
            emission: Vec3A::ZERO,
        }
    }

    pub fn is_emissive(&self) -> bool {
        self.emission.max_element() > 0.0
    }
}

/// A pinhole camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub position: Vec3A,
    pub target: Vec3A,
    pub up: Vec3A,
    /// Vertical field of view in degrees.
    pub fov_y: f32,
}

impl Camera {
    /// The primary ray direction through film position (px, py) in pixels of a w × h image.
    pub fn direction(&self, px: f32, py: f32, w: u32, h: u32) -> Vec3A {
        let forward = (self.target - self.position).normalize();
        let right = forward.cross(self.up).normalize();
        let up = right.cross(forward);
        let tan = (self.fov_y.to_radians() * 0.5).tan();
        let aspect = w as f32 / h.max(1) as f32;
        let sx = (2.0 * px / w as f32 - 1.0) * tan * aspect;
        let sy = (1.0 - 2.0 * py / h as f32) * tan;
        (forward + right * sx + up * sy).normalize()
    }
}

/// What loading found and did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct LoadReport {
    pub triangles: usize,
    /// Degenerate triangles (no area) skipped.
    pub degenerate_skipped: usize,
    pub materials: usize,
    pub emitters: usize,
}

/// A scene ready to trace.
#[derive(Clone, Debug)]
pub struct Scene {
    pub name: String,
    pub tris: Vec<[Vec3A; 3]>,
    /// Unit geometric normal per triangle.
    pub normals: Vec<Vec3A>,
    pub tri_material: Vec<u32>,
    pub materials: Vec<Material>,
    /// Emissive triangles, and the cumulative distribution of their areas.
    pub lights: Vec<u32>,
    pub light_cdf: Vec<f32>,
    pub light_area: f32,
    pub camera: Camera,
    pub report: LoadReport,
}

impl Scene {
    /// Assembles a scene, skipping (and counting) degenerate triangles.
    pub fn new(
        name: &str,
        tris: Vec<[Vec3A; 3]>,
        tri_material: Vec<u32>,
        materials: Vec<Material>,
        camera: Camera,
    ) -> Result<Scene> {
        if tris.len() != tri_material.len() {
            return Err(Error::Scene("one material index per triangle expected".into()));
        }
        let mut s = Scene {
            name: name.into(),
            tris: Vec::with_capacity(tris.len()),
            normals: Vec::with_capacity(tris.len()),
            tri_material: Vec::with_capacity(tris.len()),
            materials,
            lights: Vec::new(),
            light_cdf: Vec::new(),
            light_area: 0.0,
            camera,
            report: LoadReport::default(),
        };
        for (t, m) in tris.into_iter().zip(tri_material) {
            if m as usize >= s.materials.len() {
                return Err(Error::Scene(format!("material index {m} out of range ({} materials)", s.materials.len())));
            }
            if is_degenerate(t[0], t[1], t[2]) {
                s.report.degenerate_skipped += 1;
                continue;
            }
            s.normals.push(triangle_normal(t[0], t[1], t[2]).normalize());
            s.tris.push(t);
            s.tri_material.push(m);
        }
        s.lights = (0..s.tris.len() as u32).filter(|&i| s.material_of(i).is_emissive()).collect();
        s.index_emitters();
        s.report.triangles = s.tris.len();
        s.report.materials = s.materials.len();
        s.report.emitters = s.lights.len();
        if s.tris.is_empty() {
            return Err(Error::Scene(format!("scene {name:?} has no usable triangles")));
        }
        Ok(s)
    }

    /// Recomputes the emitters' cumulative area distribution from their triangles.
    fn index_emitters(&mut self) {
        self.light_area = 0.0;
        self.light_cdf.clear();
        for &l in &self.lights {
            let t = self.tris[l as usize];
            self.light_area += 0.5 * triangle_normal(t[0], t[1], t[2]).length();
            self.light_cdf.push(self.light_area);
        }
    }

    /// Area of the `i`-th emitter.
    pub fn emitter_area(&self, i: usize) -> f32 {
        self.light_cdf[i] - if i == 0 { 0.0 } else { self.light_cdf[i - 1] }
    }

    /// The emitter a uniform number `u` in [0, 1) picks, with probability proportional to area.
    pub fn pick_emitter(&self, u: f32) -> usize {
        let target = u * self.light_area;
        self.light_cdf.partition_point(|&c| c <= target).min(self.lights.len().saturating_sub(1))
    }

    pub fn material_of(&self, prim: u32) -> &Material {
        &self.materials[self.tri_material[prim as usize] as usize]
    }

    /// Whether any material is a dielectric (only then is the transmission path used).
    pub fn has_dielectric(&self) -> bool {
        self.materials.iter().any(|m| m.kind == MaterialKind::Dielectric)
    }

    /// Bounds of all vertices.
    pub fn bounds(&self) -> (Vec3A, Vec3A) {
        let mut lo = Vec3A::splat(f32::INFINITY);
        let mut hi = Vec3A::splat(f32::NEG_INFINITY);
        for t in &self.tris {
            for v in t {
                lo = lo.min(*v);
                hi = hi.max(*v);
            }
        }
        (lo, hi)
    }

    /// The scene scaled by `s` and moved by `offset` (for the extreme-scale tests).
    pub fn transformed(&self, s: f32, offset: Vec3A) -> Scene {
        let f = |v: Vec3A| v * s + offset;
        let mut out = self.clone();
        for t in &mut out.tris {
            *t = [f(t[0]), f(t[1]), f(t[2])];
        }
        out.index_emitters();
        out.camera.position = f(out.camera.position);
        out.camera.target = f(out.camera.target);
        out
    }
}

/// The built-in scenes, so nothing has to be downloaded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BuiltinScene {
    /// The Cornell box with its measured geometry.
    Cornell,
    /// The Cornell box with a glass tall block (the paper's Figure 9).
    CornellGlass,
    /// The Cornell box with a glossy floor (the paper's Figure 3).
    Glossy,
}

impl BuiltinScene {
    pub fn parse(name: &str) -> Option<BuiltinScene> {
        match name {
            "cornell" => Some(BuiltinScene::Cornell),
            "cornell-glass" => Some(BuiltinScene::CornellGlass),
            "glossy" => Some(BuiltinScene::Glossy),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            BuiltinScene::Cornell => "cornell",
            BuiltinScene::CornellGlass => "cornell-glass",
            BuiltinScene::Glossy => "glossy",
        }
    }

    /// Builds the scene; `subdivide` > 1 splits every quad into subdivide² quads (for
    /// benchmarks that need more triangles with the same shape).
    pub fn build(self, subdivide: u32) -> Result<Scene> {
        cornell(self, subdivide.max(1))
    }
}

type Quad = [[f32; 3]; 4];

// The Cornell box data as measured (Cornell University Program of Computer Graphics), in mm.
const FLOOR: Quad = [[552.8, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 559.2], [549.6, 0.0, 559.2]];
const BACK: Quad = [[549.6, 0.0, 559.2], [0.0, 0.0, 559.2], [0.0, 548.8, 559.2], [556.0, 548.8, 559.2]];
const GREEN: Quad = [[0.0, 0.0, 559.2], [0.0, 0.0, 0.0], [0.0, 548.8, 0.0], [0.0, 548.8, 559.2]];
const RED: Quad = [[552.8, 0.0, 0.0], [549.6, 0.0, 559.2], [556.0, 548.8, 559.2], [556.0, 548.8, 0.0]];
// The light is flush with the ceiling, filling a hole cut in it (as in the real box): the ceiling
// cannot see the light (no near-singular geometry term at the light's edges), and the two never
// overlap, however coarse the floating-point grid (the box moved 1e6 mm from the origin).
const LIGHT: Quad = [[343.0, 548.8, 227.0], [343.0, 548.8, 332.0], [213.0, 548.8, 332.0], [213.0, 548.8, 227.0]];
const CEILING_PARTS: [Quad; 4] = [
    [[556.0, 548.8, 0.0], [556.0, 548.8, 227.0], [0.0, 548.8, 227.0], [0.0, 548.8, 0.0]],
    [[556.0, 548.8, 332.0], [556.0, 548.8, 559.2], [0.0, 548.8, 559.2], [0.0, 548.8, 332.0]],
    [[213.0, 548.8, 227.0], [213.0, 548.8, 332.0], [0.0, 548.8, 332.0], [0.0, 548.8, 227.0]],
    [[556.0, 548.8, 227.0], [556.0, 548.8, 332.0], [343.0, 548.8, 332.0], [343.0, 548.8, 227.0]],
];
const SHORT: [Quad; 5] = [
    [[130.0, 165.0, 65.0], [82.0, 165.0, 225.0], [240.0, 165.0, 272.0], [290.0, 165.0, 114.0]],
    [[290.0, 0.0, 114.0], [290.0, 165.0, 114.0], [240.0, 165.0, 272.0], [240.0, 0.0, 272.0]],
    [[130.0, 0.0, 65.0], [130.0, 165.0, 65.0], [290.0, 165.0, 114.0], [290.0, 0.0, 114.0]],
    [[82.0, 0.0, 225.0], [82.0, 165.0, 225.0], [130.0, 165.0, 65.0], [130.0, 0.0, 65.0]],
    [[240.0, 0.0, 272.0], [240.0, 165.0, 272.0], [82.0, 165.0, 225.0], [82.0, 0.0, 225.0]],
];
const TALL: [Quad; 5] = [
    [[423.0, 330.0, 247.0], [265.0, 330.0, 296.0], [314.0, 330.0, 456.0], [472.0, 330.0, 406.0]],
    [[423.0, 0.0, 247.0], [423.0, 330.0, 247.0], [472.0, 330.0, 406.0], [472.0, 0.0, 406.0]],
    [[472.0, 0.0, 406.0], [472.0, 330.0, 406.0], [314.0, 330.0, 456.0], [314.0, 0.0, 456.0]],
    [[314.0, 0.0, 456.0], [314.0, 330.0, 456.0], [265.0, 330.0, 296.0], [265.0, 0.0, 296.0]],
    [[265.0, 0.0, 296.0], [265.0, 330.0, 296.0], [423.0, 330.0, 247.0], [423.0, 0.0, 247.0]],
];

fn push_quad(q: &Quad, m: u32, n: u32, tris: &mut Vec<[Vec3A; 3]>, mats: &mut Vec<u32>) {
    let p = |u: f32, v: f32| -> Vec3A {
        let a = Vec3A::from_array(q[0]).lerp(Vec3A::from_array(q[1]), u);
        let b = Vec3A::from_array(q[3]).lerp(Vec3A::from_array(q[2]), u);
        a.lerp(b, v)
    };
    let k = n as f32;
    for i in 0..n {
        for j in 0..n {
            let (u0, u1, v0, v1) = (i as f32 / k, (i + 1) as f32 / k, j as f32 / k, (j + 1) as f32 / k);
            let (a, b, c, d) = (p(u0, v0), p(u1, v0), p(u1, v1), p(u0, v1));
            tris.push([a, b, c]);
            tris.push([a, c, d]);
            mats.push(m);
            mats.push(m);
        }
    }
}

fn cornell(which: BuiltinScene, n: u32) -> Result<Scene> {
    let white = Material::diffuse("white", [0.725, 0.71, 0.68]);
    let red = Material::diffuse("red", [0.63, 0.065, 0.05]);
    let green = Material::diffuse("green", [0.14, 0.45, 0.091]);
    let mut light = Material::diffuse("light", [0.78, 0.78, 0.78]);
    light.emission = Vec3A::new(17.0, 12.0, 4.0);
    let mut materials = vec![white, red, green, light];
    let floor_mat = if which == BuiltinScene::Glossy {
        materials.push(Material {
            name: "glossy-floor".into(),
            kind: MaterialKind::Glossy,
            diffuse: Vec3A::new(0.3, 0.3, 0.3),
            specular: Vec3A::new(0.6, 0.6, 0.6),
            exponent: 200.0,
            ior: 1.0,
            emission: Vec3A::ZERO,
        });
        4
    } else {
        0
    };
    let tall_mat = if which == BuiltinScene::CornellGlass {
        materials.push(Material {
            name: "glass".into(),
            kind: MaterialKind::Dielectric,
            diffuse: Vec3A::ZERO,
            specular: Vec3A::ONE,
            exponent: 0.0,
            ior: 1.5,
            emission: Vec3A::ZERO,
        });
        materials.len() as u32 - 1
    } else {
        0
    };
    let mut tris = Vec::new();
    let mut mats = Vec::new();
    push_quad(&FLOOR, floor_mat, n, &mut tris, &mut mats);
    for q in &CEILING_PARTS {
        push_quad(q, 0, n, &mut tris, &mut mats);
    }
    push_quad(&BACK, 0, n, &mut tris, &mut mats);
    push_quad(&GREEN, 2, n, &mut tris, &mut mats);
    push_quad(&RED, 1, n, &mut tris, &mut mats);
    push_quad(&LIGHT, 3, 1, &mut tris, &mut mats);
    for q in &SHORT {
        push_quad(q, 0, n, &mut tris, &mut mats);
    }
    for q in &TALL {
        push_quad(q, tall_mat, n, &mut tris, &mut mats);
    }
    // The glass block has no bottom face: it stands on the floor, and a bottom face would lie in
    // the floor's plane, where which of two coplanar triangles a ray hits is decided by traversal
    // order alone (the CPU BVH took the floor, the GPU's the glass, whose exit ray then went
    // out under the floor: the GPU image was 2.2 % darker). A ray inside the glass going down
    // hits the floor; one coming up from it leaves through the sides or the top, the interfaces
    // being told apart by the normals' orientation, so the solid need not be closed.
    let camera = Camera {
        position: Vec3A::new(278.0, 273.0, -800.0),
        target: Vec3A::new(278.0, 273.0, 0.0),
        up: Vec3A::Y,
        // 35 mm lens on a 25 mm film.
        fov_y: 2.0 * (12.5f32 / 35.0).atan().to_degrees(),
    };
    Scene::new(which.name(), tris, mats, materials, camera)
}

/// Checks every `v` line of an OBJ before tobj parses it, so bad vertices get a line number.
fn prevalidate_obj(path: &Path, text: &str) -> Result<()> {
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        let Some(rest) = line.strip_prefix("v ").or_else(|| line.strip_prefix("v\t")) else { continue };
        let coords: Vec<&str> = rest.split_whitespace().collect();
        if coords.len() < 3 {
            return Err(Error::ObjLine {
                path: path.into(),
                line: i + 1,
                message: format!("vertex needs 3 coordinates, found {}: {line:?}", coords.len()),
            });
        }
        for c in &coords[..3] {
            let v: f32 = c.parse().map_err(|_| Error::ObjLine {
                path: path.into(),
                line: i + 1,
                message: format!("vertex coordinate {c:?} is not a number"),
            })?;
            if !v.is_finite() {
                return Err(Error::ObjLine {
                    path: path.into(),
                    line: i + 1,
                    message: format!("vertex coordinate {c:?} is NaN or infinite; expected a finite number"),
                });
            }
        }
    }
    Ok(())
}

fn material_from_mtl(m: &tobj::Material) -> Material {
    let v = |a: Option<[f32; 3]>| Vec3A::from_array(a.unwrap_or([0.0; 3]));
    let param = |k: &str| m.unknown_param.get(k).map(|s| s.trim().to_string());
    let parse3 = |s: Option<String>| -> Option<[f32; 3]> {
        let s = s?;
        let v: Vec<f32> = s.split_whitespace().filter_map(|x| x.parse().ok()).collect();
        match v.len() {
            1 => Some([v[0]; 3]),
            3 => Some([v[0], v[1], v[2]]),
            _ => None,
        }
    };
    let illum = m.illumination_model.unwrap_or(2);
    let dissolve = m.dissolve.unwrap_or(1.0);
    let tr = param("Tr").and_then(|s| s.parse::<f32>().ok()).unwrap_or(0.0);
    let mut diffuse = v(m.diffuse).clamp(Vec3A::ZERO, Vec3A::ONE);
    let mut specular = v(m.specular).clamp(Vec3A::ZERO, Vec3A::ONE);
    let exponent = m.shininess.unwrap_or(0.0).max(0.0);
    let emission = Vec3A::from_array(m.emissive.or_else(|| parse3(param("Ke"))).unwrap_or([0.0; 3])).max(Vec3A::ZERO);
    let kind = if dissolve < 1.0 || tr > 0.0 || matches!(illum, 4 | 6 | 7) {
        MaterialKind::Dielectric
    } else if (matches!(illum, 3 | 5) || exponent >= 10_000.0) && specular.max_element() > 0.0 {
        MaterialKind::Mirror
    } else if specular.max_element() > 0.0 && exponent > 0.0 {
        MaterialKind::Glossy
    } else {
        MaterialKind::Diffuse
    };
    // No material may create energy: diffuse + specular albedo at most 1 per channel.
    let total = (diffuse + specular).max_element();
    if kind == MaterialKind::Glossy && total > 1.0 {
        diffuse /= total;
        specular /= total;
    }
    Material {
        name: m.name.clone(),
        kind,
        diffuse,
        specular,
        exponent,
        ior: m.optical_density.filter(|n| *n >= 1.0 && n.is_finite()).unwrap_or(1.5),
        emission,
    }
}

/// Loads an OBJ (and the MTL files it names). Missing MTL materials fall back to a grey diffuse.
pub fn load_obj(path: &Path, camera: Option<Camera>) -> Result<Scene> {
    let text =
        std::fs::read_to_string(path).map_err(|e| Error::Io { what: "the OBJ file", path: path.into(), source: e })?;
    prevalidate_obj(path, &text)?;
    let opts = tobj::LoadOptions { triangulate: true, single_index: false, ignore_points: true, ignore_lines: true };
    let (models, mtls) =
        tobj::load_obj(path, &opts).map_err(|e| Error::Obj { path: path.into(), message: e.to_string() })?;
    let mut materials = vec![Material::diffuse("default", [0.7, 0.7, 0.7])];
    match mtls {
        Ok(ms) => materials.extend(ms.iter().map(material_from_mtl)),
        Err(tobj::LoadError::OpenFileFailed) => {
            return Err(Error::Obj {
                path: path.into(),
                message: "a material library (mtllib) named by the OBJ cannot be opened".into(),
            });
        }
        Err(e) => return Err(Error::Obj { path: path.into(), message: format!("material library: {e}") }),
    }
    let mut tris = Vec::new();
    let mut mats = Vec::new();
    for m in &models {
        let mesh = &m.mesh;
        let mat = mesh.material_id.map_or(0, |i| i as u32 + 1);
        if mat as usize >= materials.len() {
            return Err(Error::Obj {
                path: path.into(),
                message: format!("object {:?} uses material {} that the MTL does not define", m.name, mat - 1),
            });
        }
        let p = |i: u32| -> Option<Vec3A> {
            let i = i as usize * 3;
            Some(Vec3A::new(*mesh.positions.get(i)?, *mesh.positions.get(i + 1)?, *mesh.positions.get(i + 2)?))
        };
        for f in mesh.indices.chunks_exact(3) {
            match (p(f[0]), p(f[1]), p(f[2])) {
                (Some(a), Some(b), Some(c)) => {
                    tris.push([a, b, c]);
                    mats.push(mat);
                }
                _ => {
                    return Err(Error::Obj {
                        path: path.into(),
                        message: format!("object {:?} has a face index out of range", m.name),
                    });
                }
            }
        }
    }
    let name = path.file_stem().map_or("obj".into(), |s| s.to_string_lossy().to_string());
    let auto = {
        let (mut lo, mut hi) = (Vec3A::splat(f32::INFINITY), Vec3A::splat(f32::NEG_INFINITY));
        for t in &tris {
            for v in t {
                lo = lo.min(*v);
                hi = hi.max(*v);
            }
        }
        let center = (lo + hi) * 0.5;
        let radius = ((hi - lo).length() * 0.5).max(1e-6);
        Camera { position: center + Vec3A::new(0.0, 0.0, radius * 2.7), target: center, up: Vec3A::Y, fov_y: 40.0 }
    };
    Scene::new(&name, tris, mats, materials, camera.unwrap_or(auto))
}
