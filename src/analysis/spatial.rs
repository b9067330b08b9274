//! Spatial resolution (paper Fig. 9) by the paper's subdivided point-load method.
//!
//! A point load of fixed normal force is applied at `n + 1` positions `p_i` stepping
//! from one force-grid node to its neighbour (plan sweep `spatial`, interval
//! `pitch / n`). For each load, every force node `q` on the grid line nearest to the
//! load line (perpendicular distance within a tolerance, a quarter pitch in
//! [`crate::analysis::RunAnalysis`], of the nearest node's) contributes one profile
//! sample. When the load line runs between grid lines, the nodes of the nearest ones
//! are used and [`SpatialAnalysis::line_offset_mm`] says how far off they are (the
//! paper loads along a grid line: offset 0). Each sample has abscissa
//! `d = (q − p_i)·ê` (signed distance from the load, ê the segment direction) and
//! ordinate its reconstructed `f_z`. Taking each load as the
//! origin interleaves the samples, so the profile is sampled `n` times more densely
//! than the grid. Samples at the same `d` (within 1 µm) are averaged. The profile is
//! normalised by its maximum, as in Fig. 9.
//!
//! **Spatial resolution** = the profile's full width at half maximum (the paper's "half
//! value of width", about 4 mm): from the maximum, walk outwards on each side to the
//! first sample below half the maximum and interpolate linearly between it and its
//! inner neighbour; the width is the distance between the two crossings.

use thiserror::Error;

use crate::formats::ForceRecord;

/// One load of the sweep: where it was applied and what was reconstructed.
#[derive(Debug, Clone, PartialEq)]
pub struct PointLoad {
    /// Setpoint index (for messages).
    pub index: usize,
    /// Load position, sensor frame, mm.
    pub position_mm: [f64; 2],
    /// The reconstructed forces of that setpoint.
    pub forces: Vec<ForceRecord>,
}

/// One point of the merged profile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProfilePoint {
    /// Signed distance from the load along the segment, mm.
    pub distance_mm: f64,
    /// Mean reconstructed f_z there, N.
    pub fz_n: f64,
    /// `fz_n` divided by the profile maximum.
    pub normalized: f64,
    /// Samples averaged into this point.
    pub n: usize,
}

/// The spatial-resolution analysis.
#[derive(Debug, Clone, PartialEq)]
pub struct SpatialAnalysis {
    /// The profile in ascending distance.
    pub profile: Vec<ProfilePoint>,
    /// Full width at half maximum, mm (the spatial resolution).
    pub fwhm_mm: f64,
    /// Left half-maximum crossing, mm.
    pub half_left_mm: f64,
    /// Right half-maximum crossing, mm.
    pub half_right_mm: f64,
    /// Distance of the profile maximum from the load, mm.
    pub peak_distance_mm: f64,
    /// The profile maximum, N.
    pub peak_fz_n: f64,
    /// Perpendicular distance of the used grid nodes from the load line, mm (0 when
    /// the loads run along a grid line, as in the paper).
    pub line_offset_mm: f64,
}

/// Why the profile could not be evaluated.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum SpatialError {
    /// Fewer than two loads, a degenerate segment, or no nodes on the line.
    #[error("spatial resolution: {0}")]
    Insufficient(String),
    /// The profile has no positive maximum or does not fall to half of it.
    #[error("spatial resolution: {0}")]
    Profile(String),
}

