#![allow(clippy::unwrap_used)]
//! One ray selection, two roads: for generated selections (kinds, and ranges of tree id, pixel,
//! sample, depth and ray index), the rows the store's plan reads, narrowed by the selection's row
//! test, are exactly the rows `SELECT ... FROM rays WHERE <selection.to_sql()>` answers, and
//! `Dataset::count` says how many. Over the `.slt` traces (lossless and plain) and one of many
//! small segments (so segments are pruned by their manifest entries).

mod common;
mod slt_db;

use std::collections::BTreeSet;
use std::sync::{Arc, OnceLock};

use arrow::array::{Array, AsArray};
use arrow::datatypes::{DataType, UInt64Type};
use proptest::prelude::*;
use store::RaySelection;
use store::scene::col;

struct Fixture {
    _dir: tempfile::TempDir,
    datasets: Vec<(String, Arc<store::Dataset>)>,
    ctx: datafusion::prelude::SessionContext,
    rt: tokio::runtime::Runtime,
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let mut sources = slt_db::sources(dir.path());
        sources.retain(|s| s.name != "bad");
        let segmented = dir.path().join("segmented");
        common::record(
            &segmented,
            &[
                "--scene",
                "cornell",
                "--size",
                "16x12",
                "--spp",
                "2",
                "--threads",
                "1",
                "--seed",
                "3",
                "--segment-rays",
                "150",
                "--chunk-rays",
                "50",
            ],
        );
        sources.push(query::TraceSource { name: "segmented".into(), path: segmented });
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
        let ctx = rt.block_on(query::session(&sources)).unwrap();
        let datasets =
            sources.iter().map(|s| (s.name.clone(), Arc::new(store::Dataset::open(&s.path).unwrap()))).collect();
        Fixture { _dir: dir, datasets, ctx, rt }
    })
}

/// (tree id, ray) of every row the plan reads that the selection keeps.
fn planned_rows(ds: &store::Dataset, sel: &RaySelection) -> BTreeSet<(u64, u64)> {
    let names: Vec<String> = [col::TREE_ID, col::RAY, col::KIND, col::DEPTH].map(String::from).to_vec();
    let mut out = BTreeSet::new();
    for part in ds.plan(sel).unwrap().segments {
        let rows = part.rows.as_deref().map(Vec::as_slice);
        for b in ds.segment_columns_in(part.segment, &names, rows, store::READ_BATCH_ROWS).unwrap() {
            let b = b.unwrap();
            let u64s = |i: usize| arrow::compute::cast(b.column(i), &DataType::UInt64).unwrap();
            let (tree, ray, depth) = (u64s(0), u64s(1), u64s(3));
            let (tree, ray, depth) = (
                tree.as_primitive::<UInt64Type>(),
                ray.as_primitive::<UInt64Type>(),
                depth.as_primitive::<UInt64Type>(),
            );
            let (kinds, codes) = store::selection::kind_codes(b.column(2).as_ref()).unwrap();
            for (r, &k) in codes.iter().enumerate() {
                let kind = kinds[k].as_deref().unwrap_or("");
                if sel.keeps_row(kind, depth.value(r), ray.value(r)) {
                    out.insert((tree.value(r), ray.value(r)));
                }
            }
        }
    }
    out
}

/// (tree id, ray) of every row SQL selects with the selection's predicate.
fn sql_rows(f: &Fixture, table: &str, sel: &RaySelection) -> BTreeSet<(u64, u64)> {
    let sql = format!("SELECT tree_id, CAST(ray AS BIGINT UNSIGNED) FROM {table}.rays WHERE {}", sel.to_sql());
    let batches = f.rt.block_on(async { f.ctx.sql(&sql).await?.collect().await }).unwrap();
    let mut out = BTreeSet::new();
    for b in batches {
        let (t, r) = (b.column(0).as_primitive::<UInt64Type>(), b.column(1).as_primitive::<UInt64Type>());
        for i in 0..b.num_rows() {
            assert!(!t.is_null(i) && !r.is_null(i));
            out.insert((t.value(i), r.value(i)));
        }
    }
    out
}

