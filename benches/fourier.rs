//! Criterion benches of the `fourier` solver: precompute and per-frame apply on the
//! synthetic regular-grid sensors (`sensor::grid_sensor`): the paper-sized 10×8 force
//! grid every 2.2 mm with markers every 1.1 mm, and 16×16, 32×32 and 64×64 force grids
//! with markers every 1.1 mm (two layers each). Targets (issue 2): 64×64 apply ≤ 2 ms,
//! precompute ≤ 5 s. Apply variants (issue 12: what accuracy costs): `direct` is the
//! periodic solve alone; `two_level` adds the precomputed coarse correction with exact
//! force sums (`coarse.rs`); `refine_K` adds exactly K CGLS refinement iterations to it
//! (tolerance 0); `default` is the default settings ([`DEFAULT_REFINE_ITERATIONS`]
//! iterations at most, stopping at [`DEFAULT_REFINE_TOLERANCE`]; the iterations it ran are
//! printed). λ = 1e-2 of the
//! periodic operator's largest singular value.
//!
//! `cargo bench --bench fourier` (wall time; `-- fourier_apply` for the applies only);
//! the `fourier_apply_oncpu` group times the same applies by this thread's CPU time
//! (`/proc/thread-self/schedstat`), which a loaded machine does not inflate.

use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use tactbench::model::{self, MarkerSite};
use tactbench::sensor::{grid_sensor, Sensor};
use tactbench::solve::fourier::{
    FourierSolver, DEFAULT_REFINE_ITERATIONS, DEFAULT_REFINE_TOLERANCE,
};
use tactbench::solve::{FrameSolver, Lambda, Method, Problem, SolverConfig};

/// λ (mm/N) of the precompute benches.
const LAMBDA: f64 = 0.1;

/// Fixed refinement counts timed.
const REFINE_COUNTS: [usize; 4] = [2, 5, 10, 20];

fn cases() -> Vec<(&'static str, Sensor)> {
    vec![
        ("10x8_f2.2_m1.1", grid_sensor(10, 8, 2.2, 1.1)),
        ("16x16_f1.1_m1.1", grid_sensor(16, 16, 1.1, 1.1)),
        ("32x32_f1.1_m1.1", grid_sensor(32, 32, 1.1, 1.1)),
        ("64x64_f1.1_m1.1", grid_sensor(64, 64, 1.1, 1.1)),
    ]
}

/// A smooth load in the middle of the grid and its exact displacements.
fn frame(sensor: &Sensor, sites: &[MarkerSite]) -> Vec<f64> {
    let g = sensor.force_grid;
    let c = g.node_mm(g.nx / 2, g.ny / 2);
    let f: Vec<f64> = sensor
        .force_points_mm()
        .iter()
        .flat_map(|p| {
            let w = (-((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)) / 8.0).exp();
            [0.02 * w, -0.01 * w, 0.05 * w]
        })
        .collect();
    let problem = Problem::new(sensor, sites);
    model::forward(&problem.model, sites, &sensor.force_points_mm(), &f)
        .expect("synthetic geometry is valid")
}

fn bench(c: &mut Criterion) {
    let fixed = SolverConfig {
        method: Method::Fourier,
        lambda: Lambda::Fixed(LAMBDA),
        ..SolverConfig::default()
    };
    let gcv = SolverConfig {
        lambda: Lambda::Gcv,
        ..fixed
    };
    let mut g = c.benchmark_group("fourier_precompute");
    g.sample_size(10).measurement_time(Duration::from_secs(8));
    for (name, sensor) in cases() {
        let sites = MarkerSite::from_sensor_grids(&sensor);
        let problem = Problem::new(&sensor, &sites);
        let u = frame(&sensor, &sites);
        g.bench_function(format!("{name}/fixed"), |b| {
            b.iter(|| FourierSolver::precompute(&problem, &fixed, None).expect("precompute"))
        });
        g.bench_function(format!("{name}/gcv"), |b| {
            b.iter(|| FourierSolver::precompute(&problem, &gcv, Some(&u)).expect("precompute"))
        });
    }
    g.finish();

    // Apply variants: (name, two-level correction, refinement cap, tolerance).
    let mut variants: Vec<(String, bool, usize, f64)> = vec![
        ("direct".into(), false, 0, 0.0),
        ("two_level".into(), true, 0, 0.0),
    ];
    variants.extend(
        REFINE_COUNTS
            .iter()
            .map(|&k| (format!("refine_{k}"), true, k, 0.0)),
    );
    variants.push((
        "default".into(),
        true,
        DEFAULT_REFINE_ITERATIONS,
        DEFAULT_REFINE_TOLERANCE,
    ));
    let oncpu = tactbench::clock::thread_cpu_ns().is_some();
    for (group, cpu) in [("fourier_apply", false), ("fourier_apply_oncpu", true)] {
        if cpu && !oncpu {
            continue;
        }
        let mut g = c.benchmark_group(group);
        g.sample_size(20).measurement_time(Duration::from_secs(3));
        for (name, sensor) in cases() {
            let sites = MarkerSite::from_sensor_grids(&sensor);
            let problem = Problem::new(&sensor, &sites);
            let u = frame(&sensor, &sites);
            let probe = FourierSolver::precompute(&problem, &fixed, None).expect("precompute");
            let lambda = 1e-2 * probe.diagnostics().singular_values[0];
            let cfg = SolverConfig {
                lambda: Lambda::Fixed(lambda),
                ..fixed
            };
            let mut solver = FourierSolver::precompute(&problem, &cfg, None).expect("precompute");
            let mut f = vec![0.0; solver.n_outputs()];
            for (variant, two_level, cap, tol) in &variants {
                solver.coarse_correction = *two_level;
                solver.refine_iterations = *cap;
                solver.refine_tolerance = *tol;
                if !cpu && variant == "default" {
                    solver.apply(&u, &mut f).expect("apply");
                    println!(
                        "{name}: default refinement ran {} iterations (λ = {lambda:.3e})",
                        solver.last_refine_iterations()
                    );
                }
                g.bench_function(format!("{name}/{variant}"), |b| {
                    if cpu {
                        b.iter_custom(|iters| {
                            let t0 = tactbench::clock::thread_cpu_ns().unwrap_or(0);
                            for _ in 0..iters {
                                solver.apply(black_box(&u), &mut f).expect("apply");
                            }
                            Duration::from_nanos(
                                tactbench::clock::thread_cpu_ns()
                                    .unwrap_or(0)
                                    .saturating_sub(t0),
                            )
                        })
                    } else {
                        b.iter(|| solver.apply(black_box(&u), &mut f).expect("apply"))
                    }
                });
            }
        }
        g.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