/// Builds the profile from `loads` applied along direction `direction` (need not be
/// unit length) and measures its FWHM. Nodes farther than `line_tolerance_mm` beyond
/// the nearest node's distance from the load line are ignored.
pub fn analyze(
    loads: &[PointLoad],
    direction: [f64; 2],
    line_tolerance_mm: f64,
) -> Result<SpatialAnalysis, SpatialError> {
    let len = direction[0].hypot(direction[1]);
    if !len.is_finite() || len <= 0.0 {
        return Err(SpatialError::Insufficient(format!(
            "load segment direction ({}, {}) mm has no length",
            direction[0], direction[1]
        )));
    }
    if loads.is_empty() {
        return Err(SpatialError::Insufficient("no loads in the run".into()));
    }
    let e = [direction[0] / len, direction[1] / len];
    // (along, across) of a node relative to a load.
    let coords = |load: &PointLoad, r: &ForceRecord| {
        let d = [
            r.position_mm[0] - load.position_mm[0],
            r.position_mm[1] - load.position_mm[1],
        ];
        (d[0] * e[0] + d[1] * e[1], (d[0] * e[1] - d[1] * e[0]).abs())
    };
    // Every load lies on the same line, so the nearest grid line is the same for all.
    let line_offset_mm = loads
        .iter()
        .flat_map(|l| l.forces.iter().map(move |r| coords(l, r).1))
        .fold(f64::INFINITY, f64::min);
    let mut samples: Vec<(f64, f64)> = Vec::new();
    for load in loads {
        for r in &load.forces {
            let (along, across) = coords(load, r);
            if across <= line_offset_mm + line_tolerance_mm && r.f_n[2].is_finite() {
                samples.push((along, r.f_n[2]));
            }
        }
    }
    if samples.len() < 3 {
        return Err(SpatialError::Insufficient(format!(
            "only {} force node sample(s) lie within {line_tolerance_mm} mm of the grid line \
             nearest the load line",
            samples.len()
        )));
    }
    samples.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut merged: Vec<(f64, f64, usize)> = Vec::new();
    for (d, f) in samples {
        match merged.last_mut() {
            Some(last) if (d - last.0 / last.2 as f64).abs() < 1e-3 => {
                last.0 += d;
                last.1 += f;
                last.2 += 1;
            }
            _ => merged.push((d, f, 1)),
        }
    }
    let pts: Vec<(f64, f64, usize)> = merged
        .into_iter()
        .map(|(d, f, n)| (d / n as f64, f / n as f64, n))
        .collect();
    let (imax, &(dpk, fpk, _)) = pts
        .iter()
        .enumerate()
        .max_by(|a, b| a.1 .1.total_cmp(&b.1 .1))
        .ok_or_else(|| SpatialError::Insufficient("empty profile".into()))?;
    if fpk.is_nan() || fpk <= 0.0 {
        return Err(SpatialError::Profile(format!(
            "profile maximum f_z = {fpk} N is not positive: no load was reconstructed"
        )));
    }
    let half = fpk / 2.0;
    let crossing = |range: &mut dyn Iterator<Item = usize>, side: &str| {
        let mut inner = imax;
        for i in range {
            if pts[i].1 < half {
                let (d0, f0) = (pts[inner].0, pts[inner].1);
                let (d1, f1) = (pts[i].0, pts[i].1);
                return Ok(d0 + (half - f0) * (d1 - d0) / (f1 - f0));
            }
            inner = i;
        }
        Err(SpatialError::Profile(format!(
            "profile does not fall to half its maximum ({half:.4} N) on the {side} side \
             within {:.2} mm of the load",
            (pts[inner].0 - dpk).abs()
        )))
    };
    let left = crossing(&mut (0..imax).rev(), "negative")?;
    let right = crossing(&mut (imax + 1..pts.len()), "positive")?;
    Ok(SpatialAnalysis {
        profile: pts
            .iter()
            .map(|&(d, f, n)| ProfilePoint {
                distance_mm: d,
                fz_n: f,
                normalized: f / fpk,
                n,
            })
            .collect(),
        fwhm_mm: right - left,
        half_left_mm: left,
        half_right_mm: right,
        peak_distance_mm: dpk,
        peak_fz_n: fpk,
        line_offset_mm,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two grid rows (y = 0 and y = 2.2) of 10 nodes at 2.2 mm pitch; loads from node 4
    /// to node 5 of row 0 in `n` steps; f_z(q) = profile(|q − p|) on row 0 and a large
    /// decoy value on row 1 (which must be ignored).
    fn loads(n: usize, profile: impl Fn(f64) -> f64) -> Vec<PointLoad> {
        let pitch = 2.2;
        (0..=n)
            .map(|i| {
                let p = [4.0 * pitch + pitch * i as f64 / n as f64, 0.0];
                let mut forces = Vec::new();
                for iy in 0..2 {
                    for ix in 0..10 {
                        let q = [ix as f64 * pitch, iy as f64 * pitch];
                        let fz = if iy == 0 { profile(q[0] - p[0]) } else { 99.0 };
                        forces.push(ForceRecord {
                            ix,
                            iy,
                            position_mm: q,
                            f_n: [0.0, 0.0, fz],
                        });
                    }
                }
                PointLoad {
                    index: i,
                    position_mm: p,
                    forces,
                }
            })
            .collect()
    }

    #[test]
    fn triangular_profile_has_its_exact_width() {
        // f = 2·max(0, 1 − |d|/3): FWHM = 3 mm exactly (linear between samples).
        let s = analyze(
            &loads(6, |d| 2.0 * (1.0 - d.abs() / 3.0).max(0.0)),
            [1.0, 0.0],
            0.55,
        )
        .unwrap();
        assert!((s.fwhm_mm - 3.0).abs() < 1e-9, "{}", s.fwhm_mm);
        assert!(s.peak_distance_mm.abs() < 1e-9);
        assert!((s.peak_fz_n - 2.0).abs() < 1e-12);
        assert_eq!(s.line_offset_mm, 0.0);
        // 6 subdivisions of 2.2 mm: samples every 0.3667 mm; d = 0 appears twice per
        // grid step covered by both end loads (i = 0 and i = 6 coincide shifted).
        let spacing = s.profile[1].distance_mm - s.profile[0].distance_mm;
        assert!((spacing - 2.2 / 6.0).abs() < 1e-9, "{spacing}");
        assert!(s.profile.iter().all(|p| p.normalized <= 1.0 + 1e-12));
    }

    #[test]
    fn a_load_line_between_grid_rows_uses_the_nearest_row_and_reports_the_offset() {
        // Loads 0.7 mm above row 0 (row 1 is 1.5 mm away and must not be mixed in):
        // the row-0 profile is still the triangle of width 3 mm.
        let mut l = loads(6, |d| 2.0 * (1.0 - d.abs() / 3.0).max(0.0));
        for load in &mut l {
            load.position_mm[1] += 0.7;
        }
        let s = analyze(&l, [1.0, 0.0], 0.55).unwrap();
        assert!((s.line_offset_mm - 0.7).abs() < 1e-12);
        assert!((s.fwhm_mm - 3.0).abs() < 1e-9, "{}", s.fwhm_mm);
    }

    #[test]
    fn gaussian_profile_width_within_one_percent() {
        // σ = 1.7 mm: FWHM = 2·sqrt(2 ln 2)·σ = 4.003 mm (the paper's ~4 mm).
        let sigma = 1.7;
        let s = analyze(
            &loads(6, |d| (-d * d / (2.0 * sigma * sigma)).exp()),
            [1.0, 0.0],
            0.55,
        )
        .unwrap();
        let expected = 2.0 * (2.0 * 2f64.ln()).sqrt() * sigma;
        assert!(
            ((s.fwhm_mm - expected) / expected).abs() < 0.01,
            "{} vs {expected}",
            s.fwhm_mm
        );
    }

    #[test]
    fn a_flat_profile_is_rejected_naming_the_side() {
        let e = analyze(
            &loads(2, |d| if d < 0.0 { 1.0 } else { 1.0 - d / 40.0 }),
            [1.0, 0.0],
            0.55,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("does not fall to half"), "{e}");
        let e = analyze(&loads(2, |_| 0.0), [1.0, 0.0], 0.55)
            .unwrap_err()
            .to_string();
        assert!(e.contains("not positive"), "{e}");
    }
}
