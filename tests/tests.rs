//! The single integration-test harness: one module per area.

mod sim;
mod vision;
