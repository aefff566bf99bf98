//! Encodings (format versions 2 to 4): bit-exact round trips, lossy error bounds, reading
//! versions 1 to 3.
#![allow(clippy::unwrap_used)]

use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, AsArray, RecordBatch, UInt8Array, UInt32Array};
use store::{
    Dataset, DatasetWriter, Encoding, Kind, KindTable, PayloadSchema, RayColumns, RayFields, TreeId, TreeRow,
    WriteOptions,
};

mod common;
use common::Rng;

/// The tree-table row of synthetic tree `id` (pixels laid out 64 wide, sample 0).
fn tree_row(id: u64, ray_count: u32, max_depth: u16, first_row: u64) -> TreeRow {
    TreeRow {
        tree_id: id,
        pixel_x: (id % 64) as u32,
        pixel_y: (id / 64) as u32,
        sample: 0,
        ray_count,
        max_depth,
        first_row,
    }
}

/// Path-tracer-like trees: a camera ray, then per bounce a shadow ray and a bounce ray leaving a
/// point just off the parent's hit point; plus rays with every special value.
fn trees(n: u64, scale: f32, offset: f32) -> RayColumns {
    let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
    let mut cols = RayColumns::new(&PayloadSchema::default());
    let specials = [f32::NAN, f32::from_bits(0x7fc0_1234), f32::INFINITY, f32::NEG_INFINITY, -0.0, 1e-40, f32::MAX];
    for id in 0..n {
        let first = cols.len() as u64;
        let mut k = 0u32;
        let mut push = |cols: &mut RayColumns, parent: u32, depth: u16, f: RayFields| {
            cols.push_core(id, k, parent, depth, &f);
            k += 1;
            k - 1
        };
        let cam = [offset + 278.0 * scale, offset + 273.0 * scale, offset - 800.0 * scale];
        let mut o = cam;
        let mut d = rng.unit();
        let mut parent = store::NONE_U32;
        let mut depth = 0u16;
        let bounces = (rng.next() % 6) as u16;
        for b in 0..=bounces {
            let t = (rng.f() + 0.01) * 500.0 * scale;
            let miss = b == bounces && rng.next().is_multiple_of(3);
            let kind = if b == 0 { Kind::CAMERA } else { Kind::DIFFUSE };
            let me = push(
                &mut cols,
                parent,
                depth,
                RayFields {
                    origin: o,
                    direction: d,
                    t: (!miss).then_some(t),
                    kind,
                    prim: (!miss).then_some(rng.next() as u32 % 1000),
                },
            );
            if miss {
                break;
            }
            // The hit point, nudged a few ULPs off the surface like a renderer does.
            let nudge = (rng.next() % 33) as i32 - 16;
            let hit = [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t]
                .map(|c| f32::from_bits((c.to_bits() as i32).wrapping_add(nudge) as u32));
            depth += 1;
            let sd = if id.is_multiple_of(17) {
                // Unnormalized and special directions cost bytes but must round-trip.
                [specials[(id as usize + b as usize) % specials.len()], 2.0, -3.0]
            } else {
                rng.unit()
            };
            push(
                &mut cols,
                me,
                depth,
                RayFields { origin: hit, direction: sd, t: Some(rng.f() * 100.0), kind: Kind::SHADOW, prim: Some(7) },
            );
            o = hit;
            d = rng.unit();
            parent = me;
        }
        cols.trees.push(tree_row(id, k, depth, first));
    }
    cols
}

