//! Validation of a parsed plan into a [`Plan`]: ranges with units, the keys each sweep
//! kind requires, the defaults a plan left out (recorded for `run --dry-run`), the
//! setpoint, frame and duration caps (computed before anything is expanded), and every
//! target checked against the force limits and the travel box.

use std::path::Path;

use super::raw::{
    RawAcquire, RawApproach, RawControl, RawIndenter, RawPlan, RawQuality, RawReconstruct,
    RawSafety, RawSettle, RawSweep,
};
use super::sweep::level_count;
use super::*;
use crate::config::Checker;
use crate::solve::{Lambda, Method, Rank, SolverConfig};
use crate::units::ForceUnit;

impl RawQuality {
    fn validate(&self, c: &Checker<'_>) -> Result<Quality, PlanError> {
        let d = Quality::default();
        let fraction = |key: &str, v: Option<f64>, default: f64| {
            let v = v.unwrap_or(default);
            if v.is_finite() && (0.0..=1.0).contains(&v) {
                Ok(v)
            } else {
                Err(c.invalid(
                    key,
                    v,
                    "must be a fraction in [0, 1] of the sensor file's markers",
                ))
            }
        };
        let max_reacquire = match self.max_reacquire {
            None => d.max_reacquire,
            Some(v) if (0..=MAX_REACQUIRE).contains(&v) => v as usize,
            Some(v) => {
                return Err(c.invalid(
                    "quality.max_reacquire",
                    v,
                    format!("must be an integer in [0, {MAX_REACQUIRE}] (re-acquisitions)"),
                ))
            }
        };
        let on_fail = match self.on_fail.as_deref() {
            None | Some("flag") => OnFail::Flag,
            Some("abort") => OnFail::Abort,
            Some(other) => {
                return Err(c.invalid(
                    "quality.on_fail",
                    format!("{other:?}"),
                    "expected \"flag\" or \"abort\"",
                ))
            }
        };
        let count = |key: &str, v: Option<i64>, default: usize| match v {
            None => Ok(default),
            Some(v) if (1..=MAX_CONSECUTIVE).contains(&v) => Ok(v as usize),
            Some(v) => Err(c.invalid(
                key,
                v,
                format!("must be an integer in [1, {MAX_CONSECUTIVE}] (consecutive setpoints)"),
            )),
        };
        let ratio_min = self.force_ratio_min.unwrap_or(d.force_ratio_min);
        if !(ratio_min.is_finite() && ratio_min > 0.0 && ratio_min < 1.0) {
            return Err(c.invalid(
                "quality.force_ratio_min",
                ratio_min,
                "must be in (0, 1) (|F_sum| / |F_ft|)",
            ));
        }
        let ratio_max = self.force_ratio_max.unwrap_or(d.force_ratio_max);
        if !(ratio_max.is_finite() && ratio_max > 1.0 && ratio_max <= 1e6) {
            return Err(c.invalid(
                "quality.force_ratio_max",
                ratio_max,
                "must be in (1, 1e6] (|F_sum| / |F_ft|)",
            ));
        }
        let floor = self.force_noise_floor_n.unwrap_or(d.force_noise_floor_n);
        if !(floor.is_finite() && floor > 0.0 && floor <= 1e4) {
            return Err(c.invalid(
                "quality.force_noise_floor_n",
                format!("{floor} N"),
                "must be in (0, 1e4] N",
            ));
        }
        Ok(Quality {
            dead_camera_setpoints: count(
                "quality.dead_camera_setpoints",
                self.dead_camera_setpoints,
                d.dead_camera_setpoints,
            )?,
            max_implausible_rows: count(
                "quality.max_implausible_rows",
                self.max_implausible_rows,
                d.max_implausible_rows,
            )?,
            force_ratio_min: ratio_min,
            force_ratio_max: ratio_max,
            force_noise_floor_n: floor,
            reference_min_found_fraction: fraction(
                "quality.reference_min_found_fraction",
                self.reference_min_found_fraction,
                d.reference_min_found_fraction,
            )?,
            min_ok_fraction: fraction(
                "quality.min_ok_fraction",
                self.min_ok_fraction,
                d.min_ok_fraction,
            )?,
            max_reacquire,
            on_fail,
        })
    }
}

/// Defaults of the optional keys (`docs/plans.md`; echoed by `run --dry-run`).
const DEFAULT_FORCE_UNIT: &str = "N";
const DEFAULT_MAX_STEPS: i64 = 40;
const DEFAULT_WINDOW_S: f64 = 0.5;
const DEFAULT_TIMEOUT_S: f64 = 10.0;
const DEFAULT_DWELL_S: f64 = 0.0;
const DEFAULT_SAMPLES: i64 = 20;
const DEFAULT_FRAMES: i64 = 1;
const DEFAULT_DIRECTION_DEG: f64 = 0.0;

/// The optional keys a plan left out, with the defaults used (for `--dry-run`).
#[derive(Default)]
struct Defaults(Vec<(String, String)>);

impl Defaults {
    /// `v`, or `default` (recorded as `key = show(default)`) when the key is absent.
    fn take<T: Clone>(
        &mut self,
        v: Option<T>,
        default: T,
        key: &str,
        show: impl FnOnce(T) -> String,
    ) -> T {
        match v {
            Some(v) => v,
            None => {
                self.push(key, show(default.clone()));
                default
            }
        }
    }

    fn push(&mut self, key: &str, value: String) {
        self.0.push((key.to_string(), value));
    }
}

