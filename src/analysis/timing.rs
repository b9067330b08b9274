//! Per-stage time per frame (paper Table II) from the journal's `t_*` columns.
//!
//! Each journal row's stage times are divided by the number of frames the setpoint
//! captured (the `frames` column's `;`-separated list, at least 1), so the figures are
//! per frame. Stages: **tracking** (`t_track_s`), **reconstruction** (`t_solve_s`),
//! **forces** = tracking + reconstruction (the paper's "time until obtain the forces",
//! 2.9 ms: image in memory to force vectors), and **rest** = moving + settling +
//! acquiring (`t_move_s + t_settle_s + t_acquire_s`, bench time, not computation).
//! For each: mean, sample SD, minimum and maximum over rows, in seconds.

use super::stats;
use crate::bench::journal::JournalRow;

/// Statistics of one stage, seconds per frame.
#[derive(Debug, Clone, PartialEq)]
pub struct StageTime {
    /// Stage name: `tracking`, `reconstruction`, `forces`, `rest`.
    pub stage: &'static str,
    /// Mean, s.
    pub mean_s: f64,
    /// Sample SD (0 for one row), s.
    pub sd_s: f64,
    /// Minimum, s.
    pub min_s: f64,
    /// Maximum, s.
    pub max_s: f64,
}

/// The timing analysis.
#[derive(Debug, Clone, PartialEq)]
pub struct TimingAnalysis {
    /// Stages in the order tracking, reconstruction, forces, rest.
    pub stages: Vec<StageTime>,
    /// Rows used.
    pub rows: usize,
    /// Frames counted over all rows.
    pub frames: usize,
}

impl TimingAnalysis {
    /// The named stage.
    pub fn stage(&self, name: &str) -> Option<&StageTime> {
        self.stages.iter().find(|s| s.stage == name)
    }
}

/// Frames a journal row captured (entries of its `frames` list, at least 1).
pub fn frame_count(row: &JournalRow) -> usize {
    row.frames
        .split(';')
        .filter(|s| !s.trim().is_empty())
        .count()
        .max(1)
}

/// Analyses the rows' stage times; `None` without rows.
pub fn analyze(rows: &[JournalRow]) -> Option<TimingAnalysis> {
    if rows.is_empty() {
        return None;
    }
    let per_frame = |f: &dyn Fn(&JournalRow) -> f64| -> Vec<f64> {
        rows.iter().map(|r| f(r) / frame_count(r) as f64).collect()
    };
    let stage = |stage: &'static str, v: Vec<f64>| StageTime {
        stage,
        mean_s: stats::mean(&v).unwrap_or(f64::NAN),
        sd_s: stats::sample_sd(&v).unwrap_or(0.0),
        min_s: v.iter().copied().fold(f64::INFINITY, f64::min),
        max_s: v.iter().copied().fold(f64::NEG_INFINITY, f64::max),
    };
    Some(TimingAnalysis {
        stages: vec![
            stage("tracking", per_frame(&|r| r.t_track_s)),
            stage("reconstruction", per_frame(&|r| r.t_solve_s)),
            stage("forces", per_frame(&|r| r.t_track_s + r.t_solve_s)),
            stage(
                "rest",
                per_frame(&|r| r.t_move_s + r.t_settle_s + r.t_acquire_s),
            ),
        ],
        rows: rows.len(),
        frames: rows.iter().map(frame_count).sum(),
    })
}

#[cfg(test)]
mod tests {
    use super::super::magnitude::tests::row;
    use super::*;

    #[test]
    fn stage_times_are_per_frame() {
        // Row 0: one frame, track 2 ms, solve 1 ms. Row 1: two frames, track 4 ms,
        // solve 2 ms (also 2 + 1 per frame) -> tracking 2 ms, SD 0; rest per frame
        // (0.5 + 0.2 + 0.1) / 1 and (0.6 + 0.2 + 0.2) / 2 -> 0.8 and 0.5 s.
        let mut a = row(0, 0, 0.0, [0.0; 3], [0.0; 3]);
        (
            a.t_track_s,
            a.t_solve_s,
            a.t_move_s,
            a.t_settle_s,
            a.t_acquire_s,
        ) = (2e-3, 1e-3, 0.5, 0.2, 0.1);
        let mut b = row(1, 0, 0.0, [0.0; 3], [0.0; 3]);
        b.frames = "frames/00001_0.png;frames/00001_1.png".into();
        (
            b.t_track_s,
            b.t_solve_s,
            b.t_move_s,
            b.t_settle_s,
            b.t_acquire_s,
        ) = (4e-3, 2e-3, 0.6, 0.2, 0.2);
        let t = analyze(&[a, b]).unwrap();
        assert_eq!((t.rows, t.frames), (2, 3));
        let tr = t.stage("tracking").unwrap();
        assert!((tr.mean_s - 2e-3).abs() < 1e-15 && tr.sd_s < 1e-15);
        assert!((t.stage("forces").unwrap().mean_s - 3e-3).abs() < 1e-15);
        let rest = t.stage("rest").unwrap();
        assert!((rest.mean_s - 0.65).abs() < 1e-12);
        assert!((rest.min_s - 0.5).abs() < 1e-12 && (rest.max_s - 0.8).abs() < 1e-12);
        assert!(analyze(&[]).is_none());
    }
}
