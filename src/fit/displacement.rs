//! The displacement route of `tactbench fit` (issue 30): the forward model driven by
//! the MEASURED wrench, spread over the indenter's contact, against the tracked marker
//! displacements, compared in pixels.
//!
//! Per setpoint: the F/T force `F_ft` (journal `fx_n, fy_n, fz_n`) is rotated into the
//! sensor frame, `F = R(θ) F_ft` ([`ModelParams::ft_to_sensor`]), and spread over the
//! contact exactly as the simulator renders it ([`crate::sim::contact`]): the
//! hemisphere's Hertz pressure over the contact radius `a = (3PR/4E*)^{1/3}` (capped at
//! R), the flat punch's `P/(2πa√(a²−r²))` over its face, or a point; the tangential
//! traction proportional to the pressure. The contact is centred on the stage's
//! position mapped to the sensor frame as the runner maps it (journal `stage_x_mm,
//! stage_y_mm` minus the sensor origin in stage coordinates, estimated as the median of
//! `stage − plan position` over the rows without a tangential target; the plan's
//! position when there is none) plus `contact_offset_mm`. Markers sit at their tracked
//! reference positions, `x_px · mm_per_px` of their layer, at their layer's depth; the
//! elastic model is the sensor file's `[elastomer] model` (half-space or bonded layer).
//!
//! **Residual** of marker `k` (both components): `(u_pred / mm_per_px − u_meas_px) / σ`,
//! pixels over the tracking noise `σ` of its layer. The pixel values are the run's
//! tracked displacements (`displacements/NNNNN.csv`, status ok: a marker lost in any
//! frame of the setpoint is left out; the mean over the frames) divided by the run's
//! `[camera] mm_per_px` (with a `run --camera` calibration the px are the calibrated
//! mm divided by that scale).
//!
//! **Tracking noise σ**, per layer, from the data: with several frames per setpoint
//! the pooled frame-to-frame scatter of the ok markers, divided by √frames (the noise
//! of the mean the route compares); with one frame, 1.4826 × the median absolute
//! residual at the nominal parameters of the far-field markers (nominal predicted
//! displacement below 5 % of the setpoint's largest in that layer, and every marker of
//! unloaded setpoints), where model errors are smallest. Floor 0.002 px.
//!
//! **Speed.** `u ∝ 1/E` at fixed ν and h: the elastic model is built at the nominal E
//! and scaled, so a change of E never rebuilds the bonded layer's tables (those are
//! cached process-wide by (E, ν, h, depth); a new h or depth builds one table per
//! marker depth). The bonded layer's response is tabulated along the distance once
//! per evaluation ([`RadialTable`]). Measured (`cargo run --example
//! fit_displacement_eval`, dev profile = crate opt-level 1, loaded 2-core machine):
//! 160 setpoints × 260 markers (83 200 residuals) 16 ms per eval for the half-space,
//! 61 ms for a 10 mm bonded layer, 98 ms when h changes every eval (new tables). The contact's quadrature is chosen
//! once per (setpoint, marker) at the nominal parameters so the residuals stay smooth
//! in every parameter: markers nearer than 4 contact radii (3-D distance) get a
//! 6 × 16 polar Gauss rule, those nearer than 15 radii a 6-point ring at the
//! pressure's RMS radius (second moment exact), the rest the resultant at the centre.

use std::path::Path;

use serde_json::json;

use super::{FitError, ModelParams, Residuals};
use crate::analysis::{displacements_path, RunData};
use crate::bench::plan::{IndenterShape, Plan};
use crate::model::{BondedLayer, ElasticModel, HalfSpace, MarkerSite, PointResponse};
use crate::sensor::{ModelKind, Sensor};

/// One marker's observation: reference position and mean displacement in pixels
/// relative to the sensor-frame origin (the run's mm divided by the run's scale).
#[derive(Debug, Clone, PartialEq)]
pub struct MarkerObs {
    /// Layer index (sensor file order).
    pub layer: usize,
    /// Marker id within the layer.
    pub marker: u64,
    /// Reference position, px from the sensor-frame origin.
    pub ref_px: [f64; 2],
    /// Measured displacement, px.
    pub u_px: [f64; 2],
    /// Quadrature tier (0 point, 1 ring, 2 full), fixed at construction.
    tier: u8,
}

impl MarkerObs {
    /// A marker observation (reference position and displacement in px from the
    /// sensor-frame origin at the run's scale).
    pub fn new(layer: usize, marker: u64, ref_px: [f64; 2], u_px: [f64; 2]) -> Self {
        MarkerObs {
            layer,
            marker,
            ref_px,
            u_px,
            tier: 0,
        }
    }
}

/// One setpoint's data.
#[derive(Debug, Clone, PartialEq)]
pub struct SetpointObs {
    /// Setpoint index (journal `index`).
    pub index: usize,
    /// Trial (journal `trial`).
    pub trial: usize,
    /// Contact centre at zero offset, sensor frame, mm.
    pub centre_mm: [f64; 2],
    /// The F/T force as read (F/T frame), N.
    pub f_ft_n: [f64; 3],
    /// The markers that carry data.
    pub markers: Vec<MarkerObs>,
}

/// The displacement route: implements [`Residuals`] for the least-squares engine.
#[derive(Debug, Clone)]
pub struct DisplacementRoute {
    kind: ModelKind,
    indenter: IndenterShape,
    layer_names: Vec<String>,
    /// E the elastic model is built at, N/mm² (u scales as e_ref / E).
    e_ref: f64,
    setpoints: Vec<SetpointObs>,
    /// Tracking noise per layer, px.
    noise_px: Vec<f64>,
    noise_method: String,
    /// Setpoints left out, with why.
    skipped: Vec<(usize, String)>,
    full: Vec<([f64; 2], f64)>,
    ring: Vec<([f64; 2], f64)>,
    len: usize,
}

