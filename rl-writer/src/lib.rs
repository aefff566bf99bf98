#![doc = include_str!("../README.md")]

mod budget;
pub mod capi;
pub mod demo;
mod error;
mod immediate;
mod reader;
mod recorder;
mod sink;
mod write;

pub use arrow::datatypes::DataType;
pub use error::{Error, Result};
pub use immediate::MemoryTrace;
pub use reader::{Reader, TreeSource};
pub use recorder::{Mode, Payload, RayId, Recorder, SiteRef, TreeBuilder};
pub use sink::{RecorderOptions, Summary};
pub use store::{
    BytesPayload, Dataset, Kind, ListValue, PayloadField, PayloadSchema, Ray, RayFields, Stats, Tree, TreeId, TreeInfo,
    Value, WriteOptions,
};
