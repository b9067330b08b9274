//! The integration-test harness: one binary, one module per area (ripgrep's layout).
//! Shared helpers live in `util.rs`; golden data under `tests/fixtures/`.

mod util;

mod acceptance_fit;
mod archive;
mod bench;
mod camera;
mod cli;
mod compare;
mod docs_figures;
mod fit;
mod fit_coverage;
mod fit_sim;
mod fourier;
mod ft;
mod ft_net_bota;
mod house;
mod import;
mod inputs;
mod layer;
mod live;
mod marlin;
mod misuse;
mod model_error;
mod plans;
mod report;
mod report_metrology;
mod reproduce;
mod run;
mod sim;
mod solver_cli;
mod solvers;
mod stage;
mod stage_stop;
mod study;
mod sweeps;
mod vision;
mod vision_faint;
mod vision_gray;
mod vision_real;
mod vision_tracking;
mod vision_tracking_real;
