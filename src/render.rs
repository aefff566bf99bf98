//! `rtvtk render`: the layered visualizer, headless, into a PNG.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Parser;
use rtvtk_viz::{Sources, ViewCamera};

#[derive(Parser, Debug)]
pub struct RenderArgs {
    /// The dataset directory (or, with --connect, none: the service's dataset is drawn).
    #[arg(required_unless_present = "connect", conflicts_with = "connect")]
    pub dataset: Option<PathBuf>,
    /// Draw a dataset an `rtvtk serve` service serves (`grpc://HOST:PORT`): scene, camera and
    /// rays are read through the service (its recorded picture is not served: the image layer
    /// traces the view).
    #[arg(long, value_name = "grpc://HOST:PORT")]
    pub connect: Option<String>,
    /// The service's dataset, where it serves several (default: its first).
    #[arg(long = "dataset", requires = "connect", value_name = "NAME")]
    pub served: Option<String>,
    /// A file holding the service's bearer token (or the environment variable RTVTK_TOKEN).
    #[arg(long, requires = "connect")]
    pub token_file: Option<PathBuf>,
    /// Layers bottom to top: image, geometry, composition, rays, bvh, query, heatmap
    /// (default: image, composition, rays; geometry in place of the image when it has none).
    #[arg(long, value_delimiter = ',')]
    pub layers: Option<Vec<String>>,
    /// The query the `query` layer draws (or the heatmap's, when there is no query layer).
    #[arg(long)]
    pub sql: Option<String>,
    /// Column that colours the query layer's rows.
    #[arg(long)]
    pub colour_by: Option<String>,
    /// Rays of this tree only.
    #[arg(long, conflicts_with = "pixel")]
    pub tree: Option<u64>,
    /// Rays of the trees of this pixel only, X,Y.
    #[arg(long, value_parser = crate::args::parse_pixel)]
    pub pixel: Option<(u32, u32)>,
    /// Rays of this sample only.
    #[arg(long)]
    pub sample: Option<u32>,
    /// Rays of these kinds only (comma separated).
    #[arg(long, value_delimiter = ',')]
    pub kinds: Option<Vec<String>>,
    /// Rays of depths A..B only (inclusive).
    #[arg(long, value_parser = parse_range)]
    pub depth: Option<[u32; 2]>,
    /// At most this many rays.
    #[arg(long)]
    pub max_rays: Option<u64>,
    /// BVH levels A..B (inclusive).
    #[arg(long, value_parser = parse_range)]
    pub bvh_levels: Option<[u32; 2]>,
    /// Only the BVH nodes that rays visited (needs a recording with --record-visits).
    #[arg(long)]
    pub bvh_visited: bool,
    /// Geometry style: wireframe, transparent or opaque.
    #[arg(long, default_value = "wireframe")]
    pub geometry: String,
    /// Camera POS:TARGET[:FOV], e.g. 278,273,-800:278,273,0:40 (default: the dataset's).
    #[arg(long, value_parser = parse_camera)]
    pub camera: Option<ViewCamera>,
    /// Picture size WxH (default: the dataset's image size).
    #[arg(long, value_parser = crate::args::parse_size)]
    pub size: Option<(u32, u32)>,
    /// Ray line width in pixels.
    #[arg(long, default_value_t = 1.5)]
    pub line_width: f32,
    /// The image layer's source: auto (the recorded picture at the recorded camera, else traced
    /// from the view: on the GPU where the adapter allows, else on the CPU), dataset, cpu or gpu.
    #[arg(long, default_value = "auto", value_parser = parse_image_source)]
    pub image_source: String,
    /// Samples per pixel of an image traced from the view (`--camera` away from the recorded one).
    #[arg(long, default_value_t = 16, value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub image_spp: u32,
    /// No legends or colour bars.
    #[arg(long)]
    pub no_legend: bool,
    /// How the rays and query layers draw: lines (opaque), alpha (translucent, order
    /// independent) or density (rays per pixel, with a colour bar).
    #[arg(long, default_value = "lines")]
    pub style: rtvtk_viz::splat::RayStyle,
    /// Opacity of the rays and query layers, 0..1 (default 1; in the alpha style, chosen so
    /// that nine in ten covered pixels stay at most half covered).
    #[arg(long)]
    pub opacity: Option<f32>,
    /// The density style's scale: log or linear.
    #[arg(long, default_value = "log")]
    pub density_scale: rtvtk_viz::splat::DensityScale,
    /// The density style's colour map (default: the rays' own colours, brightness by density).
    #[arg(long)]
    pub density_map: Option<String>,
    /// The colour map of the query layer's --colour-by column.
    #[arg(long)]
    pub map: Option<String>,
    #[arg(long)]
    pub out: PathBuf,
}