/// The setpoint and frame caps, from the sweep's parameters alone (before anything
/// is expanded). `max_normal` is `safety.max_force[2]` in the plan's force unit.
fn check_caps(
    c: &Checker<'_>,
    sweep: &Sweep,
    direction: SweepDirection,
    positions: usize,
    frames: usize,
    fu: &str,
    max_normal: f64,
) -> Result<(), PlanError> {
    if let Sweep::Hold {
        duration_s, trials, ..
    } = sweep
    {
        let hold_s = duration_s * *trials as f64;
        if hold_s > MAX_DURATION_S {
            return Err(c.invalid(
                "sweep.duration_s",
                format!("{duration_s} s"),
                format!(
                    "sweep.trials {trials} holds of sweep.duration_s {duration_s} s = {:.1} h of holding alone, above the cap of {:.0} h per plan",
                    hold_s / 3600.0,
                    MAX_DURATION_S / 3600.0
                ),
            ));
        }
    }
    let total = total_count(sweep, direction, positions);
    let base = sweep.count();
    // NaN (cannot happen after the range checks) is refused as well.
    if total.is_nan() || total > MAX_SETPOINTS as f64 {
        let (key, value, how) = match sweep {
            _ if base <= MAX_SETPOINTS as f64 && positions > 1 && base * positions as f64 > MAX_SETPOINTS as f64 => (
                "sweep.positions_mm",
                format!("{positions} positions"),
                format!(
                    "{base:.0} setpoints per position x {positions} positions = {total:.0} setpoints"
                ),
            ),
            Sweep::Hold {
                duration_s,
                sample_interval_s,
                trials,
                ..
            } => {
                let per_hold = hold_sample_count(*duration_s, *sample_interval_s);
                let how = format!(
                    "sweep.duration_s {duration_s} s sampled every sweep.sample_interval_s {sample_interval_s} s is {per_hold:.0} samples per hold x sweep.trials {trials} (+ {} unloaded readings) = {total:.0} setpoints",
                    trials + 1
                );
                if per_hold <= MAX_SETPOINTS as f64 {
                    ("sweep.trials", trials.to_string(), how)
                } else {
                    ("sweep.sample_interval_s", format!("{sample_interval_s} s"), how)
                }
            }
            Sweep::Magnitude {
                from,
                to,
                step,
                trials,
            } => {
                let levels = level_count(*from, *to, *step);
                let how = match direction {
                    SweepDirection::Up => format!(
                        "sweep.from {from} to sweep.to {to} {fu} by sweep.step {step} {fu} is {levels:.0} levels x sweep.trials {trials} = {total:.0} setpoints"
                    ),
                    SweepDirection::UpDown => format!(
                        "sweep.from {from} to sweep.to {to} {fu} by sweep.step {step} {fu} is {levels:.0} levels, up and down (sweep.direction = \"up-down\") x sweep.trials {trials} = {total:.0} setpoints"
                    ),
                };
                if levels <= MAX_SETPOINTS as f64 {
                    ("sweep.trials", trials.to_string(), how)
                } else if *to > max_normal {
                    (
                        "sweep.to",
                        format!("{to} {fu}"),
                        format!(
                            "{how} (and sweep.to is above safety.max_force[2] = {} {fu})",
                            round9(max_normal)
                        ),
                    )
                } else {
                    ("sweep.step", format!("{step} {fu}"), how)
                }
            }
            Sweep::Angle {
                from_deg,
                to_deg,
                step_deg,
                trials,
                ..
            } => {
                let levels = level_count(*from_deg, *to_deg, *step_deg);
                let how = format!(
                    "sweep.angle_from_deg {from_deg} to sweep.angle_to_deg {to_deg} deg by sweep.angle_step_deg {step_deg} deg is {levels:.0} angles x sweep.trials {trials} = {total:.0} setpoints"
                );
                if levels <= MAX_SETPOINTS as f64 {
                    ("sweep.trials", trials.to_string(), how)
                } else {
                    ("sweep.angle_step_deg", format!("{step_deg} deg"), how)
                }
            }
            _ => (
                "sweep",
                format!("{total:.0} setpoints"),
                "the sweep is too long".to_string(),
            ),
        };
        return Err(c.invalid(
            key,
            value,
            format!("{how}, above the cap of {MAX_SETPOINTS} setpoints per plan"),
        ));
    }
    let n_frames = total * frames as f64;
    if n_frames > MAX_FRAMES as f64 {
        return Err(c.invalid(
            "acquire.frames",
            frames,
            format!(
                "{total:.0} setpoints x {frames} frames = {n_frames:.0} frames, above the cap of {MAX_FRAMES} frames per plan"
            ),
        ));
    }
    Ok(())
}

/// A key the chosen sweep kind requires.
fn need<T>(c: &Checker<'_>, key: &str, v: Option<T>, kind: &str) -> Result<T, PlanError> {
    v.ok_or_else(|| {
        c.invalid(
            key,
            "(missing)",
            format!("required by sweep kind \"{kind}\""),
        )
    })
}

impl RawPlan {
    /// The validated plan, in named steps taken in the order their errors are
    /// reported (the first invalid key wins) and their defaults recorded: the force
    /// unit, the indenter, the approach and the safety limits, force control, settle
    /// and acquisition, the sweep, its direction and positions, the setpoint and frame
    /// caps, the solver, the quality gates; then, on the assembled plan, the duration
    /// cap and every target against the force limits and the travel box.
    pub(super) fn validate(mut self, path: &Path) -> Result<Plan, PlanError> {
        let c = Checker { path };
        let mut defaults = Defaults::default();
        let unit = force_unit(&c, self.force_unit.clone(), &mut defaults)?;
        let fu = unit.symbol();
        let indenter = self.indenter.validate(&c)?;
        let (approach_position_mm, approach_speed_mm_s, contact_force_n) =
            self.approach.validate(&c, unit)?;
        let safety = self.safety.validate(&c, unit)?;
        if approach_speed_mm_s > safety.max_speed_mm_s {
            return Err(c.invalid(
                "approach.speed_mm_s",
                format!("{approach_speed_mm_s} mm/s"),
                format!(
                    "must not exceed safety.max_speed_mm_s = {} mm/s",
                    safety.max_speed_mm_s
                ),
            ));
        }
        let (force_tolerance_n, max_control_steps) =
            self.control
                .validate(&c, unit, contact_force_n, &mut defaults)?;
        let settle = self
            .settle
            .validate(&c, unit, force_tolerance_n, &mut defaults)?;
        let (samples, frames) = self.acquire.validate(&c, &mut defaults)?;

        let sweep = self.sweep.validate(&c, unit, &mut defaults)?;
        let sweep_direction = self.sweep.direction(&c, &sweep, &mut defaults)?;
        let positions_mm = self.sweep.positions(&c, &sweep, &safety)?;
        check_caps(
            &c,
            &sweep,
            sweep_direction,
            positions_mm.len(),
            frames,
            fu,
            unit.from_newtons(safety.max_force_n[2]),
        )?;

        let solver = self.reconstruct.validate(&c, &mut defaults)?;
        let quality = self.quality.validate(&c)?;
        self.quality.record_defaults(&quality, &mut defaults);
        let plan = Plan {
            sweep_direction,
            positions_mm,
            quality,
            solver,
            path: path.to_path_buf(),
            name: self.name,
            sensor_path: path.parent().unwrap_or(Path::new(".")).join(&self.sensor),
            build_id: self.build_id,
            force_unit: unit,
            indenter,
            approach_position_mm,
            approach_speed_mm_s,
            contact_force_n,
            force_tolerance_n,
            max_control_steps,
            settle,
            samples,
            frames,
            safety,
            sweep,
            defaults: defaults.0,
        };
        check_duration(&c, &plan)?;
        check_targets(&c, &plan)?;
        Ok(plan)
    }
}