/// Gauss–Legendre nodes and weights on [lo, hi].
fn gauss_legendre(n: usize, lo: f64, hi: f64) -> Vec<(f64, f64)> {
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        let mut dp = 1.0;
        for _ in 0..100 {
            let (mut p0, mut p1) = (1.0, x);
            for k in 2..=n {
                let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                p0 = p1;
                p1 = p2;
            }
            dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
            let dx = p1 / dp;
            x -= dx;
            if dx.abs() < 1e-15 {
                break;
            }
        }
        let w = 2.0 / ((1.0 - x * x) * dp * dp);
        out.push((0.5 * (hi - lo) * x + 0.5 * (hi + lo), 0.5 * (hi - lo) * w));
    }
    out
}

/// The quadrature of the unit contact disc for a pressure profile: a polar rule
/// (Gauss in φ with ρ = sin φ, the load density `dP/dφ` as weight; equal sectors),
/// and the 6-point ring at the RMS radius.
#[allow(clippy::type_complexity)]
fn disc_rules(hertz: bool) -> (Vec<([f64; 2], f64)>, Vec<([f64; 2], f64)>) {
    let (nr, ns) = (6, 16);
    let mut full = Vec::with_capacity(nr * ns);
    let mut m2 = 0.0;
    let mut total = 0.0;
    for (j, (phi, w)) in gauss_legendre(nr, 0.0, std::f64::consts::FRAC_PI_2)
        .into_iter()
        .enumerate()
    {
        let dens = if hertz {
            3.0 * phi.cos().powi(2) * phi.sin()
        } else {
            phi.sin()
        };
        let rho = phi.sin();
        total += w * dens;
        m2 += w * dens * rho * rho;
        for s in 0..ns {
            let th = (s as f64 + 0.5 * (j % 2) as f64) * 2.0 * std::f64::consts::PI / ns as f64;
            full.push(([rho * th.cos(), rho * th.sin()], w * dens / ns as f64));
        }
    }
    for f in &mut full {
        f.1 /= total;
    }
    let r = (m2 / total).sqrt();
    let ring = (0..6)
        .map(|s| {
            let th = s as f64 * std::f64::consts::PI / 3.0;
            ([r * th.cos(), r * th.sin()], 1.0 / 6.0)
        })
        .collect();
    (full, ring)
}

/// What varies per evaluation, resolved from the parameters once.
struct Resolved {
    scale: f64,
    e_star: f64,
    depth: Vec<f64>,
    mm_per_px: Vec<f64>,
}

impl DisplacementRoute {
    /// The route over a run directory, with the nominal sensor file the fit starts
    /// from (its model kind and layers; the run's own sensor file gives the scale the
    /// displacements were tracked with). Failed rows, rows without a displacement file
    /// and markers not ok are skipped and counted ([`Self::skipped`]).
    pub fn from_run(run_dir: &Path, nominal: &Sensor) -> Result<Self, FitError> {
        let input = |message: String| FitError::Input {
            path: run_dir.to_path_buf(),
            message,
        };
        let run = RunData::load(run_dir).map_err(|e| input(e.to_string()))?;
        let names = |s: &Sensor| s.layers.iter().map(|l| l.name.clone()).collect::<Vec<_>>();
        if names(nominal) != names(&run.sensor) {
            return Err(input(format!(
                "the sensor file's layers ({}) do not match the run's sensor ({}): give the sensor file the run was made with",
                names(nominal).join(", "),
                names(&run.sensor).join(", ")
            )));
        }
        let s_run = run.sensor.camera.mm_per_px;
        let mut skipped: Vec<(usize, String)> =
            run.failed.iter().map(|f| (f.index, f.describe())).collect();
        // The runner's sensor origin in stage coordinates, from the normal-only rows.
        let mut ox = Vec::new();
        let mut oy = Vec::new();
        for r in &run.rows {
            let sp = &run.setpoints[r.index];
            if sp.tangential_n == [0.0, 0.0] {
                ox.push(r.stage_x_mm - sp.position_mm[0]);
                oy.push(r.stage_y_mm - sp.position_mm[1]);
            }
        }
        let origin = (!ox.is_empty()).then(|| [median(&mut ox), median(&mut oy)]);
        let nl = run.sensor.layers.len();
        let (mut ss, mut dof) = (vec![0.0; nl], vec![0usize; nl]);
        let mut frames_seen = 1usize;
        let mut setpoints = Vec::new();
        for r in &run.rows {
            let path = displacements_path(run_dir, r.index);
            if !path.is_file() {
                skipped.push((r.index, format!("{}: no displacement file", path.display())));
                continue;
            }
            let frames = run
                .displacements(r.index)
                .map_err(|e| input(e.to_string()))?;
            frames_seen = frames_seen.max(frames.len());
            let nf = frames.len() as f64;
            let mut markers = Vec::new();
            for (i, rec) in frames[0].records.iter().enumerate() {
                let us: Option<Vec<[f64; 2]>> = frames
                    .iter()
                    .map(|f| {
                        f.records
                            .get(i)
                            .filter(|x| x.marker == rec.marker && x.layer == rec.layer)
                            .and_then(|x| x.u_mm)
                    })
                    .collect();
                let Some(us) = us else { continue };
                let mean = [0, 1].map(|a| us.iter().map(|u| u[a]).sum::<f64>() / nf);
                if us.len() > 1 {
                    for u in &us {
                        ss[rec.layer] += (u[0] - mean[0]).powi(2) + (u[1] - mean[1]).powi(2);
                    }
                    dof[rec.layer] += 2 * (us.len() - 1);
                }
                markers.push(MarkerObs {
                    layer: rec.layer,
                    marker: rec.marker,
                    ref_px: [rec.position_mm[0] / s_run, rec.position_mm[1] / s_run],
                    u_px: [mean[0] / s_run, mean[1] / s_run],
                    tier: 0,
                });
            }
            if markers.is_empty() {
                skipped.push((r.index, format!("{}: no marker tracked ok", path.display())));
                continue;
            }
            let sp = &run.setpoints[r.index];
            let centre_mm = match origin {
                Some(o) => [r.stage_x_mm - o[0], r.stage_y_mm - o[1]],
                None => sp.position_mm,
            };
            setpoints.push(SetpointObs {
                index: r.index,
                trial: r.trial,
                centre_mm,
                f_ft_n: [r.fx_n, r.fy_n, r.fz_n],
                markers,
            });
        }
        if setpoints.is_empty() {
            return Err(FitError::NotEnoughData(format!(
                "{}: no setpoint has tracked displacements ({} journal rows, {} skipped): the displacement route needs displacements/NNNNN.csv with markers tracked ok",
                run_dir.display(),
                run.journalled(),
                skipped.len()
            )));
        }
        let mut route = Self::assemble(
            run.plan.indenter,
            nominal,
            setpoints,
            vec![1.0; nl],
            skipped,
        )?;
        let p0 = ModelParams {
            mm_per_px: vec![s_run; nl],
            ..ModelParams::nominal(nominal, 0.0)
        };
        if frames_seen > 1 && dof.iter().all(|d| *d > 0) {
            route.noise_px = (0..nl)
                .map(|l| {
                    ((ss[l] / dof[l] as f64).sqrt() / (frames_seen as f64).sqrt() / s_run)
                        .max(NOISE_FLOOR_PX)
                })
                .collect();
            route.noise_method = format!(
                "pooled frame-to-frame scatter of the ok markers over {frames_seen} frames per setpoint, / sqrt(frames)"
            );
        } else {
            route.noise_px = route.far_field_noise(&p0)?;
            route.noise_method =
                "1.4826 x median absolute residual of the far-field markers at the nominal parameters (one frame per setpoint)".into();
        }
        Ok(route)
    }

