//! One headless render of a dataset's layers into a picture: what `rtvtk render` and the Python
//! package's `Session.render` both call, with the same options and defaults.

use std::sync::Arc;

use crate::component::Settings;
use crate::components::bvh::BvhSettings;
use crate::components::geometry::{GeometrySettings, SurfaceStyle};
use crate::components::picture::{HeatmapSettings, ImageSettings, ImageSource};
use crate::components::query::QuerySettings;
use crate::components::rays::RaysSettings;
use crate::splat::{DensityScale, RayStyle};
use crate::{Error, Gpu, Pipeline, Result, Sources, ViewCamera};

/// What to draw (`rtvtk render`'s flags).
#[derive(Clone, Debug, PartialEq)]
pub struct RenderRequest {
    /// Layers bottom to top (default: image, composition, rays; geometry in place of the image
    /// when the dataset has none).
    pub layers: Option<Vec<String>>,
    /// The query layer's query (or the heatmap's, when there is no query layer).
    pub sql: Option<String>,
    /// The column that colours the query layer (the heatmap's title).
    pub colour_by: Option<String>,
    /// Rays of this tree only.
    pub tree: Option<u64>,
    /// Rays of the trees of this pixel only.
    pub pixel: Option<[u32; 2]>,
    /// Rays of this sample only.
    pub sample: Option<u32>,
    /// Rays of these kinds only.
    pub kinds: Option<Vec<String>>,
    /// Rays of depths A..=B only.
    pub depth: Option<[u32; 2]>,
    /// At most this many rays (default 10M).
    pub max_rays: Option<u64>,
    /// BVH levels A..=B.
    pub bvh_levels: Option<[u32; 2]>,
    /// Only the BVH nodes that rays visited.
    pub bvh_visited: bool,
    /// Geometry style: wireframe, transparent or opaque.
    pub geometry: String,
    /// The view (default: the dataset's camera).
    pub camera: Option<ViewCamera>,
    /// Picture size (default: the dataset's image size, scaled up to about 640 pixels).
    pub size: Option<[u32; 2]>,
    /// Ray line width in pixels.
    pub line_width: f32,
    /// The image layer's source (`ImageSource::NAMES`).
    pub image_source: String,
    /// Samples per pixel of an image traced from the view.
    pub image_spp: u32,
    /// Legends and colour bars.
    pub legend: bool,
    /// How the rays and query layers draw: lines, alpha or density.
    pub style: RayStyle,
    /// Their opacity (default: 1; in the alpha style, chosen from how many rays cover each pixel).
    pub opacity: Option<f32>,
    /// The density style's scale.
    pub density_scale: DensityScale,
    /// The density style's colour map (default: the rays' own colours, brightness by density).
    pub density_map: Option<String>,
    /// The query layer's colour map for `colour_by` (default: plasma).
    pub map: Option<String>,
}

impl Default for RenderRequest {
    fn default() -> Self {
        RenderRequest {
            layers: None,
            sql: None,
            colour_by: None,
            tree: None,
            pixel: None,
            sample: None,
            kinds: None,
            depth: None,
            max_rays: None,
            bvh_levels: None,
            bvh_visited: false,
            geometry: "wireframe".into(),
            camera: None,
            size: None,
            line_width: 1.5,
            image_source: "auto".into(),
            image_spp: 16,
            legend: true,
            style: RayStyle::Lines,
            opacity: None,
            density_scale: DensityScale::Log,
            density_map: None,
            map: None,
        }
    }
}

impl RenderRequest {
    /// The opacity of the ray and query layers (in the alpha style without one, the most the
    /// automatic choice may take).
    fn opacity(&self) -> f32 {
        self.opacity.unwrap_or(if self.style == RayStyle::Alpha { 0.5 } else { 1.0 })
    }

