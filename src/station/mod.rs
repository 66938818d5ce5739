//! The station: plan poses, move the turntable, capture, detect, judge coverage, solve, give a verdict
//! and write a profile. Work in progress: the run itself lands with issue 16; the event and verdict
//! types are the interface the CLI, the service, the profile store and the report build on.

pub mod event;
pub mod notify;
pub mod verdict;

pub use event::{Event, EventSink};
pub use verdict::{Check, Verdict};
