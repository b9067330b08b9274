//! Criterion benchmarks of the dense solvers: precompute (build `H`, SVD, λ / rank
//! choice, `P`) and the per-frame apply `f = P u`, for `pinv`, `tikhonov` (fixed λ and
//! GCV), `tsvd` (automatic rank), in f64 and f32, on the paper geometry (10×8 force
//! grid, 260 markers: `H` is 520×240) and on `sensor::grid_sensor(n, n, 1.1, 1.1)`
//! with two marker layers at n = 16 (`H` 1024×768) and n = 32 (`H` 4096×3072).
//!
//! Sample counts and times are kept small so the whole run takes a few minutes:
//! `cargo bench --bench solvers`. Filters select parts, e.g.
//! `cargo bench --bench solvers -- apply/paper`. Precompute at n = 32 (one SVD of a
//! 4096×3072 matrix) is not benchmarked here, it is timed once by
//! `examples/dense_cost.rs`; the n = 32 apply builds its solver once, lazily, only when
//! selected.

use std::cell::{OnceCell, RefCell};
use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use tactbench::model::{self, MarkerSite};
use tactbench::sensor::{self, Sensor};
use tactbench::solve::dense::DenseSolver;
use tactbench::solve::{FrameSolver, Lambda, Method, Precision, Problem, Rank, SolverConfig};

/// A geometry with a realistic frame: a smooth 1.2 N press, noise-free.
struct Geometry {
    name: &'static str,
    sensor: Sensor,
    sites: Vec<MarkerSite>,
    frame: Vec<f64>,
}

impl Geometry {
    fn new(name: &'static str, sensor: Sensor) -> Geometry {
        let sites = MarkerSite::from_sensor_grids(&sensor);
        let fps = sensor.force_points_mm();
        let c = [
            fps.iter().map(|p| p[0]).sum::<f64>() / fps.len() as f64,
            fps.iter().map(|p| p[1]).sum::<f64>() / fps.len() as f64,
        ];
        let forces: Vec<f64> = fps
            .iter()
            .flat_map(|p| {
                let d2 = (p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2);
                let w = 0.1 * (-d2 / 18.0).exp();
                [0.3 * w, -0.2 * w, w]
            })
            .collect();
        let model = Problem::new(&sensor, &sites).model;
        let frame = model::forward(&model, &sites, &fps, &forces).expect("valid geometry");
        Geometry {
            name,
            sensor,
            sites,
            frame,
        }
    }

    fn solver(&self, cfg: &SolverConfig) -> DenseSolver {
        DenseSolver::precompute(
            &Problem::new(&self.sensor, &self.sites),
            cfg,
            Some(&self.frame),
        )
        .expect("precompute")
    }
}

fn methods() -> [(&'static str, SolverConfig); 4] {
    let base = SolverConfig::default();
    [
        (
            "pinv",
            SolverConfig {
                method: Method::Pinv,
                ..base
            },
        ),
        (
            "tikhonov_fixed",
            SolverConfig {
                method: Method::Tikhonov,
                lambda: Lambda::Fixed(1e-3),
                ..base
            },
        ),
        (
            "tikhonov_gcv",
            SolverConfig {
                method: Method::Tikhonov,
                lambda: Lambda::Gcv,
                ..base
            },
        ),
        (
            "tsvd_auto",
            SolverConfig {
                method: Method::Tsvd,
                rank: Rank::Auto,
                ..base
            },
        ),
    ]
}

fn precisions() -> [(&'static str, Precision); 2] {
    [("f64", Precision::F64), ("f32", Precision::F32)]
}

fn bench_precompute(c: &mut Criterion) {
    let mut group = c.benchmark_group("precompute");
    group.warm_up_time(Duration::from_millis(500));
    for (geo, samples, secs) in [
        (Geometry::new("paper", sensor::paper_sensor()), 10, 3),
        (
            Geometry::new("grid16", sensor::grid_sensor(16, 16, 1.1, 1.1)),
            10,
            10,
        ),
    ] {
        group.sample_size(samples);
        group.measurement_time(Duration::from_secs(secs));
        for (name, cfg) in methods() {
            for (pname, precision) in precisions() {
                // Precision only changes the final copy of P: bench f32 for pinv only.
                if precision == Precision::F32 && name != "pinv" {
                    continue;
                }
                let cfg = SolverConfig { precision, ..cfg };
                group.bench_function(
                    BenchmarkId::new(format!("{}/{name}", geo.name), pname),
                    |b| b.iter(|| black_box(geo.solver(&cfg))),
                );
            }
        }
    }
    group.finish();
}

fn bench_apply(c: &mut Criterion) {
    let mut group = c.benchmark_group("apply");
    group.warm_up_time(Duration::from_millis(300));
    group.measurement_time(Duration::from_secs(1));
    group.sample_size(30);
    let geometries = [
        (
            OnceCell::new(),
            "paper",
            sensor::paper_sensor as fn() -> Sensor,
            true,
        ),
        (
            OnceCell::new(),
            "grid16",
            || sensor::grid_sensor(16, 16, 1.1, 1.1),
            false,
        ),
        (
            OnceCell::new(),
            "grid32",
            || sensor::grid_sensor(32, 32, 1.1, 1.1),
            false,
        ),
    ];
    for (cell, name, make, all_methods) in &geometries {
        for (mname, cfg) in methods() {
            // The apply is the same product P u for every method; off the paper
            // geometry only pinv is timed (it shares the precompute cost of the others).
            if !all_methods && mname != "pinv" {
                continue;
            }
            // Criterion calls the routine many times (warm-up, samples): precompute
            // once, lazily (only for selected benchmarks), and derive f32 from f64.
            let solver64: RefCell<Option<DenseSolver>> = RefCell::new(None);
            for (pname, precision) in precisions() {
                let id = BenchmarkId::new(format!("{name}/{mname}"), pname);
                let solver: RefCell<Option<DenseSolver>> = RefCell::new(None);
                group.bench_function(id, |b| {
                    let geo: &Geometry = cell.get_or_init(|| Geometry::new(name, make()));
                    let mut slot = solver.borrow_mut();
                    let s = slot.get_or_insert_with(|| {
                        let mut s64 = solver64.borrow_mut();
                        let base = s64.get_or_insert_with(|| geo.solver(&cfg));
                        base.with_precision(precision)
                    });
                    let mut f = vec![0.0; s.n_outputs()];
                    b.iter(|| {
                        s.apply(black_box(&geo.frame), black_box(&mut f))
                            .expect("apply")
                    })
                });
            }
        }
    }
    group.finish();
}

criterion_group!(benches, bench_apply, bench_precompute);
criterion_main!(benches);