/// Rays bouncing inside a box, each stopping where it meets a wall (the wall is its primitive),
/// with shadow rays to points on the top wall: hit distances a renderer would record, on flat
/// primitives. The box is tilted (no wall is axis-aligned), `scale` wide, `offset` from the origin.
fn box_trees(n: u64, scale: f32, offset: f32) -> RayColumns {
    let mut rng = Rng(0x2545_F491_4F6C_DD1D);
    let mut cols = RayColumns::new(&PayloadSchema::default());
    // A rotation (unit quaternion (0.9, 0.3, 0.3, 0.1) as a matrix) into world space.
    let (w, x, y, z) = (0.9f32, 0.3f32, 0.3f32, 0.1f32);
    let l = (w * w + x * x + y * y + z * z).sqrt();
    let (w, x, y, z) = (w / l, x / l, y / l, z / l);
    let m = [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ];
    let rot = |v: [f32; 3]| [0, 1, 2].map(|r| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2]);
    let world = |p: [f32; 3]| rot(p.map(|c| c * scale)).map(|c| c + offset);
    // Box space is [0, 1]^3: the distance to the wall a ray leaves through, and that wall's id.
    let exit = |o: [f32; 3], d: [f32; 3]| -> (f32, u32) {
        let mut best = (f32::INFINITY, 0);
        for a in 0..3 {
            if d[a] != 0.0 {
                let wall = if d[a] > 0.0 { 1.0 } else { 0.0 };
                let t = (wall - o[a]) / d[a];
                if t < best.0 {
                    best = (t, a as u32 * 2 + u32::from(d[a] > 0.0));
                }
            }
        }
        best
    };
    for id in 0..n {
        let first = cols.len() as u64;
        let mut k = 0u32;
        let mut o = [0.5f32, 0.5, 0.5];
        let mut d = rng.unit();
        let mut parent = store::NONE_U32;
        let mut depth = 0u16;
        let mut max_depth = 0u16;
        for b in 0..=(rng.next() % 5) {
            let (t, wall) = exit(o, d);
            let kind = if b == 0 { Kind::CAMERA } else { Kind::DIFFUSE };
            // World-space rays: directions keep their length, so box-space t is the world t.
            let fields = RayFields { origin: world(o), direction: rot(d), t: Some(t * scale), kind, prim: Some(wall) };
            cols.push_core(id, k, parent, depth, &fields);
            let me = k;
            k += 1;
            depth += 1;
            let hit = [0, 1, 2].map(|a| (o[a] + d[a] * t).clamp(0.0, 1.0));
            // A shadow ray to a random point of the top wall (y = 1).
            let target = [rng.f(), 1.0, rng.f()];
            let to = [target[0] - hit[0], target[1] - hit[1], target[2] - hit[2]];
            let len = (to[0] * to[0] + to[1] * to[1] + to[2] * to[2]).sqrt();
            if len > 1e-3 && to[1] > 1e-3 {
                let sd = to.map(|c| c / len);
                let st = (1.0 - hit[1]) / sd[1];
                let f = RayFields {
                    origin: world(hit),
                    direction: rot(sd),
                    t: Some(st * scale),
                    kind: Kind::SHADOW,
                    prim: Some(3),
                };
                cols.push_core(id, k, me, depth, &f);
                k += 1;
                max_depth = depth;
            }
            o = hit;
            d = rng.unit();
            // Turn the bounce back into the box.
            for a in 0..3 {
                if (o[a] >= 1.0 && d[a] > 0.0) || (o[a] <= 0.0 && d[a] < 0.0) {
                    d[a] = -d[a];
                }
            }
            parent = me;
        }
        cols.trees.push(tree_row(id, k, max_depth.max(depth - 1), first));
    }
    cols
}

fn write(dir: &Path, cols: &RayColumns, encoding: Encoding, chunks: usize) {
    write_pages(dir, cols, encoding, chunks, 100);
}

/// [`write`] with pages of `page_rows` rows.
fn write_pages(dir: &Path, cols: &RayColumns, encoding: Encoding, chunks: usize, page_rows: usize) {
    let schema = PayloadSchema::default();
    let opts = WriteOptions { row_group_rows: 1000, page_rows, encoding, ..Default::default() };
    let w = DatasetWriter::create(dir, schema.clone(), opts).unwrap();
    let kinds = KindTable::default();
    let mut seg = w.open_segment().unwrap();
    // Split the trees into a few chunks, as the recorder's workers would see them.
    let per = cols.trees.len().div_ceil(chunks);
    for part in cols.trees.chunks(per) {
        let mut c = RayColumns::new(&schema);
        for t in part {
            let (a, b) = (t.first_row as usize, t.first_row as usize + t.ray_count as usize);
            let first = c.len() as u64;
            for i in a..b {
                let f = RayFields {
                    origin: [cols.origin[0][i], cols.origin[1][i], cols.origin[2][i]],
                    direction: [cols.direction[0][i], cols.direction[1][i], cols.direction[2][i]],
                    t: cols.hit[i].then_some(cols.t[i]),
                    kind: Kind(cols.kind[i]),
                    prim: (cols.prim[i] != store::NONE_U32).then_some(cols.prim[i]),
                };
                c.push_core(cols.tree_id[i], cols.ray[i], cols.parent[i], cols.depth[i], &f);
            }
            c.trees.push(TreeRow { first_row: first, ..*t });
        }
        seg.write(c, &schema, &kinds).unwrap();
    }
    seg.seal(&w, &kinds).unwrap();
    w.mark_complete().unwrap();
}

