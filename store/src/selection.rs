//! Which rays a filter selects, said once: a [`RaySelection`] holds the kinds and the inclusive
//! ranges of the integer columns a ray is chosen by (tree, pixel, sample, depth, index in its
//! tree). Everything that picks rays builds one: the viewer's layers from their settings, the SQL
//! scan from the filters DataFusion pushes down. [`crate::Dataset::plan`] turns it into the rows
//! to read, [`crate::Dataset::count`] counts what it keeps, [`RaySelection::keeps_row`] decides
//! a decoded row, and [`RaySelection::to_sql`] says it as a predicate over the `rays` table (for
//! a dataset served elsewhere), so the local and the served roads select the same rays.

use std::collections::{BTreeMap, BTreeSet};

use arrow::array::{Array, AsArray};
use arrow::error::ArrowError;

use crate::schema::col;
use crate::tree::TreeInfo;

/// The integer columns a selection constrains, in the order [`RaySelection::to_sql`] says them.
pub const SELECTION_COLUMNS: [&str; 6] = [col::TREE_ID, col::PIXEL_X, col::PIXEL_Y, col::SAMPLE, col::DEPTH, col::RAY];

/// The selection columns answered by the tree table alone (a tree keeps all its rays or none).
pub const TREE_SELECTION_COLUMNS: [&str; 4] = [col::TREE_ID, col::PIXEL_X, col::PIXEL_Y, col::SAMPLE];

/// Which rays to take: those of the kinds `kinds` (any kind when `None`) whose selection columns
/// each lie in one of the column's inclusive ranges (any value for a column without ranges). An
/// empty kind set or an empty range list selects nothing. Built with [`RaySelection::all`] and
/// narrowed with [`RaySelection::only_kinds`] and [`RaySelection::only`]; each narrowing
/// intersects with what is already there.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RaySelection {
    kinds: Option<BTreeSet<String>>,
    ranges: BTreeMap<&'static str, Vec<(u64, u64)>>,
}

/// Sorted, disjoint, non-adjacent inclusive ranges.
pub fn normalize(mut v: Vec<(u64, u64)>) -> Vec<(u64, u64)> {
    v.retain(|(lo, hi)| lo <= hi);
    v.sort_unstable();
    let mut out: Vec<(u64, u64)> = Vec::with_capacity(v.len());
    for (lo, hi) in v {
        match out.last_mut() {
            Some(last) if lo <= last.1.saturating_add(1) => last.1 = last.1.max(hi),
            _ => out.push((lo, hi)),
        }
    }
    out
}

/// The values both sorted, disjoint range lists hold.
fn intersect(a: &[(u64, u64)], b: &[(u64, u64)]) -> Vec<(u64, u64)> {
    let mut out = Vec::new();
    for &(a0, a1) in a {
        for &(b0, b1) in b {
            let (lo, hi) = (a0.max(b0), a1.min(b1));
            if lo <= hi {
                out.push((lo, hi));
            }
        }
    }
    normalize(out)
}

/// Whether `v` lies in `ranges` (sorted, disjoint; any value when `None`).
pub fn in_ranges(ranges: Option<&[(u64, u64)]>, v: u64) -> bool {
    ranges.is_none_or(|r| {
        let i = r.partition_point(|&(_, hi)| hi < v);
        i < r.len() && r[i].0 <= v
    })
}

/// Whether `ranges` (any value when `None`) meet `[lo, hi]`.
pub fn meets(ranges: Option<&[(u64, u64)]>, lo: u64, hi: u64) -> bool {
    ranges.is_none_or(|r| r.iter().any(|&(a, b)| a <= hi && lo <= b))
}

/// How many values inclusive ranges cover (saturating).
pub fn span(r: &[(u64, u64)]) -> u64 {
    r.iter().map(|&(lo, hi)| hi.saturating_sub(lo).saturating_add(1)).fold(0u64, u64::saturating_add)
}

