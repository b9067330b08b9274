//! Displacement accuracy (paper Table I): the tracked displacements of every marker
//! against the commanded whole-sensor shift, per layer and axis.
//!
//! For each layer and axis (x, y), over every tracked (not lost) marker of every frame
//! of every setpoint: **mean** and sample **SD** of the displacement, and the **bias**
//! `mean − commanded`. Values are given in mm and in camera pixels
//! (`px = mm / mm_per_px`); the paper's table is in pixels (3 px shift: means 2.98 /
//! 3.00 px, SD 0.06–0.10 px ≈ 50 µm). When setpoints command different shifts the
//! statistics are of the error `u − shift` shifted back by the mean commanded shift,
//! so the mean is still comparable to the command.

use crate::formats::DisplacementFrame;

use super::stats;

/// One setpoint's tracked displacements and its commanded shift.
#[derive(Debug, Clone, PartialEq)]
pub struct ShiftMeasurement {
    /// Setpoint index.
    pub index: usize,
    /// Commanded shift, mm.
    pub shift_mm: [f64; 2],
    /// The tracked frames of this setpoint.
    pub frames: Vec<DisplacementFrame>,
}

/// Statistics of one layer along one axis.
#[derive(Debug, Clone, PartialEq)]
pub struct AxisStats {
    /// Layer name.
    pub layer: String,
    /// `"x"` or `"y"`.
    pub axis: &'static str,
    /// Mean commanded shift along the axis, mm.
    pub commanded_mm: f64,
    /// Mean measured displacement, mm.
    pub mean_mm: f64,
    /// Sample SD, mm.
    pub sd_mm: f64,
    /// Mean measured displacement, px.
    pub mean_px: f64,
    /// Sample SD, px.
    pub sd_px: f64,
    /// `mean − commanded`, px.
    pub bias_px: f64,
    /// Marker samples used.
    pub n: usize,
}

/// The displacement-accuracy analysis: one entry per layer and axis, layers in sensor
/// order, x before y.
#[derive(Debug, Clone, PartialEq)]
pub struct DisplacementAnalysis {
    /// Per layer and axis.
    pub axes: Vec<AxisStats>,
    /// Lost markers (summed over frames) per layer.
    pub lost: Vec<(String, usize)>,
}

/// Why the analysis could not be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("displacement accuracy: {0}")]
pub struct DisplacementError(pub String);

/// Analyses the shift measurements; `layer_names` in sensor order, `mm_per_px` the
/// camera scale.
pub fn analyze(
    measurements: &[ShiftMeasurement],
    layer_names: &[String],
    mm_per_px: f64,
) -> Result<DisplacementAnalysis, DisplacementError> {
    if mm_per_px.is_nan() || mm_per_px <= 0.0 {
        return Err(DisplacementError(format!(
            "camera scale {mm_per_px} mm/px must be > 0"
        )));
    }
    let mut axes = Vec::new();
    let mut lost = Vec::new();
    for (li, name) in layer_names.iter().enumerate() {
        let mut err = [Vec::new(), Vec::new()];
        let mut cmd = [Vec::new(), Vec::new()];
        let mut n_lost = 0;
        for m in measurements {
            for f in &m.frames {
                for r in f.records.iter().filter(|r| r.layer == li) {
                    match r.u_mm {
                        Some(u) => {
                            for a in 0..2 {
                                err[a].push(u[a] - m.shift_mm[a]);
                                cmd[a].push(m.shift_mm[a]);
                            }
                        }
                        None => n_lost += 1,
                    }
                }
            }
        }
        if err[0].is_empty() {
            return Err(DisplacementError(format!(
                "layer `{name}` has no tracked marker in any displacement file"
            )));
        }
        for (a, axis) in ["x", "y"].into_iter().enumerate() {
            let c = stats::mean(&cmd[a]).unwrap_or(0.0);
            let bias = stats::mean(&err[a]).unwrap_or(f64::NAN);
            let sd = stats::sample_sd(&err[a]).unwrap_or(0.0);
            axes.push(AxisStats {
                layer: name.clone(),
                axis,
                commanded_mm: c,
                mean_mm: c + bias,
                sd_mm: sd,
                mean_px: (c + bias) / mm_per_px,
                sd_px: sd / mm_per_px,
                bias_px: bias / mm_per_px,
                n: err[a].len(),
            });
        }
        lost.push((name.clone(), n_lost));
    }
    Ok(DisplacementAnalysis { axes, lost })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::DisplacementRecord;

    #[test]
    fn table_one_statistics_from_known_marker_motions() {
        // 0.05 mm/px, 3 px shift along x = 0.15 mm. Layer 0: ux = 0.15 ± 0.003 mm
        // alternating (SD 0.06 px·sqrt(n/(n−1))), uy = ±0.002. Layer 1: ux biased by
        // +0.001 mm exactly (0.02 px), uy = 0; one lost marker.
        let mm_per_px = 0.05;
        let n = 40;
        let mut records = Vec::new();
        for k in 0..n {
            let s = if k % 2 == 0 { 1.0 } else { -1.0 };
            records.push(DisplacementRecord {
                layer: 0,
                marker: k as u64,
                position_mm: [k as f64, 0.0],
                u_mm: Some([0.15 + s * 0.003, s * 0.002]),
                line: k as u64 + 2,
            });
            records.push(DisplacementRecord {
                layer: 1,
                marker: k as u64,
                position_mm: [k as f64, 1.0],
                u_mm: if k == 0 { None } else { Some([0.151, 0.0]) },
                line: k as u64 + 100,
            });
        }
        let m = ShiftMeasurement {
            index: 0,
            shift_mm: [0.15, 0.0],
            frames: vec![DisplacementFrame {
                frame: "f".into(),
                records,
            }],
        };
        let names = vec!["blue".to_string(), "red".to_string()];
        let a = analyze(&[m], &names, mm_per_px).unwrap();
        assert_eq!(a.axes.len(), 4);
        let bx = &a.axes[0];
        assert_eq!((bx.layer.as_str(), bx.axis, bx.n), ("blue", "x", 40));
        assert!((bx.mean_px - 3.0).abs() < 1e-9, "{}", bx.mean_px);
        let corr = (n as f64 / (n as f64 - 1.0)).sqrt();
        assert!((bx.sd_px - 0.06 * corr).abs() < 1e-9, "{}", bx.sd_px);
        let by = &a.axes[1];
        assert!(by.mean_px.abs() < 1e-9 && (by.sd_px - 0.04 * corr).abs() < 1e-9);
        let rx = &a.axes[2];
        assert!((rx.bias_px - 0.02).abs() < 1e-9 && rx.sd_px < 1e-9 && rx.n == 39);
        assert_eq!(a.lost, vec![("blue".into(), 0), ("red".into(), 1)]);
    }
}