    /// The route a plan would give on the nominal sensor: every loaded setpoint's
    /// target force at its position, the sensor's grid markers, "measured"
    /// displacements predicted at the nominal parameters, and the given tracking
    /// noise (px). For `fit --predict`: the engine's Jacobian at the nominal values
    /// gives the intervals the plan can expect.
    pub fn from_plan(
        plan: &Plan,
        sensor: &Sensor,
        tracking_noise_px: f64,
    ) -> Result<Self, FitError> {
        if !(tracking_noise_px.is_finite() && tracking_noise_px > 0.0) {
            return Err(FitError::Input {
                path: plan.path.clone(),
                message: format!(
                    "tracking noise {tracking_noise_px} px must be a finite number > 0"
                ),
            });
        }
        let s0 = sensor.camera.mm_per_px;
        let sites = MarkerSite::from_sensor_grids(sensor);
        let mut ids = Vec::new();
        for (li, l) in sensor.layers.iter().enumerate() {
            if let Some(m) = &l.markers {
                ids.extend((0..m.grid.len() as u64).map(|k| (li, k)));
            }
        }
        let mut skipped = Vec::new();
        let mut setpoints = Vec::new();
        for sp in plan.setpoints() {
            if sp.normal_n <= 0.0 {
                skipped.push((sp.index, format!("setpoint {}: no load", sp.index)));
                continue;
            }
            let markers = sites
                .iter()
                .zip(&ids)
                .map(|(s, &(layer, marker))| MarkerObs {
                    layer,
                    marker,
                    ref_px: [s.position_mm[0] / s0, s.position_mm[1] / s0],
                    u_px: [0.0, 0.0],
                    tier: 0,
                })
                .collect();
            setpoints.push(SetpointObs {
                index: sp.index,
                trial: sp.trial,
                centre_mm: sp.position_mm,
                f_ft_n: [sp.tangential_n[0], sp.tangential_n[1], sp.normal_n],
                markers,
            });
        }
        if setpoints.is_empty() {
            return Err(FitError::NotEnoughData(format!(
                "{}: no setpoint loads the sensor: the displacement route needs loaded setpoints",
                plan.path.display()
            )));
        }
        let nl = sensor.layers.len();
        let mut route = Self::assemble(
            plan.indenter,
            sensor,
            setpoints,
            vec![tracking_noise_px; nl],
            skipped,
        )?;
        route.noise_method = "given (the bench's or scene's tracking noise)".into();
        let p0 = ModelParams::nominal(sensor, 0.0);
        let pred = route.predict_px(&p0).map_err(FitError::Numerical)?;
        let mut k = 0;
        for sp in &mut route.setpoints {
            for m in &mut sp.markers {
                m.u_px = [pred[k], pred[k + 1]];
                k += 2;
            }
        }
        Ok(route)
    }

    /// A route over observations made elsewhere (an import, a test), with the
    /// tracking noise per layer (px).
    pub fn from_observations(
        indenter: IndenterShape,
        nominal: &Sensor,
        setpoints: Vec<SetpointObs>,
        noise_px: Vec<f64>,
    ) -> Result<Self, FitError> {
        if noise_px.len() != nominal.layers.len()
            || noise_px.iter().any(|v| !(v.is_finite() && *v > 0.0))
        {
            return Err(FitError::NotEnoughData(format!(
                "tracking noise {noise_px:?} px: one finite value > 0 per layer"
            )));
        }
        let mut r = Self::assemble(indenter, nominal, setpoints, noise_px, Vec::new())?;
        r.noise_method = "given".into();
        Ok(r)
    }

    fn assemble(
        indenter: IndenterShape,
        nominal: &Sensor,
        mut setpoints: Vec<SetpointObs>,
        noise_px: Vec<f64>,
        skipped: Vec<(usize, String)>,
    ) -> Result<Self, FitError> {
        let (full, ring) = disc_rules(matches!(indenter, IndenterShape::Hemisphere { .. }));
        let e_ref = nominal.elastomer.young_modulus_n_per_mm2();
        let p0 = ModelParams::nominal(nominal, 0.0);
        let e_star = e_ref / (1.0 - p0.poisson_ratio.powi(2));
        // Tiers at the nominal geometry (fixed: residuals stay smooth in the parameters).
        for sp in &mut setpoints {
            let a = contact_radius(indenter, sp.f_ft_n[2].max(0.0), e_star);
            for m in &mut sp.markers {
                let s = nominal.camera.mm_per_px;
                let d = [
                    m.ref_px[0] * s - sp.centre_mm[0],
                    m.ref_px[1] * s - sp.centre_mm[1],
                ];
                let z = nominal.layers[m.layer].depth_mm;
                let r = (d[0] * d[0] + d[1] * d[1] + z * z).sqrt();
                m.tier = if a <= 0.0 || r >= 15.0 * a {
                    0
                } else if r >= 4.0 * a {
                    1
                } else {
                    2
                };
            }
        }
        let len = setpoints.iter().map(|s| 2 * s.markers.len()).sum();
        Ok(DisplacementRoute {
            kind: nominal.elastomer.model,
            indenter,
            layer_names: nominal.layers.iter().map(|l| l.name.clone()).collect(),
            e_ref,
            setpoints,
            noise_px,
            noise_method: String::new(),
            skipped,
            full,
            ring,
            len,
        })
    }