fn bits3(v: [f32; 3]) -> [u32; 3] {
    v.map(f32::to_bits)
}

#[test]
fn lossless_and_plain_round_trip_bit_exactly_at_any_scale() {
    for (scale, offset, flat) in [(1.0, 0.0, false), (1e-4, 0.0, false), (1e5, 0.0, false), (1.0, 1e6, false)]
        .into_iter()
        .chain([(500.0, 0.0, true), (1e-4, 0.0, true), (1e5, 0.0, true), (1.0, 1e6, true), (500.0, -3e4, true)])
    {
        let cols = if flat { box_trees(400, scale, offset) } else { trees(400, scale, offset) };
        for encoding in [Encoding::Lossless, Encoding::Plain] {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("ds");
            write(&path, &cols, encoding, 3);
            let ds = Dataset::open(&path).unwrap();
            assert_eq!(ds.encoding(), encoding);
            assert!(ds.check().is_ok(), "{:?}", ds.check());
            // Sequential scan (decoder state carried across batches and row groups) and random access.
            let mut seen = 0;
            for tree in ds.trees() {
                let tree = tree.unwrap();
                let again = ds.tree(tree.info.id).unwrap();
                assert_eq!(format!("{:?}", tree.rays), format!("{:?}", again.rays));
                for r in &tree.rays {
                    let i = (cols.trees[tree.info.id.0 as usize].first_row + u64::from(r.index)) as usize;
                    let o = [cols.origin[0][i], cols.origin[1][i], cols.origin[2][i]];
                    let d = [cols.direction[0][i], cols.direction[1][i], cols.direction[2][i]];
                    assert_eq!(
                        bits3(r.origin),
                        bits3(o),
                        "{encoding:?} scale {scale} tree {} ray {}",
                        tree.info.id.0,
                        r.index
                    );
                    assert_eq!(bits3(r.direction), bits3(d), "{encoding:?} scale {scale}");
                    assert_eq!(r.t.map(f32::to_bits), cols.hit[i].then_some(cols.t[i].to_bits()));
                    seen += 1;
                }
            }
            assert_eq!(seen, cols.len());
            assert!(matches!(ds.tree(TreeId(1 << 40)), Err(store::Error::NoSuchTree(_))));
        }
    }
}

#[test]
fn lossless_is_smaller_than_plain_on_tree_structured_rays() {
    let cols = trees(3000, 1.0, 0.0);
    let mut sizes = Vec::new();
    for encoding in [Encoding::Plain, Encoding::Lossless] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ds");
        // Pages of 1,000 rows (one per row group): 100-row pages are mostly page headers.
        write_pages(&path, &cols, encoding, 1, 1000);
        let ds = Dataset::open(&path).unwrap();
        sizes.push(ds.manifest().segments[0].rays.bytes);
    }
    assert!(sizes[1] * 10 < sizes[0] * 8, "lossless {} B vs plain {} B", sizes[1], sizes[0]);
}