fn ranges(max: u64) -> impl Strategy<Value = Vec<(u64, u64)>> {
    let bound = prop_oneof![4 => 0..=max, 1 => Just(u64::MAX)];
    proptest::collection::vec((0..=max, bound), 0..3)
        .prop_map(|v| v.into_iter().map(|(a, b)| (a.min(b), a.max(b))).collect())
}

fn selection() -> impl Strategy<Value = RaySelection> {
    let kinds = proptest::option::of(proptest::sample::subsequence(
        vec!["camera", "shadow", "diffuse", "specular", "transmission", "no_such_kind"],
        0..4,
    ));
    // Each column: unconstrained, or 0-2 ranges over its values (and past them).
    let tree = proptest::option::of(ranges(400));
    let px = proptest::option::of(ranges(17));
    let py = proptest::option::of(ranges(13));
    let sample = proptest::option::of(ranges(2));
    let depth = proptest::option::of(ranges(9));
    let ray = proptest::option::of(ranges(24));
    (kinds, tree, px, py, sample, depth, ray).prop_map(|(kinds, tree, px, py, sample, depth, ray)| {
        let mut sel = RaySelection::all();
        if let Some(k) = kinds {
            sel = sel.only_kinds(k);
        }
        for (c, r) in [
            (col::TREE_ID, tree),
            (col::PIXEL_X, px),
            (col::PIXEL_Y, py),
            (col::SAMPLE, sample),
            (col::DEPTH, depth),
            (col::RAY, ray),
        ] {
            if let Some(r) = r {
                sel = sel.only(c, r);
            }
        }
        sel
    })
}

/// The hand-picked selections the layers make (one tree, one pixel, a depth band) find rows.
#[test]
fn typical_selections_agree_and_find_rays() {
    let f = fixture();
    for (name, ds) in &f.datasets {
        for sel in [
            RaySelection::all(),
            RaySelection::all().only(col::TREE_ID, [(7, 7)]),
            RaySelection::all().only(col::PIXEL_X, [(3, 3)]).only(col::PIXEL_Y, [(5, 5)]).only(col::SAMPLE, [(1, 1)]),
            RaySelection::all().only_kinds(["shadow"]).only(col::DEPTH, [(1, 2)]),
            RaySelection::all().only(col::DEPTH, [(3, u64::MAX)]),
            RaySelection::all().only(col::RAY, [(0, 1)]).only(col::TREE_ID, [(100, 300)]),
        ] {
            let (plan, sql) = (planned_rows(ds, &sel), sql_rows(f, name, &sel));
            assert!(!sql.is_empty(), "{name}: {} finds no ray", sel.to_sql());
            assert_eq!(plan, sql, "{name}: {}", sel.to_sql());
            assert_eq!(ds.count(&sel).unwrap(), sql.len() as u64, "{name}: {}", sel.to_sql());
        }
    }
    let segmented = &f.datasets.iter().find(|(n, _)| n == "segmented").unwrap().1;
    let n = segmented.manifest().segments.len();
    assert!(n > 4, "{n} segments: too few to prune");
    let one = RaySelection::all().only(col::TREE_ID, [(7, 7)]);
    assert_eq!(segmented.plan(&one).unwrap().segments.len(), 1, "one tree: one segment read");
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn the_plan_reads_what_sql_selects(sel in selection()) {
        let f = fixture();
        for (name, ds) in &f.datasets {
            let (plan, sql) = (planned_rows(ds, &sel), sql_rows(f, name, &sel));
            prop_assert_eq!(&plan, &sql, "{}: {}", name, sel.to_sql());
            prop_assert_eq!(ds.count(&sel).unwrap(), sql.len() as u64, "{}: {}", name, sel.to_sql());
        }
    }
}