/// `--image-source`: one of `ImageSource::NAMES` (`cpu` and `trace` are read as `path`).
fn parse_image_source(s: &str) -> Result<String, String> {
    rtvtk_viz::components::picture::ImageSource::try_from(s.to_string()).map(String::from)
}

fn parse_range(s: &str) -> Result<[u32; 2], String> {
    let (a, b) = s.split_once("..").unwrap_or((s, s));
    let p = |v: &str| v.trim().parse::<u32>().map_err(|_| format!("bad range {s:?}: expected A..B with integers"));
    let r = [p(a)?, p(b)?];
    if r[0] > r[1] {
        return Err(format!("bad range {s:?}: the start is after the end"));
    }
    Ok(r)
}

fn parse_camera(s: &str) -> Result<ViewCamera, String> {
    let parts: Vec<&str> = s.split(':').collect();
    if !(2..=3).contains(&parts.len()) {
        return Err(format!("bad camera {s:?}: expected POS:TARGET[:FOV], e.g. 0,1,5:0,1,0:45"));
    }
    let v = |p: &str| -> Result<[f64; 3], String> {
        let n: Vec<f64> = p
            .split(',')
            .map(|x| x.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| format!("bad camera {s:?}: {p:?} is not X,Y,Z"))?;
        n.try_into().map_err(|_| format!("bad camera {s:?}: {p:?} is not three numbers"))
    };
    let fov = match parts.get(2) {
        Some(f) => f.parse::<f64>().map_err(|_| format!("bad camera {s:?}: field of view {f:?} is not a number"))?,
        None => 40.0,
    };
    let c = ViewCamera { position: v(parts[0])?, target: v(parts[1])?, up: [0.0, 1.0, 0.0], fov_y: fov };
    c.validate().map_err(|e| format!("bad camera {s:?}: {e}"))?;
    Ok(c)
}

/// Renders the layers of a dataset into a PNG; returns what the layers reported.
pub fn render_to_png(a: &RenderArgs) -> Result<Vec<String>> {
    let sources = match (&a.dataset, &a.connect) {
        (Some(dir), _) => Sources::open(dir).with_context(|| format!("opening {}", dir.display()))?,
        (None, Some(url)) => served(a, url)?,
        (None, None) => bail!("no dataset: give a dataset directory or --connect grpc://HOST:PORT"),
    };
    let request = rtvtk_viz::headless::RenderRequest {
        layers: a.layers.clone(),
        sql: a.sql.clone(),
        colour_by: a.colour_by.clone(),
        tree: a.tree,
        pixel: a.pixel.map(|(x, y)| [x, y]),
        sample: a.sample,
        kinds: a.kinds.clone(),
        depth: a.depth,
        max_rays: a.max_rays,
        bvh_levels: a.bvh_levels,
        bvh_visited: a.bvh_visited,
        geometry: a.geometry.clone(),
        camera: a.camera,
        size: a.size.map(|(w, h)| [w, h]),
        line_width: a.line_width,
        image_source: a.image_source.clone(),
        image_spp: a.image_spp,
        legend: !a.no_legend,
        style: a.style,
        opacity: a.opacity,
        density_scale: a.density_scale,
        density_map: a.density_map.clone(),
        map: a.map.clone(),
    };
    let (img, report) = rtvtk_viz::headless::render(sources, &request)?;
    save(&img, &a.out)?;
    Ok(report)
}

/// The sources of a dataset a service serves (`--connect`), read through the query engine.
#[cfg(feature = "sql")]
fn served(a: &RenderArgs, url: &str) -> Result<Sources> {
    let token = match &a.token_file {
        Some(p) => Some(
            std::fs::read_to_string(p)
                .with_context(|| format!("cannot read the token file {}", p.display()))?
                .trim()
                .to_string(),
        ),
        None => std::env::var("RTVTK_TOKEN").ok().filter(|t| !t.is_empty()),
    };
    let engine = query::Engine::blocking(query::Engine::connect(url, token))?;
    Sources::with_engine(std::sync::Arc::new(engine), a.served.as_deref())
        .with_context(|| format!("reading the dataset served at {url}"))
}

/// Built without the `sql` feature: no query engine to reach a service with.
#[cfg(not(feature = "sql"))]
fn served(_a: &RenderArgs, _url: &str) -> Result<Sources> {
    bail!("--connect needs the query engine: this rtvtk was built without the `sql` feature")
}

pub fn save(img: &image::RgbaImage, out: &Path) -> Result<()> {
    if let Some(d) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
    }
    img.save(out).with_context(|| format!("writing {}", out.display()))
}

pub fn run(a: &RenderArgs) -> Result<()> {
    for line in render_to_png(a)? {
        eprintln!("{line}");
    }
    println!("wrote {}", a.out.display());
    Ok(())
}
