//! The runner's pure decision logic, kept free of devices so it can be tested exactly:
//! settle detection, force-limit checks (the safety watchdog's test), and the z step of
//! closed-loop normal-force control.
//!
//! **Settle criterion.** A setpoint is settled when the standard deviation of the force
//! magnitude over the trailing `window_s` is below `max_sd_n` and the window is full.
//! Against a fixed dwell this ends as soon as the elastomer has relaxed, instead of
//! always waiting for the worst case.
//!
//! **Force control.** The contact is stiffening (Hertz: `F ∝ δ^{3/2}`), so a fixed gain
//! either crawls or overshoots. [`ForceController`] uses the secant of the last two
//! (z, F) readings as the local stiffness, falls back to a conservative initial
//! stiffness, never steps by more than `max_step_mm`, and never plans a step whose
//! predicted force exceeds the safety limit.

use std::collections::VecDeque;

use crate::device::Wrench;

/// Detects when the force has settled.
#[derive(Debug, Clone)]
pub struct SettleDetector {
    window_s: f64,
    max_sd_n: f64,
    samples: VecDeque<(f64, f64)>,
    /// Running sums of `f − offset` and its square over the window: the SD costs
    /// O(1) per sample instead of O(window) (a 1 kHz sensor fills a 0.5 s window with
    /// 500 samples). The offset (first sample of the window's run) keeps the sums
    /// small, avoiding cancellation in `Σx² − (Σx)²/n`.
    offset: f64,
    sum: f64,
    sum_sq: f64,
}

impl SettleDetector {
    /// A detector over `window_s` seconds with threshold `max_sd_n` (N).
    pub fn new(window_s: f64, max_sd_n: f64) -> Self {
        SettleDetector {
            window_s,
            max_sd_n,
            samples: VecDeque::new(),
            offset: 0.0,
            sum: 0.0,
            sum_sq: 0.0,
        }
    }

    /// Adds a force-magnitude sample (N) taken at `t_s` seconds; returns whether the
    /// force is settled now.
    pub fn push(&mut self, t_s: f64, force_n: f64) -> bool {
        if self.samples.is_empty() {
            self.offset = force_n;
            self.sum = 0.0;
            self.sum_sq = 0.0;
        }
        let x = force_n - self.offset;
        self.samples.push_back((t_s, force_n));
        self.sum += x;
        self.sum_sq += x * x;
        // Keep one sample at or before the window's start (t − window): then the
        // samples span the whole window whatever the sampling interval. (Dropping every
        // sample older than the window instead made a slow reader, 0.1 window or more
        // between readings on a loaded host, never see a full window.)
        while self.samples.len() >= 2 && t_s - self.samples[1].0 >= self.window_s {
            if let Some((_, f0)) = self.samples.pop_front() {
                let y = f0 - self.offset;
                self.sum -= y;
                self.sum_sq -= y * y;
            }
        }
        self.is_settled()
    }

    /// The window is full (its samples span at least `window_s`) and its SD is below
    /// the threshold.
    pub fn is_settled(&self) -> bool {
        let n = self.samples.len();
        if n < 2 {
            return false;
        }
        let span = self.samples[n - 1].0 - self.samples[0].0;
        span >= self.window_s && self.sd_n() < self.max_sd_n
    }

    /// Standard deviation of the window, N.
    pub fn sd_n(&self) -> f64 {
        let n = self.samples.len() as f64;
        if n < 2.0 {
            return f64::INFINITY;
        }
        let var = (self.sum_sq - self.sum * self.sum / n) / (n - 1.0);
        var.max(0.0).sqrt()
    }

    /// Forgets all samples (after a move).
    pub fn reset(&mut self) {
        self.samples.clear();
        self.sum = 0.0;
        self.sum_sq = 0.0;
    }
}

/// A force component beyond its limit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LimitTrip {
    /// 0 = fx, 1 = fy, 2 = fz.
    pub axis: usize,
    /// Measured value, N.
    pub value_n: f64,
    /// The limit, N.
    pub limit_n: f64,
}

