//! The bench runner's inputs and state: experiment plans (this module so far). The
//! runner itself (force control, settle detection, safety watchdog, journal and resume)
//! builds on these types and emits progress as events; it never prints or draws.

pub mod plan;
