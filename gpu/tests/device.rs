#![allow(clippy::unwrap_used)]
//! The process's one device on whatever adapter this machine has (lavapipe, llvmpipe or a GPU):
//! opened once, errors captured instead of panicking, values read back as they were written.

use rtvtk_gpu::{Error, Gpu};

#[test]
fn one_device_per_process_errors_captured_values_read_back() {
    let a = Gpu::shared().unwrap_or_else(|e| panic!("this test needs a GPU adapter: {e}"));
    let b = Gpu::shared().unwrap();
    assert_eq!(a.device, b.device, "the second call gives the same device");
    // A device handed in later does not replace the one already open.
    assert_eq!(Gpu::share(b.clone()).device, a.device);

    // A shader the device refuses is an error naming what was being made, not a panic.
    let bad = a.capture("a broken shader", || {
        a.device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("broken"),
            source: wgpu::ShaderSource::Wgsl("fn f( {".into()),
        })
    });
    match bad {
        Err(Error::Gpu(m)) => assert!(m.contains("a broken shader"), "{m}"),
        Err(e) => panic!("expected a GPU error, got {e}"),
        Ok(_) => panic!("a broken shader was accepted"),
    }
    a.check().unwrap();

    // What is written comes back, as bytes and as typed values.
    let values: Vec<[f32; 4]> = (0..1000).map(|i| [i as f32, -(i as f32), 0.5, f32::INFINITY]).collect();
    let buf = a.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("values"),
        size: 16_000,
        usage: wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    a.queue.write_buffer(&buf, 0, bytemuck::cast_slice(&values));
    assert_eq!(a.read_values::<[f32; 4]>(&buf, 16_000).unwrap(), values);
    assert_eq!(a.read_buffer(&buf, 8).unwrap(), bytemuck::cast_slice::<f32, u8>(&[0.0, -0.0]));
    assert!(a.read_buffer(&buf, 0).unwrap().is_empty());

    // The adapter runs the GPU tracer's 12 storage buffers or says why not; nobody has a million.
    let e = a.compute_support(1_000_000).unwrap_err().to_string();
    assert!(e.contains(&a.describe()) && e.contains("storage buffers"), "{e}");
}