/// The plan's force unit (`force_unit`, default newtons).
fn force_unit(
    c: &Checker<'_>,
    v: Option<String>,
    defaults: &mut Defaults,
) -> Result<ForceUnit, PlanError> {
    let unit_text = defaults.take(v, DEFAULT_FORCE_UNIT.to_string(), "force_unit", |v| {
        format!("{v:?}")
    });
    unit_text
        .parse()
        .map_err(|e: String| c.invalid("force_unit", format!("{unit_text:?}"), e))
}

impl RawIndenter {
    /// The indenter's shape, with the diameter the flat and hemispherical ones need.
    fn validate(&self, c: &Checker<'_>) -> Result<IndenterShape, PlanError> {
        Ok(match self.shape.as_str() {
            "flat" | "hemisphere" => {
                let d = need(c, "indenter.diameter_mm", self.diameter_mm, &self.shape)?;
                let diameter_mm = c.positive("indenter.diameter_mm", d, "mm")?;
                if self.shape == "flat" {
                    IndenterShape::Flat { diameter_mm }
                } else {
                    IndenterShape::Hemisphere { diameter_mm }
                }
            }
            "point" => IndenterShape::Point,
            other => {
                return Err(c.invalid(
                    "indenter.shape",
                    format!("{other:?}"),
                    "unknown shape: expected flat, hemisphere or point",
                ))
            }
        })
    }
}

impl RawApproach {
    /// The approach position (mm), speed (mm/s) and contact force (N).
    fn validate(
        &self,
        c: &Checker<'_>,
        unit: ForceUnit,
    ) -> Result<([f64; 2], f64, f64), PlanError> {
        let position_mm = [
            c.finite("approach.position_mm[0]", self.position_mm[0], "mm")?,
            c.finite("approach.position_mm[1]", self.position_mm[1], "mm")?,
        ];
        let speed_mm_s = c.positive("approach.speed_mm_s", self.speed_mm_s, "mm/s")?;
        let contact_force_n = unit.to_newtons(c.positive(
            "approach.contact_force",
            self.contact_force,
            unit.symbol(),
        )?);
        Ok((position_mm, speed_mm_s, contact_force_n))
    }
}

impl RawSafety {
    /// The force limits (converted to N), the travel box (each axis's minimum below
    /// its maximum) and the speed limit.
    fn validate(&self, c: &Checker<'_>, unit: ForceUnit) -> Result<Safety, PlanError> {
        let mut max_force_n = [0.0; 3];
        for (i, v) in self.max_force.iter().enumerate() {
            max_force_n[i] = unit.to_newtons(c.positive(
                &format!("safety.max_force[{i}]"),
                *v,
                unit.symbol(),
            )?);
        }
        for i in 0..3 {
            c.finite(
                &format!("safety.travel_min_mm[{i}]"),
                self.travel_min_mm[i],
                "mm",
            )?;
            c.finite(
                &format!("safety.travel_max_mm[{i}]"),
                self.travel_max_mm[i],
                "mm",
            )?;
            if self.travel_min_mm[i] >= self.travel_max_mm[i] {
                return Err(c.invalid(
                    &format!("safety.travel_max_mm[{i}]"),
                    format!("{} mm", self.travel_max_mm[i]),
                    format!(
                        "must exceed safety.travel_min_mm[{i}] = {} mm",
                        self.travel_min_mm[i]
                    ),
                ));
            }
        }
        let max_speed_mm_s = c.positive("safety.max_speed_mm_s", self.max_speed_mm_s, "mm/s")?;
        Ok(Safety {
            max_force_n,
            travel_min_mm: self.travel_min_mm,
            travel_max_mm: self.travel_max_mm,
            max_speed_mm_s,
        })
    }
}

/// `v` in the plan's force unit, rounded for messages.
fn with_unit(v: f64, fu: &str) -> String {
    format!("{} {fu}", round9(v))
}

impl RawControl {
    /// The force tolerance (N; default: the approach's contact force) and the
    /// controller's step limit.
    fn validate(
        &self,
        c: &Checker<'_>,
        unit: ForceUnit,
        contact_force_n: f64,
        defaults: &mut Defaults,
    ) -> Result<(f64, usize), PlanError> {
        let fu = unit.symbol();
        let tol_default = unit.from_newtons(contact_force_n);
        let force_tolerance_n = unit.to_newtons(c.positive(
            "control.force_tolerance",
            defaults.take(
                self.force_tolerance,
                tol_default,
                "control.force_tolerance",
                |v| format!("{} (approach.contact_force)", with_unit(v, fu)),
            ),
            fu,
        )?);
        let max_control_steps = c.count(
            "control.max_steps",
            defaults.take(
                self.max_steps,
                DEFAULT_MAX_STEPS,
                "control.max_steps",
                |v| v.to_string(),
            ),
            10_000,
        )?;
        Ok((force_tolerance_n, max_control_steps))
    }
}

impl RawSettle {
    /// The settle criterion (default spread: half the force tolerance), its timeout
    /// (capped) and the dwell.
    fn validate(
        &self,
        c: &Checker<'_>,
        unit: ForceUnit,
        force_tolerance_n: f64,
        defaults: &mut Defaults,
    ) -> Result<Settle, PlanError> {
        let fu = unit.symbol();
        let secs = |v: f64| format!("{v} s");
        Ok(Settle {
            window_s: c.positive(
                "settle.window_s",
                defaults.take(self.window_s, DEFAULT_WINDOW_S, "settle.window_s", secs),
                "s",
            )?,
            max_sd_n: unit.to_newtons(c.positive(
                "settle.max_sd",
                defaults.take(
                    self.max_sd,
                    unit.from_newtons(force_tolerance_n) / 2.0,
                    "settle.max_sd",
                    |v| format!("{} (control.force_tolerance / 2)", with_unit(v, fu)),
                ),
                fu,
            )?),
            timeout_s: {
                let t = c.positive(
                    "settle.timeout_s",
                    defaults.take(self.timeout_s, DEFAULT_TIMEOUT_S, "settle.timeout_s", secs),
                    "s",
                )?;
                if t > MAX_SETTLE_TIMEOUT_S {
                    return Err(c.invalid(
                        "settle.timeout_s",
                        format!("{t} s"),
                        format!(
                            "must be at most {MAX_SETTLE_TIMEOUT_S} s (ten minutes: a force that has not settled by then will not; the row is flagged at the timeout)"
                        ),
                    ));
                }
                t
            },
            dwell_s: c.non_negative(
                "settle.dwell_s",
                defaults.take(self.dwell_s, DEFAULT_DWELL_S, "settle.dwell_s", secs),
                "s",
            )?,
        })
    }
}

