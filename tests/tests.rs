//! The single integration-test harness: one module per area.

mod ft;
mod stage;
