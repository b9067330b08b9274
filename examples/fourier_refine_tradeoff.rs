//! Accuracy of the refined `fourier` solve against refinement iterations and stopping
//! tolerance (the trade-off table of README *Performance*): on `grid_sensor(n,n,1.1,1.1)`
//! and the five acceptance loads of issue 12 (centred fx / fz / mixed, off-centre fy /
//! mixed), the worst force-sum error (fraction of the applied total), field error and
//! interior field error (≥ 4 mm from the edges) against the refinement run to
//! convergence (tolerance 0, 200 iterations: dense Tikhonov to rounding), and the
//! iterations run. λ = FACTOR × the periodic operator's σ_max.
//!
//! `cargo run --release --example fourier_refine_tradeoff -- N FACTOR`
//! (issue 12's λ = 1e-2·σ₁ of the dense H: `16 2.06e-3`; `32 2e-3`; `64 2e-3`).
//! The times it prints are one loop over five frames; criterion's are in
//! `cargo bench --bench fourier`.
use tactbench::model::{self, MarkerSite};
use tactbench::sensor::{grid_sensor, Sensor};
use tactbench::solve::fourier::FourierSolver;
use tactbench::solve::{FrameSolver, Lambda, Method, Problem, SolverConfig};

fn blob(sensor: &Sensor, c: [f64; 2], w: f64, amp: [f64; 3]) -> Vec<f64> {
    sensor
        .force_points_mm()
        .iter()
        .flat_map(|p| {
            let g = (-((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)) / (2.0 * w * w)).exp();
            [amp[0] * g, amp[1] * g, amp[2] * g]
        })
        .collect()
}
fn sums(f: &[f64]) -> [f64; 3] {
    let mut s = [0.0; 3];
    for (i, v) in f.iter().enumerate() {
        s[i % 3] += v;
    }
    s
}
fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}
fn rel(a: &[f64], b: &[f64]) -> f64 {
    let d: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
    norm(&d) / norm(b)
}
fn interior(s: &Sensor, f: &[f64]) -> Vec<f64> {
    let g = s.force_grid;
    let m = (4.0 / g.pitch_mm).ceil() as usize;
    let mut o = Vec::new();
    for iy in m..g.ny - m {
        for ix in m..g.nx - m {
            let k = iy * g.nx + ix;
            o.extend_from_slice(&f[3 * k..3 * k + 3]);
        }
    }
    o
}
fn main() {
    let n: usize = std::env::args()
        .nth(1)
        .map(|a| a.parse().unwrap())
        .unwrap_or(16);
    let s = grid_sensor(n, n, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    let padding: f64 = std::env::args()
        .nth(3)
        .map(|a| a.parse().unwrap())
        .unwrap_or(SolverConfig::default().fourier_padding);
    let cfg = |l: f64| SolverConfig {
        method: Method::Fourier,
        lambda: Lambda::Fixed(l),
        fourier_padding: padding,
        ..SolverConfig::default()
    };
    let probe = FourierSolver::precompute(&p, &cfg(1.0), None).unwrap();
    let lfac: f64 = std::env::args()
        .nth(2)
        .map(|a| a.parse().unwrap())
        .unwrap_or(if n == 16 { 8.3e-3 } else { 2e-3 });
    let lambda = lfac * probe.diagnostics().singular_values[0];
    let t0 = std::time::Instant::now();
    let mut solver = FourierSolver::precompute(&p, &cfg(lambda), None).unwrap();
    println!(
        "{n}x{n} λ = {lambda:e}; precompute {:?}; coarse space (k, spacing) {:?}",
        t0.elapsed(),
        solver.coarse_space()
    );
    let g = s.force_grid;
    let c = 0.5 * g.pitch_mm * (g.nx - 1) as f64;
    let loads = vec![
        ("centred fx", blob(&s, [c, c], 2.0, [0.1, 0.0, 0.0])),
        ("centred fz", blob(&s, [c, c], 2.0, [0.0, 0.0, 0.1])),
        ("centred mixed", blob(&s, [c, c], 2.0, [0.02, -0.01, 0.1])),
        ("off fy", blob(&s, [c - 3.0, c + 2.0], 2.0, [0.0, 0.1, 0.0])),
        (
            "off mixed",
            blob(&s, [c + 4.0, c + 3.0], 2.0, [0.02, -0.01, 0.1]),
        ),
    ];
    let mut f = vec![0.0; p.n_outputs()];
    let mut refs = Vec::new();
    for (_, ft) in &loads {
        let u = model::forward(&p.model, &sites, &s.force_points_mm(), ft).unwrap();
        solver.refine_tolerance = 0.0;
        solver.refine_iterations = 200;
        let mut r = vec![0.0; p.n_outputs()];
        solver.apply(&u, &mut r).unwrap();
        refs.push((u, r));
    }
    // (two-level correction, refinement cap, tolerance); the first row is the direct
    // periodic solve alone.
    let mut settings: Vec<(bool, usize, f64)> = vec![(false, 0, 0.0)];
    settings.extend([0usize, 1, 2, 3, 5, 10, 20].iter().map(|&k| (true, k, 0.0)));
    settings.extend(
        [1e-1, 5e-2, 2e-2, 1e-2, 1e-3]
            .iter()
            .map(|&t| (true, 300usize, t)),
    );
    for (two_level, k, tol) in settings {
        solver.coarse_correction = two_level;
        solver.refine_iterations = k;
        solver.refine_tolerance = tol;
        let (mut es, mut ea, mut ei, mut its) = (0.0f64, 0.0f64, 0.0f64, 0usize);
        let t = std::time::Instant::now();
        for ((_, ft), (u, r)) in loads.iter().zip(&refs) {
            solver.apply(u, &mut f).unwrap();
            its = its.max(solver.last_refine_iterations());
            let (st, sr, sf) = (sums(ft), sums(r), sums(&f));
            if std::env::var("DBG").is_ok() {
                println!("{st:?} {sr:?} {sf:?}");
            }
            let tot = st.iter().map(|v| v.abs()).fold(0.0, f64::max);
            for ax in 0..3 {
                es = es.max((sf[ax] - sr[ax]).abs() / tot);
            }
            ea = ea.max(rel(&f, r));
            ei = ei.max(rel(&interior(&s, &f), &interior(&s, r)));
        }
        let mode = if two_level { "two-level" } else { "direct   " };
        println!("{mode} cap {k:3} tol {tol:7.0e}: its {its:3}  Fsum {:.2e}  field {:.2e}  interior {:.2e}  t/frame {:.2?}", es, ea, ei, t.elapsed() / loads.len() as u32);
    }
}
