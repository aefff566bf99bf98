//! `rl`: record the rays a renderer traces, as ray trees, from any number of threads.
//!
//! * **Write mode** ([`Recorder::create`]): trees are sealed into Parquet segments on disk by
//!   background workers; memory stays under a budget with backpressure; a crash loses only
//!   trees not yet sealed.
//! * **Immediate mode** ([`Recorder::immediate`]): trees land in memory and are readable from
//!   other threads while recording goes on ([`MemoryTrace`]).
//! * **Read mode** ([`Reader`]): a cursor over a recorded dataset.
//! * A C ABI (`include/rl.h`) for C and C++ renderers.
//!
//! ```
//! use rl::{Kind, Payload, RayFields, Recorder, RecorderOptions};
//! let dir = tempfile::tempdir()?;
//! let rec = Recorder::create(dir.path().join("trace"), RecorderOptions::default())?;
//! let mut tree = rec.begin_tree(10, 20, 0);
//! let camera = RayFields { origin: [0.0; 3], direction: [0.0, 0.0, -1.0], t: Some(2.0), kind: Kind::CAMERA, prim: Some(7) };
//! tree.add_ray(&camera, Payload::NONE);
//! tree.descend();
//! let shadow = RayFields { origin: [0.0, 0.0, -2.0], direction: [0.0, 1.0, 0.0], t: None, kind: Kind::SHADOW, prim: None };
//! tree.add_ray(&shadow, Payload::NONE);
//! tree.ascend();
//! let id = tree.end();
//! rec.finish()?;
//! let ds = rl::Dataset::open(dir.path().join("trace"))?;
//! assert_eq!(ds.tree(id)?.rays.len(), 2);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

mod budget;
pub mod capi;
pub mod demo;
mod error;
mod immediate;
mod reader;
mod recorder;
mod write;

pub use error::{Error, Result};
pub use immediate::MemoryTrace;
pub use reader::{Reader, TraceSource};
pub use recorder::{Payload, RayId, Recorder, RecorderOptions, Sink, Summary, TreeBuilder};
pub use store::{
    BytesPayload, Dataset, Kind, ListValue, PayloadField, PayloadSchema, Ray, RayFields, Stats, Tree, TreeId, TreeInfo,
    Value, WriteOptions,
};
