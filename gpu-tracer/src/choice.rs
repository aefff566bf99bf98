//! The GPU path tracer as a `renderers::Tracer`, and [`register`]: it installs the GPU choice in
//! `renderers::tracer`, the one factory of every [`TracerChoice`].

use renderers::{Film, ProgressiveImage, RenderOptions, RenderStats, Tracer, TracerChoice};
use rl::Recorder;

use crate::GpuTracer;

fn tracer_error(e: crate::Error) -> renderers::Error {
    renderers::Error::Tracer(e.to_string())
}

/// Installs the GPU tracer (on the process's one device) as `renderers::tracer`'s GPU choice, so
/// that one factory builds every tracer. Idempotent: call it before asking for the GPU choice.
pub fn register() {
    renderers::register_gpu_tracer(|scene, bvh| Ok(Box::new(GpuTracer::new(&scene, &bvh).map_err(tracer_error)?)));
}

impl Tracer for GpuTracer {
    fn choice(&self) -> TracerChoice {
        TracerChoice::Gpu
    }

    fn device(&self) -> Option<String> {
        Some(self.adapter())
    }

    fn render(
        &self,
        opts: &RenderOptions,
        recorder: Option<&Recorder>,
        progress: &(dyn Fn(u32) + Sync),
    ) -> renderers::Result<(Film, RenderStats)> {
        let whole = opts.window.is_none() && opts.samples.is_none() && opts.bug.is_none();
        if recorder.is_some() || !whole {
            return self.render_recorded(opts, recorder, progress).map_err(tracer_error);
        }
        // Nothing to record: the samples accumulate on the GPU, read back once.
        let t0 = std::time::Instant::now();
        let seed = (opts.seed ^ (opts.seed >> 32)) as u32;
        let mut p =
            GpuTracer::progressive(self, opts.width, opts.height, seed, opts.max_depth).map_err(tracer_error)?;
        self.trace(&mut p, opts.spp).map_err(tracer_error)?;
        let film = self.film(&p).map_err(tracer_error)?;
        progress(opts.height);
        let kinds = [rl::Kind::CAMERA, rl::Kind::SHADOW, rl::Kind::DIFFUSE, rl::Kind::SPECULAR, rl::Kind::TRANSMISSION];
        let rays_by_kind: Vec<(rl::Kind, u64)> =
            kinds.into_iter().zip(p.rays_by_kind).filter(|(_, n)| *n > 0).collect();
        let stats = RenderStats {
            samples: u64::from(opts.width) * u64::from(opts.height) * u64::from(opts.spp),
            rays: rays_by_kind.iter().map(|(_, n)| n).sum(),
            rays_by_kind,
            secs: t0.elapsed().as_secs_f64(),
        };
        Ok((film, stats))
    }

    fn set_camera(&mut self, camera: renderers::Camera) {
        GpuTracer::set_camera(self, camera);
    }

    fn progressive(
        &self,
        width: u32,
        height: u32,
        seed: u32,
        max_depth: u32,
    ) -> renderers::Result<Box<dyn ProgressiveImage + '_>> {
        let image = GpuTracer::progressive(self, width, height, seed, max_depth).map_err(tracer_error)?;
        Ok(Box::new(GpuProgressive { tracer: self, image }))
    }
}

/// The GPU tracer's progressive image: the accumulation stays on the GPU until the mean is read.
struct GpuProgressive<'a> {
    tracer: &'a GpuTracer,
    image: crate::Accumulation,
}

impl ProgressiveImage for GpuProgressive<'_> {
    fn add(&mut self, samples: u32) -> renderers::Result<()> {
        self.tracer.trace(&mut self.image, samples).map_err(tracer_error)
    }

    fn spp(&self) -> u32 {
        self.image.spp
    }

    fn mean(&self) -> renderers::Result<Film> {
        self.tracer.film(&self.image).map_err(tracer_error)
    }
}