    /// The index of the layer named `name`.
    pub fn layer_index(&self, name: &str) -> Option<usize> {
        self.layer_names.iter().position(|l| l == name)
    }

    /// The setpoints the route uses.
    pub fn setpoints(&self) -> &[SetpointObs] {
        &self.setpoints
    }

    /// Setpoints left out (index, why).
    pub fn skipped(&self) -> &[(usize, String)] {
        &self.skipped
    }

    /// Tracking noise per layer, px, and how it was estimated.
    pub fn noise_px(&self) -> (&[f64], &str) {
        (&self.noise_px, &self.noise_method)
    }

    /// The indenter whose contact spreads the wrench.
    pub fn indenter(&self) -> IndenterShape {
        self.indenter
    }

    /// A copy restricted to the setpoints whose index `keep` accepts (the tracking
    /// noise is kept: cross-validation folds fit on the rest).
    pub fn subset(&self, keep: impl Fn(usize) -> bool) -> DisplacementRoute {
        let mut r = self.clone();
        r.setpoints.retain(|s| keep(s.index));
        r.len = r.setpoints.iter().map(|s| 2 * s.markers.len()).sum();
        r
    }

    fn resolve(&self, p: &ModelParams) -> Result<Resolved, String> {
        let nl = self.layer_names.len();
        if p.depth_mm.len() != nl || p.mm_per_px.len() != nl {
            return Err(format!(
                "{} depths and {} scales for {nl} layers",
                p.depth_mm.len(),
                p.mm_per_px.len()
            ));
        }
        let e = crate::units::kpa_to_n_per_mm2(p.young_modulus_kpa);
        if !(e.is_finite() && e > 0.0) {
            return Err(format!(
                "young_modulus_kpa = {} must be > 0",
                p.young_modulus_kpa
            ));
        }
        if !(p.poisson_ratio.is_finite() && (0.0..=0.5).contains(&p.poisson_ratio)) {
            return Err(format!(
                "poisson_ratio = {} must be in [0, 0.5]",
                p.poisson_ratio
            ));
        }
        for (name, (d, s)) in self
            .layer_names
            .iter()
            .zip(p.depth_mm.iter().zip(&p.mm_per_px))
        {
            if !(d.is_finite() && *d > 0.0) {
                return Err(format!("depth_mm.{name} = {d} must be > 0 mm"));
            }
            if self.kind == ModelKind::BondedLayer && *d >= p.thickness_mm {
                return Err(format!(
                    "depth_mm.{name} = {d} mm is not inside the {} mm layer",
                    p.thickness_mm
                ));
            }
            if !(s.is_finite() && *s > 0.0) {
                return Err(format!("mm_per_px.{name} = {s} must be > 0"));
            }
        }
        for v in [
            p.ft_rotation_deg,
            p.contact_offset_mm[0],
            p.contact_offset_mm[1],
        ] {
            if !v.is_finite() {
                return Err(format!("mounting parameter {v} is not finite"));
            }
        }
        Ok(Resolved {
            scale: self.e_ref / e,
            e_star: e / (1.0 - p.poisson_ratio.powi(2)),
            depth: p.depth_mm.clone(),
            mm_per_px: p.mm_per_px.clone(),
        })
    }

    /// Predicted displacements in px, interleaved per marker in setpoint order (the
    /// residual order).
    pub fn predict_px(&self, p: &ModelParams) -> Result<Vec<f64>, String> {
        let mut out = vec![0.0; self.len];
        self.predict_into(p, &mut out)?;
        Ok(out)
    }

    fn predict_into(&self, p: &ModelParams, out: &mut [f64]) -> Result<(), String> {
        let r = self.resolve(p)?;
        let half = HalfSpace::new(self.e_ref, p.poisson_ratio).map_err(|e| e.to_string())?;
        match self.kind {
            ModelKind::HalfSpace => {
                let z = r.depth.clone();
                self.predict_with(|dx, dy, l| half.point_response(dx, dy, z[l]), p, &r, out)
            }
            ModelKind::BondedLayer => {
                let layer = BondedLayer::new(self.e_ref, p.poisson_ratio, p.thickness_mm)
                    .map_err(|e| e.to_string())?;
                let reach = self.reach_mm(p, &r);
                layer
                    .check_reach(&r.depth, reach)
                    .map_err(|e| e.to_string())?;
                layer.prepare(&r.depth, reach);
                let tables: Vec<RadialTable> = r
                    .depth
                    .iter()
                    .map(|&z| RadialTable::new(&layer, z, reach))
                    .collect();
                self.predict_with(|dx, dy, l| tables[l].response(dx, dy), p, &r, out)
            }
        }
    }

    /// The largest marker–load distance, mm (for the layer's tables).
    fn reach_mm(&self, p: &ModelParams, r: &Resolved) -> f64 {
        let mut reach: f64 = 0.0;
        for sp in &self.setpoints {
            let f = p.ft_to_sensor(sp.f_ft_n);
            let a = contact_radius(self.indenter, f[2].max(0.0), r.e_star);
            let c = [
                sp.centre_mm[0] + p.contact_offset_mm[0],
                sp.centre_mm[1] + p.contact_offset_mm[1],
            ];
            for m in &sp.markers {
                let s = r.mm_per_px[m.layer];
                reach = reach.max((m.ref_px[0] * s - c[0]).hypot(m.ref_px[1] * s - c[1]) + a);
            }
        }
        reach
    }

