//! The indentation route of `tactbench fit` (issue 30): the stage's depth past first
//! contact against the F/T sensor's normal force, through the indenter's contact law
//! ([`crate::model::indentation`]: Hertz for the hemisphere, the flat punch, and the
//! bonded layer's own laws when the sensor's model is the bonded layer).
//!
//! Per loaded journal row: depth `δ = press · (stage_z − contact_z)` and residual
//! `(P(δ; E*, h) − F_z)/σ`, `E* = E/(1 − ν²)`. The F/T z axis is the press axis
//! whatever the F/T's rotation about z, so this route does not see the rotation.
//!
//! - **Rows**: those with `F_z` above `max(5 × its recorded SD, 2 % of the largest
//!   F_z)` (in contact); rows below are out of contact or at its noise.
//! - **Press direction and nominal contact z**: the run's `bench.geometry`
//!   (`press_direction`, `surface_z_mm`) when the manifest records it; otherwise the
//!   direction is the sign of the correlation of stage z with `F_z` over the loaded
//!   rows, and the contact z is where the law's linearised form extrapolates to zero
//!   force (`F_z^{2/3}` linear in z for the hemisphere, `F_z` for the punch).
//! - **Noise σ** (N): the RMS residual of this route's own fit (`χ²/(n − p)`,
//!   [`IndentationRoute::set_noise`]), floored at 0.1 mN: stage repeatability and F/T
//!   noise together, as the data show them.
//! - **Not available** (the caller says why, the fit goes on with the displacement
//!   route): a point indenter (no contact law), an import without a depth column,
//!   fewer than 3 loaded rows or fewer than 2 distinct depths.

use serde_json::json;

use super::{ModelParams, Residuals};
use crate::analysis::RunData;
use crate::bench::plan::{IndenterShape, Plan};
use crate::model::indentation::{indentation_force, reduced_modulus, Body, Shape};
use crate::sensor::{ModelKind, Sensor};

/// Floor of the route's noise, N.
const NOISE_FLOOR_N: f64 = 1e-4;

/// One loaded row.
#[derive(Debug, Clone, PartialEq)]
pub struct IndentRow {
    /// Setpoint index (journal `index`).
    pub index: usize,
    /// Trial.
    pub trial: usize,
    /// Stage z, mm (machine coordinates; an import's depth).
    pub stage_z_mm: f64,
    /// F/T normal force, N.
    pub force_n: f64,
}

/// The indentation route: implements [`Residuals`].
#[derive(Debug, Clone)]
pub struct IndentationRoute {
    shape: Shape,
    kind: ModelKind,
    press: f64,
    rows: Vec<IndentRow>,
    noise_n: f64,
    /// Nominal contact z and where it came from.
    contact_z: (f64, String),
    press_from: String,
}

fn shape_of(indenter: IndenterShape) -> Result<Shape, String> {
    match indenter {
        IndenterShape::Hemisphere { diameter_mm } => Ok(Shape::Hemisphere {
            radius_mm: diameter_mm / 2.0,
        }),
        IndenterShape::Flat { diameter_mm } => Ok(Shape::Flat {
            radius_mm: diameter_mm / 2.0,
        }),
        IndenterShape::Point => Err(
            "the plan's indenter is a point, which has no contact law: the indentation route needs a hemisphere or a flat indenter".into(),
        ),
    }
}

fn geometry(run: &RunData) -> Option<(f64, f64)> {
    let g = run.manifest.bench.get("geometry")?;
    let press = g.get("press_direction")?.as_f64()?;
    let z = g.get("surface_z_mm")?.as_f64()?;
    (press != 0.0 && z.is_finite()).then_some((press.signum(), z))
}

