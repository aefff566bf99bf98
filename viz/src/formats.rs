//! The visualizer's texture formats. The device itself is the process's one GPU context
//! (`rtvtk_gpu::Gpu`, shared with the GPU tracer and the viewer's window).

/// Colour format of every layer and of the composited picture (display-referred values, as the
/// tone-mapped PNG of a dataset holds them).
pub const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
/// Depth format of every layer.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// The pick target's format: layer slot and item index + 1 per texel.
pub const PICK_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rg32Uint;