/// The distinct names of a kind column (dictionary-encoded or plain strings; `None` for a null)
/// and each row's index into them: what [`RaySelection::keeps_kind`] is asked once per name.
pub fn kind_codes(col: &dyn Array) -> std::result::Result<(Vec<Option<String>>, Vec<usize>), ArrowError> {
    let names_of = |col: &dyn Array| -> std::result::Result<Vec<Option<String>>, ArrowError> {
        let strings = arrow::compute::cast(col, &arrow::datatypes::DataType::Utf8)?;
        let s = strings.as_string::<i32>();
        Ok((0..s.len()).map(|i| (!s.is_null(i)).then(|| s.value(i).to_string())).collect())
    };
    if let Some(dict) = col.as_any_dictionary_opt() {
        return Ok((names_of(dict.values().as_ref())?, dict.normalized_keys()));
    }
    let mut names: Vec<Option<String>> = Vec::new();
    let codes = names_of(col)?
        .into_iter()
        .map(|n| match names.iter().position(|m| *m == n) {
            Some(i) => i,
            None => {
                names.push(n);
                names.len() - 1
            }
        })
        .collect();
    Ok((names, codes))
}

impl RaySelection {
    /// Every ray.
    pub fn all() -> RaySelection {
        RaySelection::default()
    }

