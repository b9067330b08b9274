//! Criterion benches of the `fourier` solver: precompute and per-frame apply on the
//! synthetic regular-grid sensors (`sensor::grid_sensor`): the paper-sized 10×8 force
//! grid every 2.2 mm with markers every 1.1 mm, and 32×32 / 64×64 force grids with
//! markers every 1.1 mm (two layers each). Targets (issue 2): 64×64 apply ≤ 2 ms,
//! precompute ≤ 5 s. `direct` is the periodic solve alone (the solver before issue 12);
//! `default` adds the default CGLS refinement ([`DEFAULT_REFINE_ITERATIONS`]), which is
//! what makes the output agree with dense Tikhonov (issue 12).
//!
//! `cargo bench --bench fourier`

use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use tactbench::model::{self, MarkerSite};
use tactbench::sensor::{grid_sensor, Sensor};
use tactbench::solve::fourier::{FourierSolver, DEFAULT_REFINE_ITERATIONS};
use tactbench::solve::{FrameSolver, Lambda, Method, Problem, SolverConfig};

/// λ (mm/N) used by the fixed-λ benches: about 1 % of the largest singular value.
const LAMBDA: f64 = 0.1;

fn cases() -> Vec<(&'static str, Sensor)> {
    vec![
        ("10x8_f2.2_m1.1", grid_sensor(10, 8, 2.2, 1.1)),
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

    let mut g = c.benchmark_group("fourier_apply");
    g.sample_size(30).measurement_time(Duration::from_secs(4));
    for (name, sensor) in cases() {
        let sites = MarkerSite::from_sensor_grids(&sensor);
        let problem = Problem::new(&sensor, &sites);
        let u = frame(&sensor, &sites);
        let mut solver = FourierSolver::precompute(&problem, &fixed, None).expect("precompute");
        let mut f = vec![0.0; solver.n_outputs()];
        solver.refine_iterations = 0;
        g.bench_function(format!("{name}/direct"), |b| {
            b.iter(|| solver.apply(black_box(&u), &mut f).expect("apply"))
        });
        solver.refine_iterations = DEFAULT_REFINE_ITERATIONS;
        g.bench_function(format!("{name}/default"), |b| {
            b.iter(|| solver.apply(black_box(&u), &mut f).expect("apply"))
        });
    }
    g.finish();

    // The same applies timed by on-CPU time of this thread (`/proc/thread-self/schedstat`,
    // ns) instead of wall time: on a shared, overloaded machine wall time includes the
    // time the scheduler gives to other processes.
    if tactbench::clock::thread_cpu_ns().is_some() {
        let mut g = c.benchmark_group("fourier_apply_oncpu");
        g.sample_size(30).measurement_time(Duration::from_secs(4));
        for (name, sensor) in cases() {
            let sites = MarkerSite::from_sensor_grids(&sensor);
            let problem = Problem::new(&sensor, &sites);
            let u = frame(&sensor, &sites);
            let mut solver = FourierSolver::precompute(&problem, &fixed, None).expect("precompute");
            solver.refine_iterations = 0;
            let mut f = vec![0.0; solver.n_outputs()];
            g.bench_function(format!("{name}/direct"), |b| {
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
            });
        }
        g.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
