//! Which tracer renders, said one way: [`TracerChoice`] (the CLI's `--tracer`, `view --tracer`,
//! the image layer's source and the ray layer's immediate-mode tracer all take it), and the
//! [`Tracer`] trait every tracer implements — the CPU tracers here ([`CpuTracer`]), the GPU path
//! tracer in `gpu_tracer` (whose `tracer` function builds any choice) — so a call site renders
//! with one call whatever the choice.

use std::sync::Arc;

use rl::Recorder;

use crate::bvh::Bvh;
pub use crate::choice::TracerChoice;
use crate::film::Film;
use crate::render::{RenderOptions, RenderStats, render};
use crate::scene::{Camera, Scene};
use crate::{Error, Result};

/// A tracer ready to render a scene (its BVH built, its device buffers made).
pub trait Tracer: Send + Sync {
    /// Which tracer it is.
    fn choice(&self) -> TracerChoice;

    /// The device it traces on, in words, where that is not this process's CPU cores.
    fn device(&self) -> Option<String> {
        None
    }

    /// Renders `opts` with this tracer, handing every ray to
    /// `recorder` when given; `progress` gets the rows finished. `window` and `samples` replay a
    /// part of a render exactly (a sample's random numbers depend on its pixel, index and seed).
    fn render(
        &self,
        opts: &RenderOptions,
        recorder: Option<&Recorder>,
        progress: &(dyn Fn(u32) + Sync),
    ) -> Result<(Film, RenderStats)>;

    /// Traces from `camera` from now on (the scene's camera at first).
    fn set_camera(&mut self, camera: Camera);

    /// An image accumulated sample by sample (`seed` picks the random sequence; two images with
    /// different seeds are independent estimates).
    fn progressive(&self, width: u32, height: u32, seed: u32, max_depth: u32)
    -> Result<Box<dyn ProgressiveImage + '_>>;
}

/// A progressive image: samples per pixel added in steps, the mean read at any time.
pub trait ProgressiveImage {
    /// Adds `samples` samples per pixel.
    fn add(&mut self, samples: u32) -> Result<()>;
    /// Samples per pixel so far.
    fn spp(&self) -> u32;
    /// The mean of the samples so far (black before the first).
    fn mean(&self) -> Result<Film>;
}

/// Makes the GPU tracer over a scene and its BVH: registered by `gpu_tracer::register`, so that
/// [`tracer`] builds every choice while this crate (and whoever wants a CPU tracer) links no wgpu.
pub type GpuTracerFactory = fn(Arc<Scene>, Arc<Bvh>) -> Result<Box<dyn Tracer>>;

static GPU_TRACER: std::sync::OnceLock<GpuTracerFactory> = std::sync::OnceLock::new();

/// Installs the GPU tracer's factory (the first one installed stays).
pub fn register_gpu_tracer(make: GpuTracerFactory) {
    let _ = GPU_TRACER.set(make);
}

/// The tracer `choice` over `scene` and its BVH, the one factory of every choice: the CPU ones
/// here, the GPU one through the factory `gpu_tracer::register` installs (on the process's one
/// device; refused where the adapter cannot run it, or where no GPU tracer is linked in).
pub fn tracer(choice: TracerChoice, scene: Arc<Scene>, bvh: Arc<Bvh>) -> Result<Box<dyn Tracer>> {
    match choice {
        TracerChoice::Gpu => match GPU_TRACER.get() {
            Some(make) => make(scene, bvh),
            None => Err(Error::Tracer(
                "the gpu tracer is not linked into this program (gpu_tracer::register installs it)".into(),
            )),
        },
        cpu => Ok(Box::new(CpuTracer::new(cpu, scene, bvh)?)),
    }
}

/// The CPU path and Whitted tracers over a scene and its BVH.
pub struct CpuTracer {
    scene: Arc<Scene>,
    bvh: Arc<Bvh>,
    choice: TracerChoice,
}

impl CpuTracer {
    /// The CPU tracer `choice` (path or Whitted) over `scene`.
    pub fn new(choice: TracerChoice, scene: Arc<Scene>, bvh: Arc<Bvh>) -> Result<CpuTracer> {
        if choice.on_gpu() {
            return Err(Error::Settings("the GPU tracer is gpu_tracer::GpuTracer, not a CPU tracer".into()));
        }
        Ok(CpuTracer { scene, bvh, choice })
    }
}

impl Tracer for CpuTracer {
    fn choice(&self) -> TracerChoice {
        self.choice
    }

    fn render(
        &self,
        opts: &RenderOptions,
        recorder: Option<&Recorder>,
        progress: &(dyn Fn(u32) + Sync),
    ) -> Result<(Film, RenderStats)> {
        render(&self.scene, &self.bvh, self.choice, opts, recorder, progress)
    }

    fn set_camera(&mut self, camera: Camera) {
        if self.scene.camera != camera {
            let mut s = (*self.scene).clone();
            s.camera = camera;
            self.scene = Arc::new(s);
        }
    }

    fn progressive(
        &self,
        width: u32,
        height: u32,
        seed: u32,
        max_depth: u32,
    ) -> Result<Box<dyn ProgressiveImage + '_>> {
        let opts = RenderOptions { width, height, spp: 1, max_depth, ..Default::default() };
        opts.validate()?;
        let sum = vec![glam::Vec3A::ZERO; width as usize * height as usize];
        Ok(Box::new(CpuProgressive { tracer: self, opts, seed, sum, spp: 0 }))
    }
}

/// A CPU tracer's progressive image: one render of one sample per pixel per step.
struct CpuProgressive<'a> {
    tracer: &'a CpuTracer,
    opts: RenderOptions,
    seed: u32,
    sum: Vec<glam::Vec3A>,
    spp: u32,
}

impl ProgressiveImage for CpuProgressive<'_> {
    fn add(&mut self, samples: u32) -> Result<()> {
        for _ in 0..samples {
            // Each sample its own seed: the sum of independent one-sample images.
            let opts = RenderOptions { seed: (u64::from(self.seed) << 32) | u64::from(self.spp), ..self.opts.clone() };
            let (film, _) = render(&self.tracer.scene, &self.tracer.bvh, self.tracer.choice, &opts, None, &|_| {})?;
            for (a, b) in self.sum.iter_mut().zip(&film.pixels) {
                *a += *b;
            }
            self.spp += 1;
        }
        Ok(())
    }

    fn spp(&self) -> u32 {
        self.spp
    }

    fn mean(&self) -> Result<Film> {
        let n = self.spp.max(1) as f32;
        Ok(Film { width: self.opts.width, height: self.opts.height, pixels: self.sum.iter().map(|v| *v / n).collect() })
    }
}