    /// The column of [`SELECTION_COLUMNS`] called `name`, if any.
    pub fn column(name: &str) -> Option<&'static str> {
        SELECTION_COLUMNS.into_iter().find(|c| *c == name)
    }

    /// Only rays of these kinds (intersected with the kinds already kept).
    pub fn only_kinds<I: IntoIterator<Item = S>, S: Into<String>>(mut self, kinds: I) -> RaySelection {
        self.keep_kinds(kinds.into_iter().map(Into::into).collect());
        self
    }

    /// Only rays whose `column` lies in one of `ranges` (inclusive; intersected with the ranges
    /// already kept). A name outside [`SELECTION_COLUMNS`] is ignored: the selection stays a
    /// superset of what was asked, never loses a ray.
    pub fn only(mut self, column: &str, ranges: impl IntoIterator<Item = (u64, u64)>) -> RaySelection {
        self.keep(column, ranges.into_iter().collect());
        self
    }

    /// Only the rays of tree `tree`, of pixel `pixel` and of sample `sample`, each where given:
    /// how the layers say "this tree", "this pixel" and "this sample".
    pub fn only_trees_of(mut self, tree: Option<u64>, pixel: Option<[u32; 2]>, sample: Option<u32>) -> RaySelection {
        if let Some(t) = tree {
            self.keep(col::TREE_ID, vec![(t, t)]);
        }
        if let Some([x, y]) = pixel.map(|p| p.map(u64::from)) {
            self.keep(col::PIXEL_X, vec![(x, x)]);
            self.keep(col::PIXEL_Y, vec![(y, y)]);
        }
        if let Some(v) = sample.map(u64::from) {
            self.keep(col::SAMPLE, vec![(v, v)]);
        }
        self
    }

    /// [`RaySelection::only_kinds`] in place.
    pub fn keep_kinds(&mut self, kinds: BTreeSet<String>) {
        self.kinds = Some(match self.kinds.take() {
            Some(old) => old.intersection(&kinds).cloned().collect(),
            None => kinds,
        });
    }

    /// [`RaySelection::only`] in place.
    pub fn keep(&mut self, column: &str, ranges: Vec<(u64, u64)>) {
        let Some(column) = RaySelection::column(column) else { return };
        let r = normalize(ranges);
        let merged = match self.ranges.get(column) {
            Some(old) => intersect(old, &r),
            None => r,
        };
        self.ranges.insert(column, merged);
    }

    /// The kinds kept (`None`: every kind).
    pub fn kinds(&self) -> Option<&BTreeSet<String>> {
        self.kinds.as_ref()
    }

    /// The ranges `column` is kept in (`None`: any value).
    pub fn ranges(&self, column: &str) -> Option<&[(u64, u64)]> {
        self.ranges.get(column).map(Vec::as_slice)
    }

    /// Every constrained column with its ranges.
    pub fn constrained(&self) -> impl Iterator<Item = (&'static str, &[(u64, u64)])> {
        self.ranges.iter().map(|(c, r)| (*c, r.as_slice()))
    }

    /// Whether every ray is kept.
    pub fn is_all(&self) -> bool {
        self.kinds.is_none() && self.ranges.is_empty()
    }

    /// Whether a column of the tree table (tree, pixel, sample) is constrained.
    pub fn has_tree_filters(&self) -> bool {
        TREE_SELECTION_COLUMNS.iter().any(|c| self.ranges.contains_key(c))
    }

    /// Whether a column of the rays themselves (kind, depth, index in the tree) is constrained.
    pub fn has_row_filters(&self) -> bool {
        self.kinds.is_some() || self.ranges.contains_key(col::DEPTH) || self.ranges.contains_key(col::RAY)
    }

    /// Whether the kind named `kind` is kept.
    pub fn keeps_kind(&self, kind: &str) -> bool {
        self.kinds.as_ref().is_none_or(|k| k.contains(kind))
    }

    /// Whether a ray at `depth`, `ray`-th in its tree, of a kept kind and a kept tree is kept.
    pub fn keeps_depth_and_ray(&self, depth: u64, ray: u64) -> bool {
        in_ranges(self.ranges(col::DEPTH), depth) && in_ranges(self.ranges(col::RAY), ray)
    }

    /// Whether a ray of kind `kind` at `depth`, `ray`-th in a kept tree, is kept.
    pub fn keeps_row(&self, kind: &str, depth: u64, ray: u64) -> bool {
        self.keeps_kind(kind) && self.keeps_depth_and_ray(depth, ray)
    }

    /// Whether tree `t` can hold a kept ray: its id, pixel and sample are kept, it reaches the
    /// lowest kept depth and holds the lowest kept ray index.
    pub fn keeps_tree(&self, t: &TreeInfo) -> bool {
        in_ranges(self.ranges(col::TREE_ID), t.id.0)
            && in_ranges(self.ranges(col::PIXEL_X), u64::from(t.pixel[0]))
            && in_ranges(self.ranges(col::PIXEL_Y), u64::from(t.pixel[1]))
            && in_ranges(self.ranges(col::SAMPLE), u64::from(t.sample))
            && u64::from(t.max_depth) >= self.min(col::DEPTH)
            && u64::from(t.ray_count) > self.min(col::RAY)
    }

    /// The lowest value `column` may take (0 when it is not constrained, `u64::MAX` when no
    /// value is kept).
    pub fn min(&self, column: &str) -> u64 {
        self.ranges(column).map_or(0, |r| r.first().map_or(u64::MAX, |r| r.0))
    }

    /// The tree-table filter of the tree, pixel and sample ranges.
    pub fn tree_filter(&self) -> crate::TreeFilter {
        let get = |c| self.ranges(c).map(<[_]>::to_vec);
        crate::TreeFilter {
            tree_id: get(col::TREE_ID),
            pixel_x: get(col::PIXEL_X),
            pixel_y: get(col::PIXEL_Y),
            sample: get(col::SAMPLE),
        }
    }

    /// The selection as a SQL predicate over the `rays` table (`TRUE` for every ray): kind
    /// names are quoted, a column's ranges become `=`, `<=`, `>=` or `BETWEEN` joined by `OR`.
    pub fn to_sql(&self) -> String {
        let mut terms = Vec::new();
        if let Some(k) = &self.kinds {
            if k.is_empty() {
                return "FALSE".into();
            }
            let names: Vec<String> = k.iter().map(|n| format!("'{}'", n.replace('\'', "''"))).collect();
            terms.push(format!("kind IN ({})", names.join(", ")));
        }
        for column in SELECTION_COLUMNS {
            let Some(r) = self.ranges(column) else { continue };
            let parts: Vec<String> = r
                .iter()
                .map(|&(lo, hi)| match (lo, hi) {
                    (lo, hi) if lo == hi => format!("{column} = {lo}"),
                    (0, hi) => format!("{column} <= {hi}"),
                    (lo, u64::MAX) => format!("{column} >= {lo}"),
                    (lo, hi) => format!("{column} BETWEEN {lo} AND {hi}"),
                })
                .collect();
            match parts.len() {
                0 => return "FALSE".into(),
                1 => terms.extend(parts),
                _ => terms.push(format!("({})", parts.join(" OR "))),
            }
        }
        if terms.is_empty() { "TRUE".into() } else { terms.join(" AND ") }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::TreeId;

    #[test]
    fn narrowing_intersects_and_sql_says_it() {
        let s = RaySelection::all()
            .only_kinds(["shadow", "diffuse"])
            .only_kinds(["shadow", "camera"])
            .only(col::DEPTH, [(1, 4)])
            .only(col::DEPTH, [(3, 9)])
            .only(col::PIXEL_X, [(5, 5), (7, 8), (6, 6)])
            .only(col::RAY, [(0, 3)])
            .only("throughput", [(0, 0)]);
        assert_eq!(s.kinds().map(|k| k.len()), Some(1));
        assert_eq!(s.ranges(col::DEPTH), Some(&[(3, 4)][..]));
        assert_eq!(s.ranges(col::PIXEL_X), Some(&[(5, 8)][..]), "adjacent ranges merge");
        assert_eq!(s.to_sql(), "kind IN ('shadow') AND pixel_x BETWEEN 5 AND 8 AND depth BETWEEN 3 AND 4 AND ray <= 3");
        assert!(s.keeps_row("shadow", 3, 2));
        assert!(!s.keeps_row("camera", 3, 2));
        assert!(!s.keeps_row("shadow", 5, 2));
        assert!(!s.keeps_row("shadow", 3, 4));
        assert_eq!(RaySelection::all().to_sql(), "TRUE");
        assert_eq!(
            RaySelection::all().only(col::SAMPLE, [(2, 2), (4, u64::MAX)]).to_sql(),
            "(sample = 2 OR sample >= 4)"
        );
        assert_eq!(RaySelection::all().only(col::DEPTH, [(3, 1)]).to_sql(), "FALSE", "an empty range keeps nothing");
        assert_eq!(RaySelection::all().only_kinds(Vec::<String>::new()).to_sql(), "FALSE");
        assert_eq!(RaySelection::all().only_kinds(["it's"]).to_sql(), "kind IN ('it''s')", "quotes are doubled");
    }

    #[test]
    fn trees_are_kept_by_their_columns_depth_and_size() {
        let t = TreeInfo { id: TreeId(7), pixel: [3, 4], sample: 1, ray_count: 5, max_depth: 2 };
        assert!(RaySelection::all().keeps_tree(&t));
        assert!(RaySelection::all().only(col::TREE_ID, [(7, 7)]).keeps_tree(&t));
        assert!(!RaySelection::all().only(col::TREE_ID, [(8, 9)]).keeps_tree(&t));
        assert!(!RaySelection::all().only(col::PIXEL_Y, [(0, 3)]).keeps_tree(&t));
        assert!(RaySelection::all().only(col::DEPTH, [(2, 5)]).keeps_tree(&t));
        assert!(!RaySelection::all().only(col::DEPTH, [(3, 5)]).keeps_tree(&t), "no ray that deep");
        assert!(RaySelection::all().only(col::RAY, [(4, 9)]).keeps_tree(&t));
        assert!(!RaySelection::all().only(col::RAY, [(5, 9)]).keeps_tree(&t), "no fifth ray");
        assert!(!RaySelection::all().only(col::SAMPLE, []).keeps_tree(&t));
        let of = RaySelection::all().only_trees_of(Some(7), Some([3, 4]), Some(1));
        assert!(of.keeps_tree(&t));
        assert_eq!(of.to_sql(), "tree_id = 7 AND pixel_x = 3 AND pixel_y = 4 AND sample = 1");
        assert!(!RaySelection::all().only_trees_of(None, Some([3, 5]), None).keeps_tree(&t));
        assert!(RaySelection::all().only_trees_of(None, None, None).is_all());
    }
}