    fn predict_with(
        &self,
        response: impl Fn(f64, f64, usize) -> PointResponse,
        p: &ModelParams,
        r: &Resolved,
        out: &mut [f64],
    ) -> Result<(), String> {
        let point = [([0.0, 0.0], 1.0)];
        let mut k = 0;
        for sp in &self.setpoints {
            let f = p.ft_to_sensor(sp.f_ft_n);
            let a = contact_radius(self.indenter, f[2].max(0.0), r.e_star);
            let c = [
                sp.centre_mm[0] + p.contact_offset_mm[0],
                sp.centre_mm[1] + p.contact_offset_mm[1],
            ];
            for m in &sp.markers {
                let s = r.mm_per_px[m.layer];
                let x = [m.ref_px[0] * s - c[0], m.ref_px[1] * s - c[1]];
                let rule: &[([f64; 2], f64)] = match m.tier {
                    _ if a <= 0.0 => &point,
                    0 => &point,
                    1 => &self.ring,
                    _ => &self.full,
                };
                let mut acc = [0.0; 2];
                for (xi, w) in rule {
                    let h = response(x[0] - a * xi[0], x[1] - a * xi[1], m.layer);
                    acc[0] += w * (h[0][0] * f[0] + h[0][1] * f[1] + h[0][2] * f[2]);
                    acc[1] += w * (h[1][0] * f[0] + h[1][1] * f[1] + h[1][2] * f[2]);
                }
                out[k] = acc[0] * r.scale / s;
                out[k + 1] = acc[1] * r.scale / s;
                k += 2;
            }
        }
        if out.iter().any(|v| !v.is_finite()) {
            return Err("the forward model gave a non-finite displacement".into());
        }
        Ok(())
    }

    /// `∂r/∂F` for each F/T axis: how the noise-normalised residuals move per newton
    /// of the F/T reading, by forward differences of 1 mN. Every setpoint's force is
    /// perturbed at once: a setpoint's prediction depends on its own force only, so
    /// one evaluation per axis gives every setpoint's column.
    pub fn force_sensitivity(&self, p: &ModelParams) -> Result<[Vec<f64>; 3], String> {
        let base = self.predict_px(p)?;
        let h = 1e-3;
        let mut out: [Vec<f64>; 3] = Default::default();
        for (axis, col) in out.iter_mut().enumerate() {
            let mut moved = self.clone();
            for sp in &mut moved.setpoints {
                sp.f_ft_n[axis] += h;
            }
            let pred = moved.predict_px(p)?;
            let mut g = Vec::with_capacity(self.len);
            for sp in &self.setpoints {
                for m in &sp.markers {
                    let k = g.len();
                    let s = self.noise_px[m.layer] * h;
                    g.push((pred[k] - base[k]) / s);
                    g.push((pred[k + 1] - base[k + 1]) / s);
                }
            }
            *col = g;
        }
        Ok(out)
    }

    /// Per-layer noise from the far-field markers at `p0` (see the module docs).
    fn far_field_noise(&self, p0: &ModelParams) -> Result<Vec<f64>, FitError> {
        let pred = self.predict_px(p0).map_err(FitError::Numerical)?;
        let nl = self.layer_names.len();
        let mut per_layer: Vec<Vec<f64>> = vec![Vec::new(); nl];
        let mut all: Vec<Vec<f64>> = vec![Vec::new(); nl];
        let mut k = 0;
        for sp in &self.setpoints {
            let n = sp.markers.len();
            let mut peak = vec![0.0f64; nl];
            for (i, m) in sp.markers.iter().enumerate() {
                peak[m.layer] = peak[m.layer].max(pred[k + 2 * i].hypot(pred[k + 2 * i + 1]));
            }
            for (i, m) in sp.markers.iter().enumerate() {
                let pr = [pred[k + 2 * i], pred[k + 2 * i + 1]];
                let res = [pr[0] - m.u_px[0], pr[1] - m.u_px[1]];
                all[m.layer].extend(res.iter().map(|v| v.abs()));
                if pr[0].hypot(pr[1]) <= 0.05 * peak[m.layer] || peak[m.layer] == 0.0 {
                    per_layer[m.layer].extend(res.iter().map(|v| v.abs()));
                }
            }
            k += 2 * n;
        }
        Ok((0..nl)
            .map(|l| {
                let v = if per_layer[l].len() >= 20 {
                    &mut per_layer[l]
                } else {
                    &mut all[l]
                };
                if v.is_empty() {
                    NOISE_FLOOR_PX
                } else {
                    (1.4826 * median(v)).max(NOISE_FLOOR_PX)
                }
            })
            .collect())
    }

    /// `∂r/∂g` of each residual for a displacement gain `g` of its layer's tracking
    /// (measured = (1 + g) × true): `−u_pred/σ` at `p`, with the layer index of each
    /// residual (the order of [`Residuals::eval`]).
    pub fn gain_sensitivity(&self, p: &ModelParams) -> Result<Vec<(usize, f64)>, String> {
        let pred = self.predict_px(p)?;
        let mut out = Vec::with_capacity(self.len);
        let mut k = 0;
        for sp in &self.setpoints {
            for m in &sp.markers {
                let s = self.noise_px[m.layer];
                out.push((m.layer, -pred[k] / s));
                out.push((m.layer, -pred[k + 1] / s));
                k += 2;
            }
        }
        Ok(out)
    }

    /// Residual RMS in px at `p`: per setpoint `(index, rms)` and per layer
    /// `(name, rms)` (layers without markers are left out).
    #[allow(clippy::type_complexity)]
    pub fn residual_rms_px(
        &self,
        p: &ModelParams,
    ) -> Result<(Vec<(usize, f64)>, Vec<(String, f64)>), String> {
        let pred = self.predict_px(p)?;
        let nl = self.layer_names.len();
        let (mut ls, mut ln) = (vec![0.0; nl], vec![0usize; nl]);
        let mut per_sp = Vec::with_capacity(self.setpoints.len());
        let mut k = 0;
        for sp in &self.setpoints {
            let mut s = 0.0;
            for m in &sp.markers {
                let d = (pred[k] - m.u_px[0]).powi(2) + (pred[k + 1] - m.u_px[1]).powi(2);
                s += d;
                ls[m.layer] += d;
                ln[m.layer] += 2;
                k += 2;
            }
            per_sp.push((sp.index, (s / (2 * sp.markers.len()) as f64).sqrt()));
        }
        let per_layer = (0..nl)
            .filter(|l| ln[*l] > 0)
            .map(|l| (self.layer_names[l].clone(), (ls[l] / ln[l] as f64).sqrt()))
            .collect();
        Ok((per_sp, per_layer))
    }