impl IndentationRoute {
    /// The route over a loaded run; `Err` says why the run offers no indentation
    /// route (module docs).
    pub fn from_run(run: &RunData, nominal: &Sensor) -> Result<Self, String> {
        let shape = shape_of(run.plan.indenter)?;
        let depth_recorded = run
            .manifest
            .bench
            .pointer("/recorded/depth")
            .and_then(|v| v.as_bool())
            .unwrap_or(true);
        if !depth_recorded {
            return Err("the imported recording has no depth or stage z column: the indentation route needs the indentation depth of every frame".into());
        }
        let fmax = run.rows.iter().map(|r| r.fz_n).fold(0.0, f64::max);
        let rows: Vec<IndentRow> = run
            .rows
            .iter()
            .filter(|r| r.stage_z_mm.is_finite() && r.fz_n.is_finite())
            .filter(|r| r.fz_n > (5.0 * r.fz_sd_n.abs()).max(0.02 * fmax) && r.fz_n > 0.0)
            .map(|r| IndentRow {
                index: r.index,
                trial: r.trial,
                stage_z_mm: r.stage_z_mm,
                force_n: r.fz_n,
            })
            .collect();
        let mut zs: Vec<f64> = rows.iter().map(|r| (r.stage_z_mm * 1e4).round()).collect();
        zs.sort_by(f64::total_cmp);
        zs.dedup();
        if rows.len() < 3 || zs.len() < 2 {
            return Err(format!(
                "{} loaded rows at {} distinct stage z: the indentation route needs normal setpoints at 3 or more depths",
                rows.len(),
                zs.len()
            ));
        }
        let (press, contact_z, press_from) = match geometry(run) {
            Some((press, z)) => (
                press,
                (z, "the bench geometry's surface_z_mm".to_string()),
                "the bench geometry's press_direction".to_string(),
            ),
            None => {
                let press = press_from_data(&rows);
                let z = extrapolated_contact_z(&rows, shape, press)
                    .ok_or("the loaded rows do not extrapolate to a contact z")?;
                (
                    press,
                    (
                        z,
                        "extrapolated from the loaded rows (no bench geometry recorded)"
                            .to_string(),
                    ),
                    "the sign of the correlation of stage z with F_z".to_string(),
                )
            }
        };
        Ok(IndentationRoute {
            shape,
            kind: nominal.elastomer.model,
            press,
            rows,
            noise_n: 1.0,
            contact_z,
            press_from,
        })
    }

    /// The route a plan would give on the nominal sensor: each loaded setpoint's
    /// target normal force at the depth the nominal law needs for it (contact z 0,
    /// pressing towards +z), with the F/T noise of the mean `noise_n`.
    pub fn from_plan(plan: &Plan, sensor: &Sensor, noise_n: f64) -> Result<Self, String> {
        let shape = shape_of(plan.indenter)?;
        let p0 = ModelParams::nominal(sensor, 0.0);
        let mut route = IndentationRoute {
            shape,
            kind: sensor.elastomer.model,
            press: 1.0,
            rows: Vec::new(),
            noise_n: noise_n.max(NOISE_FLOOR_N),
            contact_z: (0.0, "the plan (nominal)".into()),
            press_from: "the plan (nominal)".into(),
        };
        for sp in plan.setpoints() {
            if sp.normal_n <= 0.0 {
                continue;
            }
            let d = route.depth_for(&p0, sp.normal_n).ok_or_else(|| {
                format!("setpoint {}: no depth gives {} N", sp.index, sp.normal_n)
            })?;
            route.rows.push(IndentRow {
                index: sp.index,
                trial: sp.trial,
                stage_z_mm: d,
                force_n: sp.normal_n,
            });
        }
        if route.rows.len() < 3 {
            return Err(format!(
                "{} loaded setpoints: the indentation route needs normal setpoints at 3 or more depths",
                route.rows.len()
            ));
        }
        Ok(route)
    }

    /// The contact law's force at depth `d`, N.
    fn force_at(&self, p: &ModelParams, d: f64) -> f64 {
        let e_star = reduced_modulus(p.young_modulus_kpa * 1e-3, p.poisson_ratio);
        let body = match self.kind {
            ModelKind::BondedLayer => Body::BondedLayer {
                thickness_mm: p.thickness_mm,
            },
            ModelKind::HalfSpace => Body::HalfSpace,
        };
        indentation_force(self.shape, body, e_star, d).force_n
    }

