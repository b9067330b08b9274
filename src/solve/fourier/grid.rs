//! Grid geometry of the `fourier` solver: commensurate pitches (the common fine lattice)
//! and FFT-friendly sizes.

use super::SolveError;

/// Largest accepted `lcm(a, b)` of the pitch ratio `p_f : p_m = a : b`. Block sizes grow
/// like `a²` and `b²`; beyond 8 the blocks stop being "small" and a dense solver is the
/// better tool anyway.
pub const MAX_LCM: usize = 8;

/// Markers further than this fraction of the pitch from their grid node are refused.
pub const OFF_GRID_TOLERANCE: f64 = 1e-3;

/// Relative tolerance on `p_f·b = p_m·a`.
pub(super) const RATIO_TOLERANCE: f64 = 1e-9;

fn gcd(a: usize, b: usize) -> usize {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

/// All accepted `(a, b)`: coprime, `a·b ≤ MAX_LCM`.
fn ratio_candidates() -> impl Iterator<Item = (usize, usize)> {
    (1..=MAX_LCM)
        .flat_map(|a| (1..=MAX_LCM).map(move |b| (a, b)))
        .filter(|&(a, b)| gcd(a, b) == 1 && a * b <= MAX_LCM)
}

/// `(a, b)` with `p_f/p_m = a/b` and the smallest `a·b`, or an error saying what would work.
pub(super) fn commensurate(
    force_pitch_mm: f64,
    marker_pitch_mm: f64,
) -> Result<(usize, usize), SolveError> {
    let mut best: Option<(usize, usize)> = None;
    for (a, b) in ratio_candidates() {
        let lhs = force_pitch_mm * b as f64;
        let rhs = marker_pitch_mm * a as f64;
        if (lhs - rhs).abs() <= RATIO_TOLERANCE * lhs.abs()
            && best.is_none_or(|(x, y)| a * b < x * y)
        {
            best = Some((a, b));
        }
    }
    if let Some(ab) = best {
        return Ok(ab);
    }
    // Suggest the nearest commensurate marker pitches and force pitches.
    let nearest = |target: f64, make: &dyn Fn(usize, usize) -> f64| -> Vec<f64> {
        let mut c: Vec<f64> = ratio_candidates().map(|(a, b)| make(a, b)).collect();
        c.sort_by(|x, y| (x - target).abs().total_cmp(&(y - target).abs()));
        c.dedup_by(|x, y| (*x - *y).abs() < 1e-9);
        c.truncate(2);
        c
    };
    let fmt = |v: Vec<f64>| {
        v.iter()
            .map(|x| format!("{x:.4} mm"))
            .collect::<Vec<_>>()
            .join(" or ")
    };
    let markers = nearest(marker_pitch_mm, &|a, b| {
        force_pitch_mm * b as f64 / a as f64
    });
    let forces = nearest(force_pitch_mm, &|a, b| {
        marker_pitch_mm * a as f64 / b as f64
    });
    let simple = [force_pitch_mm / 2.0, force_pitch_mm]
        .iter()
        .map(|x| format!("{x:.4} mm"))
        .collect::<Vec<_>>()
        .join(" or ");
    Err(SolveError::Incompatible(format!(
        "force pitch {force_pitch_mm} mm and marker pitch {marker_pitch_mm} mm have ratio {:.6}, \
         which is not a ratio a:b of small integers (a·b ≤ {MAX_LCM}), so the grids share no \
         common fine lattice; markers every {simple} (or {}) would work, as would force points \
         every {}; otherwise use a dense solver (pinv, tikhonov, tsvd)",
        force_pitch_mm / marker_pitch_mm,
        fmt(markers),
        fmt(forces)
    )))
}

/// Smallest 2-3-5-7-smooth integer ≥ n (fast FFT sizes).
pub(super) fn smooth_at_least(n: usize) -> usize {
    let mut k = n.max(1);
    loop {
        let mut r = k;
        for p in [2, 3, 5, 7] {
            while r.is_multiple_of(p) {
                r /= p;
            }
        }
        if r == 1 {
            return k;
        }
        k += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn commensurate_pitches_give_the_smallest_factors() {
        assert_eq!(commensurate(1.1, 1.1).unwrap(), (1, 1));
        assert_eq!(commensurate(2.2, 1.1).unwrap(), (2, 1));
        assert_eq!(commensurate(1.0, 1.5).unwrap(), (2, 3));
        assert_eq!(commensurate(0.5, 2.0).unwrap(), (1, 4));
    }

    #[test]
    fn paper_pitches_are_refused_with_suggestions() {
        let e = commensurate(2.2, 1.5).unwrap_err().to_string();
        assert!(e.contains("2.2 mm") && e.contains("1.5 mm"), "{e}");
        assert!(e.contains("1.1000 mm") && e.contains("2.2000 mm"), "{e}");
        assert!(e.contains("dense solver"), "{e}");
    }

    #[test]
    fn smooth_sizes_are_smooth_and_minimal() {
        assert_eq!(smooth_at_least(97), 98);
        assert_eq!(smooth_at_least(190), 192);
        assert_eq!(smooth_at_least(11), 12);
        assert_eq!(smooth_at_least(1), 1);
    }
}
