//! The bench runner and its inputs and record: experiment plans ([`plan`]), the bench
//! file ([`config`]), the runner's pure decision logic ([`control`]: settle detection,
//! force limits, force control), a stage move outside a run watched for a stop
//! signal and the force limits ([`guard`]), the runner itself ([`runner`]: setpoints, safety
//! watchdog, resume), the crash-safe run directory ([`journal`]) and its one-writer
//! lock ([`lock`]); a recording made elsewhere turned into a run directory
//! ([`import`]); a run directory made from a plan and a simulated scene without
//! devices, in the runner's format ([`synthetic`]: fast, for `fit`'s coverage tests;
//! it lives here, not in `sim`, because it writes the runner's record: `sim` depends
//! on nothing in `bench`); `live.json`, the runner's current activity for watchers
//! ([`live`]). Nothing here prints or draws: the runner emits
//! [`runner::RunEvent`]s.

pub mod config;
pub mod connect;
pub mod control;
pub mod events;
pub mod guard;
pub mod import;
pub mod integrity;
pub mod journal;
pub mod live;
pub mod lock;
pub mod plan;
pub mod provenance;
pub mod runner;
pub mod synthetic;
