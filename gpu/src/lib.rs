#![doc = include_str!("../README.md")]

use std::sync::{Arc, Mutex};

/// The longest [`Gpu::wait`] waits for submitted work before it is an error.
pub const WAIT_LIMIT: std::time::Duration = std::time::Duration::from_secs(600);

/// What package gives a machine with no GPU adapter one (Debian/Ubuntu names): Mesa's Vulkan
/// driver on the CPU, or Mesa's EGL for wgpu's GL backend.
pub const INSTALL_HINT: &str = "install Mesa's software drivers: `apt-get install mesa-vulkan-drivers` (Vulkan, \
     lavapipe) or `apt-get install libegl-mesa0` (GL, llvmpipe)";

/// What opening or using the GPU can report.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// No adapter of any backend.
    #[error("no GPU adapter ({0}); {INSTALL_HINT}")]
    NoAdapter(String),
    /// Adapters, but none opened a device (a driver that fails, e.g. wgpu's GL backend on
    /// NVIDIA's proprietary driver, gfx-rs/wgpu#7068; or a backend forced by `WGPU_BACKEND`).
    #[error(
        "no GPU adapter opened a device ({0}); leave WGPU_BACKEND unset so that every backend is \
         tried, or {INSTALL_HINT}"
    )]
    NoDevice(String),
    /// The adapter cannot do what a caller needs (compute shaders, enough storage buffers).
    #[error("{adapter} cannot {what}: {why}")]
    Unsupported { adapter: String, what: String, why: String },
    /// A validation or out-of-memory error of the device, or a failed read-back.
    #[error("GPU error: {0}")]
    Gpu(String),
}

/// Result alias of the GPU crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// The device, its queue and what its adapter can do. Cloning is cheap and shares the device
/// (wgpu's handles are reference counted): every clone draws on the same GPU.
#[derive(Clone)]
pub struct Gpu {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub adapter: wgpu::AdapterInfo,
    /// What the adapter supports below WebGPU (compute shaders, storage buffers in vertex shaders).
    pub downlevel: wgpu::DownlevelCapabilities,
    /// Validation and out-of-memory errors the device reported, not yet returned by [`Gpu::check`].
    errors: Arc<Mutex<Vec<String>>>,
}

/// The process's device: opened by the first [`Gpu::shared`], or handed in by [`Gpu::share`].
static SHARED: Mutex<Option<Gpu>> = Mutex::new(None);

/// Vulkan, Metal and DX12 before GL (the GL backend has the lowest limits), then by adapter kind:
/// a real GPU before a CPU one.
fn preference(backend: wgpu::Backend, device_type: wgpu::DeviceType) -> (u8, u8) {
    let backend = match backend {
        wgpu::Backend::Vulkan | wgpu::Backend::Metal | wgpu::Backend::Dx12 => 0,
        wgpu::Backend::Gl => 1,
        _ => 2,
    };
    let kind = match device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 3,
        wgpu::DeviceType::Other => 4,
    };
    (backend, kind)
}

/// `adapters` best first: `WGPU_ADAPTER_NAME` (a substring of the name, any case) keeps only
/// those it names; Vulkan/Metal/DX12 before GL, a real GPU before a CPU one. The viewer's window
/// chooses its adapter with it too (eframe's adapter selector).
pub fn ranked(mut adapters: Vec<wgpu::Adapter>) -> Vec<wgpu::Adapter> {
    if let Ok(name) = std::env::var("WGPU_ADAPTER_NAME") {
        let name = name.to_lowercase();
        adapters.retain(|a| a.get_info().name.to_lowercase().contains(&name));
    }
    adapters.sort_by_key(|a| {
        let i = a.get_info();
        preference(i.backend, i.device_type)
    });
    adapters
}

/// The device every part of rtvtk needs, on `adapter`: the adapter's own limits (its largest
/// buffers and storage bindings for millions of segments in few buffers, all its storage buffers
/// per stage for the GPU tracer's 12, and no more than it has: the GL backend's are below
/// WebGPU's defaults). The viewer asks eframe for the same device.
pub fn device_descriptor(adapter: &wgpu::Adapter) -> wgpu::DeviceDescriptor<'static> {
    wgpu::DeviceDescriptor {
        label: Some("rtvtk"),
        required_features: wgpu::Features::empty(),
        required_limits: adapter.limits(),
        experimental_features: wgpu::ExperimentalFeatures::disabled(),
        memory_hints: wgpu::MemoryHints::Performance,
        trace: wgpu::Trace::Off,
    }
}

impl Gpu {
    /// The process's device, opened on first use (see [`Gpu::open`]); later calls, on any thread,
    /// return the same device. A failure is not kept: the next call tries again.
    pub fn shared() -> Result<Gpu> {
        let mut slot = SHARED.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(g) = slot.as_ref() {
            return Ok(g.clone());
        }
        let g = Gpu::open()?;
        *slot = Some(g.clone());
        Ok(g)
    }