    /// Measured against predicted displacement vectors (px) of the setpoints with the
    /// `n` largest F/T forces, for the page: `[{"index", "trial", "force_n",
    /// "markers": [{"layer", "marker", "x_px", "y_px", "measured_px": [..],
    /// "predicted_px": [..]}]}]`.
    pub fn vectors(&self, p: &ModelParams, n: usize) -> Result<serde_json::Value, String> {
        let pred = self.predict_px(p)?;
        let mut offsets = Vec::with_capacity(self.setpoints.len());
        let mut k = 0;
        for sp in &self.setpoints {
            offsets.push(k);
            k += 2 * sp.markers.len();
        }
        let mut order: Vec<usize> = (0..self.setpoints.len()).collect();
        let norm = |f: [f64; 3]| (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt();
        order.sort_by(|a, b| {
            norm(self.setpoints[*b].f_ft_n).total_cmp(&norm(self.setpoints[*a].f_ft_n))
        });
        let out: Vec<_> = order
            .into_iter()
            .take(n)
            .map(|i| {
                let sp = &self.setpoints[i];
                let markers: Vec<_> = sp
                    .markers
                    .iter()
                    .enumerate()
                    .map(|(j, m)| {
                        let o = offsets[i] + 2 * j;
                        json!({"layer": self.layer_names[m.layer], "marker": m.marker,
                               "x_px": m.ref_px[0], "y_px": m.ref_px[1],
                               "measured_px": m.u_px, "predicted_px": [pred[o], pred[o + 1]]})
                    })
                    .collect();
                json!({"index": sp.index, "trial": sp.trial, "force_n": sp.f_ft_n, "markers": markers})
            })
            .collect();
        Ok(serde_json::Value::Array(out))
    }

    /// The route's summary for `fit.json` `routes.displacement`.
    pub fn summary(&self, p: &ModelParams) -> Result<serde_json::Value, String> {
        let (_, per_layer) = self.residual_rms_px(p)?;
        let noise: serde_json::Map<_, _> = self
            .layer_names
            .iter()
            .zip(&self.noise_px)
            .map(|(n, v)| (n.clone(), json!(v)))
            .collect();
        Ok(json!({
            "setpoints": self.setpoints.len(),
            "markers": self.len / 2,
            "skipped": self.skipped.iter().map(|(i, w)| json!({"index": i, "reason": w})).collect::<Vec<_>>(),
            "tracking_noise_px": noise,
            "tracking_noise_method": self.noise_method,
            "residual_rms_px": per_layer
                .into_iter()
                .map(|(k, v)| (k, json!(v)))
                .collect::<serde_json::Map<_, _>>(),
        }))
    }
}

/// An axisymmetric model's horizontal response at one depth, tabulated along the
/// distance ρ once per evaluation (the bonded layer's own lookup per call costs ~10×
/// the half-space's closed form). Stored along +x: `a = h_xx`, `b = h_yy`, `c = h_xz`
/// at `(ρ, 0)`; elsewhere, with `ê = (dx, dy)/ρ`: `h_ab = b δ_ab − ê_a ê_b (b − a)`,
/// `h_az = ê_a c` (the layer's `I₀, I₁, I₂` structure). Rows from ρ = −Δ (parity:
/// `a, b` even, `c` odd), Δ = depth / 50, 4-point Lagrange cubics: relative error
/// ~1e-7 of the field (test `the_bonded_layer_table_matches_the_direct_response`).
struct RadialTable {
    step: f64,
    rows: Vec<[f64; 3]>,
}

impl RadialTable {
    fn new<M: ElasticModel>(model: &M, z: f64, reach: f64) -> Self {
        let step = z / 50.0;
        let n = (reach / step).ceil() as usize + 5;
        let rows = (0..n)
            .map(|i| {
                let h = model.point_response((i as f64 - 1.0) * step, 0.0, z);
                [h[0][0], h[1][1], h[0][2]]
            })
            .collect();
        RadialTable { step, rows }
    }

