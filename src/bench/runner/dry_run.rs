//! `--dry-run`: the setpoints, an estimated duration and the limit checks of a plan,
//! without touching any device.

use crate::bench::config::BenchGeometry;
use crate::bench::plan::{Plan, Setpoint};
use crate::device::TravelLimits;

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

/// What `--dry-run` reports: the setpoints, an estimated duration and the limit checks.
#[derive(Debug, Clone, PartialEq)]
pub struct DryRun {
    /// Every setpoint, in run order.
    pub setpoints: Vec<Setpoint>,
    /// Estimated duration, s.
    pub estimated_s: f64,
    /// Checks performed, each `(passed, description)`.
    pub checks: Vec<(bool, String)>,
}

/// Plans a run without touching any device: setpoints, estimated duration and limit
/// checks (plan box, force limits, and the stage box when the bench geometry and the
/// stage limits are known).
pub fn dry_run(
    plan: &Plan,
    limit: Option<usize>,
    geometry: Option<&BenchGeometry>,
    stage_limits: Option<&TravelLimits>,
) -> DryRun {
    let mut setpoints = plan.setpoints();
    if let Some(n) = limit {
        setpoints.truncate(n);
    }
    let s = &plan.safety;
    let u = plan.force_unit;
    let fu = u.symbol();
    let mut checks = Vec::new();
    let max = setpoints.iter().fold([0.0f64; 3], |m, sp| {
        [
            m[0].max(sp.tangential_n[0].abs()),
            m[1].max(sp.tangential_n[1].abs()),
            m[2].max(sp.normal_n),
        ]
    });
    for (i, axis) in ["fx", "fy", "fz"].iter().enumerate() {
        checks.push((
            max[i] <= s.max_force_n[i],
            format!(
                "largest target |{axis}| {:.4} {fu} within safety.max_force[{i}] = {:.4} {fu}",
                u.from_newtons(max[i]),
                u.from_newtons(s.max_force_n[i])
            ),
        ));
    }
    let clearance = geometry.map_or(1.0, |g| g.clearance_mm);
    checks.push((
        -clearance >= s.travel_min_mm[2],
        format!(
            "retract height {clearance} mm above the surface within travel_min_mm[2] = {} mm",
            s.travel_min_mm[2]
        ),
    ));
    for sp in &setpoints {
        let p = [
            sp.position_mm[0] + sp.shift_mm[0],
            sp.position_mm[1] + sp.shift_mm[1],
        ];
        for i in 0..2 {
            if p[i] < s.travel_min_mm[i] || p[i] > s.travel_max_mm[i] {
                checks.push((
                    false,
                    format!(
                        "setpoint {}: {} = {} mm outside the plan's travel box",
                        sp.index,
                        ["x", "y"][i],
                        p[i]
                    ),
                ));
            }
        }
        if let (Some(g), Some(lim)) = (geometry, stage_limits) {
            for depth in [-clearance, s.travel_max_mm[2]] {
                if let Err(e) = lim.check(g.stage_point(p, depth)) {
                    checks.push((false, format!("setpoint {}: stage {e}", sp.index)));
                }
            }
        }
    }
    checks.push((
        true,
        format!(
            "{} setpoint positions checked against the plan's travel box x {}..{} mm, y {}..{} mm{}",
            setpoints.len(),
            s.travel_min_mm[0],
            s.travel_max_mm[0],
            s.travel_min_mm[1],
            s.travel_max_mm[1],
            if stage_limits.is_some() {
                " and the stage's travel limits"
            } else {
                " (stage limits unknown without a bench: checked when the run starts)"
            }
        ),
    ));
    DryRun {
        estimated_s: estimate_duration(plan, &setpoints, clearance),
        setpoints,
        checks,
    }
}

/// A rough duration estimate: moves at their speeds, a few control steps per loaded
/// setpoint, the settle window (or dwell), acquisition at 1 kHz, 30 ms per frame.
pub fn estimate_duration(plan: &Plan, setpoints: &[Setpoint], clearance_mm: f64) -> f64 {
    let v = plan.approach_speed_mm_s;
    let vmax = plan.safety.max_speed_mm_s;
    let settle = if plan.settle.dwell_s > 0.0 {
        plan.settle.dwell_s
    } else {
        plan.settle.window_s * 1.2
    };
    let mut t = 0.0;
    let mut prev: Option<&Setpoint> = None;
    for sp in setpoints {
        if needs_retract(prev, sp) {
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
        t += settle + plan.samples as f64 * 1e-3 + plan.frames as f64 * 0.03;
        prev = Some(sp);
    }
    t
}