impl RawAcquire {
    /// F/T samples and camera frames per setpoint.
    fn validate(
        &self,
        c: &Checker<'_>,
        defaults: &mut Defaults,
    ) -> Result<(usize, usize), PlanError> {
        let samples = c.count(
            "acquire.samples",
            defaults.take(self.samples, DEFAULT_SAMPLES, "acquire.samples", |v| {
                v.to_string()
            }),
            100_000,
        )?;
        let frames = c.count(
            "acquire.frames",
            defaults.take(self.frames, DEFAULT_FRAMES, "acquire.frames", |v| {
                v.to_string()
            }),
            1000,
        )?;
        Ok((samples, frames))
    }
}

impl RawSweep {
    /// The sweep of `sweep.kind` with the keys that kind requires.
    fn validate(
        &mut self,
        c: &Checker<'_>,
        unit: ForceUnit,
        defaults: &mut Defaults,
    ) -> Result<Sweep, PlanError> {
        match self.kind.as_str() {
            "magnitude" => self.magnitude(c, unit.symbol()),
            "angle" => self.angle(c, unit.symbol(), defaults),
            "spatial" => self.spatial(c, unit.symbol()),
            "hold" => self.hold(c, unit.symbol()),
            "displacement" => self.displacement(c),
            "setpoints" => self.setpoints(c, unit.symbol(), defaults),
            other => Err(c.invalid(
                "sweep.kind",
                format!("{other:?}"),
                "unknown sweep: expected magnitude, angle, hold, spatial, displacement or setpoints",
            )),
        }
    }

    /// A key this sweep's kind requires.
    fn need<T>(&self, c: &Checker<'_>, key: &str, v: Option<T>) -> Result<T, PlanError> {
        need(c, key, v, &self.kind)
    }

    /// `sweep.trials`, required by every kind that repeats.
    fn trials(&self, c: &Checker<'_>) -> Result<usize, PlanError> {
        c.count(
            "sweep.trials",
            self.need(c, "sweep.trials", self.trials)?,
            10_000,
        )
    }

    /// `sweep.force`, the load of the angle, spatial and hold sweeps.
    fn force(&self, c: &Checker<'_>, fu: &str) -> Result<f64, PlanError> {
        c.positive("sweep.force", self.need(c, "sweep.force", self.force)?, fu)
    }

    /// Fig. 7: normal force levels `from..=to` by `step`.
    fn magnitude(&self, c: &Checker<'_>, fu: &str) -> Result<Sweep, PlanError> {
        let from = c.non_negative("sweep.from", self.need(c, "sweep.from", self.from)?, fu)?;
        let to = c.non_negative("sweep.to", self.need(c, "sweep.to", self.to)?, fu)?;
        let step = c.positive("sweep.step", self.need(c, "sweep.step", self.step)?, fu)?;
        if to < from {
            return Err(c.invalid(
                "sweep.to",
                format!("{to} {fu}"),
                format!("must be >= sweep.from = {from} {fu}"),
            ));
        }
        Ok(Sweep::Magnitude {
            from,
            to,
            step,
            trials: self.trials(c)?,
        })
    }

    /// Fig. 8: one force tilted from the normal over `[from, to]` deg, in `[0, 90)`.
    fn angle(
        &self,
        c: &Checker<'_>,
        fu: &str,
        defaults: &mut Defaults,
    ) -> Result<Sweep, PlanError> {
        let force = self.force(c, fu)?;
        let from_deg = self.need(c, "sweep.angle_from_deg", self.angle_from_deg)?;
        let to_deg = self.need(c, "sweep.angle_to_deg", self.angle_to_deg)?;
        for (key, v) in [
            ("sweep.angle_from_deg", from_deg),
            ("sweep.angle_to_deg", to_deg),
        ] {
            if !(v.is_finite() && (0.0..90.0).contains(&v)) {
                return Err(c.invalid(
                    key,
                    format!("{v} deg"),
                    "must be in [0, 90) deg from the normal",
                ));
            }
        }
        if to_deg < from_deg {
            return Err(c.invalid(
                "sweep.angle_to_deg",
                format!("{to_deg} deg"),
                format!("must be >= sweep.angle_from_deg = {from_deg} deg"),
            ));
        }
        Ok(Sweep::Angle {
            force,
            from_deg,
            to_deg,
            step_deg: c.positive(
                "sweep.angle_step_deg",
                self.need(c, "sweep.angle_step_deg", self.angle_step_deg)?,
                "deg",
            )?,
            direction_deg: c.finite(
                "sweep.direction_deg",
                defaults.take(
                    self.direction_deg,
                    DEFAULT_DIRECTION_DEG,
                    "sweep.direction_deg",
                    |v| format!("{v} deg (+x)"),
                ),
                "deg",
            )?,
            trials: self.trials(c)?,
        })
    }

    /// Fig. 9: one force at points along a line.
    fn spatial(&self, c: &Checker<'_>, fu: &str) -> Result<Sweep, PlanError> {
        let force = self.force(c, fu)?;
        let start_mm = self.need(c, "sweep.start_mm", self.start_mm)?;
        let end_mm = self.need(c, "sweep.end_mm", self.end_mm)?;
        for (key, p) in [("sweep.start_mm", start_mm), ("sweep.end_mm", end_mm)] {
            c.finite(key, p[0], "mm")?;
            c.finite(key, p[1], "mm")?;
        }
        Ok(Sweep::Spatial {
            force,
            start_mm,
            end_mm,
            subdivisions: c.count(
                "sweep.subdivisions",
                self.need(c, "sweep.subdivisions", self.subdivisions)?,
                10_000,
            )?,
        })
    }

    /// Creep: one force held for `duration_s`, sampled every `sample_interval_s`.
    fn hold(&self, c: &Checker<'_>, fu: &str) -> Result<Sweep, PlanError> {
        let force = self.force(c, fu)?;
        let duration_s = c.positive(
            "sweep.duration_s",
            self.need(c, "sweep.duration_s", self.duration_s)?,
            "s",
        )?;
        let sample_interval_s = c.positive(
            "sweep.sample_interval_s",
            self.need(c, "sweep.sample_interval_s", self.sample_interval_s)?,
            "s",
        )?;
        if sample_interval_s > duration_s {
            return Err(c.invalid(
                "sweep.sample_interval_s",
                format!("{sample_interval_s} s"),
                format!("must not exceed sweep.duration_s = {duration_s} s"),
            ));
        }
        Ok(Sweep::Hold {
            force,
            duration_s,
            sample_interval_s,
            trials: self.trials(c)?,
        })
    }

