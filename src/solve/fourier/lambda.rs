//! Automatic λ for the `fourier` solver: GCV and the L-curve evaluated in the Fourier
//! domain from the per-block singular values.

use super::super::Lambda;

/// Points of the log-spaced λ scan used by GCV and the L-curve.
const LAMBDA_SCAN: usize = 161;

/// Chooses λ by GCV or the L-curve from per-singular-value data of the periodic operator:
/// `sig` singular values, `beta2` squared projections of the frame on the left singular
/// vectors, `weights` multiplicities (Hermitian partners), `rest` the frame energy outside
/// the range, `m` the number of (periodic) measurements.
pub(super) fn choose_lambda(
    choice: Lambda,
    sig: &[f64],
    beta2: &[f64],
    weights: &[f64],
    rest: f64,
    m: f64,
    sigma_max: f64,
) -> (f64, String) {
    let terms = |lam: f64| -> (f64, f64, f64) {
        // (residual², solution², trace of the influence matrix)
        let l2 = lam * lam;
        let mut res = rest;
        let mut sol = 0.0;
        let mut tr = 0.0;
        for ((&s, &b2), &w) in sig.iter().zip(beta2).zip(weights) {
            let d = s * s + l2;
            if d <= 0.0 {
                continue;
            }
            let fres = l2 / d;
            res += w * fres * fres * b2;
            sol += w * s * s * b2 / (d * d);
            tr += w * s * s / d;
        }
        (res, sol, tr)
    };
    let lo = (sigma_max * 1e-9).ln();
    let hi = sigma_max.ln();
    let grid: Vec<f64> = (0..LAMBDA_SCAN)
        .map(|i| (lo + (hi - lo) * i as f64 / (LAMBDA_SCAN - 1) as f64).exp())
        .collect();
    match choice {
        Lambda::LCurve => {
            let pts: Vec<(f64, f64)> = grid
                .iter()
                .map(|&l| {
                    let (res, sol, _) = terms(l);
                    (0.5 * res.max(1e-300).ln(), 0.5 * sol.max(1e-300).ln())
                })
                .collect();
            let dt = (hi - lo) / (LAMBDA_SCAN - 1) as f64;
            let mut best = (f64::NEG_INFINITY, grid[LAMBDA_SCAN / 2]);
            for i in 1..LAMBDA_SCAN - 1 {
                let (x0, y0) = pts[i - 1];
                let (x1, y1) = pts[i];
                let (x2, y2) = pts[i + 1];
                let (dx, dy) = ((x2 - x0) / (2.0 * dt), (y2 - y0) / (2.0 * dt));
                let (ddx, ddy) = (
                    (x2 - 2.0 * x1 + x0) / (dt * dt),
                    (y2 - 2.0 * y1 + y0) / (dt * dt),
                );
                let den = (dx * dx + dy * dy).powf(1.5);
                if den > 0.0 {
                    let k = (dx * ddy - dy * ddx) / den;
                    if k.is_finite() && k > best.0 {
                        best = (k, grid[i]);
                    }
                }
            }
            let note = format!(
                "λ = {:e} mm/N at the L-curve corner (curvature {:.3}) of the periodic problem",
                best.1, best.0
            );
            // The corner is looked for between the scan's ends (curvature needs both
            // neighbours): its first or last interior point is the range's edge.
            let at_edge = best.1 <= grid[1] || best.1 >= grid[LAMBDA_SCAN - 2];
            if at_edge {
                (
                    best.1,
                    format!(
                        "{}{note}, on the {} boundary of the scanned range [{:.3e}, {:.3e}] mm/N: \
                         not a corner inside it; set λ by hand (--lambda) if the forces look wrong",
                        super::super::WARNING_PREFIX,
                        if best.1 <= grid[1] { "lower" } else { "upper" },
                        grid[0],
                        grid[LAMBDA_SCAN - 1]
                    ),
                )
            } else {
                (best.1, note)
            }
        }
        _ => {
            let gcv = |l: f64| {
                let (res, _, tr) = terms(l);
                let den = (m - tr).max(1e-12 * m);
                res / (den * den)
            };
            let vals: Vec<f64> = grid.iter().map(|&l| gcv(l)).collect();
            let mut ib = 0;
            for (i, v) in vals.iter().enumerate() {
                if *v < vals[ib] {
                    ib = i;
                }
            }
            // Golden-section refinement in ln λ between the scan neighbours.
            let (mut x0, mut x1) = (
                grid[ib.saturating_sub(1)].ln(),
                grid[(ib + 1).min(LAMBDA_SCAN - 1)].ln(),
            );
            let g = 0.5 * (5f64.sqrt() - 1.0);
            for _ in 0..40 {
                let c = x1 - g * (x1 - x0);
                let d = x0 + g * (x1 - x0);
                if gcv(c.exp()) < gcv(d.exp()) {
                    x1 = d;
                } else {
                    x0 = c;
                }
            }
            let l = (0.5 * (x0 + x1)).exp();
            let note = format!("λ = {l:e} mm/N by GCV on the given frame, periodic problem");
            let step = (hi - lo) / (LAMBDA_SCAN - 1) as f64;
            if ib == 0 || ib == LAMBDA_SCAN - 1 || l.ln() - lo < step || hi - l.ln() < step {
                // The search ended on its boundary: the choice is not a GCV minimum.
                (
                    l,
                    format!(
                        "{}{note}, on the boundary of the scanned range [{:.3e}, {:.3e}] mm/N: \
                         not a GCV minimum; set λ by hand (--lambda) if the forces look wrong",
                        super::super::WARNING_PREFIX,
                        grid[0],
                        grid[LAMBDA_SCAN - 1]
                    ),
                )
            } else {
                (l, note)
            }
        }
    }
}
