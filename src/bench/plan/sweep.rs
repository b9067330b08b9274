//! The sweep kinds of a plan (`[sweep] kind`, `direction`) and the number of setpoints
//! each expands to, computed from its parameters alone (so the caps are checked before
//! anything is listed).

use super::hold_sample_count;

/// `[sweep] direction` of a magnitude sweep.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SweepDirection {
    /// `"up"` (default): each trial runs the levels from `from` up to `to`.
    #[default]
    Up,
    /// `"up-down"`: each trial runs up to `to` and back down to `from` (the top level
    /// measured once), starting and ending with an unloaded reading.
    UpDown,
}

impl SweepDirection {
    /// The name used in plans.
    pub fn name(self) -> &'static str {
        match self {
            SweepDirection::Up => "up",
            SweepDirection::UpDown => "up-down",
        }
    }
}

/// Which sweep the plan runs (display units kept for reports).
#[derive(Debug, Clone, PartialEq)]
pub enum Sweep {
    /// Paper Fig. 7: normal force from..to by step.
    Magnitude {
        /// First force (force_unit).
        from: f64,
        /// Last force (force_unit), inclusive.
        to: f64,
        /// Step (force_unit), > 0.
        step: f64,
        /// Repetitions.
        trials: usize,
    },
    /// Paper Fig. 8: fixed magnitude at angles from the normal.
    Angle {
        /// Force magnitude (force_unit).
        force: f64,
        /// First angle, degrees.
        from_deg: f64,
        /// Last angle, degrees, inclusive (< 90).
        to_deg: f64,
        /// Step, degrees, > 0.
        step_deg: f64,
        /// Azimuth of the tangential part in the sensor plane, degrees from +x.
        direction_deg: f64,
        /// Repetitions.
        trials: usize,
    },
    /// Paper Fig. 9: point loads at sub-steps along a segment.
    Spatial {
        /// Normal force (force_unit).
        force: f64,
        /// Segment start, mm.
        start_mm: [f64; 2],
        /// Segment end, mm.
        end_mm: [f64; 2],
        /// Number of intervals (positions = subdivisions + 1).
        subdivisions: usize,
    },
    /// Constant normal force held for a stated time, sampled through it (creep).
    Hold {
        /// Normal force held (force_unit).
        force: f64,
        /// How long each hold lasts after the force is reached, s.
        duration_s: f64,
        /// Time between samples, s (first at 0, last at `duration_s`).
        sample_interval_s: f64,
        /// Holds (contact released between them).
        trials: usize,
    },
    /// Paper Table I: whole-sensor shift, no load.
    Displacement {
        /// Shift, mm.
        shift_mm: [f64; 2],
        /// Repetitions.
        trials: usize,
    },
    /// An explicit list.
    Setpoints(Vec<ExplicitPoint>),
}

/// One explicit setpoint as written (force_unit).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExplicitPoint {
    /// Position, mm.
    pub position_mm: [f64; 2],
    /// Normal force (force_unit).
    pub normal: f64,
    /// Tangential force (force_unit).
    pub tangential: [f64; 2],
}

impl Sweep {
    /// The number of setpoints the sweep expands to, from its parameters alone (as
    /// f64: a typo can make it astronomically large, which validation refuses), for
    /// `direction = "up"` at one position; [`total_count`] includes both.
    pub fn count(&self) -> f64 {
        match self {
            Sweep::Magnitude {
                from,
                to,
                step,
                trials,
            } => level_count(*from, *to, *step) * *trials as f64,
            Sweep::Angle {
                from_deg,
                to_deg,
                step_deg,
                trials,
                ..
            } => level_count(*from_deg, *to_deg, *step_deg) * *trials as f64,
            Sweep::Spatial { subdivisions, .. } => *subdivisions as f64 + 1.0,
            Sweep::Hold {
                duration_s,
                sample_interval_s,
                trials,
                ..
            } => {
                // An unloaded reading before the first hold and after each.
                (hold_sample_count(*duration_s, *sample_interval_s) + 1.0) * *trials as f64 + 1.0
            }
            Sweep::Displacement { trials, .. } => *trials as f64,
            Sweep::Setpoints(points) => points.len() as f64,
        }
    }
}

/// The number of setpoints of a sweep with its direction and `positions` contact
/// positions (0 = the approach position only), from the parameters alone.
pub fn total_count(sweep: &Sweep, direction: SweepDirection, positions: usize) -> f64 {
    let positions = positions.max(1) as f64;
    match sweep {
        Sweep::Magnitude {
            from,
            to,
            step,
            trials,
        } => {
            let n = level_count(*from, *to, *step);
            let per_trial = match direction {
                SweepDirection::Up => n,
                SweepDirection::UpDown => 2.0 * n - 1.0 + if *from > 0.0 { 2.0 } else { 0.0 },
            };
            per_trial * *trials as f64 * positions
        }
        Sweep::Angle { .. } => sweep.count() * positions,
        _ => sweep.count(),
    }
}

/// The number of values `from, from+step, …` up to `to` inclusive (within a small
/// tolerance), computed without listing them.
pub(super) fn level_count(from: f64, to: f64, step: f64) -> f64 {
    ((to - from) / step + 1e-9).floor() + 1.0
}
