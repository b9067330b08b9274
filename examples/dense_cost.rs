//! Cost of the dense solvers on growing regular grids: precompute time (build `H`,
//! SVD + filtered pseudo-inverse) and memory (bytes of `H`, `U`, `V`, `P`) for
//! `sensor::grid_sensor(n, n, 1.1, 1.1)` (two marker layers), measured once per size,
//! then a power-law fit `t = a·N^b` over the two largest measured sizes (N = force
//! unknowns) extrapolated to 64×64. Extrapolated rows are labelled as such.
//!
//! It also times the two SVD implementations on `H` (nalgebra's `try_svd`, faer's
//! `thin_svd`) on the paper geometry and, with `--compare-svd`, on every size.
//!
//! Run in release: `cargo run --release --example dense_cost -- 8 16 24 32`
//! (default sizes 8 16 24), `cargo run --release --example dense_cost -- --compare-svd 16 32`
//! (nalgebra at n = 32 takes several minutes).

use std::hint::black_box;
use std::time::Instant;

use nalgebra::DMatrix;

use tactbench::model::{self, MarkerSite};
use tactbench::sensor;
use tactbench::solve::dense::DenseSolver;
use tactbench::solve::kernel::{self, Isa};
use tactbench::solve::{FrameSolver, Method, Precision, Problem, SolverConfig};

struct Row {
    n: usize,
    n_cols: usize,
    build_s: f64,
    precompute_s: f64,
    apply_us: f64,
}

fn mb(bytes: f64) -> String {
    format!("{:.1} MB", bytes / 1e6)
}

/// Bytes of H (m×n), U (m×p), V (n×p), P (n×m), all f64, p = min(m, n).
fn memory(m: usize, n: usize) -> [f64; 4] {
    let p = m.min(n) as f64;
    let (m, n) = (m as f64, n as f64);
    [8.0 * m * n, 8.0 * m * p, 8.0 * n * p, 8.0 * n * m]
}

/// Seconds for one SVD of `h` (with vectors) by nalgebra and by faer, and the largest
/// relative difference of their singular values.
fn compare_svd(h: &DMatrix<f64>) -> (f64, f64, f64) {
    let (m, n) = h.shape();
    let t0 = Instant::now();
    let a = h.clone().try_svd(true, true, f64::EPSILON, 0);
    let t_nalgebra = t0.elapsed().as_secs_f64();
    let t0 = Instant::now();
    let fm = faer::Mat::<f64>::from_fn(m, n, |i, j| h[(i, j)]);
    let b = fm.thin_svd();
    let t_faer = t0.elapsed().as_secs_f64();
    let diff = match (a, b) {
        (Some(a), Ok(b)) => {
            let sb = b.S().column_vector();
            a.singular_values
                .iter()
                .enumerate()
                .map(|(i, &x)| (x - sb[i]).abs() / a.singular_values[0])
                .fold(0.0, f64::max)
        }
        _ => f64::NAN,
    };
    (t_nalgebra, t_faer, diff)
}

fn print_svd_comparison(label: &str, h: &DMatrix<f64>) {
    let (tn, tf, d) = compare_svd(h);
    println!(
        "svd {label:<7} {:>5}×{:<5}: nalgebra {tn:>8.3} s, faer {tf:>8.3} s (×{:.1}), max |Δσ|/σ_max = {d:.1e}",
        h.nrows(),
        h.ncols(),
        tn / tf
    );
}

/// Per-call apply time in µs: (median, minimum) over batches of calls. On a shared
/// machine the minimum batch is the best estimate of the uncontended cost.
fn time_apply(solver: &mut DenseSolver) -> (f64, f64) {
    let u: Vec<f64> = (0..solver.n_inputs())
        .map(|i| 1e-3 * ((i % 7) as f64 - 3.0))
        .collect();
    let mut f = vec![0.0; solver.n_outputs()];
    let size = solver.n_inputs() * solver.n_outputs();
    let batch = (2e6 / size as f64).clamp(1.0, 1000.0) as usize;
    let batches = (2e9 / (size * batch) as f64).clamp(5.0, 300.0) as usize;
    let mut per_call: Vec<f64> = (0..batches)
        .map(|_| {
            let t0 = Instant::now();
            for _ in 0..batch {
                if let Err(e) = solver.apply(std::hint::black_box(&u), &mut f) {
                    eprintln!("{e}");
                }
            }
            t0.elapsed().as_secs_f64() * 1e6 / batch as f64
        })
        .collect();
    per_call.sort_by(f64::total_cmp);
    (per_call[per_call.len() / 2], per_call[0])
}

/// Best-batch time (µs) of the bare kernel on a 240×520 operator for every
/// instruction set this CPU has: shows what each specialisation buys.
fn compare_isas() {
    let (rows, cols) = (240, 520);
    let a: Vec<f64> = (0..rows * cols)
        .map(|i| ((i * 37 % 101) as f64 - 50.0) * 1e-2)
        .collect();
    let a32: Vec<f32> = a.iter().map(|&v| v as f32).collect();
    let x: Vec<f64> = (0..cols).map(|i| ((i % 13) as f64 - 6.0) * 1e-3).collect();
    let x32: Vec<f32> = x.iter().map(|&v| v as f32).collect();
    let mut y = vec![0.0; rows];
    let best = |f: &mut dyn FnMut()| {
        (0..200)
            .map(|_| {
                let t0 = Instant::now();
                for _ in 0..20 {
                    f();
                }
                t0.elapsed().as_secs_f64() * 1e6 / 20.0
            })
            .fold(f64::INFINITY, f64::min)
    };
    for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable] {
        if !isa.is_supported() {
            continue;
        }
        let t64 =
            best(&mut || kernel::gemv_f64(isa, black_box(&a), rows, cols, black_box(&x), &mut y));
        let t32 = best(&mut || {
            kernel::gemv_f32(isa, black_box(&a32), rows, cols, black_box(&x32), &mut y)
        });
        println!(
            "kernel 240×520 {:<9}: f64 {t64:6.2} µs, f32 {t32:6.2} µs (best batch)",
            isa.name()
        );
    }
}

