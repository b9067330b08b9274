//! The bench runner's inputs and record: experiment plans and the crash-safe journal. The
//! runner itself (force control, settle detection, safety watchdog, journal and resume)
//! builds on these types and emits progress as events; it never prints or draws.

pub mod control;
pub mod journal;
pub mod plan;