    /// Table I: the indenter shifted by `shift_mm` after contact.
    fn displacement(&self, c: &Checker<'_>) -> Result<Sweep, PlanError> {
        let shift_mm = self.need(c, "sweep.shift_mm", self.shift_mm)?;
        c.finite("sweep.shift_mm[0]", shift_mm[0], "mm")?;
        c.finite("sweep.shift_mm[1]", shift_mm[1], "mm")?;
        Ok(Sweep::Displacement {
            shift_mm,
            trials: self.trials(c)?,
        })
    }

    /// An explicit list of `[[sweep.points]]` (at most [`MAX_SETPOINTS`]), tangential
    /// force zero where not given.
    fn setpoints(
        &mut self,
        c: &Checker<'_>,
        fu: &str,
        defaults: &mut Defaults,
    ) -> Result<Sweep, PlanError> {
        let points = self.points.take();
        let points = self.need(c, "sweep.points", points)?;
        if points.is_empty() {
            return Err(c.invalid(
                "sweep.points",
                "[]",
                "at least one [[sweep.points]] is required",
            ));
        }
        if points.len() > MAX_SETPOINTS {
            return Err(c.invalid(
                "sweep.points",
                format!("{} points", points.len()),
                format!("a plan may have at most {MAX_SETPOINTS} setpoints (cap)"),
            ));
        }
        let mut out = Vec::with_capacity(points.len());
        let mut untangential = false;
        for (i, p) in points.into_iter().enumerate() {
            untangential |= p.tangential.is_none();
            let tangential = p.tangential.unwrap_or([0.0; 2]);
            let key = format!("sweep.points[{i}]");
            c.finite(&format!("{key}.position_mm[0]"), p.position_mm[0], "mm")?;
            c.finite(&format!("{key}.position_mm[1]"), p.position_mm[1], "mm")?;
            out.push(ExplicitPoint {
                position_mm: p.position_mm,
                normal: c.non_negative(&format!("{key}.normal"), p.normal, fu)?,
                tangential: [
                    c.finite(&format!("{key}.tangential[0]"), tangential[0], fu)?,
                    c.finite(&format!("{key}.tangential[1]"), tangential[1], fu)?,
                ],
            });
        }
        if untangential {
            defaults.push(
                "sweep.points[].tangential",
                format!("[0, 0] {fu} (where not given)"),
            );
        }
        Ok(Sweep::Setpoints(out))
    }

    /// `sweep.direction`: up, or up and down for magnitude sweeps only.
    fn direction(
        &self,
        c: &Checker<'_>,
        sweep: &Sweep,
        defaults: &mut Defaults,
    ) -> Result<SweepDirection, PlanError> {
        Ok(match (self.direction.as_deref(), sweep) {
            (None, Sweep::Magnitude { .. }) => {
                defaults.push("sweep.direction", "\"up\"".into());
                SweepDirection::Up
            }
            (None, _) => SweepDirection::Up,
            (Some(d), Sweep::Magnitude { .. }) => match d {
                "up" => SweepDirection::Up,
                "up-down" => SweepDirection::UpDown,
                other => {
                    return Err(c.invalid(
                        "sweep.direction",
                        format!("{other:?}"),
                        "expected \"up\" or \"up-down\"",
                    ))
                }
            },
            (Some(d), _) => {
                return Err(c.invalid(
                    "sweep.direction",
                    format!("{d:?}"),
                    format!(
                        "only magnitude sweeps run up and down (sweep kind is \"{}\")",
                        self.kind
                    ),
                ))
            }
        })
    }

    /// `sweep.positions_mm`: the contact positions magnitude and angle sweeps repeat
    /// their trials at (at most [`MAX_POSITIONS`], each inside the travel box).
    fn positions(
        &mut self,
        c: &Checker<'_>,
        sweep: &Sweep,
        safety: &Safety,
    ) -> Result<Vec<[f64; 2]>, PlanError> {
        Ok(match self.positions_mm.take() {
            None => Vec::new(),
            Some(_) if !matches!(sweep, Sweep::Magnitude { .. } | Sweep::Angle { .. }) => {
                return Err(c.invalid(
                    "sweep.positions_mm",
                    "(given)",
                    format!(
                        "only magnitude and angle sweeps repeat their trials at several positions (sweep kind is \"{}\")",
                        self.kind
                    ),
                ))
            }
            Some(list) if list.is_empty() => {
                return Err(c.invalid(
                    "sweep.positions_mm",
                    "[]",
                    "give at least one [x, y] position (mm), or leave the key out",
                ))
            }
            Some(list) if list.len() > MAX_POSITIONS => {
                return Err(c.invalid(
                    "sweep.positions_mm",
                    format!("{} positions", list.len()),
                    format!("at most {MAX_POSITIONS} positions"),
                ))
            }
            Some(list) => {
                for (i, p) in list.iter().enumerate() {
                    for (a, axis) in ["x", "y"].iter().enumerate() {
                        let key = format!("sweep.positions_mm[{i}][{a}]");
                        c.finite(&key, p[a], "mm")?;
                        let (lo, hi) = (safety.travel_min_mm[a], safety.travel_max_mm[a]);
                        if p[a] < lo || p[a] > hi {
                            return Err(c.invalid(
                                &key,
                                format!("{} mm", p[a]),
                                format!(
                                    "{axis} is outside the travel box safety.travel_min_mm[{a}]..travel_max_mm[{a}] = {lo}..{hi} mm"
                                ),
                            ));
                        }
                    }
                }
                list
            }
        })
    }
}

impl RawReconstruct {
    /// The solver a run reconstructs with: method (default pinv), λ and rank rules,
    /// the Fourier solver's refinement iterations (refused for other methods).
    fn validate(
        &self,
        c: &Checker<'_>,
        defaults: &mut Defaults,
    ) -> Result<SolverConfig, PlanError> {
        let method: Method = match &self.solver {
            None => {
                defaults.push("reconstruct.solver", "\"pinv\"".into());
                Method::Pinv
            }
            Some(m) => m
                .parse()
                .map_err(|e: String| c.invalid("reconstruct.solver", format!("{m:?}"), e))?,
        };
        let as_text = |v: &toml::Value| match v {
            toml::Value::String(s) => s.clone(),
            other => other.to_string(),
        };
        let lambda: Lambda = match &self.lambda {
            None if method == Method::Fourier => {
                defaults.push("reconstruct.lambda", "\"lcurve\" (fourier)".into());
                Lambda::LCurve
            }
            None => {
                if matches!(method, Method::Tikhonov) {
                    defaults.push("reconstruct.lambda", "\"gcv\"".into());
                }
                Lambda::Gcv
            }
            Some(v) => as_text(v)
                .parse()
                .map_err(|e: String| c.invalid("reconstruct.lambda", v, e))?,
        };
        let rank: Rank = match &self.rank {
            None => {
                if matches!(method, Method::Tsvd) {
                    defaults.push("reconstruct.rank", "\"auto\"".into());
                }
                Rank::Auto
            }
            Some(v) => as_text(v)
                .parse()
                .map_err(|e: String| c.invalid("reconstruct.rank", v, e))?,
        };
        let fourier_refine_iterations = self.refine_iterations(c, method, defaults)?;
        Ok(SolverConfig {
            method,
            lambda,
            rank,
            fourier_refine_iterations,
            ..SolverConfig::default()
        })
    }

