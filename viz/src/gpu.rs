//! The GPU device every layer draws with, headless (no window, no surface).

use std::sync::{Arc, Mutex};

use crate::{Error, Result};

/// Colour format of every layer and of the composited picture (display-referred values, as the
/// tone-mapped PNG of a dataset holds them).
pub const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
/// Depth format of every layer.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// The pick target's format: layer slot and item index + 1 per texel.
pub const PICK_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rg32Uint;

/// A device and its queue.
pub struct Gpu {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub adapter: wgpu::AdapterInfo,
    /// Largest storage buffer binding this device accepts (bytes).
    pub max_storage_binding: u64,
    /// Validation and out-of-memory errors the device reported, not yet returned by [`Gpu::check`].
    errors: Arc<Mutex<Vec<String>>>,
}

impl Gpu {
    /// The first adapter wgpu finds (`WGPU_BACKEND`, `WGPU_ADAPTER_NAME` select one), with the
    /// adapter's own buffer limits so millions of segments fit in few buffers.
    pub fn headless() -> Result<Gpu> {
        // The GPU tracer's adapter choice, so both run on the same adapter.
        let adapter = gpu_tracer::headless_adapter().map_err(|e| match e {
            gpu_tracer::Error::NoAdapter(why) => Error::NoAdapter(why),
            e => Error::NoAdapter(e.to_string()),
        })?;
        let info = adapter.get_info();
        let have = adapter.limits();
        let limits = wgpu::Limits {
            max_storage_buffer_binding_size: have.max_storage_buffer_binding_size,
            max_buffer_size: have.max_buffer_size,
            max_texture_dimension_2d: have.max_texture_dimension_2d,
            ..Default::default()
        };
        let desc = wgpu::DeviceDescriptor {
            label: Some("rtvtk-viz"),
            required_features: wgpu::Features::empty(),
            required_limits: limits.clone(),
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        };
        let (device, queue) =
            pollster::block_on(adapter.request_device(&desc)).map_err(|e| Error::Device(e.to_string()))?;
        let max_storage_binding = limits.max_storage_buffer_binding_size.min(limits.max_buffer_size);
        // Errors come back from `check` (after each frame) instead of panicking in wgpu.
        let errors: Arc<Mutex<Vec<String>>> = Arc::default();
        let sink = errors.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            sink.lock().unwrap_or_else(|p| p.into_inner()).push(e.to_string());
        }));
        Ok(Gpu { device, queue, adapter: info, max_storage_binding, errors })
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

    /// Waits for all submitted work.
    pub fn wait(&self) -> Result<()> {
        self.device.poll(wgpu::PollType::wait_indefinitely()).map(|_| ()).map_err(|e| Error::Gpu(e.to_string()))
    }

    /// A render target texture of `format` (colour layers are also copy sources and sampled).
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

    /// Uploads RGBA8 pixels into a new sampled texture.
    pub fn rgba_texture(&self, label: &str, width: u32, height: u32, rgba: &[u8]) -> wgpu::Texture {
        let t = self.target(label, COLOR_FORMAT, width, height);
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

    /// Reads an RGBA8 texture back (rows tightly packed).
    pub fn read_rgba(&self, texture: &wgpu::Texture) -> Result<Vec<u8>> {
        self.read_texels(texture, 4)
    }

    /// Reads a texture of `bytes` bytes per texel back (rows tightly packed).
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
        let slice = buf.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.wait()?;
        rx.recv().map_err(|e| Error::Gpu(e.to_string()))?.map_err(|e| Error::Gpu(e.to_string()))?;
        let data = slice.get_mapped_range().map_err(|e| Error::Gpu(e.to_string()))?;
        let mut out = Vec::with_capacity((bytes * w * h) as usize);
        for y in 0..h as usize {
            out.extend_from_slice(&data[y * row as usize..y * row as usize + (bytes * w) as usize]);
        }
        drop(data);
        buf.unmap();
        Ok(out)
    }
}
