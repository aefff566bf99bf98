//! The store's pieces, each beside its baseline in the same run: writing a segment with plain
//! float columns versus the lossless and octahedral encodings, and reading it back (decoding
//! included). Run with `cargo bench -p rtvtk-store --bench codec`; throughput is in rays.
#![allow(clippy::unwrap_used)]

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use store::{
    Dataset, DatasetWriter, Encoding, Kind, KindTable, PayloadSchema, RayColumns, RayFields, TreeRow, WriteOptions,
};

/// Path-tracer-shaped trees: a camera ray, then per bounce a shadow ray and a bounce ray leaving
/// the parent's hit point nudged off the surface.
fn trees(n_trees: u64) -> RayColumns {
    let mut s = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let unit = |r: &mut dyn FnMut() -> f32| {
        let z = r() * 2.0 - 1.0;
        let a = r() * std::f32::consts::TAU;
        let q = (1.0 - z * z).max(0.0).sqrt();
        [q * a.cos(), q * a.sin(), z]
    };
    let mut cols = RayColumns::new(&PayloadSchema::default());
    for id in 0..n_trees {
        let first = cols.len() as u64;
        let (mut o, mut d) = ([278.0f32, 273.0, -800.0], unit(&mut next));
        let (mut k, mut parent, mut depth) = (0u32, store::NONE_U32, 0u16);
        let bounces = (next() * 5.0) as u16;
        for b in 0..=bounces {
            let t = next() * 500.0 + 1.0;
            let kind = if b == 0 { Kind::CAMERA } else { Kind::DIFFUSE };
            cols.push_core(
                id,
                k,
                parent,
                depth,
                &RayFields { origin: o, direction: d, t: Some(t), kind, prim: Some(k) },
            );
            let me = k;
            k += 1;
            let hit = [0, 1, 2].map(|i| f32::from_bits((o[i] + d[i] * t).to_bits() + 3));
            depth += 1;
            let sd = unit(&mut next);
            cols.push_core(
                id,
                k,
                me,
                depth,
                &RayFields { origin: hit, direction: sd, t: Some(next() * 300.0), kind: Kind::SHADOW, prim: Some(1) },
            );
            k += 1;
            (o, d, parent) = (hit, unit(&mut next), me);
        }
        cols.trees.push(TreeRow {
            tree_id: id,
            pixel_x: 0,
            pixel_y: 0,
            sample: 0,
            ray_count: k,
            max_depth: depth,
            first_row: first,
        });
    }
    cols
}

fn write(dir: &std::path::Path, cols: &RayColumns, encoding: Encoding) {
    let schema = PayloadSchema::default();
    let opts = WriteOptions { encoding, sync: false, ..Default::default() };
    let w = DatasetWriter::create(dir, schema.clone(), opts).unwrap();
    let kinds = KindTable::default();
    let mut seg = w.open_segment().unwrap();
    seg.write(cols.clone(), &schema, &kinds).unwrap();
    seg.seal(&w, &kinds).unwrap();
}

fn bench(c: &mut Criterion) {
    let cols = trees(50_000);
    let rays = cols.len() as u64;
    let encodings = [Encoding::Plain, Encoding::Lossless, Encoding::Oct(16)];
    let mut g = c.benchmark_group("segment_write");
    g.throughput(Throughput::Elements(rays)).sample_size(10);
    for enc in encodings {
        g.bench_function(enc.name(), |b| {
            b.iter(|| {
                let dir = tempfile::tempdir().unwrap();
                write(&dir.path().join("ds"), &cols, enc);
            })
        });
    }
    g.finish();
    let mut g = c.benchmark_group("segment_read");
    g.throughput(Throughput::Elements(rays)).sample_size(10);
    for enc in encodings {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ds");
        write(&path, &cols, enc);
        let ds = Dataset::open(&path).unwrap();
        let bytes = ds.manifest().segments[0].rays.bytes;
        eprintln!("{}: {:.2} bytes/ray", enc.name(), bytes as f64 / rays as f64);
        g.bench_function(enc.name(), |b| {
            b.iter(|| ds.segment_batches(0).unwrap().map(|b| b.unwrap().num_rows()).sum::<usize>())
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