impl std::fmt::Display for LimitTrip {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let name = ["fx", "fy", "fz"][self.axis.min(2)];
        write!(
            f,
            "measured {name} = {:.4} N exceeds the safety limit {:.4} N",
            self.value_n, self.limit_n
        )
    }
}

/// The watchdog's test: the first force component whose magnitude exceeds its limit.
/// A non-finite reading counts as a trip (never trust garbage while moving).
pub fn check_force_limits(w: &Wrench, max_force_n: &[f64; 3]) -> Option<LimitTrip> {
    (0..3).find_map(|axis| {
        let v = w.force_n[axis];
        (!v.is_finite() || v.abs() > max_force_n[axis]).then_some(LimitTrip {
            axis,
            value_n: v,
            limit_n: max_force_n[axis],
        })
    })
}

/// Closed-loop normal-force control along z (z positive = deeper into the elastomer).
#[derive(Debug, Clone)]
pub struct ForceController {
    /// Initial (and fallback) stiffness estimate, N/mm.
    pub initial_stiffness_n_per_mm: f64,
    /// Largest single z step, mm.
    pub max_step_mm: f64,
    /// Safety limit on the normal force, N.
    pub max_force_n: f64,
    last: Option<(f64, f64)>,
}

impl ForceController {
    /// A controller with a conservative initial stiffness.
    pub fn new(initial_stiffness_n_per_mm: f64, max_step_mm: f64, max_force_n: f64) -> Self {
        ForceController {
            initial_stiffness_n_per_mm,
            max_step_mm,
            max_force_n,
            last: None,
        }
    }

    /// Forgets the previous reading (after a lateral move or retract).
    pub fn reset(&mut self) {
        self.last = None;
    }