    /// Makes `gpu` the process's device (the viewer hands in eframe's), unless one is open already;
    /// returns the device [`Gpu::shared`] gives from now on.
    pub fn share(gpu: Gpu) -> Gpu {
        let mut slot = SHARED.lock().unwrap_or_else(|p| p.into_inner());
        slot.get_or_insert(gpu).clone()
    }

    /// Opens a device on the best adapter wgpu finds ([`ranked`]: every backend `WGPU_BACKEND`
    /// allows, all by default); the first adapter that opens a device wins, so a Vulkan driver
    /// that fails falls back to GL.
    fn open() -> Result<Gpu> {
        let desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        let backends = desc.backends;
        let instance = wgpu::Instance::new(desc);
        let adapters = ranked(pollster::block_on(instance.enumerate_adapters(backends)));
        let mut tried = Vec::new();
        for adapter in adapters {
            let info = adapter.get_info();
            match pollster::block_on(adapter.request_device(&device_descriptor(&adapter))) {
                Ok((device, queue)) => return Ok(Gpu::from_device(&adapter, device, queue)),
                Err(e) => tried.push(format!("{} ({:?}): {e}", info.name, info.backend)),
            }
        }
        if tried.is_empty() {
            return Err(Error::NoAdapter(format!("wgpu found none on the backends {backends:?}")));
        }
        Err(Error::NoDevice(tried.join("; ")))
    }