fn main() {
    compare_isas();
    let compare = std::env::args().any(|a| a == "--compare-svd");
    {
        let s = sensor::paper_sensor();
        let sites = MarkerSite::from_sensor_grids(&s);
        let problem = Problem::new(&s, &sites);
        match model::transfer_matrix(&problem.model, &sites, &s.force_points_mm()) {
            Ok(h) => {
                print_svd_comparison("paper", &h);
                if let Ok(solver) = DenseSolver::from_matrix(h, &SolverConfig::default(), None) {
                    for precision in [Precision::F64, Precision::F32] {
                        let mut s = solver.with_precision(precision);
                        let (med, min) = time_apply(&mut s);
                        println!(
                            "apply paper 240×520 {precision:?} ({}): median {med:.2} µs, best batch {min:.2} µs",
                            s.isa().name()
                        );
                    }
                }
            }
            Err(e) => eprintln!("paper: {e}"),
        }
    }
    let sizes: Vec<usize> = {
        let args: Vec<usize> = std::env::args()
            .skip(1)
            .filter_map(|a| a.parse().ok())
            .collect();
        if args.is_empty() {
            vec![8, 16, 24]
        } else {
            args
        }
    };
    let mut rows = Vec::new();
    println!("n×n grid  | H shape      | build H  | precompute (pinv) | apply f64 | H        | U        | V        | P (f64)");
    for &n in &sizes {
        let s = sensor::grid_sensor(n, n, 1.1, 1.1);
        let sites = MarkerSite::from_sensor_grids(&s);
        let problem = Problem::new(&s, &sites);
        let t0 = Instant::now();
        let h = match model::transfer_matrix(&problem.model, &sites, &s.force_points_mm()) {
            Ok(h) => h,
            Err(e) => {
                eprintln!("n = {n}: {e}");
                continue;
            }
        };
        let build_s = t0.elapsed().as_secs_f64();
        let (m_rows, n_cols) = h.shape();
        if compare {
            print_svd_comparison(&format!("{n}×{n}"), &h);
        }
        let cfg = SolverConfig {
            method: Method::Pinv,
            ..SolverConfig::default()
        };
        let t0 = Instant::now();
        let mut solver = match DenseSolver::from_matrix(h, &cfg, None) {
            Ok(s) => s,
            Err(e) => {
                eprintln!("n = {n}: {e}");
                continue;
            }
        };
        let precompute_s = t0.elapsed().as_secs_f64();
        let (apply_us, _) = time_apply(&mut solver);
        let mem = memory(m_rows, n_cols);
        println!(
            "{n:>2}×{n:<2} meas. | {m_rows:>5}×{n_cols:<5}  | {build_s:>6.3} s | {precompute_s:>13.3} s   | {apply_us:>7.1} µs | {} | {} | {} | {}",
            mb(mem[0]),
            mb(mem[1]),
            mb(mem[2]),
            mb(mem[3])
        );
        rows.push(Row {
            n,
            n_cols,
            build_s,
            precompute_s,
            apply_us,
        });
    }
    if rows.len() < 2 {
        println!("(need two sizes to extrapolate)");
        return;
    }
    // Power law t = a·N^b by least squares in log-log over the measured sizes with
    // n ≥ 16 (smaller ones are dominated by fixed costs), N = force unknowns.
    let fitted: Vec<&Row> = rows.iter().filter(|r| r.n >= 16).collect();
    let fitted = if fitted.len() >= 2 {
        fitted
    } else {
        rows.iter().collect()
    };
    let fit = |y: &dyn Fn(&Row) -> f64| {
        let pts: Vec<(f64, f64)> = fitted
            .iter()
            .map(|r| ((r.n_cols as f64).ln(), y(r).max(1e-12).ln()))
            .collect();
        let k = pts.len() as f64;
        let (sx, sy) = pts.iter().fold((0.0, 0.0), |(a, b), p| (a + p.0, b + p.1));
        let (mx, my) = (sx / k, sy / k);
        let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
        let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
        let e = sxy / sxx;
        (e, move |n_cols: f64| (my + e * (n_cols.ln() - mx)).exp())
    };
    let sizes_used: Vec<String> = fitted.iter().map(|r| r.n.to_string()).collect();
    let target = 64;
    let s = sensor::grid_sensor(target, target, 1.1, 1.1);
    let m_rows = 2 * MarkerSite::from_sensor_grids(&s).len();
    let n_cols = 3 * s.force_grid.len();
    let (eb, build) = fit(&|r: &Row| r.build_s);
    let (ep, pre) = fit(&|r: &Row| r.precompute_s);
    let (ea, app) = fit(&|r: &Row| r.apply_us);
    let mem = memory(m_rows, n_cols);
    println!(
        "{target}×{target} EXTRAPOLATED (not measured; t ∝ N^b fitted over n = {}: build b = {eb:.2}, precompute b = {ep:.2}, apply b = {ea:.2})",
        sizes_used.join(", ")
    );
    println!(
        "{target}×{target} extrap. | {m_rows:>5}×{n_cols:<5}  | {:>6.1} s | {:>13.0} s   | {:>7.0} µs | {} | {} | {} | {}",
        build(n_cols as f64),
        pre(n_cols as f64),
        app(n_cols as f64),
        mb(mem[0]),
        mb(mem[1]),
        mb(mem[2]),
        mb(mem[3])
    );
}
