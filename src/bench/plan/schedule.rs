//! Time in a plan: the sample schedule of a hold, when the contact is renewed between
//! setpoints, and the duration estimate the caps and `run --dry-run` use.

use super::{Plan, Setpoint};

/// Samples per hold: `0, dt, 2·dt, … ≤ duration`, plus `duration` itself when it is
/// not on that grid (as f64: a typo can make it astronomically large, which
/// validation refuses before anything is listed).
pub fn hold_sample_count(duration_s: f64, sample_interval_s: f64) -> f64 {
    let k = (duration_s / sample_interval_s + 1e-9).floor();
    let on_grid = (duration_s - k * sample_interval_s).abs() <= 1e-9 * duration_s.max(1.0);
    k + 1.0 + if on_grid { 0.0 } else { 1.0 }
}

/// The sample times of one hold, s after the hold force is reached: `0, dt, 2·dt, …`
/// and the last at `duration` (see [`hold_sample_count`]).
pub fn hold_schedule(duration_s: f64, sample_interval_s: f64) -> impl Iterator<Item = f64> {
    let n = hold_sample_count(duration_s, sample_interval_s) as usize;
    (0..n).map(move |k| (k as f64 * sample_interval_s).min(duration_s))
}

/// Whether the contact must be renewed (retract first) between `prev` and `sp`.
pub fn needs_retract(prev: Option<&Setpoint>, sp: &Setpoint) -> bool {
    let Some(p) = prev else { return true };
    let tangential = |s: &Setpoint| s.tangential_n != [0.0, 0.0];
    p.trial != sp.trial
        || p.position_mm != sp.position_mm
        || tangential(p)
        || tangential(sp)
        || sp.normal_n <= 0.0
        || p.normal_n <= 0.0
        || sp.shift_mm != [0.0, 0.0]
}

impl Plan {
    /// A rough duration estimate for the first `limit` setpoints (all when `None`):
    /// moves at their speeds (retract to `clearance_mm` and back when the contact is
    /// renewed, lateral moves at the safety speed), four control steps per loaded
    /// setpoint, the settle window × 1.2 (or the dwell), acquisition at 1 kHz and
    /// 30 ms per frame. Streams over the setpoints: no list is built.
    pub fn estimate_duration_s(&self, clearance_mm: f64, limit: Option<usize>) -> f64 {
        let v = self.approach_speed_mm_s;
        let vmax = self.safety.max_speed_mm_s;
        let settle = if self.settle.dwell_s > 0.0 {
            self.settle.dwell_s
        } else {
            self.settle.window_s * 1.2
        };
        let per_setpoint = settle + self.samples as f64 * 1e-3 + self.frames as f64 * 0.03;
        let mut t = 0.0;
        let mut prev: Option<Setpoint> = None;
        let acquisition = self.samples as f64 * 1e-3 + self.frames as f64 * 0.03;
        for sp in self.setpoints_iter().take(limit.unwrap_or(usize::MAX)) {
            // A hold sample after the first waits for its time in the schedule (the
            // acquisition happens within that wait, or later when it is longer).
            if let (Some(t_hold), Some(t_prev)) = (sp.hold_t_s, prev.and_then(|p| p.hold_t_s)) {
                if t_hold > t_prev && !needs_retract(prev.as_ref(), &sp) {
                    t += (t_hold - t_prev).max(acquisition);
                    prev = Some(sp);
                    continue;
                }
            }
            if needs_retract(prev.as_ref(), &sp) {
                t += 2.0 * clearance_mm / vmax + 0.5;
                if let Some(p) = prev {
                    t += (p.position_mm[0] - sp.position_mm[0])
                        .hypot(p.position_mm[1] - sp.position_mm[1])
                        / vmax;
                }
                if sp.normal_n > 0.0 {
                    t += clearance_mm / v;
                }
            }
            if sp.normal_n > 0.0 {
                t += 4.0 * (0.1 / v + 0.02);
            }
            // The first sample of a hold is taken as soon as the force is reached.
            t += if sp.hold_t_s.is_some() {
                acquisition
            } else {
                per_setpoint
            };
            prev = Some(sp);
        }
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench::plan::fixtures::*;
    use crate::bench::plan::DEFAULT_CLEARANCE_MM;
    use crate::units::gf_to_n;

    #[test]
    fn a_hold_sweep_samples_each_hold_on_its_schedule_between_unloaded_readings() {
        let p = parse(&with_sweep(
            "kind = \"hold\"\nforce = 300.0\nduration_s = 2.5\nsample_interval_s = 1.0\ntrials = 2",
        ))
        .unwrap();
        let s = p.setpoints();
        let got: Vec<(usize, f64, Option<f64>)> = s
            .iter()
            .map(|s| (s.trial, s.normal_n, s.hold_t_s))
            .collect();
        let f = gf_to_n(300.0);
        let hold = |t| {
            vec![
                (t, f, Some(0.0)),
                (t, f, Some(1.0)),
                (t, f, Some(2.0)),
                (t, f, Some(2.5)),
                (t, 0.0, None),
            ]
        };
        assert_eq!(got, [vec![(0, 0.0, None)], hold(0), hold(1)].concat());
        assert_eq!(s[1].swept_value, 300.0);
        assert_eq!(s[0].swept_value, 0.0);
        assert!(s
            .iter()
            .all(|s| s.direction.is_none() && s.position.is_none()));
        // Consecutive samples of a hold keep the contact; each hold starts afresh.
        assert!(!needs_retract(Some(&s[1]), &s[2]));
        assert!(needs_retract(Some(&s[5]), &s[6]) && needs_retract(Some(&s[4]), &s[5]));
        assert_eq!(
            hold_schedule(3.0, 1.0).collect::<Vec<_>>(),
            [0.0, 1.0, 2.0, 3.0]
        );
        assert_eq!(hold_sample_count(0.3, 0.1), 4.0, "0.3 / 0.1 is on the grid");
        // The estimate includes the holds' own time.
        assert!(p.estimate_duration_s(DEFAULT_CLEARANCE_MM, None) > 2.0 * 2.5);
    }
}
