#![doc = include_str!("../README.md")]

pub mod analyze;
pub mod codec;
mod count_by_key;
mod engine;
mod error;
mod functions;
mod live;
pub mod memory;
pub mod numerics;
mod plan_util;
mod scan;
pub mod service;
mod sliced;
mod small_groups;
mod tables;
mod unavailable;

pub use count_by_key::{CountByKey, CountByKeyExec};
pub use engine::{Catalog, Engine};
pub use error::{Error, Result};
pub use functions::{
    RAY_SECTION, SceneContext, SceneTriangles, TriangleBvh, functions_markdown, ray_aggregates, ray_functions,
    ray_scalar_functions, register_functions,
};
pub use live::LiveTrace;
pub use sliced::{SegmentFiles, SliceableScans};
pub use small_groups::{SmallGroups, SmallGroupsExec};
pub use tables::{
    ATTRIBUTES_TABLE, Registered, SessionOptions, TraceSource, open_sources, physical_optimizer_rules,
    register_dataset, register_datasets, session, session_config, session_state, session_with,
};