    fn response(&self, dx: f64, dy: f64) -> PointResponse {
        let rho = dx.hypot(dy);
        let t = rho / self.step + 1.0;
        let i = (t.floor() as usize).clamp(1, self.rows.len() - 3);
        let x = t - i as f64;
        // Lagrange weights on nodes i−1, i, i+1, i+2 at offset x from node i.
        let w = [
            -x * (x - 1.0) * (x - 2.0) / 6.0,
            (x + 1.0) * (x - 1.0) * (x - 2.0) / 2.0,
            -(x + 1.0) * x * (x - 2.0) / 2.0,
            (x + 1.0) * x * (x - 1.0) / 6.0,
        ];
        let mut v = [0.0; 3];
        for (k, wk) in w.iter().enumerate() {
            for (vj, rj) in v.iter_mut().zip(&self.rows[i - 1 + k]) {
                *vj += wk * rj;
            }
        }
        let (ex, ey) = if rho > 0.0 {
            (dx / rho, dy / rho)
        } else {
            (1.0, 0.0)
        };
        let d = v[1] - v[0];
        [
            [v[1] - ex * ex * d, -ex * ey * d, ex * v[2]],
            [-ex * ey * d, v[1] - ey * ey * d, ey * v[2]],
        ]
    }
}

/// σ of the tracker's displacement gain per layer, in the intervals
/// ([`crate::fit::force_error`]): a tracked displacement is `(1 + g)` times the true
/// one. Measured on the calibration plan's rendered frames without noise (tracked
/// against the simulator's true displacements, least-squares slope per setpoint and
/// layer): +0.03 % to +0.76 %, largest at the smallest displacements (0.1 px RMS).
/// With the true displacements in place of the tracked ones, the bias it leaves in
/// the thin gel's thickness (+0.008 mm at ±0.003 mm without it) disappears.
pub const TRACKING_GAIN_SD: f64 = 0.005;

/// Smallest tracking noise the route assumes, px.
pub const NOISE_FLOOR_PX: f64 = 0.002;

/// Contact radius for a normal force `p` (N) at reduced modulus `e_star` (N/mm²).
fn contact_radius(indenter: IndenterShape, p: f64, e_star: f64) -> f64 {
    match indenter {
        IndenterShape::Flat { diameter_mm } => 0.5 * diameter_mm,
        IndenterShape::Hemisphere { diameter_mm } => {
            let r = 0.5 * diameter_mm;
            (3.0 * p * r / (4.0 * e_star)).cbrt().min(r)
        }
        IndenterShape::Point => 0.0,
    }
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

impl Residuals for DisplacementRoute {
    fn len(&self) -> usize {
        self.len
    }

    fn groups(&self) -> Vec<usize> {
        self.setpoints
            .iter()
            .flat_map(|sp| std::iter::repeat_n(sp.index, 2 * sp.markers.len()))
            .collect()
    }

    fn marker_groups(&self) -> Vec<usize> {
        self.setpoints
            .iter()
            .flat_map(|sp| {
                sp.markers.iter().flat_map(|m| {
                    let key = (m.layer << 40) | (m.marker as usize & ((1 << 40) - 1));
                    [key, key]
                })
            })
            .collect()
    }

    fn eval(&self, p: &ModelParams, out: &mut [f64]) -> Result<(), String> {
        if out.len() != self.len {
            return Err(format!(
                "{} residual slots for {} residuals",
                out.len(),
                self.len
            ));
        }
        self.predict_into(p, out)?;
        let mut k = 0;
        for sp in &self.setpoints {
            for m in &sp.markers {
                let s = self.noise_px[m.layer];
                out[k] = (out[k] - m.u_px[0]) / s;
                out[k + 1] = (out[k + 1] - m.u_px[1]) / s;
                k += 2;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::paper_sensor;
    use crate::sim::contact::{Indenter, LoadCase, Normal, Tangential};
    use crate::sim::effects::Pipeline;
    use crate::sim::simulate::Simulation;

    /// A route over hand-made setpoints (measured = 0), noise 1 px.
    fn route(indenter: IndenterShape, sensor: &Sensor, sps: Vec<SetpointObs>) -> DisplacementRoute {
        let nl = sensor.layers.len();
        DisplacementRoute::assemble(indenter, sensor, sps, vec![1.0; nl], Vec::new()).unwrap()
    }

    fn marker(layer: usize, pos_mm: [f64; 2], s: f64) -> MarkerObs {
        MarkerObs {
            layer,
            marker: 0,
            ref_px: [pos_mm[0] / s, pos_mm[1] / s],
            u_px: [0.0, 0.0],
            tier: 0,
        }
    }

    #[test]
    fn a_point_load_through_the_route_matches_boussinesq_and_cerruti_at_nu_one_half() {
        // Independent closed forms for an incompressible half-space (ν = 1/2):
        // u_x = 3/(4πE) [x z / r³ · P + (1/r + x²/r³) Qx + x y / r³ · Qy].
        let s = paper_sensor();
        let mm = s.camera.mm_per_px;
        let e = s.elastomer.young_modulus_n_per_mm2();
        let (x, y, z) = (2.0, 1.0, s.layers[0].depth_mm);
        let f = [0.3, -0.2, 1.5];
        let sp = SetpointObs {
            index: 0,
            trial: 0,
            centre_mm: [1.0, -0.5],
            f_ft_n: f,
            markers: vec![marker(0, [1.0 + x, -0.5 + y], mm)],
        };
        let r = route(IndenterShape::Point, &s, vec![sp]);
        let u = r.predict_px(&ModelParams::nominal(&s, 0.0)).unwrap();
        let rr = (x * x + y * y + z * z).sqrt();
        let c = 3.0 / (4.0 * std::f64::consts::PI * e);
        let ux = c
            * (x * z / rr.powi(3) * f[2]
                + (1.0 / rr + x * x / rr.powi(3)) * f[0]
                + x * y / rr.powi(3) * f[1]);
        let uy = c
            * (y * z / rr.powi(3) * f[2]
                + (1.0 / rr + y * y / rr.powi(3)) * f[1]
                + x * y / rr.powi(3) * f[0]);
        assert!(
            (u[0] - ux / mm).abs() < 1e-9 * (ux / mm).abs().max(1.0),
            "{} vs {}",
            u[0],
            ux / mm
        );
        assert!(
            (u[1] - uy / mm).abs() < 1e-9 * (uy / mm).abs().max(1.0),
            "{} vs {}",
            u[1],
            uy / mm
        );
    }

    /// The route against `sim::Simulation`'s rendered truth (its fine 0.05 mm contact
    /// cells) for the same load: the largest error as a share of the largest
    /// displacement.
    fn route_against_simulation(indenter: Indenter, shape: IndenterShape, load: LoadCase) -> f64 {
        let s = paper_sensor();
        let mm = s.camera.mm_per_px;
        let mut sim = Simulation::new(s.clone(), indenter, Pipeline::ideal());
        let mut frame = sim.blank_frame();
        let truth = sim.render_load(&load, 1, &mut frame).unwrap();
        let c = truth.contact.as_ref().unwrap();
        let f = [c.tangential_n[0], c.tangential_n[1], c.normal_force_n];
        let markers: Vec<MarkerObs> = sim
            .markers()
            .iter()
            .enumerate()
            .map(|(k, m)| MarkerObs {
                u_px: [
                    truth.elastic_u_mm[2 * k] / mm,
                    truth.elastic_u_mm[2 * k + 1] / mm,
                ],
                ..marker(m.layer, m.position_mm, mm)
            })
            .collect();
        let sp = SetpointObs {
            index: 0,
            trial: 0,
            centre_mm: load.position_mm,
            f_ft_n: f,
            markers,
        };
        let r = route(shape, &s, vec![sp]);
        let p = ModelParams::nominal(&s, 0.0);
        let mut out = vec![0.0; r.len()];
        r.eval(&p, &mut out).unwrap();
        let peak = r.setpoints[0]
            .markers
            .iter()
            .map(|m| m.u_px[0].hypot(m.u_px[1]))
            .fold(0.0, f64::max);
        out.iter().map(|v| v.abs()).fold(0.0, f64::max) / peak
    }

    #[test]
    fn noise_free_simulated_displacements_give_zero_residual_up_to_the_quadrature() {
        let load = |n: f64, q: [f64; 2]| LoadCase {
            position_mm: [9.0, 6.75],
            normal: Normal::ForceN(n),
            tangential: Tangential::ForceN(q),
            friction: 1.0,
        };
        let hemi = route_against_simulation(
            Indenter::Hemisphere { radius_mm: 5.0 },
            IndenterShape::Hemisphere { diameter_mm: 10.0 },
            load(4.0, [0.8, -0.5]),
        );
        let flat = route_against_simulation(
            Indenter::Flat { diameter_mm: 5.0 },
            IndenterShape::Flat { diameter_mm: 5.0 },
            load(3.0, [0.5, 0.4]),
        );
        let point =
            route_against_simulation(Indenter::Point, IndenterShape::Point, load(2.0, [0.3, 0.0]));
        eprintln!("max |route - simulation| / peak: hemisphere {hemi:.2e}, flat {flat:.2e}, point {point:.2e}");
        assert!(point < 1e-12, "{point}");
        assert!(hemi < 2e-3, "{hemi}");
        assert!(flat < 2e-3, "{flat}");
    }

    /// Central difference of the predicted px of marker 0 along a parameter.
    fn slope(
        r: &DisplacementRoute,
        p: &ModelParams,
        set: impl Fn(&mut ModelParams, f64),
        h: f64,
        comp: usize,
    ) -> f64 {
        let (mut a, mut b) = (p.clone(), p.clone());
        set(&mut a, h);
        set(&mut b, -h);
        (r.predict_px(&a).unwrap()[comp] - r.predict_px(&b).unwrap()[comp]) / (2.0 * h)
    }

    #[test]
    fn each_parameter_moves_the_prediction_the_way_physics_says() {
        let mut s = paper_sensor();
        let mm = s.camera.mm_per_px;
        // A marker 8 mm to the +x side of a normal load (beyond the u_x peak at
        // x = z/√2), and a pure +x shear.
        let sp = |f: [f64; 3]| SetpointObs {
            index: 0,
            trial: 0,
            centre_mm: [0.0, 0.0],
            f_ft_n: f,
            markers: vec![marker(0, [8.0, 0.0], mm)],
        };
        let hemi = IndenterShape::Hemisphere { diameter_mm: 10.0 };
        let r = route(hemi, &s, vec![sp([0.0, 0.0, 3.0])]);
        let p = ModelParams::nominal(&s, 0.0);
        let u0 = r.predict_px(&p).unwrap()[0];
        assert!(u0 > 0.0, "a normal load pushes markers outwards: {u0}");
        // Stiffer: smaller.
        assert!(slope(&r, &p, |q, h| q.young_modulus_kpa += h, 10.0, 0) < 0.0);
        // Deeper markers far out move more (x z / r³ grows with z while z < x/√2).
        assert!(slope(&r, &p, |q, h| q.depth_mm[0] += h, 0.05, 0) > 0.0);
        // The load moving towards the marker (offset +x) raises u_x out here.
        assert!(slope(&r, &p, |q, h| q.contact_offset_mm[0] += h, 0.05, 0) > 0.0);
        // A larger scale puts the marker further out and shrinks its px: smaller.
        assert!(slope(&r, &p, |q, h| q.mm_per_px[0] += h, 1e-3, 0) < 0.0);
        // A +x shear read by an F/T mounted +θ: the force turns towards +y.
        let rs = route(hemi, &s, vec![sp([0.5, 0.0, 3.0])]);
        assert!(slope(&rs, &p, |q, h| q.ft_rotation_deg += h, 0.5, 1) > 0.0);
        // A thicker bonded layer is softer: larger displacement.
        s.elastomer.model = ModelKind::BondedLayer;
        s.elastomer.thickness_mm = 8.0;
        let rb = route(hemi, &s, vec![sp([0.0, 0.0, 3.0])]);
        let pb = ModelParams::nominal(&s, 0.0);
        assert!(slope(&rb, &pb, |q, h| q.thickness_mm += h, 0.1, 0) > 0.0);
        // u ∝ 1/E exactly (the scaling the route relies on).
        let mut p2 = pb.clone();
        p2.young_modulus_kpa *= 2.0;
        let (a, b) = (
            rb.predict_px(&pb).unwrap()[0],
            rb.predict_px(&p2).unwrap()[0],
        );
        let a_c = contact_radius(hemi, 3.0, 1.0);
        assert!(a_c > 0.0);
        // Halving E also grows the contact by 2^(1/3): only the spread changes.
        assert!((b / a - 0.5).abs() < 0.01, "{a} {b}");
    }

    #[test]
    fn the_bonded_layer_table_matches_the_direct_response() {
        let layer = BondedLayer::new(1.0, 0.49, 8.0).unwrap();
        let t = RadialTable::new(&layer, 3.0, 30.0);
        let peak = layer.point_response(0.0, 0.0, 3.0)[0][0].abs();
        let mut worst: f64 = 0.0;
        for &(dx, dy) in &[
            (0.0, 0.0),
            (0.7, -0.2),
            (2.3, 1.9),
            (-5.1, 3.3),
            (12.0, -17.0),
            (0.01, 0.0),
        ] {
            let a = t.response(dx, dy);
            let b = ElasticModel::point_response(&layer, dx, dy, 3.0);
            for r in 0..2 {
                for c in 0..3 {
                    worst = worst.max((a[r][c] - b[r][c]).abs() / peak);
                }
            }
        }
        assert!(worst < 1e-6, "{worst}");
    }

    #[test]
    fn a_depth_outside_the_bonded_layer_is_an_error_naming_the_layer() {
        let mut s = paper_sensor();
        s.elastomer.model = ModelKind::BondedLayer;
        s.elastomer.thickness_mm = 8.0;
        let sp = SetpointObs {
            index: 0,
            trial: 0,
            centre_mm: [0.0, 0.0],
            f_ft_n: [0.0, 0.0, 1.0],
            markers: vec![marker(1, [2.0, 0.0], s.camera.mm_per_px)],
        };
        let r = route(IndenterShape::Point, &s, vec![sp]);
        let mut p = ModelParams::nominal(&s, 0.0);
        p.depth_mm[1] = 9.0;
        let e = r.predict_px(&p).unwrap_err();
        assert!(
            e.contains(&format!("depth_mm.{}", s.layers[1].name)) && e.contains("9"),
            "{e}"
        );
    }
}
