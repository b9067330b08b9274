//! Small statistics shared by the analyses: mean, sample standard deviation, ordinary
//! least-squares line fit with R², pooled within-group SD.
//!
//! Least squares (measured `y` against applied `x`, n points):
//! `slope = Σ(x−x̄)(y−ȳ) / Σ(x−x̄)²`, `offset = ȳ − slope·x̄`,
//! `R² = 1 − Σ(y − ŷ)² / Σ(y − ȳ)²`. The sample SD uses n − 1 (Bessel).
//! Pooled SD of groups i with n_i samples and sample SDs s_i:
//! `s_p = sqrt(Σ(n_i − 1)s_i² / Σ(n_i − 1))`.

/// Arithmetic mean; `None` for an empty slice.
pub fn mean(v: &[f64]) -> Option<f64> {
    if v.is_empty() {
        None
    } else {
        Some(v.iter().sum::<f64>() / v.len() as f64)
    }
}

/// Sample standard deviation (n − 1); `None` for fewer than two values.
pub fn sample_sd(v: &[f64]) -> Option<f64> {
    if v.len() < 2 {
        return None;
    }
    let m = mean(v)?;
    let ss: f64 = v.iter().map(|x| (x - m).powi(2)).sum();
    Some((ss / (v.len() - 1) as f64).sqrt())
}

/// A least-squares line `y = slope·x + offset`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LineFit {
    /// dy/dx.
    pub slope: f64,
    /// y at x = 0.
    pub offset: f64,
    /// Coefficient of determination (1 when every point lies on the line; 1 also when
    /// all y are equal and the line fits them exactly).
    pub r2: f64,
    /// SD of the residuals about the line with n − 2 degrees of freedom (0 for n = 2).
    pub residual_sd: f64,
}

impl LineFit {
    /// The line's value at `x`.
    pub fn at(&self, x: f64) -> f64 {
        self.slope * x + self.offset
    }
}

/// Fits `y = slope·x + offset` by ordinary least squares. `None` when there are fewer
/// than two points or all `x` are equal (the slope is undetermined).
pub fn fit_line(x: &[f64], y: &[f64]) -> Option<LineFit> {
    let n = x.len().min(y.len());
    if n < 2 {
        return None;
    }
    let (x, y) = (&x[..n], &y[..n]);
    let mx = mean(x)?;
    let my = mean(y)?;
    let sxx: f64 = x.iter().map(|a| (a - mx).powi(2)).sum();
    let sxy: f64 = x.iter().zip(y).map(|(a, b)| (a - mx) * (b - my)).sum();
    let scale = x.iter().fold(0.0f64, |m, a| m.max(a.abs())).max(1e-300);
    if sxx <= (1e-12 * scale).powi(2) * n as f64 {
        return None;
    }
    let slope = sxy / sxx;
    let offset = my - slope * mx;
    let ss_res: f64 = x
        .iter()
        .zip(y)
        .map(|(a, b)| (b - (slope * a + offset)).powi(2))
        .sum();
    let ss_tot: f64 = y.iter().map(|b| (b - my).powi(2)).sum();
    let r2 = if ss_tot > 0.0 {
        1.0 - ss_res / ss_tot
    } else {
        1.0
    };
    let residual_sd = if n > 2 {
        (ss_res / (n - 2) as f64).sqrt()
    } else {
        0.0
    };
    Some(LineFit {
        slope,
        offset,
        r2,
        residual_sd,
    })
}

/// Pooled within-group SD from `(n_i, s_i)` pairs; groups with n_i < 2 carry no
/// information and are skipped. `None` when no group has two samples.
pub fn pooled_sd(groups: impl IntoIterator<Item = (usize, f64)>) -> Option<f64> {
    let (mut num, mut dof) = (0.0, 0usize);
    for (n, s) in groups {
        if n >= 2 {
            num += (n - 1) as f64 * s * s;
            dof += n - 1;
        }
    }
    (dof > 0).then(|| (num / dof as f64).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sample_sd_matches_the_textbook_example() {
        // 2,4,4,4,5,5,7,9: population SD 2, sample SD sqrt(32/7).
        let v = [2.0, 4.0, 4.0, 4.0, 5.0, 5.0, 7.0, 9.0];
        assert_eq!(mean(&v), Some(5.0));
        assert!((sample_sd(&v).unwrap() - (32.0f64 / 7.0).sqrt()).abs() < 1e-12);
        assert_eq!(sample_sd(&[1.0]), None);
    }

    #[test]
    fn fit_recovers_an_exact_line_and_rejects_a_vertical_one() {
        let x = [0.0, 1.0, 2.0, 3.0];
        let y: Vec<f64> = x.iter().map(|a| 0.5 * a - 2.0).collect();
        let f = fit_line(&x, &y).unwrap();
        assert!((f.slope - 0.5).abs() < 1e-12 && (f.offset + 2.0).abs() < 1e-12);
        assert!((f.r2 - 1.0).abs() < 1e-12 && f.residual_sd < 1e-12);
        assert!(fit_line(&[1.0, 1.0], &[0.0, 2.0]).is_none());
    }

    #[test]
    fn fit_of_symmetric_scatter_has_the_closed_form_r2() {
        // Points (0,0),(0,2),(2,2),(2,4): slope 1, offset 1, residuals ±1,
        // SSres = 4, SStot = 8 -> R² = 0.5, residual SD = sqrt(4/2).
        let f = fit_line(&[0.0, 0.0, 2.0, 2.0], &[0.0, 2.0, 2.0, 4.0]).unwrap();
        assert!((f.slope - 1.0).abs() < 1e-12 && (f.offset - 1.0).abs() < 1e-12);
        assert!((f.r2 - 0.5).abs() < 1e-12);
        assert!((f.residual_sd - 2f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn pooled_sd_weights_groups_by_degrees_of_freedom() {
        // (3, 1) and (5, 2): sqrt((2·1 + 4·4) / 6) = sqrt(3).
        let p = pooled_sd([(3, 1.0), (5, 2.0), (1, 100.0)]).unwrap();
        assert!((p - 3f64.sqrt()).abs() < 1e-12);
        assert_eq!(pooled_sd([(1, 1.0)]), None);
    }
}