    /// `reconstruct.refine_iterations`: the Fourier solver's CGLS iterations.
    fn refine_iterations(
        &self,
        c: &Checker<'_>,
        method: Method,
        defaults: &mut Defaults,
    ) -> Result<usize, PlanError> {
        let max_refine = crate::solve::fourier::MAX_REFINE_ITERATIONS as i64;
        Ok(match self.refine_iterations {
            None => {
                if method == Method::Fourier {
                    defaults.push(
                        "reconstruct.refine_iterations",
                        crate::solve::fourier::DEFAULT_REFINE_ITERATIONS.to_string(),
                    );
                }
                crate::solve::fourier::DEFAULT_REFINE_ITERATIONS
            }
            Some(_) if method != Method::Fourier => {
                return Err(c.invalid(
                    "reconstruct.refine_iterations",
                    self.refine_iterations.unwrap_or(0),
                    format!("only the fourier solver refines (solver is {method})"),
                ))
            }
            Some(v) if (0..=max_refine).contains(&v) => v as usize,
            Some(v) => {
                return Err(c.invalid(
                    "reconstruct.refine_iterations",
                    v,
                    format!("must be an integer in [0, {max_refine}] (CGLS iterations)"),
                ))
            }
        })
    }
}

impl RawQuality {
    /// The tracking gates the plan left at their defaults, echoed like the others.
    fn record_defaults(&self, quality: &Quality, defaults: &mut Defaults) {
        if self.reference_min_found_fraction.is_none() {
            defaults.push(
                "quality.reference_min_found_fraction",
                format!("{}", quality.reference_min_found_fraction),
            );
        }
        if self.min_ok_fraction.is_none() {
            defaults.push(
                "quality.min_ok_fraction",
                format!("{}", quality.min_ok_fraction),
            );
        }
        if self.max_reacquire.is_none() {
            defaults.push(
                "quality.max_reacquire",
                format!("{}", quality.max_reacquire),
            );
        }
        if self.on_fail.is_none() {
            defaults.push("quality.on_fail", "\"flag\"".into());
        }
    }
}

/// The duration cap, on the plan's estimated duration from its (bounded) setpoints
/// one at a time; blames the dwell when it alone takes half the cap.
fn check_duration(c: &Checker<'_>, plan: &Plan) -> Result<(), PlanError> {
    let est = plan.estimate_duration_s(DEFAULT_CLEARANCE_MM, None);
    if est > MAX_DURATION_S {
        let (key, value) = if plan.settle.dwell_s > 0.0
            && plan.settle.dwell_s * plan.setpoint_count() as f64 > MAX_DURATION_S / 2.0
        {
            ("settle.dwell_s", format!("{} s", plan.settle.dwell_s))
        } else {
            ("sweep", format!("{} setpoints", plan.setpoint_count()))
        };
        return Err(c.invalid(
            key,
            value,
            format!(
                "the plan's estimated duration is {:.1} h, above the cap of {:.0} h per plan",
                est / 3600.0,
                MAX_DURATION_S / 3600.0
            ),
        ));
    }
    Ok(())
}

/// Every target must stay within the force limits and the travel box before anything
/// moves.
fn check_targets(c: &Checker<'_>, plan: &Plan) -> Result<(), PlanError> {
    let (unit, fu) = (plan.force_unit, plan.force_unit.symbol());
    for sp in plan.setpoints_iter() {
        for i in 0..2 {
            let v = sp.position_mm[i] + sp.shift_mm[i];
            let (lo, hi) = (plan.safety.travel_min_mm[i], plan.safety.travel_max_mm[i]);
            if v < lo || v > hi {
                return Err(c.invalid(
                    "sweep",
                    format!("setpoint {} at {} = {} mm", sp.index, ["x", "y"][i], round9(v)),
                    format!(
                        "outside the travel box safety.travel_min_mm[{i}]..travel_max_mm[{i}] = {lo}..{hi} mm"
                    ),
                ));
            }
        }
        let f = [sp.tangential_n[0], sp.tangential_n[1], sp.normal_n];
        for (i, axis) in ["x", "y", "z"].iter().enumerate() {
            if f[i].abs() > plan.safety.max_force_n[i] {
                return Err(c.invalid(
                    "sweep",
                    format!(
                        "setpoint {} with f{axis} = {} {fu}",
                        sp.index,
                        round9(unit.from_newtons(f[i]))
                    ),
                    format!(
                        "exceeds safety.max_force[{i}] = {} {fu}",
                        round9(unit.from_newtons(plan.safety.max_force_n[i]))
                    ),
                ));
            }
        }
    }
    Ok(())
}