    /// The depth at which the law gives `force_n`, by bisection (the laws increase).
    fn depth_for(&self, p: &ModelParams, force_n: f64) -> Option<f64> {
        let (mut lo, mut hi) = (0.0f64, 0.01f64);
        while self.force_at(p, hi) < force_n {
            lo = hi;
            hi *= 2.0;
            if hi > 1e3 {
                return None;
            }
        }
        for _ in 0..80 {
            let mid = 0.5 * (lo + hi);
            if self.force_at(p, mid) < force_n {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        Some(0.5 * (lo + hi))
    }

    /// Depth past contact of a stage z at the parameters' contact z, mm.
    pub fn depth_mm(&self, p: &ModelParams, stage_z_mm: f64) -> f64 {
        self.press * (stage_z_mm - p.contact_z_mm)
    }

    /// The nominal contact z and where it came from.
    pub fn nominal_contact_z(&self) -> (f64, &str) {
        (self.contact_z.0, &self.contact_z.1)
    }

    /// The rows the route uses.
    pub fn rows(&self) -> &[IndentRow] {
        &self.rows
    }

    /// Sets the noise σ (N) the residuals are divided by (floored at 0.1 mN).
    pub fn set_noise(&mut self, noise_n: f64) {
        self.noise_n = if noise_n.is_finite() {
            noise_n.max(NOISE_FLOOR_N)
        } else {
            1.0
        };
    }

    /// The noise σ, N.
    pub fn noise_n(&self) -> f64 {
        self.noise_n
    }

    /// The route over the rows whose setpoint index `keep` accepts.
    pub fn subset(&self, keep: impl Fn(usize) -> bool) -> IndentationRoute {
        let mut r = self.clone();
        r.rows.retain(|row| keep(row.index));
        r
    }

    /// Measured against fitted force along the depth, for the page:
    /// `[{"depth_mm", "force_n", "predicted_n"}]` sorted by depth.
    pub fn curve(&self, p: &ModelParams) -> serde_json::Value {
        let mut pts: Vec<(f64, f64, f64)> = self
            .rows
            .iter()
            .map(|r| {
                let d = self.depth_mm(p, r.stage_z_mm);
                (d, r.force_n, self.force_at(p, d))
            })
            .collect();
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        serde_json::Value::Array(
            pts.into_iter()
                .map(|(d, f, pr)| json!({"depth_mm": d, "force_n": f, "predicted_n": pr}))
                .collect(),
        )
    }

    /// The route's figures for `fit.json` `routes.indentation`.
    pub fn summary(&self, p: &ModelParams) -> serde_json::Value {
        let res: Vec<f64> = self
            .rows
            .iter()
            .map(|r| self.force_at(p, self.depth_mm(p, r.stage_z_mm)) - r.force_n)
            .collect();
        let rms = (res.iter().map(|v| v * v).sum::<f64>() / res.len().max(1) as f64).sqrt();
        let depths: Vec<f64> = self
            .rows
            .iter()
            .map(|r| self.depth_mm(p, r.stage_z_mm))
            .collect();
        json!({
            "rows": self.rows.len(),
            "law": self.law_name(),
            "press_direction": self.press,
            "press_direction_from": self.press_from,
            "nominal_contact_z_mm": self.contact_z.0,
            "nominal_contact_z_from": self.contact_z.1,
            "noise_n": self.noise_n,
            "residual_rms_n": rms,
            "depth_range_mm": [depths.iter().cloned().fold(f64::INFINITY, f64::min),
                               depths.iter().cloned().fold(f64::NEG_INFINITY, f64::max)],
        })
    }

    fn law_name(&self) -> String {
        let body = match self.kind {
            ModelKind::BondedLayer => "bonded layer (Shull 2002)",
            ModelKind::HalfSpace => "half-space",
        };
        match self.shape {
            Shape::Hemisphere { radius_mm } => {
                format!("hemisphere R = {radius_mm} mm (Hertz), {body}")
            }
            Shape::Flat { radius_mm } => format!("flat punch a = {radius_mm} mm, {body}"),
        }
    }
}

fn press_from_data(rows: &[IndentRow]) -> f64 {
    let n = rows.len() as f64;
    let mz = rows.iter().map(|r| r.stage_z_mm).sum::<f64>() / n;
    let mf = rows.iter().map(|r| r.force_n).sum::<f64>() / n;
    let cov: f64 = rows
        .iter()
        .map(|r| (r.stage_z_mm - mz) * (r.force_n - mf))
        .sum();
    if cov < 0.0 {
        -1.0
    } else {
        1.0
    }
}

/// Where the law's linearised form (`F^{2/3}` for a sphere, `F` for a punch) is zero.
fn extrapolated_contact_z(rows: &[IndentRow], shape: Shape, press: f64) -> Option<f64> {
    let power = match shape {
        Shape::Hemisphere { .. } => 2.0 / 3.0,
        Shape::Flat { .. } => 1.0,
    };
    let pts: Vec<(f64, f64)> = rows
        .iter()
        .map(|r| (r.stage_z_mm, r.force_n.powf(power)))
        .collect();
    let n = pts.len() as f64;
    let (mx, my) = (
        pts.iter().map(|p| p.0).sum::<f64>() / n,
        pts.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    if sxx <= 0.0 || sxy * press <= 0.0 {
        return None;
    }
    let slope = sxy / sxx;
    let z = mx - my / slope;
    z.is_finite().then_some(z)
}

impl Residuals for IndentationRoute {
    fn len(&self) -> usize {
        self.rows.len()
    }

    fn eval(&self, p: &ModelParams, out: &mut [f64]) -> Result<(), String> {
        for (o, r) in out.iter_mut().zip(&self.rows) {
            let d = self.depth_mm(p, r.stage_z_mm);
            *o = (self.force_at(p, d) - r.force_n) / self.noise_n;
        }
        Ok(())
    }

    fn groups(&self) -> Vec<usize> {
        self.rows.iter().map(|r| r.index).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::lm::{levenberg_marquardt, LmOptions};
    use crate::fit::space::ParamId;
    use crate::sensor::paper_sensor;

    fn hertz_route(e_kpa: f64, z0: f64, press: f64) -> IndentationRoute {
        let s = paper_sensor();
        let mut truth = ModelParams::nominal(&s, z0);
        truth.young_modulus_kpa = e_kpa;
        let mut r = IndentationRoute {
            shape: Shape::Hemisphere { radius_mm: 2.5 },
            kind: ModelKind::HalfSpace,
            press,
            rows: Vec::new(),
            noise_n: 1.0,
            contact_z: (0.0, String::new()),
            press_from: String::new(),
        };
        for (i, d) in [0.2, 0.4, 0.6, 0.9, 1.2].iter().enumerate() {
            let z = z0 + press * d;
            r.rows.push(IndentRow {
                index: i,
                trial: 0,
                stage_z_mm: z,
                force_n: r.force_at(&truth, *d),
            });
        }
        r
    }

    #[test]
    fn hertz_data_give_back_their_modulus_and_contact_z() {
        let route = hertz_route(700.0, -30.0, -1.0);
        // Hertz: 4/3 E* sqrt(R) d^1.5 with E* = 0.7/0.75 N/mm^2 at d = 1 mm.
        let p = ModelParams {
            young_modulus_kpa: 700.0,
            ..ModelParams::nominal(&paper_sensor(), -30.0)
        };
        let want = 4.0 / 3.0 * (0.7 / 0.75) * 2.5f64.sqrt();
        assert!((route.force_at(&p, 1.0) - want).abs() < 1e-12);
        let z =
            extrapolated_contact_z(&route.rows, route.shape, press_from_data(&route.rows)).unwrap();
        assert!((z + 30.0).abs() < 1e-9, "{z}");
        let start = ModelParams::nominal(&paper_sensor(), -29.7);
        let fit = levenberg_marquardt(
            &route,
            &start,
            &[ParamId::YoungModulus, ParamId::ContactZ],
            ModelKind::HalfSpace,
            LmOptions::default(),
            &mut |_, _| {},
        )
        .unwrap();
        assert!(
            (fit.params.young_modulus_kpa - 700.0).abs() < 1e-6,
            "{:?}",
            fit.params
        );
        assert!(
            (fit.params.contact_z_mm + 30.0).abs() < 1e-8,
            "{:?}",
            fit.params
        );
    }

    #[test]
    fn the_press_direction_follows_the_force() {
        assert_eq!(press_from_data(&hertz_route(700.0, 5.0, 1.0).rows), 1.0);
        assert_eq!(press_from_data(&hertz_route(700.0, 5.0, -1.0).rows), -1.0);
    }
}
