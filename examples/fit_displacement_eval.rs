//! Times one evaluation of the displacement route's residuals (issue 30: the whole
//! fit of a 160-setpoint run must take ≤ 10 s; the engine evaluates ~10–20 times per
//! iteration). Run: `cargo run --release --example fit_displacement_eval`.
//!
//! 160 setpoints on the paper sensor (every grid marker of both layers), a 10 mm
//! hemisphere, loads 0.5–4 N with shear, "measured" = predicted at nominal values.
//! Prints the mean time per eval for the half-space and for a 10 mm bonded layer
//! (the latter also with the thickness changed every eval, which builds new tables).
//! With a run directory argument (`-- RUN_DIR`), loads that run's displacement route
//! against the run's own sensor file and prints its summary at the nominal values.

use std::time::Instant;

use tactbench::bench::plan::IndenterShape;
use tactbench::fit::displacement::{DisplacementRoute, MarkerObs, SetpointObs};
use tactbench::fit::{ModelParams, Residuals};
use tactbench::model::MarkerSite;
use tactbench::sensor::{paper_sensor, ModelKind, Sensor};

fn route(sensor: &Sensor) -> DisplacementRoute {
    let mm = sensor.camera.mm_per_px;
    let sites = MarkerSite::from_sensor_grids(sensor);
    let sps = (0..160)
        .map(|i| SetpointObs {
            index: i,
            trial: i / 40,
            centre_mm: [4.0 + (i % 6) as f64 * 2.0, 3.0 + (i / 6 % 4) as f64 * 2.5],
            f_ft_n: [
                0.05 * (i % 5) as f64,
                -0.03 * (i % 3) as f64,
                0.5 + 0.1 * (i % 36) as f64,
            ],
            markers: sites
                .iter()
                .enumerate()
                .map(|(k, s)| {
                    MarkerObs::new(
                        s.layer,
                        k as u64,
                        [s.position_mm[0] / mm, s.position_mm[1] / mm],
                        [0.0, 0.0],
                    )
                })
                .collect(),
        })
        .collect();
    DisplacementRoute::from_observations(
        IndenterShape::Hemisphere { diameter_mm: 10.0 },
        sensor,
        sps,
        vec![0.05; sensor.layers.len()],
    )
    .expect("route")
}

fn time(label: &str, r: &DisplacementRoute, p: &ModelParams, vary_h: bool) {
    let mut out = vec![0.0; r.len()];
    r.eval(p, &mut out).expect("eval");
    let n = 20;
    let t0 = Instant::now();
    for i in 0..n {
        let mut q = p.clone();
        q.young_modulus_kpa *= 1.0 + 1e-4 * i as f64;
        if vary_h {
            q.thickness_mm *= 1.0 + 1e-4 * (i + 1) as f64;
        }
        r.eval(&q, &mut out).expect("eval");
    }
    let dt = t0.elapsed().as_secs_f64() / n as f64;
    println!(
        "{label}: {} residuals, {:.2} ms per eval",
        r.len(),
        dt * 1e3
    );
}

fn main() {
    if let Some(dir) = std::env::args().nth(1) {
        let dir = std::path::PathBuf::from(dir);
        let run = tactbench::analysis::RunData::load(&dir).expect("run directory");
        let t0 = Instant::now();
        let r = DisplacementRoute::from_run(&dir, &run.sensor).expect("route");
        let p = ModelParams::nominal(&run.sensor, 0.0);
        println!("loaded in {:.3} s", t0.elapsed().as_secs_f64());
        println!("{:#}", r.summary(&p).expect("summary"));
        let (per_sp, _) = r.residual_rms_px(&p).expect("rms");
        println!("per setpoint residual RMS (px): {per_sp:?}");
        return;
    }
    let s = paper_sensor();
    let r = route(&s);
    time("half-space", &r, &ModelParams::nominal(&s, 0.0), false);
    let mut b = s.clone();
    b.elastomer.model = ModelKind::BondedLayer;
    b.elastomer.thickness_mm = 10.0;
    let rb = route(&b);
    let pb = ModelParams::nominal(&b, 0.0);
    time("bonded layer 10 mm, E changed", &rb, &pb, false);
    time(
        "bonded layer 10 mm, h changed (new tables each eval)",
        &rb,
        &pb,
        true,
    );
}