/// Rounds away unit-conversion noise for messages (1000 gf, not 999.9999999999999 gf).
fn round9(v: f64) -> f64 {
    (v * 1e9).round() / 1e9
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench::plan::fixtures::*;

    #[test]
    fn quality_section_has_documented_defaults_and_checked_values() {
        let p = parse(FIG7).unwrap();
        assert_eq!(
            p.quality,
            Quality {
                reference_min_found_fraction: 0.9,
                min_ok_fraction: 0.9,
                max_reacquire: 2,
                on_fail: OnFail::Flag,
                dead_camera_setpoints: 3,
                force_ratio_min: 0.1,
                force_ratio_max: 10.0,
                force_noise_floor_n: 0.05,
                max_implausible_rows: 3,
            }
        );
        let q = parse(&format!(
            "{FIG7}[quality]\nreference_min_found_fraction = 0.5\nmin_ok_fraction = 0.75\nmax_reacquire = 0\non_fail = \"abort\"\n"
        ))
        .unwrap()
        .quality;
        assert_eq!(
            q,
            Quality {
                reference_min_found_fraction: 0.5,
                min_ok_fraction: 0.75,
                max_reacquire: 0,
                on_fail: OnFail::Abort,
                ..Quality::default()
            }
        );
        for (line, key, value) in [
            ("min_ok_fraction = 1.5", "quality.min_ok_fraction", "1.5"),
            (
                "reference_min_found_fraction = -0.1",
                "quality.reference_min_found_fraction",
                "-0.1",
            ),
            ("max_reacquire = 11", "quality.max_reacquire", "11"),
            ("on_fail = \"retry\"", "quality.on_fail", "\"retry\""),
            (
                "dead_camera_setpoints = 0",
                "quality.dead_camera_setpoints",
                "0",
            ),
            ("force_ratio_min = 1.5", "quality.force_ratio_min", "1.5"),
            ("force_ratio_max = 0.5", "quality.force_ratio_max", "0.5"),
            (
                "force_noise_floor_n = -1.0",
                "quality.force_noise_floor_n",
                "-1 N",
            ),
            (
                "max_implausible_rows = 0",
                "quality.max_implausible_rows",
                "0",
            ),
        ] {
            let e = parse(&format!("{FIG7}[quality]\n{line}\n"))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("experiments/p.toml") && e.contains(key) && e.contains(value),
                "{line}: {e}"
            );
        }
        let e = parse(&format!("{FIG7}[quality]\nmin_ok = 0.5\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("min_ok"), "{e}");
    }

    #[test]
    fn rejects_bad_values_naming_file_key_value_and_unit() {
        let e = parse(&FIG7.replace("step = 50.0", "step = -50.0"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("experiments/p.toml")
                && e.contains("sweep.step = -50 gf")
                && e.contains("> 0 gf"),
            "{e}"
        );
        let e = parse(&FIG7.replace("shape = \"hemisphere\"", "shape = \"cone\""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("indenter.shape") && e.contains("cone"), "{e}");
        let e = parse(&FIG7.replace("force_unit = \"gf\"", "force_unit = \"lbf\""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("force_unit") && e.contains("lbf"), "{e}");
        let e = parse(&FIG7.replace("trials = 10", "trials = 10\nbogus = 1"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("bogus") && e.contains("line"), "{e}");
        let e = parse(&FIG7.replace("speed_mm_s = 0.5", "speed_mm_s = 9.0"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("approach.speed_mm_s = 9 mm/s") && e.contains("max_speed_mm_s = 5"),
            "{e}"
        );
    }

    #[test]
    fn rejects_targets_beyond_the_force_limit_before_anything_moves() {
        let e = parse(&FIG7.replace("to = 750.0", "to = 1200.0"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("fz = 1000") || e.contains("fz = 1050"), "{e}");
        assert!(e.contains("safety.max_force[2] = 1000 gf"), "{e}");
    }

    #[test]
    fn a_sweep_to_1e9_is_refused_by_the_setpoint_cap_naming_key_value_and_cap() {
        let e = parse(&FIG7.replace("to = 750.0", "to = 1e9"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("experiments/p.toml")
                && e.contains("sweep.to = 1000000000 gf")
                && e.contains("200000010 setpoints")
                && e.contains(&format!("cap of {MAX_SETPOINTS} setpoints")),
            "{e}"
        );
        // A tiny step within the force limit names the step instead.
        let e = parse(&FIG7.replace("step = 50.0", "step = 1e-6"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("sweep.step = 0.000001 gf") && e.contains("cap"),
            "{e}"
        );
        let e = parse(&FIG7.replace(
            "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
            "kind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 45.0\nangle_step_deg = 1e-12\ntrials = 1",
        ))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("sweep.angle_step_deg") && e.contains("cap"),
            "{e}"
        );
    }

    #[test]
    fn the_frame_and_duration_caps_refuse_plans_that_would_run_for_weeks() {
        let e = parse(&FIG7.replace("trials = 10", "trials = 20\n[acquire]\nframes = 1000"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("acquire.frames = 1000")
                && e.contains("320000 frames")
                && e.contains(&format!("cap of {MAX_FRAMES} frames")),
            "{e}"
        );
        let e = parse(&FIG7.replace("trials = 10", "trials = 10\n[settle]\ndwell_s = 86400.0"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("settle.dwell_s = 86400 s") && e.contains("cap of 168 h"),
            "{e}"
        );
        let p = parse(FIG7).unwrap();
        let est = p.estimate_duration_s(DEFAULT_CLEARANCE_MM, None);
        assert!(est > 0.0 && est < MAX_DURATION_S);
        assert!(p.estimate_duration_s(DEFAULT_CLEARANCE_MM, Some(16)) < est / 5.0);
    }

    #[test]
    fn a_missing_trials_is_refused_instead_of_meaning_one() {
        let e = parse(&FIG7.replace("trials = 10\n", ""))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("sweep.trials = (missing)") && e.contains("required by sweep kind"),
            "{e}"
        );
    }

    #[test]
    fn fourier_refinement_is_a_plan_choice_checked_against_the_solver() {
        let p = parse(&format!("{FIG7}[reconstruct]\nsolver = \"fourier\"\n")).unwrap();
        assert_eq!(
            p.solver.fourier_refine_iterations,
            crate::solve::fourier::DEFAULT_REFINE_ITERATIONS
        );
        assert!(p
            .defaults
            .iter()
            .any(|(k, _)| k == "reconstruct.refine_iterations"));
        let p = parse(&format!(
            "{FIG7}[reconstruct]\nsolver = \"fourier\"\nrefine_iterations = 0\n"
        ))
        .unwrap();
        assert_eq!(p.solver.fourier_refine_iterations, 0);
        for (extra, needle) in [
            (
                "solver = \"pinv\"\nrefine_iterations = 5",
                "only the fourier solver",
            ),
            ("solver = \"fourier\"\nrefine_iterations = -1", "[0, 1000]"),
            (
                "solver = \"fourier\"\nrefine_iterations = 5000",
                "[0, 1000]",
            ),
        ] {
            let e = parse(&format!("{FIG7}[reconstruct]\n{extra}\n"))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("reconstruct.refine_iterations") && e.contains(needle),
                "{extra}: {e}"
            );
        }
    }

    #[test]
    fn keys_left_out_are_listed_with_their_defaults() {
        let p = parse(FIG7).unwrap();
        let keys: Vec<&str> = p.defaults.iter().map(|(k, _)| k.as_str()).collect();
        assert_eq!(
            keys,
            [
                "control.force_tolerance",
                "control.max_steps",
                "settle.window_s",
                "settle.max_sd",
                "settle.timeout_s",
                "settle.dwell_s",
                "acquire.samples",
                "acquire.frames",
                "sweep.direction",
                "reconstruct.solver",
                "quality.reference_min_found_fraction",
                "quality.min_ok_fraction",
                "quality.max_reacquire",
                "quality.on_fail"
            ]
        );
        assert_eq!(p.defaults[0].1, "5 gf (approach.contact_force)");
        assert_eq!(p.defaults[3].1, "2.5 gf (control.force_tolerance / 2)");
        assert_eq!(p.settle.window_s, DEFAULT_WINDOW_S);
        let p = parse(&FIG7.replace("force_unit = \"gf\"\n", "")).unwrap();
        assert_eq!(p.force_unit, ForceUnit::Newton);
        assert_eq!(p.defaults[0], ("force_unit".into(), "\"N\"".into()));
    }

    #[test]
    fn sweep_direction_positions_and_hold_keys_are_checked_naming_file_key_and_value() {
        let hold = "kind = \"hold\"\nforce = 300.0\nduration_s = 10.0\nsample_interval_s = 1.0\ntrials = 2";
        for (sweep, key, needle) in [
            (
                format!("{MAG}\ndirection = \"down\""),
                "sweep.direction = \"down\"",
                "expected \"up\" or \"up-down\"",
            ),
            (
                "kind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 10.0\nangle_step_deg = 10.0\ntrials = 1\ndirection = \"up-down\"".into(),
                "sweep.direction",
                "only magnitude sweeps",
            ),
            (
                format!("{MAG}\npositions_mm = []"),
                "sweep.positions_mm = []",
                "at least one",
            ),
            (
                format!("{MAG}\npositions_mm = [[9.0, 6.75], [60.0, 6.75]]"),
                "sweep.positions_mm[1][0] = 60 mm",
                "travel box",
            ),
            (
                format!("{hold}\npositions_mm = [[9.0, 6.75]]"),
                "sweep.positions_mm",
                "only magnitude and angle",
            ),
            (
                hold.replace("duration_s = 10.0\n", ""),
                "sweep.duration_s = (missing)",
                "required by sweep kind \"hold\"",
            ),
            (
                hold.replace("sample_interval_s = 1.0", "sample_interval_s = 20.0"),
                "sweep.sample_interval_s = 20 s",
                "must not exceed sweep.duration_s = 10 s",
            ),
            (
                hold.replace("duration_s = 10.0", "duration_s = -1.0"),
                "sweep.duration_s = -1",
                "> 0",
            ),
            (
                hold.replace("force = 300.0", "force = 2000.0"),
                "fz = 2000 gf",
                "safety.max_force[2]",
            ),
            (
                hold.replace("trials = 2\n", "").replace("trials = 2", ""),
                "sweep.trials = (missing)",
                "required",
            ),
        ] {
            let e = parse(&with_sweep(&sweep)).unwrap_err().to_string();
            assert!(
                e.contains("experiments/p.toml") && e.contains(key) && e.contains(needle),
                "{sweep}: {e}"
            );
        }
        // An unknown key in [sweep] is named with its line.
        let e = parse(&with_sweep(&format!("{hold}\nhold_s = 3")))
            .unwrap_err()
            .to_string();
        assert!(e.contains("hold_s") && e.contains("line"), "{e}");
    }

    #[test]
    fn hold_caps_are_checked_before_anything_is_expanded() {
        let hold = "kind = \"hold\"\nforce = 300.0\nduration_s = 10.0\nsample_interval_s = 1.0\ntrials = 2";
        let e = parse(&with_sweep(
            &hold.replace("sample_interval_s = 1.0", "sample_interval_s = 1e-6"),
        ))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("sweep.sample_interval_s = 0.000001 s")
                && e.contains("samples per hold")
                && e.contains(&format!("cap of {MAX_SETPOINTS} setpoints")),
            "{e}"
        );
        let e = parse(&with_sweep(
            &hold
                .replace("duration_s = 10.0", "duration_s = 1e9")
                .replace("sample_interval_s = 1.0", "sample_interval_s = 1e8"),
        ))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("sweep.duration_s = 1000000000 s") && e.contains("cap of 168 h"),
            "{e}"
        );
        let e = parse(&with_sweep(&format!(
            "{MAG}\npositions_mm = [{}]",
            vec!["[9.0, 6.75]"; 1000].join(", ")
        )))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("sweep.positions_mm = 1000 positions") && e.contains("cap"),
            "{e}"
        );
    }

    /// Issue 24, case 7: extra elements were silently cut (`[f64; N]` takes the first
    /// N); now they are refused like missing ones, naming the key, the length given
    /// and the length expected.
    #[test]
    fn case7_plan_arrays_with_extra_elements_are_refused_naming_key_and_lengths() {
        for (from, to, key, given, expected) in [
            (
                "max_force = [300.0, 300.0, 1000.0]",
                "max_force = [300.0, 300.0, 1000.0, 5.0]",
                "safety.max_force",
                4,
                3,
            ),
            (
                "position_mm = [9.0, 6.75]",
                "position_mm = [9.0, 6.75, 2.0]",
                "approach.position_mm",
                3,
                2,
            ),
            (
                "trials = 10",
                "trials = 10\npositions_mm = [[9.0, 6.75, 1.0]]",
                "sweep.positions_mm[0]",
                3,
                2,
            ),
            (
                "travel_min_mm = [0.0, 0.0, -2.0]",
                "travel_min_mm = [0.0, 0.0]",
                "safety.travel_min_mm",
                2,
                3,
            ),
        ] {
            let e = parse(&FIG7.replace(from, to)).unwrap_err();
            let ConfigError::Invalid { key: k, .. } = &e else {
                panic!("{to}: not an Invalid error: {e}")
            };
            assert_eq!(k, key, "{e}");
            let msg = e.to_string();
            assert!(
                msg.contains("experiments/p.toml")
                    && msg.contains(&format!(
                        "{given} elements given, exactly {expected} expected"
                    )),
                "{msg}"
            );
        }
        // Spatial, displacement and explicit sweeps: optional arrays and arrays in tables.
        let spatial = with_sweep(
            "kind = \"spatial\"\nforce = 200.0\nstart_mm = [8.9, 6.75, 0.0]\nend_mm = [11.1, 6.75]\nsubdivisions = 6",
        );
        let e = parse(&spatial).unwrap_err().to_string();
        assert!(
            e.contains("sweep.start_mm") && e.contains("3 elements given"),
            "{e}"
        );
        let points = with_sweep(
            "kind = \"setpoints\"\n[[sweep.points]]\nposition_mm = [9.0, 6.75]\nnormal = 100.0\ntangential = [1.0, 2.0, 3.0]",
        );
        let e = parse(&points).unwrap_err().to_string();
        assert!(
            e.contains("sweep.points[0].tangential") && e.contains("3 elements given"),
            "{e}"
        );
    }
}
