//! Every component kind, in one place: the GUI's "add component" menu, `rtvtk render --layers`
//! and saved layouts all make components through [`make`].

use crate::component::{Component, ComponentId, Settings};
use crate::components::bvh::{self, BvhBoxes};
use crate::components::query::{self, Query};
use crate::components::rays::{Rays, RaysSettings};
use crate::components::{geometry, picture};
use crate::sources::Sources;
use crate::{Error, Result};

/// A kind of component.
pub struct ComponentInfo {
    pub kind: &'static str,
    pub display_name: &'static str,
    pub description: &'static str,
    /// Whether `sources` can feed this kind (a layer it cannot feed is not offered), and if not why.
    pub offered: fn(&Sources) -> Result<(), String>,
    pub make: fn(ComponentId, &Sources, &serde_json::Value) -> Result<Box<dyn Component>>,
}

fn needs_scene(s: &Sources) -> Result<(), String> {
    if s.scene.is_some() { Ok(()) } else { Err(s.why_no_scene()) }
}

static REGISTRY: [ComponentInfo; 7] = [
    ComponentInfo {
        kind: <picture::ImageSettings as Settings>::KIND,
        display_name: "Image",
        description: "the path-traced image of the dataset, or one refined progressively by the CPU path tracer",
        offered: |s| {
            if s.picture.is_some() || s.scene.is_some() { Ok(()) } else { Err("no image and no scene".into()) }
        },
        make: |id, s, v| Ok(Box::new(picture::Image::new(id, s, v)?)),
    },
    ComponentInfo {
        kind: <geometry::GeometrySettings as Settings>::KIND,
        display_name: "Geometry",
        description: "the scene's triangles: wireframe, alpha-blended or opaque, coloured by material",
        offered: needs_scene,
        make: |id, s, v| Ok(Box::new(geometry::Geometry::new(id, s, v)?)),
    },
    ComponentInfo {
        kind: <geometry::CompositionSettings as Settings>::KIND,
        display_name: "2D/3D composition",
        description: "the scene's depth, so the scene-space layers above it hide behind geometry over the image",
        offered: needs_scene,
        make: |id, s, _| Ok(Box::new(geometry::Composition::new(id, s)?)),
    },
    ComponentInfo {
        kind: <RaysSettings as Settings>::KIND,
        display_name: "Rays",
        description: "ray trees as segments coloured by kind, filtered by kind, depth, tree, pixel, sample; ctrl-click traces a pixel",
        offered: |s| {
            if s.has_rays() || s.scene.is_some() { Ok(()) } else { Err("no dataset and no scene".into()) }
        },
        make: |id, s, v| Ok(Box::new(Rays::new(id, s, v)?)),
    },
    ComponentInfo {
        kind: <bvh::BvhSettings as Settings>::KIND,
        display_name: "BVH",
        description: "BVH node boxes of a range of levels, optionally only the visited ones, coloured by level or visits",
        offered: |s| {
            s.can_query()?;
            if s.has_bvh_nodes { Ok(()) } else { Err("no bvh_nodes table".into()) }
        },
        make: |id, s, v| Ok(Box::new(BvhBoxes::new(id, s, v)?)),
    },
    ComponentInfo {
        kind: <query::QuerySettings as Settings>::KIND,
        display_name: "Query results",
        description: "the rows of a SQL query in scene space (segments or points), coloured by a column",
        offered: Sources::can_query,
        make: |id, s, v| Ok(Box::new(Query::new(id, s, v)?)),
    },
    ComponentInfo {
        kind: <picture::HeatmapSettings as Settings>::KIND,
        display_name: "Heatmap",
        description: "a per-pixel value over the image (rays per pixel or any GROUP BY pixel_x, pixel_y query)",
        offered: Sources::can_query,
        make: |id, s, v| Ok(Box::new(picture::Heatmap::new(id, s, v)?)),
    },
];

/// Every component kind.
pub fn registry() -> &'static [ComponentInfo] {
    &REGISTRY
}

/// The names of every kind, comma separated.
pub fn known_kinds() -> String {
    REGISTRY.iter().map(|c| c.kind).collect::<Vec<_>>().join(", ")
}

/// The registry entry of `kind`, or an error listing the known kinds.
pub fn info(kind: &str) -> Result<&'static ComponentInfo> {
    REGISTRY
        .iter()
        .find(|c| c.kind == kind)
        .ok_or_else(|| Error::UnknownLayer { name: kind.to_string(), known: known_kinds() })
}

/// Makes a component of `kind` with `settings` (`null`: defaults).
pub fn make(
    kind: &str,
    id: ComponentId,
    sources: &Sources,
    settings: &serde_json::Value,
) -> Result<Box<dyn Component>> {
    let i = info(kind)?;
    (i.offered)(sources).map_err(|why| Error::Layer {
        layer: kind.into(),
        message: format!("not available for this dataset: {why}"),
    })?;
    (i.make)(id, sources, settings)
}