/// Hit distances on flat primitives are predicted from planes the writer learns: the planes
/// are in the ray file's metadata, nearly every hit is flagged as predicted, and `enc_t` costs a
/// fraction of the raw `t` bits. Curved or random hits (the other generator) get no planes.
#[test]
fn hit_distances_on_flat_primitives_are_predicted_from_learned_planes() {
    let dir = tempfile::tempdir().unwrap();
    for (name, cols) in [("box", box_trees(3000, 500.0, 0.0)), ("random", trees(3000, 1.0, 0.0))] {
        let path = dir.path().join(name);
        write(&path, &cols, Encoding::Lossless, 3);
        let ds = Dataset::open(&path).unwrap();
        let file = &ds.ray_files()[0];
        let reader = parquet::file::reader::SerializedFileReader::new(std::fs::File::open(file).unwrap()).unwrap();
        let meta = parquet::file::reader::FileReader::metadata(&reader);
        let planes = meta
            .file_metadata()
            .key_value_metadata()
            .and_then(|kv| kv.iter().find(|e| e.key == store::PLANES_KEY).and_then(|e| e.value.clone()));
        let column_bytes = |col: &str| -> i64 {
            meta.row_groups()
                .iter()
                .map(|g| g.columns().iter().find(|c| c.column_path().string() == col).unwrap().compressed_size())
                .sum()
        };
        let raw: Vec<RecordBatch> =
            parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(std::fs::File::open(file).unwrap())
                .unwrap()
                .build()
                .unwrap()
                .map(Result::unwrap)
                .collect();
        let (mut hits, mut predicted) = (0usize, 0usize);
        for b in &raw {
            let codes = b.column_by_name("enc_dir_code").unwrap().as_any().downcast_ref::<UInt8Array>().unwrap();
            let t = b.column_by_name(store::ENC_T).unwrap();
            for i in 0..b.num_rows() {
                if arrow::array::Array::is_valid(t, i) {
                    hits += 1;
                    predicted += usize::from(codes.value(i) & 64 != 0);
                }
            }
        }
        let t_bytes = column_bytes(store::ENC_T) as f64 / hits as f64;
        if name == "box" {
            // Six walls; every hit after a wall's first dozen is predicted.
            let planes = store::Planes::from_metadata(&planes.expect("planes in the metadata")).unwrap();
            assert_eq!(planes.len(), 6);
            assert!(predicted * 100 > hits * 95, "{predicted} of {hits} hits predicted");
            assert!(t_bytes < 1.5, "{t_bytes} B per hit distance");
        } else {
            assert!(planes.is_none(), "random hit points share no plane");
            assert_eq!(predicted, 0);
            assert!(t_bytes > 2.5, "{t_bytes} B per raw hit distance");
        }
    }
}

#[test]
fn octahedral_directions_stay_within_their_error_and_the_rest_is_exact() {
    let cols = trees(300, 1.0, 1e3);
    for (bits, bound) in [(16u8, 6e-5f64), (10, 4e-3)] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ds");
        write(&path, &cols, Encoding::Oct(bits), 2);
        let ds = Dataset::open(&path).unwrap();
        assert!(ds.encoding().is_lossy());
        let mut worst = 0.0f64;
        for tree in ds.trees() {
            let tree = tree.unwrap();
            for r in &tree.rays {
                let i = (cols.trees[tree.info.id.0 as usize].first_row + u64::from(r.index)) as usize;
                let o = [cols.origin[0][i], cols.origin[1][i], cols.origin[2][i]];
                assert_eq!(bits3(r.origin), bits3(o), "origins stay lossless");
                let d = [cols.direction[0][i], cols.direction[1][i], cols.direction[2][i]];
                if !d.iter().all(|c| c.is_finite()) {
                    continue;
                }
                worst = worst.max(store::geom::angle_between_f32(d, r.direction));
                let g = r.direction.map(f64::from);
                let gl = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
                assert!((gl - 1.0).abs() < 1e-6, "decoded directions are unit length");
            }
        }
        assert!(worst > 0.0 && worst < bound, "oct{bits}: worst angular error {worst} rad");
    }
}

