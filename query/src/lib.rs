#![doc = include_str!("../README.md")]

pub mod analyze;
mod error;
mod functions;
mod scan;
pub mod service;
mod tables;

pub use error::{Error, Result};
pub use functions::{SceneContext, register_functions};
pub use tables::{SessionOptions, TraceSource, register_dataset, session, session_with};
