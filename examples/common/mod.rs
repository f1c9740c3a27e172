//! Harness code shared by the examples, benchmarks and tests (included with
//! `#[path]`; not library API).
#![allow(dead_code)]

pub mod args;
pub mod bench;
pub mod display;
pub mod faces;
#[cfg(feature = "bevy")]
pub mod headless;
pub mod soak;
