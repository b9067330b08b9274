//! Plans shared by the module's unit tests.

use super::{Plan, PlanError};

pub(crate) const FIG7: &str = r#"
name = "fig7"
sensor = "paper_sensor.toml"
force_unit = "gf"
[indenter]
shape = "hemisphere"
diameter_mm = 5.0
[approach]
position_mm = [9.0, 6.75]
speed_mm_s = 0.5
contact_force = 5.0
[safety]
max_force = [300.0, 300.0, 1000.0]
travel_min_mm = [0.0, 0.0, -2.0]
travel_max_mm = [50.0, 50.0, 20.0]
max_speed_mm_s = 5.0
[sweep]
kind = "magnitude"
from = 0.0
to = 750.0
step = 50.0
trials = 10
"#;

pub(crate) fn parse(t: &str) -> Result<Plan, PlanError> {
    Plan::from_toml_str(t, "experiments/p.toml")
}

pub(crate) const MAG: &str =
    "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10";

pub(crate) fn with_sweep(sweep: &str) -> String {
    FIG7.replace(MAG, sweep)
}