    /// A device somebody else opened (eframe's, through egui-wgpu's render state); its
    /// uncaptured errors are captured from now on.
    pub fn from_device(adapter: &wgpu::Adapter, device: wgpu::Device, queue: wgpu::Queue) -> Gpu {
        let errors: Arc<Mutex<Vec<String>>> = Arc::default();
        let sink = errors.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            let text = e.to_string();
            // The window's own surface (re)configuration, on the UI thread, is eframe's: it
            // tries again on the next frame (lavapipe times out waiting for idle while a long
            // compute pass runs). Not an error of the layers' work, which `check` reports.
            if text.contains("Surface::configure") {
                eprintln!("rtvtk: the window's surface was not reconfigured this frame: {}", text.replace('\n', " "));
                return;
            }
            sink.lock().unwrap_or_else(|p| p.into_inner()).push(text);
        }));
        Gpu { device, queue, adapter: adapter.get_info(), downlevel: adapter.get_downlevel_capabilities(), errors }
    }

    /// The adapter in words: `llvmpipe (LLVM 15.0.6, 256 bits) (Gl)`.
    pub fn describe(&self) -> String {
        format!("{} ({:?})", self.adapter.name, self.adapter.backend)
    }

    /// Largest storage buffer binding the device accepts (bytes).
    pub fn max_storage_binding(&self) -> u64 {
        let l = self.device.limits();
        l.max_storage_buffer_binding_size.min(l.max_buffer_size)
    }

    /// Whether compute shaders with `storage_buffers` storage buffers in one stage run here
    /// (the GL backend of an old driver may have no compute, or fewer buffers); the reason when not.
    pub fn compute_support(&self, storage_buffers: u32) -> Result<()> {
        let unsupported = |why: String| Error::Unsupported {
            adapter: self.describe(),
            what: format!("run compute shaders with {storage_buffers} storage buffers"),
            why,
        };
        if !self.downlevel.flags.contains(wgpu::DownlevelFlags::COMPUTE_SHADERS) {
            return Err(unsupported("the adapter has no compute shaders".into()));
        }
        let have = self.device.limits().max_storage_buffers_per_shader_stage;
        if have < storage_buffers {
            return Err(unsupported(format!("it allows {have} storage buffers per shader stage")));
        }
        Ok(())
    }

    /// Runs `f` inside an error scope (this thread's work on the device): a validation or
    /// out-of-memory error it causes comes back as `Err`, naming `what`.
    pub fn capture<T>(&self, what: &str, f: impl FnOnce() -> T) -> Result<T> {
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let out = f();
        let v = pollster::block_on(validation.pop());
        let m = pollster::block_on(oom.pop());
        match v.or(m) {
            Some(e) => Err(Error::Gpu(format!("{what}: {e}"))),
            None => Ok(out),
        }
    }

    /// The first error the device reported since the last check (validation errors of a shader
    /// or pipeline, out of memory), as an `Err`.
    pub fn check(&self) -> Result<()> {
        let mut e = self.errors.lock().unwrap_or_else(|p| p.into_inner());
        match e.first().cloned() {
            Some(first) => {
                let n = e.len();
                e.clear();
                Err(Error::Gpu(if n > 1 { format!("{first} (and {} more)", n - 1) } else { first }))
            }
            None => Ok(()),
        }
    }

    /// Waits for all submitted work. wgpu's GL backend gives up an "indefinite" wait after its
    /// own timeout while a software rasterizer (llvmpipe) is still drawing millions of lines, so
    /// a timed-out wait is waited again, for up to `WAIT_LIMIT` in all.
    pub fn wait(&self) -> Result<()> {
        let start = std::time::Instant::now();
        loop {
            match self.device.poll(wgpu::PollType::wait_indefinitely()) {
                Ok(_) => return Ok(()),
                Err(wgpu::PollError::Timeout) if start.elapsed() < WAIT_LIMIT => continue,
                Err(e) => return Err(Error::Gpu(format!("{e} (after {:.0} s)", start.elapsed().as_secs_f64()))),
            }
        }
    }

    /// Maps `buf` (made with `MAP_READ`) after the work submitted so far and copies `keep` out of
    /// each mapped view.
    fn map_read<T>(&self, buf: &wgpu::Buffer, keep: impl FnOnce(&[u8]) -> T) -> Result<T> {
        let slice = buf.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.wait()?;
        rx.recv().map_err(|e| Error::Gpu(e.to_string()))?.map_err(|e| Error::Gpu(e.to_string()))?;
        let data = slice.get_mapped_range().map_err(|e| Error::Gpu(e.to_string()))?;
        let out = keep(&data);
        drop(data);
        buf.unmap();
        Ok(out)
    }

    /// The first `bytes` of `buf` (made with `COPY_SRC`), read back.
    pub fn read_buffer(&self, buf: &wgpu::Buffer, bytes: u64) -> Result<Vec<u8>> {
        self.read_values(buf, bytes)
    }

    /// The first `bytes` of `buf` (made with `COPY_SRC`) read back as values of `T`, cast
    /// straight from the mapped range (a whole number of them: `bytes` is rounded down).
    pub fn read_values<T: bytemuck::Pod>(&self, buf: &wgpu::Buffer, bytes: u64) -> Result<Vec<T>> {
        let size = std::mem::size_of::<T>().max(1) as u64;
        let bytes = bytes / size * size;
        if bytes == 0 {
            return Ok(Vec::new());
        }
        let read = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("read back"),
            size: bytes,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(buf, 0, &read, 0, bytes);
        self.queue.submit([enc.finish()]);
        self.map_read(&read, |data| match bytemuck::try_cast_slice::<u8, T>(data) {
            Ok(v) => v.to_vec(),
            // A mapped range is aligned to wgpu::MAP_ALIGNMENT; a type aligned wider is copied.
            Err(_) => data.chunks_exact(size as usize).map(bytemuck::pod_read_unaligned).collect(),
        })
    }

    /// A 2D texture of `format` that passes render into, samples, copies from and to.
    pub fn target(&self, label: &str, format: wgpu::TextureFormat, width: u32, height: u32) -> wgpu::Texture {
        self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some(label),
            size: wgpu::Extent3d { width: width.max(1), height: height.max(1), depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC
                | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        })
    }

    /// Uploads RGBA8 pixels (rows tightly packed, top to bottom) into a new `Rgba8Unorm` texture.
    pub fn rgba_texture(&self, label: &str, width: u32, height: u32, rgba: &[u8]) -> wgpu::Texture {
        let t = self.target(label, wgpu::TextureFormat::Rgba8Unorm, width, height);
        self.queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &t,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            rgba,
            wgpu::TexelCopyBufferLayout { offset: 0, bytes_per_row: Some(4 * width), rows_per_image: Some(height) },
            wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
        );
        t
    }

    /// Reads an RGBA8 texture back (rows tightly packed, top to bottom).
    pub fn read_rgba(&self, texture: &wgpu::Texture) -> Result<Vec<u8>> {
        self.read_texels(texture, 4)
    }

    /// Reads a colour texture of `bytes` bytes per texel back (rows tightly packed, top to bottom).
    pub fn read_texels(&self, texture: &wgpu::Texture, bytes: u32) -> Result<Vec<u8>> {
        let (w, h) = (texture.width(), texture.height());
        let row = (bytes * w).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let buf = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: u64::from(row) * u64::from(h),
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let mut enc = self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("readback") });
        enc.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyBufferInfo {
                buffer: &buf,
                layout: wgpu::TexelCopyBufferLayout { offset: 0, bytes_per_row: Some(row), rows_per_image: Some(h) },
            },
            wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
        );
        self.queue.submit([enc.finish()]);
        self.map_read(&buf, |data| {
            let mut out = Vec::with_capacity((bytes * w * h) as usize);
            for y in 0..h as usize {
                out.extend_from_slice(&data[y * row as usize..y * row as usize + (bytes * w) as usize]);
            }
            out
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vulkan_comes_before_gl_and_a_gpu_before_a_cpu() {
        let gl_gpu = preference(wgpu::Backend::Gl, wgpu::DeviceType::DiscreteGpu);
        let vk_cpu = preference(wgpu::Backend::Vulkan, wgpu::DeviceType::Cpu);
        let vk_gpu = preference(wgpu::Backend::Vulkan, wgpu::DeviceType::IntegratedGpu);
        assert!(vk_gpu < vk_cpu && vk_cpu < gl_gpu);
    }

    #[test]
    fn the_install_hint_names_both_packages() {
        let e = Error::NoAdapter("wgpu found none".into()).to_string();
        assert!(e.contains("mesa-vulkan-drivers") && e.contains("libegl-mesa0"), "{e}");
        let e = Error::NoDevice("NVIDIA H200 (Gl): Parent device is lost".into()).to_string();
        assert!(e.contains("Parent device is lost") && e.contains("WGPU_BACKEND") && e.contains("libegl-mesa0"), "{e}");
    }
}