    /// The settings of layer `kind` from the request.
    fn settings(&self, kind: &str, has_query_layer: bool) -> Result<serde_json::Value> {
        Ok(match kind {
            RaysSettings::KIND => RaysSettings {
                tree: self.tree,
                pixel: self.pixel,
                sample: self.sample,
                kinds: self.kinds.clone(),
                depth: self.depth,
                max_rays: self.max_rays.or(Some(10_000_000)),
                line_width: self.line_width,
                opacity: self.opacity(),
                auto_opacity: self.opacity.is_none(),
                style: self.style,
                density_scale: self.density_scale,
                density_map: self.density_map.clone(),
                ..Default::default()
            }
            .encode(),
            ImageSettings::KIND => {
                let source = ImageSource::try_from(self.image_source.clone()).map_err(Error::Settings)?;
                ImageSettings { source, max_spp: self.image_spp, ..Default::default() }.encode()
            }
            GeometrySettings::KIND => {
                let style: SurfaceStyle = serde_json::from_value(serde_json::Value::String(self.geometry.clone()))
                    .map_err(|_| {
                        Error::Settings(format!(
                            "geometry style {:?}: expected one of {}",
                            self.geometry,
                            SurfaceStyle::NAMES.join(", ")
                        ))
                    })?;
                GeometrySettings { style, opacity: 0.8, line_width: 1.2 }.encode()
            }
            BvhSettings::KIND => {
                let d = BvhSettings::default();
                BvhSettings {
                    only_visited: self.bvh_visited,
                    tree: self.tree,
                    pixel: self.pixel,
                    sample: self.sample,
                    levels: self.bvh_levels.unwrap_or(d.levels),
                    ..d
                }
                .encode()
            }
            QuerySettings::KIND => {
                let Some(sql) = &self.sql else {
                    return Err(Error::Settings("the query layer needs a query (--sql \"SELECT ...\")".into()));
                };
                QuerySettings {
                    sql: sql.clone(),
                    colour_by: self.colour_by.clone(),
                    line_width: self.line_width.max(2.0),
                    opacity: self.opacity(),
                    auto_opacity: self.opacity.is_none(),
                    style: self.style,
                    density_scale: self.density_scale,
                    density_map: self.density_map.clone(),
                    map: self.map.clone().unwrap_or_else(|| QuerySettings::default().map),
                }
                .encode()
            }
            HeatmapSettings::KIND => match (&self.sql, has_query_layer) {
                (Some(sql), false) => HeatmapSettings {
                    sql: sql.clone(),
                    title: self.colour_by.clone().unwrap_or_else(|| "value".into()),
                    ..Default::default()
                }
                .encode(),
                _ => serde_json::Value::Null,
            },
            _ => serde_json::Value::Null,
        })
    }
}

/// Draws `request`'s layers over `sources` on the process's GPU, progressive layers refined to
/// their sample count; the picture (with legends unless asked otherwise) and what the layers
/// reported.
pub fn render(sources: Sources, request: &RenderRequest) -> Result<(image::RgbaImage, Vec<String>)> {
    render_with(sources, request, Arc::default())
}

/// [`render`], with the layers' long loads reported to (and cancellable through) `progress`:
/// a cancelled load keeps what it loaded, and the picture shows that much.
pub fn render_with(
    sources: Sources,
    request: &RenderRequest,
    progress: Arc<crate::component::Progress>,
) -> Result<(image::RgbaImage, Vec<String>)> {
    let layers = match &request.layers {
        Some(l) => l.clone(),
        None => {
            let first = if sources.picture.is_some() { "image" } else { "geometry" };
            let mut l = vec![first.to_string()];
            if sources.scene.is_some() {
                l.push("composition".into());
            }
            l.push("rays".into());
            l
        }
    };
    for l in &layers {
        crate::registry::info(l)?;
    }
    let has_query = layers.iter().any(|l| l == QuerySettings::KIND);
    let mut p = Pipeline::new(Gpu::shared()?, sources);
    p.progress = progress;
    match request.size {
        Some([w, h]) => p.resize(w, h)?,
        None => {
            // Small images are drawn larger (same aspect, so registration holds), with room
            // for legends and lines of a few pixels.
            let [w, h] = p.size();
            let k = 640u32.div_ceil(w.max(h)).clamp(1, 8);
            p.resize(w * k, h * k)?;
        }
    }
    if let Some(c) = request.camera {
        p.set_camera(c)?;
    }
    // A layer whose table is broken is left out, saying why: the rest draw. A layer the dataset
    // cannot feed at all, or asked for with settings it does not take, is an error.
    let mut left_out = Vec::new();
    for l in &layers {
        let s = request.settings(l, has_query)?;
        match p.add(l, &s) {
            Ok(_) => {}
            Err(e) if store::says_unavailable(&e.to_string()) => {
                left_out.push(format!("warning: the {l} layer is not drawn: {e}"));
            }
            Err(e) => return Err(Error::Settings(format!("adding the {l} layer: {e}"))),
        }
    }
    while p.idle()? {}
    let img = p.snapshot(request.legend)?;
    let mut report = left_out;
    report.extend(p.report());
    Ok((img, report))
}