/// Reads a committed fixture of an older format version and compares every ray with the CSV
/// written beside it when it was recorded.
fn older_fixture_reads_back(name: &str, version: u32, encoding: Encoding) {
    // At run time: a target directory reused from a checkout elsewhere keeps env!'s old path.
    let dir = std::path::PathBuf::from(
        std::env::var_os("CARGO_MANIFEST_DIR").unwrap_or_else(|| env!("CARGO_MANIFEST_DIR").into()),
    )
    .join("tests/fixtures")
    .join(name);
    let ds = Dataset::open(&dir).unwrap();
    assert_eq!(ds.manifest().format_version, version);
    assert_eq!(ds.encoding(), encoding);
    assert!(ds.check().is_ok(), "{:?}", ds.check());
    let csv = std::fs::read_to_string(dir.join("rays.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let f = |s: &str| -> Option<f32> { (!s.is_empty()).then(|| s.parse::<f64>().unwrap() as f32) };
    let mut n = 0u64;
    let mut hits = 0u64;
    for line in lines {
        let v: Vec<&str> = line.split(',').collect();
        let tree = ds.tree(TreeId(v[col("tree_id")].parse().unwrap())).unwrap();
        let r = &tree.rays[v[col("ray")].parse::<usize>().unwrap()];
        assert_eq!(r.parent, v[col("parent")].parse().ok());
        assert_eq!(r.kind, ds.kinds().lookup(v[col("kind")]).unwrap());
        let o = [f(v[col("ox")]), f(v[col("oy")]), f(v[col("oz")])].map(Option::unwrap);
        let d = [f(v[col("dx")]), f(v[col("dy")]), f(v[col("dz")])].map(Option::unwrap);
        assert_eq!(bits3(r.origin), bits3(o));
        assert_eq!(bits3(r.direction), bits3(d));
        assert_eq!(r.t.map(f32::to_bits), f(v[col("t")]).map(f32::to_bits));
        assert_eq!(r.prim, v[col("prim")].parse().ok());
        if let Some(r0) = header.iter().position(|h| *h == "r0") {
            // Radiance as version 3 stored it (plain floats; version 4 predicts it).
            let row = v[col("ray")].parse::<usize>().unwrap();
            let l = tree.batch.column_by_name("radiance").unwrap().as_fixed_size_list();
            let got = l.value(row);
            let got = got.as_primitive::<arrow::datatypes::Float32Type>();
            for c in 0..3 {
                assert_eq!(got.value(c).to_bits(), f(v[r0 + c]).unwrap().to_bits());
            }
        }
        hits += u64::from(r.t.is_some());
        n += 1;
    }
    assert_eq!(n, ds.ray_count());
    assert!(hits > n / 2, "{hits} of {n} rays hit");
    // The payload columns declared then read through unchanged.
    assert!(ds.payload_schema().index_of("throughput").is_some());
}

#[test]
fn version_1_datasets_still_read() {
    older_fixture_reads_back("v1-cornell", 1, Encoding::Plain);
}

#[test]
fn version_2_lossless_datasets_still_read() {
    // Version 2 stored `t` as plain floats in encoded files (version 3 predicts it).
    older_fixture_reads_back("v2-cornell-lossless", 2, Encoding::Lossless);
}

#[test]
fn version_3_lossless_datasets_still_read() {
    // Version 3 stored the path payload's radiance as plain floats (version 4 predicts it).
    older_fixture_reads_back("v3-cornell-lossless", 3, Encoding::Lossless);
}

#[test]
fn corrupt_encoded_rows_are_errors_that_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ds");
    write(&path, &trees(5, 1.0, 0.0), Encoding::Lossless, 1);
    let ds = Dataset::open(&path).unwrap();
    let file = &ds.ray_files()[0];
    let reader =
        parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(std::fs::File::open(file).unwrap())
            .unwrap()
            .build()
            .unwrap();
    let raw: Vec<RecordBatch> = reader.map(Result::unwrap).collect();
    let raw = arrow::compute::concat_batches(&ds.file_schema(), &raw).unwrap();
    assert!(raw.num_rows() > 4);
    // The untouched rows decode; each kind of damage is an error naming the file, not a panic.
    assert_eq!(ds.decoder(0).unwrap().decode(raw.clone(), file).unwrap().num_rows(), raw.num_rows());
    let replace = |name: &str, col: ArrayRef| {
        let mut cols = raw.columns().to_vec();
        cols[raw.schema().index_of(name).unwrap()] = col;
        RecordBatch::try_new(raw.schema(), cols).unwrap()
    };
    let n = raw.num_rows();
    let cases = [
        (replace("ray", Arc::new(UInt32Array::from_iter_values((0..n as u32).map(|i| i + 3)))), "contiguous"),
        (
            replace("parent", Arc::new(UInt32Array::from_iter((0..n as u32).map(|i| (i > 0).then_some(i + 5))))),
            "is not an earlier ray",
        ),
        (replace("enc_dir_code", Arc::new(UInt8Array::from(vec![7u8; n]))), "direction code 7"),
        (replace("enc_dir_code", Arc::new(UInt8Array::from(vec![128u8; n]))), "unknown bits"),
        (
            // Hit distances flagged as predicted in a segment whose ray file holds no planes.
            replace(
                "enc_dir_code",
                Arc::new(UInt8Array::from_iter_values(
                    raw.column_by_name("enc_dir_code")
                        .unwrap()
                        .as_any()
                        .downcast_ref::<UInt8Array>()
                        .unwrap()
                        .values()
                        .iter()
                        .map(|c| c | 64),
                )),
            ),
            "which has no usable plane",
        ),
    ];
    for (batch, expected) in cases {
        let err = ds.decoder(0).unwrap().decode(batch, file).unwrap_err().to_string();
        assert!(err.contains(expected) && err.contains("000001.rays.parquet"), "{err}");
    }
}

#[test]
fn every_row_group_starts_at_a_tree_and_decodes_alone() {
    let cols = trees(2000, 1.0, 0.0);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ds");
    write(&path, &cols, Encoding::Lossless, 7);
    let ds = Dataset::open(&path).unwrap();
    assert!(ds.check().is_ok(), "{:?}", ds.check());
    let file = &ds.ray_files()[0];
    let builder =
        parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(std::fs::File::open(file).unwrap())
            .unwrap();
    let groups = builder.metadata().num_row_groups();
    assert!(groups > 3, "{groups} row groups");
    let mut rows = 0;
    for g in 0..groups {
        let reader =
            parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(std::fs::File::open(file).unwrap())
                .unwrap()
                .with_row_groups(vec![g])
                .build()
                .unwrap();
        let mut dec = ds.decoder(0).unwrap();
        for b in reader {
            rows += dec.decode(b.unwrap(), file).unwrap().num_rows();
        }
    }
    assert_eq!(rows, cols.len());
}

/// Projected reads decode only what they need (directions alone from the direction columns;
/// origins from the tree structure, without the other columns) and give exactly the columns of
/// a full decode, for every encoding, whole segments and subsets of trees.
#[test]
fn projected_columns_equal_the_full_decode() {
    for (cols, encoding) in [
        (trees(600, 1e3, 1e5), Encoding::Lossless),
        (trees(600, 1e3, 1e5), Encoding::Plain),
        (trees(600, 1e3, 1e5), Encoding::Oct(12)),
        (box_trees(600, 500.0, 0.0), Encoding::Lossless),
        (box_trees(600, 500.0, 0.0), Encoding::Oct(12)),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ds");
        write(&path, &cols, encoding, 4);
        let ds = Dataset::open(&path).unwrap();
        let full: Vec<RecordBatch> = ds.segment_batches(0).unwrap().map(|b| b.unwrap()).collect();
        let full = arrow::compute::concat_batches(&full[0].schema(), &full).unwrap();
        let trees = ds.segment_tree_entries(0).unwrap();
        // Trees 10..40 and 300..310, as row ranges.
        let range =
            |a: usize, b: usize| trees[a].first_row..trees[b - 1].first_row + u64::from(trees[b - 1].info.ray_count);
        let subset = [range(10, 40), range(300, 310)];
        for names in [
            vec!["dir_x", "dir_y", "dir_z"],
            vec!["kind", "dir_z", "depth"],
            vec!["origin_y", "kind"],
            vec!["dir_y", "origin_x", "t", "origin_z", "tree_id"],
            vec!["t"],
            vec!["prim", "t", "depth"],
        ] {
            let names: Vec<String> = names.into_iter().map(String::from).collect();
            for rows in [None, Some(&subset[..])] {
                let got: Vec<RecordBatch> = ds
                    .segment_columns_in(0, &names, rows, store::READ_BATCH_ROWS)
                    .unwrap()
                    .map(|b| b.unwrap())
                    .collect();
                let got = arrow::compute::concat_batches(&got[0].schema(), &got).unwrap();
                let expected_rows: Vec<usize> = match rows {
                    None => (0..full.num_rows()).collect(),
                    Some(r) => r.iter().flat_map(|r| r.start as usize..r.end as usize).collect(),
                };
                assert_eq!(got.num_rows(), expected_rows.len(), "{encoding:?} {names:?}");
                let idx = arrow::array::UInt64Array::from_iter_values(expected_rows.iter().map(|&r| r as u64));
                for (k, name) in names.iter().enumerate() {
                    let want = arrow::compute::take(full.column_by_name(name).unwrap(), &idx, None).unwrap();
                    assert_eq!(got.schema().field(k).name(), name);
                    // ArrayData equality compares float values bit by bit (NaN payloads included).
                    assert!(
                        got.column(k).to_data() == want.to_data(),
                        "{encoding:?} {name} of {names:?}, rows {rows:?}"
                    );
                }
            }
        }
    }
}