    /// The next z target (mm) to bring the measured normal force `force_n` (at stage
    /// z `z_mm`) to `target_n`.
    pub fn next_z(&mut self, z_mm: f64, force_n: f64, target_n: f64) -> f64 {
        let mut k = self.initial_stiffness_n_per_mm;
        if let Some((z0, f0)) = self.last {
            let dz = z_mm - z0;
            if dz.abs() > 1e-9 {
                let secant = (force_n - f0) / dz;
                // Only trust a physically sensible (positive, finite) secant.
                if secant.is_finite() && secant > 1e-9 {
                    k = secant;
                }
            }
        }
        self.last = Some((z_mm, force_n));
        let mut step = (target_n - force_n) / k;
        // Do not plan past the safety limit with the current stiffness estimate.
        let headroom = (self.max_force_n - force_n) / k;
        if step > 0.0 && step > 0.9 * headroom {
            step = 0.9 * headroom.max(0.0);
        }
        z_mm + step.clamp(-self.max_step_mm, self.max_step_mm)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settles_only_once_the_window_is_full_and_quiet() {
        let mut d = SettleDetector::new(0.5, 0.01);
        // Relaxing force: exponential approach to 1 N with time constant 0.3 s.
        let mut settled_at = None;
        for i in 0..400 {
            let t = i as f64 * 0.01;
            let f = 1.0 - 0.5 * (-t / 0.3).exp();
            if d.push(t, f) && settled_at.is_none() {
                settled_at = Some(t);
            }
        }
        let t = settled_at.expect("settles");
        // SD over a 0.5 s window of 0.5·e^{-t/0.3} drops below 0.01 N after ~1.2 s.
        assert!(t > 0.9 && t < 1.8, "settled at {t}");
        let mut d = SettleDetector::new(0.5, 0.01);
        assert!(
            !d.push(0.0, 1.0) && !d.push(0.1, 1.0) && !d.push(0.2, 1.0),
            "window not full yet"
        );
    }

    #[test]
    fn a_slow_reader_still_sees_a_full_window() {
        // A constant force read every 0.2 s, 0.3 s window: settled at the third
        // reading (0.4 s of history), whatever the sampling interval.
        let mut d = SettleDetector::new(0.3, 0.01);
        assert!(!d.push(0.0, 1.0));
        assert!(!d.push(0.2, 1.0), "0.2 s of history is not a 0.3 s window");
        assert!(d.push(0.4, 1.0));
        assert!(d.push(0.6, 1.0));
        // A step inside the window is seen until it has left it.
        assert!(!d.push(0.8, 1.5));
        assert!(!d.push(1.0, 1.5));
        assert!(d.push(1.2, 1.5) || d.push(1.4, 1.5));
        // Readings 1 s apart: every window holds the previous reading (the anchor)
        // and this one; a quiet force settles at the second reading, a moving one not.
        let mut d = SettleDetector::new(0.3, 0.01);
        let settled: Vec<bool> = (0..4).map(|i| d.push(i as f64, 2.0)).collect();
        assert_eq!(settled, [false, true, true, true]);
        let mut d = SettleDetector::new(0.3, 0.01);
        let settled: Vec<bool> = (0..4).map(|i| d.push(i as f64, i as f64)).collect();
        assert_eq!(settled, [false; 4]);
    }

    #[test]
    fn running_sd_matches_the_two_pass_sd_of_the_window() {
        let mut d = SettleDetector::new(0.05, 1e-3);
        let mut all = Vec::new();
        for i in 0..1000 {
            let t = i as f64 * 1e-3;
            // Large mean, small wiggle: the case that cancels in naive Σx² − (Σx)²/n.
            let f = 1000.0 + 0.01 * (i as f64 * 0.7).sin();
            d.push(t, f);
            all.push((t, f));
        }
        // The window: from the last sample at or before 0.999 − 0.05 s on.
        let t_last = all.last().unwrap().0;
        let start = all.iter().rposition(|(t, _)| t_last - t >= 0.05).unwrap();
        let w: Vec<f64> = all[start..].iter().map(|s| s.1).collect();
        let n = w.len() as f64;
        let m = w.iter().sum::<f64>() / n;
        let sd = (w.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        assert!(
            (d.sd_n() - sd).abs() < 1e-9 * sd.max(1e-3),
            "{} vs {sd}",
            d.sd_n()
        );
    }

    #[test]
    fn watchdog_trips_on_any_component_and_on_garbage() {
        let lim = [1.0, 1.0, 5.0];
        let ok = Wrench {
            force_n: [0.5, -0.9, 4.9],
            torque_nm: [0.0; 3],
        };
        assert_eq!(check_force_limits(&ok, &lim), None);
        let w = Wrench {
            force_n: [0.5, -1.2, 4.9],
            ..ok
        };
        assert_eq!(check_force_limits(&w, &lim).unwrap().axis, 1);
        let w = Wrench {
            force_n: [0.0, 0.0, f64::NAN],
            ..ok
        };
        assert_eq!(check_force_limits(&w, &lim).unwrap().axis, 2);
    }

    #[test]
    fn converges_on_a_hertzian_contact_without_overshoot() {
        // F = c·δ^{3/2}, the hemisphere's Hertz law; contact at z = 0.
        let c = 2.0;
        let force = |z: f64| if z > 0.0 { c * z.powf(1.5) } else { 0.0 };
        let target = 3.0;
        let mut ctl = ForceController::new(0.5, 0.5, 10.0);
        let mut z = 0.05;
        let mut steps = 0;
        while (force(z) - target).abs() > 0.01 && steps < 50 {
            z = ctl.next_z(z, force(z), target);
            assert!(force(z) < 10.0, "never past the safety limit");
            steps += 1;
        }
        assert!(
            (force(z) - target).abs() <= 0.01,
            "converged to {} in {steps} steps",
            force(z)
        );
        assert!(steps < 20, "{steps} steps");
    }

    #[test]
    fn never_plans_a_step_beyond_the_limit() {
        let mut ctl = ForceController::new(1.0, 10.0, 2.0);
        let z = ctl.next_z(0.0, 1.5, 5.0);
        // Headroom 0.5 N at 1 N/mm -> at most 0.45 mm.
        assert!(z <= 0.45 + 1e-12, "{z}");
    }
}
