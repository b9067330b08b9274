//! Marker health: how well the markers were tracked at each setpoint, from the
//! journal's `markers_*`, `reacquired` and `quality` columns (see `bench::journal`),
//! against the plan's `[quality] min_ok_fraction` gate.
//!
//! A marker counts as ok at a setpoint when it was ok in every frame of it; the four
//! counts of a row add up to the sensor file's markers. Rows of journals written
//! before these columns have no counts and are left out (see [`analyze`]).

use crate::bench::journal::JournalRow;

/// One setpoint's marker counts.
#[derive(Debug, Clone, PartialEq)]
pub struct SetpointHealth {
    /// Setpoint index.
    pub index: usize,
    /// The swept quantity (display unit of the plan).
    pub swept_value: f64,
    /// Markers ok in every frame.
    pub ok: usize,
    /// Markers lost in some frame.
    pub lost: usize,
    /// Markers merged in some frame.
    pub merged: usize,
    /// Markers that were outliers in some frame.
    pub outlier: usize,
    /// Re-acquisitions before the row was kept.
    pub reacquired: usize,
    /// The row is flagged (below the gate after every re-acquisition).
    pub flagged: bool,
}

impl SetpointHealth {
    /// Markers in all (the sensor file's markers).
    pub fn total(&self) -> usize {
        self.ok + self.lost + self.merged + self.outlier
    }

    /// `count / total` (0 for a row without markers).
    pub fn fraction(&self, count: usize) -> f64 {
        match self.total() {
            0 => 0.0,
            t => count as f64 / t as f64,
        }
    }

    /// Fraction of the markers that were ok.
    pub fn ok_fraction(&self) -> f64 {
        self.fraction(self.ok)
    }
}

/// Marker health over a run.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackingAnalysis {
    /// Rows with counts, in journal order.
    pub setpoints: Vec<SetpointHealth>,
    /// The plan's `min_ok_fraction` gate.
    pub gate: f64,
    /// Rows without counts (journals written before the columns existed).
    pub rows_without_counts: usize,
}

impl TrackingAnalysis {
    /// Smallest ok fraction of any row.
    pub fn min_ok_fraction(&self) -> f64 {
        self.setpoints
            .iter()
            .map(SetpointHealth::ok_fraction)
            .fold(f64::INFINITY, f64::min)
    }

    /// Mean ok fraction over the rows.
    pub fn mean_ok_fraction(&self) -> f64 {
        let n = self.setpoints.len().max(1) as f64;
        self.setpoints
            .iter()
            .map(SetpointHealth::ok_fraction)
            .sum::<f64>()
            / n
    }

    /// Rows flagged for tracking quality.
    pub fn flagged(&self) -> impl Iterator<Item = &SetpointHealth> {
        self.setpoints.iter().filter(|s| s.flagged)
    }

    /// Rows whose frames were re-acquired at least once.
    pub fn reacquired_rows(&self) -> usize {
        self.setpoints.iter().filter(|s| s.reacquired > 0).count()
    }
}

/// Marker health of `rows` against the gate `min_ok_fraction`; `None` when no row
/// has marker counts (an empty journal, or one written before the columns existed).
pub fn analyze(rows: &[JournalRow], min_ok_fraction: f64) -> Option<TrackingAnalysis> {
    let mut setpoints = Vec::with_capacity(rows.len());
    let mut without = 0;
    for r in rows {
        match (
            r.markers_ok,
            r.markers_lost,
            r.markers_merged,
            r.markers_outlier,
        ) {
            (Some(ok), Some(lost), Some(merged), Some(outlier)) => setpoints.push(SetpointHealth {
                index: r.index,
                swept_value: r.swept_value,
                ok,
                lost,
                merged,
                outlier,
                reacquired: r.reacquired.unwrap_or(0),
                flagged: r.flagged(),
            }),
            _ => without += 1,
        }
    }
    (!setpoints.is_empty()).then_some(TrackingAnalysis {
        setpoints,
        gate: min_ok_fraction,
        rows_without_counts: without,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench::journal::RowQuality;

    fn row(index: usize, counts: Option<[usize; 4]>, quality: Option<RowQuality>) -> JournalRow {
        JournalRow {
            index,
            markers_ok: counts.map(|c| c[0]),
            markers_lost: counts.map(|c| c[1]),
            markers_merged: counts.map(|c| c[2]),
            markers_outlier: counts.map(|c| c[3]),
            reacquired: counts.map(|_| usize::from(quality == Some(RowQuality::Flagged)) * 2),
            quality,
            ..JournalRow::default()
        }
    }

    #[test]
    fn fractions_flags_and_rows_without_counts() {
        let rows = vec![
            row(0, Some([260, 0, 0, 0]), Some(RowQuality::Ok)),
            row(1, Some([130, 120, 8, 2]), Some(RowQuality::Flagged)),
            row(2, None, None),
            row(3, Some([247, 10, 2, 1]), Some(RowQuality::Ok)),
        ];
        let a = analyze(&rows, 0.9).unwrap();
        assert_eq!(a.setpoints.len(), 3);
        assert_eq!(a.rows_without_counts, 1);
        assert_eq!(a.min_ok_fraction(), 0.5);
        assert!((a.mean_ok_fraction() - (1.0 + 0.5 + 0.95) / 3.0).abs() < 1e-12);
        assert_eq!(a.flagged().map(|s| s.index).collect::<Vec<_>>(), vec![1]);
        assert_eq!(a.reacquired_rows(), 1);
        assert_eq!(a.setpoints[1].fraction(120), 120.0 / 260.0);
        assert!(analyze(&rows[2..3], 0.9).is_none());
        assert!(analyze(&[], 0.9).is_none());
    }
}
