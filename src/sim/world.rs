//! The virtual bench world shared by the simulated devices: one stage position, one
//! indenter, one elastomer. The stage simulators publish where the stage is; the
//! force-sensor simulators ask for the wrench that position produces; the simulated
//! camera renders the marker image of the same contact (with the scene's effects
//! only). Everything is a pure function of the stage position history, so a simulated
//! run is reproducible.
//!
//! Geometry (stage machine coordinates, mm): the indenter tip is over sensor-frame
//! point `xy_stage − sensor_origin_in_stage_mm`, and touches the elastomer surface at
//! stage `z = surface_z_mm`. Indentation `δ = press_direction · (z − surface_z)`:
//! `press_direction = +1` when larger z presses deeper, `−1` for a CNC-style stage
//! (GRBL: +z is up, machine coordinates are ≤ 0).
//!
//! Contact laws: [`crate::model::indentation::indentation_force`], the law the fit's
//! indentation route inverts, on the body of the scene's sensor file (the truth the
//! camera sees): its `[elastomer] model = "bonded-layer"` presses as a layer of its
//! `thickness_mm` bonded to a rigid plate (Shull 2002), any other model as the
//! half-space (Johnson, *Contact Mechanics*, §3.4, §5.2, §7.2; `E* = E/(1−ν²)`,
//! `G = E/(2(1+ν))`):
//! - flat cylinder of radius `a`: half-space `P = 2 a E* δ` (contact radius `a` at any
//!   depth);
//! - hemisphere of radius `R`: half-space `P = 4/3 E* √R δ^{3/2}`, contact radius
//!   `a = √(Rδ)`, past the equator the flank presses like a punch;
//! - point: modelled for the force law as a half-space hemisphere of radius
//!   [`POINT_TIP_RADIUS_MM`] (whatever the body: its contact is far smaller than any
//!   layer), its traction applied as a concentrated load.
//!
//! Tangential force comes from lateral stage motion while in contact (Mindlin):
//! `Q = k_t · s`, `k_t = 8 G a / (2 − ν)`, `s` the lateral travel since the contact
//! stuck, limited by friction `|Q| ≤ μ P`; beyond it the contact slides and the stick
//! point follows. Leaving contact releases the stick point.
//!
//! The force/torque sensor sits `tool_length_mm` above the tip with its axes aligned to
//! the sensor frame and reports the force the indenter applies to the elastomer
//! (`fz > 0` pressing) and its moment about the F/T origin.
//!
//! Opt-in bench effects ([`BenchEffects`], the scene's `[bench]` table; none listed =
//! ideal and exact):
//! - **force relaxation** (viscoelastic elastomer, standard linear solid / one-term
//!   Prony series): every change `ΔF_e` of the elastic force adds `a·ΔF_e` to an
//!   excess force `r` that decays as `r(t) = r(t₀)·e^{−(t−t₀)/τ}`; the sensor reads
//!   `F_e + r`. After a step in indentation the force jumps to `(1+a)` of the step and
//!   relaxes to the elastic value with time constant τ. The camera still sees the
//!   elastic field (the indentation, not the force, is held).
//! - **F/T noise**: independent Gaussian noise of σ (N) on each force component of each
//!   sample the force sensor serves, from a seeded stream; torques follow the noisy
//!   force (`M = r × F`).
//! - **viscoelastic** (what the camera sees; the F/T side is the force relaxation
//!   above): the marker displacement field is the elastic field of the contact scaled
//!   by `(F_e + c + H) / F_e` (`F_e` the elastic normal force of the indentation):
//!   - *creep* `c` (N) follows `dc/dt = (a·F_e − c)/τ` (a one-term Kelvin–Voigt creep
//!     compliance, Boltzmann superposition), advanced exactly between updates with
//!     `F_e` held: under a constant load applied at `t₀` with `c = 0` the
//!     displacements grow as `1 + a·(1 − e^{−(t−t₀)/τ})`; after unloading `c` decays
//!     with τ and the camera sees the last contact's field scaled to `c` (creep
//!     recovery: the zero returns with τ);
//!   - *hysteresis* `H = 4h·F_e·(P − F_e)/P`, `P` the largest `F_e` since the contact
//!     began (reset when it is released): 0 while loading (`F_e = P`), and on
//!     unloading a lens-shaped loop, rate-independent, closed at `P` and at 0, whose
//!     widest point (`F_e = P/2`) is `h·P`; reloading below `P` retraces it.
//!
//!   With the effect absent the scale is exactly 1 (zero creep, zero hysteresis).
//! - **stage carries the sensor**: the stage's xy motion moves the whole sensor under a
//!   fixed camera: every marker appears shifted by the stage's xy travel from the
//!   position where the tip is over `carry_zero_mm`, and the contact stays at
//!   `carry_zero_mm` (the paper's Table I, whole-sensor shift without load).
//! - **F/T mounted rotated** (`ft_rotation_deg = θ`): the F/T sensor's axes are turned
//!   by +θ about z from the sensor frame, so it reports `R(θ)ᵀ F` and `R(θ)ᵀ M`
//!   (`R(θ)` the counter-clockwise rotation in x-y; the convention of
//!   [`crate::fit::ModelParams`], whose `ft_to_sensor` undoes it). The camera is not
//!   affected.
//! - **stage offset** (`stage_offset_mm = [dx, dy]`): the contact happens at the
//!   stage's notion of the contact point plus `[dx, dy]` in the camera's sensor frame
//!   (force law, friction and the rendered field all at the true point); the stage
//!   position, and so the runner's journal, are the stage's notion.

use std::sync::{Arc, Mutex, MutexGuard};

use image::Rgb32FImage;

use std::time::Instant;

use super::contact::{Indenter, LoadCase, Normal, Tangential};
use super::rng::Rng;
use super::simulate::{FrameTruth, SimError, Simulation};
use crate::device::Wrench;
use crate::model::indentation::{indentation_force, Body, Shape};
use crate::model::HalfSpace;
use crate::sensor::{Elastomer, ModelKind};

// The bench-effect types are scene data; re-exported here under their old paths.
pub use super::scene::{BenchEffects, ForceRelaxation, FtNoise, Viscoelastic};

/// Tip radius used for the force law of a point indenter, mm.
pub const POINT_TIP_RADIUS_MM: f64 = 0.25;

/// Deepest indentation [`World::indentation_for_normal_force`] searches, mm.
pub const MAX_INVERTED_DEPTH_MM: f64 = 100.0;

/// A force in the sensor frame as an F/T sensor mounted rotated by +θ (degrees) about
/// z reports it: `R(θ)ᵀ F` (the inverse of `fit::ModelParams::ft_to_sensor`).
pub fn rotate_into_ft(theta_deg: f64, f: [f64; 3]) -> [f64; 3] {
    let (s, c) = theta_deg.to_radians().sin_cos();
    [c * f[0] + s * f[1], -s * f[0] + c * f[1], f[2]]
}

/// The body an elastomer section presses as: the bonded layer of its thickness when
/// its model is `bonded-layer`, else the half-space.
pub fn body_of(elastomer: &Elastomer) -> Body {
    match elastomer.model {
        ModelKind::BondedLayer => Body::BondedLayer {
            thickness_mm: elastomer.thickness_mm,
        },
        ModelKind::HalfSpace => Body::HalfSpace,
    }
}

/// Where the sensor sits in stage coordinates, and the contact parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WorldGeometry {
    /// Stage xy that puts the indenter tip over the sensor-frame origin, mm.
    pub sensor_origin_in_stage_mm: [f64; 2],
    /// Stage z at which the tip touches the surface, mm.
    pub surface_z_mm: f64,
    /// +1: increasing stage z presses into the elastomer; −1: decreasing z does.
    pub press_direction: f64,
    /// Friction coefficient μ between indenter and elastomer.
    pub friction: f64,
    /// Distance from the F/T sensor origin down to the tip, mm (for torques).
    pub tool_length_mm: f64,
}

impl Default for WorldGeometry {
    fn default() -> Self {
        WorldGeometry {
            sensor_origin_in_stage_mm: [0.0, 0.0],
            surface_z_mm: 10.0,
            press_direction: 1.0,
            friction: 1.0,
            tool_length_mm: 50.0,
        }
    }
}

/// The state the devices share.
#[derive(Debug, Clone)]
struct State {
    stage_mm: [f64; 3],
    /// Sensor-frame point where the contact stuck, while in contact.
    stick_mm: Option<[f64; 2]>,
    /// Next camera frame index (the effects pipeline counts frames).
    next_frame: u64,
    /// Force relaxation: elastic force at the last update, excess force, its time.
    elastic_n: [f64; 3],
    excess_n: [f64; 3],
    updated: Instant,
    noise: Option<Rng>,
    /// Viscoelastic creep `c` of the displacement field, N of normal force.
    creep_n: f64,
    /// Largest elastic normal force since the contact began, N (0 out of contact).
    peak_n: f64,
    /// The last contact's load case and normal force (creep recovery is rendered as
    /// its field scaled to `c`).
    last_load: Option<(LoadCase, f64)>,
}

/// The virtual world. Cheap to share: clone the [`Arc`] from [`World::new`].
pub struct World {
    effects: BenchEffects,
    geometry: WorldGeometry,
    model: HalfSpace,
    /// The body the indenter presses into (the scene sensor's `[elastomer] model`).
    body: Body,
    indenter: Indenter,
    state: Mutex<State>,
    camera: Mutex<Simulation>,
}

impl std::fmt::Debug for World {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("World")
            .field("geometry", &self.geometry)
            .field("indenter", &self.indenter)
            .field("state", &*lock(&self.state))
            .finish()
    }
}

/// A lock that survives a panicked holder: the state is plain data, always valid.
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// What the contact looks like at the current stage position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactState {
    /// Tip position in the sensor frame, mm.
    pub tip_in_sensor_mm: [f64; 2],
    /// Indentation depth δ, mm (≤ 0: not in contact).
    pub indentation_mm: f64,
    /// Normal force P, N.
    pub normal_n: f64,
    /// Tangential force Q applied to the elastomer, N.
    pub tangential_n: [f64; 2],
    /// Contact radius a, mm.
    pub contact_radius_mm: f64,
    /// True when friction limits Q (sliding).
    pub sliding: bool,
    /// When the stage carries the sensor: where the tip would be without carrying
    /// (the image shift is this minus `carry_zero_mm`), mm.
    pub carried_from_mm: Option<[f64; 2]>,
}

impl World {
    /// A world around a simulation (sensor, indenter, effects) at stage position
    /// `start_mm`.
    pub fn new(
        simulation: Simulation,
        indenter: Indenter,
        geometry: WorldGeometry,
        start_mm: [f64; 3],
    ) -> Arc<World> {
        Self::with_effects(
            simulation,
            indenter,
            geometry,
            start_mm,
            BenchEffects::default(),
        )
    }

    /// A world with opt-in bench effects.
    pub fn with_effects(
        simulation: Simulation,
        indenter: Indenter,
        geometry: WorldGeometry,
        start_mm: [f64; 3],
        effects: BenchEffects,
    ) -> Arc<World> {
        let model = HalfSpace::from_elastomer(&simulation.sensor().elastomer);
        let body = body_of(&simulation.sensor().elastomer);
        let world = World {
            effects,
            geometry,
            model,
            body,
            indenter,
            state: Mutex::new(State {
                stage_mm: start_mm,
                stick_mm: None,
                next_frame: 1,
                elastic_n: [0.0; 3],
                excess_n: [0.0; 3],
                updated: Instant::now(),
                noise: effects.ft_noise.map(|n| Rng::new(n.seed)),
                creep_n: 0.0,
                peak_n: 0.0,
                last_load: None,
            }),
            camera: Mutex::new(simulation),
        };
        {
            let mut s = lock(&world.state);
            let c = world.contact_of(s.stage_mm, s.stick_mm);
            s.elastic_n = [c.tangential_n[0], c.tangential_n[1], c.normal_n];
        }
        Arc::new(world)
    }

    /// The opt-in effects.
    pub fn effects(&self) -> &BenchEffects {
        &self.effects
    }

    /// Advances force relaxation and viscoelastic creep to now with the current
    /// contact (the elastic force of the interval since the last update is the one
    /// recorded then; the new one applies from now).
    fn relax(&self, s: &mut State) {
        let (r, v) = (self.effects.force_relaxation, self.effects.viscoelastic);
        if r.is_none() && v.is_none() {
            return;
        }
        let now = Instant::now();
        let dt = now.duration_since(s.updated).as_secs_f64();
        s.updated = now;
        let c = self.contact_of(s.stage_mm, s.stick_mm);
        let fe = [c.tangential_n[0], c.tangential_n[1], c.normal_n];
        let last = s.elastic_n;
        if let Some(r) = r {
            let decay = (-dt / r.time_constant_s).exp();
            for ((e, f), l) in s.excess_n.iter_mut().zip(fe).zip(last) {
                // Out of contact there is nothing to relax.
                *e = if c.normal_n > 0.0 {
                    *e * decay + r.fraction * (f - l)
                } else {
                    0.0
                };
            }
        }
        if let Some(v) = v {
            // Exact for the normal force held at `last` over the interval.
            let goal = v.creep * last[2];
            s.creep_n = goal + (s.creep_n - goal) * (-dt / v.time_constant_s).exp();
            if c.normal_n > 0.0 {
                s.peak_n = s.peak_n.max(c.normal_n);
                s.last_load = Some((self.load_case(&c), c.normal_n));
            } else {
                s.peak_n = 0.0;
            }
        }
        s.elastic_n = fe;
    }

    /// The load case the camera renders and the scale of its displacement field
    /// (1 without the viscoelastic effect; see the module docs).
    fn rendered_load(&self, s: &State, c: &ContactState) -> (LoadCase, f64) {
        let Some(v) = self.effects.viscoelastic else {
            return (self.load_case(c), 1.0);
        };
        let fe = c.normal_n;
        if c.indentation_mm > 0.0 && fe > 0.0 {
            let h = if s.peak_n > fe {
                4.0 * v.hysteresis * fe * (s.peak_n - fe) / s.peak_n
            } else {
                0.0
            };
            return (self.load_case(c), (fe + s.creep_n + h) / fe);
        }
        match &s.last_load {
            Some((load, f_last)) if *f_last > 0.0 && s.creep_n > 0.0 => (*load, s.creep_n / f_last),
            _ => (self.load_case(c), 1.0),
        }
    }

    /// The geometry.
    pub fn geometry(&self) -> &WorldGeometry {
        &self.geometry
    }

    /// Stage position, mm.
    pub fn stage_mm(&self) -> [f64; 3] {
        lock(&self.state).stage_mm
    }

    /// The stage simulators call this whenever the stage moved. Updates the friction
    /// stick point so tangential force follows the motion history.
    pub fn set_stage_mm(&self, p: [f64; 3]) {
        let mut s = lock(&self.state);
        s.stage_mm = p;
        let c = self.contact_of(p, s.stick_mm);
        s.stick_mm = if c.indentation_mm <= 0.0 {
            None
        } else {
            match s.stick_mm {
                None => Some(c.tip_in_sensor_mm),
                Some(stick) if c.sliding => {
                    // Slide: move the stick point so |Q| sits exactly at μP.
                    let k = self.tangential_stiffness(c.contact_radius_mm);
                    if k > 0.0 {
                        Some([
                            c.tip_in_sensor_mm[0] - c.tangential_n[0] / k,
                            c.tip_in_sensor_mm[1] - c.tangential_n[1] / k,
                        ])
                    } else {
                        Some(stick)
                    }
                }
                keep => keep,
            }
        };
        self.relax(&mut s);
    }

    /// The contact at the current stage position.
    pub fn contact(&self) -> ContactState {
        let s = lock(&self.state);
        self.contact_of(s.stage_mm, s.stick_mm)
    }

    /// The wrench the F/T sensor feels now (force on the elastomer, N; moment about
    /// the F/T origin, N·m), in the F/T sensor's axes (rotated by the bench's
    /// `ft_rotation_deg` when one is set), with its noise.
    pub fn wrench(&self) -> Wrench {
        self.reading(true)
    }

    /// The wrench the F/T sensor reports without its noise (force relaxation and the
    /// mounting rotation included): what a long average converges to.
    pub fn wrench_without_noise(&self) -> Wrench {
        self.reading(false)
    }

    fn reading(&self, noisy: bool) -> Wrench {
        let f = {
            let mut s = lock(&self.state);
            self.relax(&mut s);
            let c = self.contact_of(s.stage_mm, s.stick_mm);
            let mut f = [c.tangential_n[0], c.tangential_n[1], c.normal_n];
            for (fi, e) in f.iter_mut().zip(s.excess_n) {
                *fi += e;
            }
            if let (true, Some(n), Some(rng)) = (noisy, self.effects.ft_noise, s.noise.as_mut()) {
                for fi in &mut f {
                    *fi += n.sigma_n * rng.normal();
                }
            }
            f
        };
        // A rotated mount reports R(θ)ᵀ F (fit::ModelParams' convention). The noise is
        // drawn per component before the rotation: independent and of equal σ, it has
        // the same distribution in the F/T's axes.
        let f = match self.effects.ft_rotation_deg {
            Some(theta) => rotate_into_ft(theta, f),
            None => f,
        };
        // r from the F/T origin to the tip: (0, 0, L) in the sensor frame (z is down
        // into the elastomer), in metres; M = r × F. r lies on the rotation axis, so
        // in the F/T's axes M = r × R(θ)ᵀF = R(θ)ᵀM.
        let l_m = self.geometry.tool_length_mm * 1e-3;
        Wrench {
            force_n: f,
            torque_nm: [-l_m * f[1], l_m * f[0], 0.0],
        }
    }

    /// The indentation depth δ (mm) at which the contact law gives the normal force
    /// `normal_n` (N > 0), by bisection of the monotonic law; `None` when no depth up
    /// to [`MAX_INVERTED_DEPTH_MM`] reaches it.
    pub fn indentation_for_normal_force(&self, normal_n: f64) -> Option<f64> {
        if !(normal_n.is_finite() && normal_n > 0.0) {
            return None;
        }
        let (mut lo, mut hi) = (0.0f64, 0.01f64);
        while self.normal_law(hi).0 < normal_n {
            lo = hi;
            hi *= 2.0;
            if hi > MAX_INVERTED_DEPTH_MM {
                return None;
            }
        }
        // 60 halvings: below 1e-15 of the bracket, far under any stage resolution.
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if self.normal_law(mid).0 < normal_n {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        Some(0.5 * (lo + hi))
    }

    /// Tangential contact stiffness at the indentation `d` (mm): `dQ/ds` of lateral
    /// travel `s` while stuck (Mindlin), N/mm; 0 out of contact.
    pub fn tangential_stiffness_at(&self, d: f64) -> f64 {
        let (p, a) = self.normal_law(d);
        if p > 0.0 {
            self.tangential_stiffness(a)
        } else {
            0.0
        }
    }

    /// Renders the camera's next frame for the current contact into `out` (effects of
    /// the simulation's pipeline included) and returns its ground truth.
    pub fn render(&self, out: &mut Rgb32FImage) -> Result<FrameTruth, SimError> {
        let (c, frame, load, scale) = {
            let mut s = lock(&self.state);
            self.relax(&mut s);
            let frame = s.next_frame;
            s.next_frame += 1;
            let c = self.contact_of(s.stage_mm, s.stick_mm);
            let (load, scale) = self.rendered_load(&s, &c);
            (c, frame, load, scale)
        };
        let shift = self.carry_shift_mm(&c);
        lock(&self.camera).render_load_scaled(&load, frame, shift, scale, out)
    }

    /// Whole-sensor shift in the image when the stage carries the sensor, mm.
    fn carry_shift_mm(&self, c: &ContactState) -> [f64; 2] {
        match (self.effects.carry_zero_mm, c.carried_from_mm) {
            (Some(z), Some(tip)) => [tip[0] - z[0], tip[1] - z[1]],
            _ => [0.0, 0.0],
        }
    }

    /// The unloaded reference frame (pipeline frame 0).
    pub fn render_reference(&self, out: &mut Rgb32FImage) -> Result<FrameTruth, SimError> {
        lock(&self.camera).render_reference(out)
    }

    /// A blank frame buffer of the camera's size.
    pub fn blank_frame(&self) -> Rgb32FImage {
        lock(&self.camera).blank_frame()
    }

    /// The load case the traction model renders for a contact state. The tangential
    /// force is already limited by friction here, so μ is raised to carry it exactly
    /// (the traction model would otherwise clamp it a second time).
    fn load_case(&self, c: &ContactState) -> LoadCase {
        if c.indentation_mm <= 0.0 || c.normal_n <= 0.0 {
            return LoadCase {
                position_mm: c.tip_in_sensor_mm,
                normal: Normal::ForceN(0.0),
                tangential: Tangential::NONE,
                friction: self.geometry.friction,
            };
        }
        let q = c.tangential_n;
        LoadCase {
            position_mm: c.tip_in_sensor_mm,
            normal: Normal::ForceN(c.normal_n),
            tangential: Tangential::ForceN(q),
            friction: self
                .geometry
                .friction
                .max(q[0].hypot(q[1]) / c.normal_n * (1.0 + 1e-9)),
        }
    }

    fn reduced_modulus(&self) -> f64 {
        self.model.young_n_per_mm2 / (1.0 - self.model.poisson * self.model.poisson)
    }

    fn tangential_stiffness(&self, a_mm: f64) -> f64 {
        let nu = self.model.poisson;
        let g = self.model.young_n_per_mm2 / (2.0 * (1.0 + nu));
        8.0 * g * a_mm / (2.0 - nu)
    }

    /// Normal force and contact radius at indentation `d` (mm).
    fn normal_law(&self, d: f64) -> (f64, f64) {
        if d <= 0.0 {
            return (0.0, 0.0);
        }
        let e_star = self.reduced_modulus();
        let shape = match self.indenter {
            Indenter::Flat { diameter_mm } => Shape::Flat {
                radius_mm: diameter_mm / 2.0,
            },
            Indenter::Hemisphere { radius_mm } => Shape::Hemisphere { radius_mm },
            Indenter::Point => {
                let r = POINT_TIP_RADIUS_MM;
                return (
                    4.0 / 3.0 * e_star * r.sqrt() * d.powf(1.5),
                    (r * d).sqrt().min(r),
                );
            }
        };
        let c = indentation_force(shape, self.body, e_star, d);
        (c.force_n, c.radius_mm)
    }

    fn contact_of(&self, stage: [f64; 3], stick: Option<[f64; 2]>) -> ContactState {
        let g = &self.geometry;
        let free_tip = [
            stage[0] - g.sensor_origin_in_stage_mm[0],
            stage[1] - g.sensor_origin_in_stage_mm[1],
        ];
        // A carried sensor moves with the stage: the tip stays over carry_zero_mm.
        // A stage offset puts the contact off the stage's notion of it (scene
        // validation refuses it together with a carried sensor).
        let (tip, carried_from_mm) =
            match (self.effects.carry_zero_mm, self.effects.stage_offset_mm) {
                (Some(z), _) => (z, Some(free_tip)),
                (None, Some(o)) => ([free_tip[0] + o[0], free_tip[1] + o[1]], None),
                (None, None) => (free_tip, None),
            };
        let d = g.press_direction.signum() * (stage[2] - g.surface_z_mm);
        let (p, a) = self.normal_law(d);
        let mut q = [0.0; 2];
        let mut sliding = false;
        if p > 0.0 {
            if let Some(st) = stick {
                let k = self.tangential_stiffness(a);
                q = [k * (tip[0] - st[0]), k * (tip[1] - st[1])];
                let limit = g.friction * p;
                let mag = q[0].hypot(q[1]);
                if mag > limit && mag > 0.0 {
                    q = [q[0] * limit / mag, q[1] * limit / mag];
                }
                // At the limit (after a slide moved the stick point) counts as sliding.
                sliding = mag > 0.0 && mag >= limit * (1.0 - 1e-9);
            }
        }
        ContactState {
            tip_in_sensor_mm: tip,
            indentation_mm: d,
            normal_n: p,
            tangential_n: q,
            contact_radius_mm: a,
            sliding,
            carried_from_mm,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::paper_sensor;
    use crate::sim::effects::Pipeline;

    fn world(indenter: Indenter) -> Arc<World> {
        let sim = Simulation::new(paper_sensor(), indenter, Pipeline::ideal());
        let g = WorldGeometry {
            sensor_origin_in_stage_mm: [20.0, 30.0],
            surface_z_mm: 5.0,
            press_direction: 1.0,
            friction: 0.5,
            tool_length_mm: 40.0,
        };
        World::new(sim, indenter, g, [29.0, 36.75, 0.0])
    }

    #[test]
    fn no_force_out_of_contact() {
        let w = world(Indenter::Flat { diameter_mm: 5.0 });
        assert_eq!(w.wrench(), Wrench::default());
        w.set_stage_mm([29.0, 36.75, 4.99]);
        assert_eq!(w.contact().normal_n, 0.0);
        assert_eq!(w.contact().tip_in_sensor_mm, [9.0, 6.75]);
    }

    #[test]
    fn normal_force_follows_the_closed_form_laws() {
        // E = 1 N/mm², ν = 0.5: E* = 4/3 N/mm².
        let e_star = 4.0 / 3.0;
        let w = world(Indenter::Flat { diameter_mm: 5.0 });
        w.set_stage_mm([29.0, 36.75, 5.2]);
        assert!((w.wrench().force_n[2] - 2.0 * 2.5 * e_star * 0.2).abs() < 1e-12);
        let w = world(Indenter::Hemisphere { radius_mm: 2.5 });
        w.set_stage_mm([29.0, 36.75, 5.4]);
        let p = 4.0 / 3.0 * e_star * 2.5f64.sqrt() * 0.4f64.powf(1.5);
        assert!((w.wrench().force_n[2] - p).abs() < 1e-12);
        assert!((w.contact().contact_radius_mm - 1.0).abs() < 1e-12);
    }

    #[test]
    fn a_cnc_stage_presses_towards_negative_z() {
        let sim = Simulation::new(
            paper_sensor(),
            Indenter::Flat { diameter_mm: 5.0 },
            Pipeline::ideal(),
        );
        let g = WorldGeometry {
            surface_z_mm: -20.0,
            press_direction: -1.0,
            ..WorldGeometry::default()
        };
        let w = World::new(
            sim,
            Indenter::Flat { diameter_mm: 5.0 },
            g,
            [9.0, 6.75, -10.0],
        );
        assert_eq!(w.wrench().force_n[2], 0.0);
        w.set_stage_mm([9.0, 6.75, -20.3]);
        assert!((w.contact().indentation_mm - 0.3).abs() < 1e-12);
        assert!(w.wrench().force_n[2] > 0.0);
    }

    #[test]
    fn lateral_motion_in_contact_sticks_then_slides_at_the_friction_limit() {
        let w = world(Indenter::Flat { diameter_mm: 5.0 });
        w.set_stage_mm([29.0, 36.75, 5.3]);
        let p = w.wrench().force_n[2];
        // Mindlin stiffness: 8 G a / (2 − ν) with G = 1/3 N/mm², a = 2.5 mm.
        let k = 8.0 * (1.0 / 3.0) * 2.5 / 1.5;
        w.set_stage_mm([29.01, 36.75, 5.3]);
        let f = w.wrench().force_n;
        assert!((f[0] - k * 0.01).abs() < 1e-9, "{f:?}");
        assert!(!w.contact().sliding);
        // Far beyond the limit: |Q| = μP, sliding; moving back relieves it at once.
        w.set_stage_mm([31.0, 36.75, 5.3]);
        let f = w.wrench().force_n;
        assert!(
            (f[0] - 0.5 * p).abs() < 1e-9 && w.contact().sliding,
            "{f:?}"
        );
        w.set_stage_mm([30.9, 36.75, 5.3]);
        let f = w.wrench().force_n;
        assert!((f[0] - (0.5 * p - k * 0.1)).abs() < 1e-9, "{f:?}");
        // Torque about the F/T origin 40 mm above the tip: My = L·Fx.
        assert!((w.wrench().torque_nm[1] - 0.04 * f[0]).abs() < 1e-12);
        // Lifting off releases the stick point.
        w.set_stage_mm([30.9, 36.75, 4.0]);
        w.set_stage_mm([30.9, 36.75, 5.3]);
        assert_eq!(w.wrench().force_n[0], 0.0);
    }

    #[test]
    fn camera_frames_show_the_same_contact() {
        let w = world(Indenter::Flat { diameter_mm: 5.0 });
        let mut img = w.blank_frame();
        let truth = w.render(&mut img).unwrap();
        assert!(
            truth.elastic_u_mm.iter().all(|u| *u == 0.0),
            "no contact, no displacement"
        );
        w.set_stage_mm([29.0, 36.75, 5.5]);
        let truth = w.render(&mut img).unwrap();
        let c = truth.contact.expect("contact");
        assert!((c.normal_force_n - w.wrench().force_n[2]).abs() < 1e-9);
        let sum: f64 = truth.forces_n.iter().skip(2).step_by(3).sum();
        assert!((sum - c.normal_force_n).abs() < 1e-6 * c.normal_force_n);
        assert!(truth.elastic_u_mm.iter().any(|u| u.abs() > 1e-3));
        assert_eq!(truth.frame, 2, "frames count up");
    }
}

#[cfg(test)]
mod effect_tests {
    use super::*;
    use crate::sensor::paper_sensor;
    use crate::sim::effects::Pipeline;

    fn world(effects: BenchEffects) -> Arc<World> {
        let ind = Indenter::Flat { diameter_mm: 5.0 };
        let sim = Simulation::new(paper_sensor(), ind, Pipeline::ideal());
        let g = WorldGeometry {
            sensor_origin_in_stage_mm: [20.0, 30.0],
            surface_z_mm: 5.0,
            ..WorldGeometry::default()
        };
        World::with_effects(sim, ind, g, [29.0, 36.75, 0.0], effects)
    }

    /// Flat punch, E* = 4/3 N/mm²: P = 2 a E* δ.
    fn flat_n(depth_mm: f64) -> f64 {
        2.0 * 2.5 * (4.0 / 3.0) * depth_mm
    }

    #[test]
    fn without_listed_effects_the_wrench_is_exact_and_repeatable() {
        let w = world(BenchEffects::default());
        w.set_stage_mm([29.0, 36.75, 5.3]);
        let a = w.wrench();
        std::thread::sleep(std::time::Duration::from_millis(20));
        assert_eq!(a, w.wrench(), "no noise, no relaxation");
        assert!((a.force_n[2] - flat_n(0.3)).abs() < 1e-12, "{a:?}");
    }

    #[test]
    fn relaxation_overshoots_by_the_fraction_and_decays_with_tau() {
        let r = ForceRelaxation {
            fraction: 0.2,
            time_constant_s: 0.05,
        };
        let w = world(BenchEffects {
            force_relaxation: Some(r),
            ..BenchEffects::default()
        });
        w.set_stage_mm([29.0, 36.75, 5.3]);
        let f0 = w.wrench().force_n[2];
        let fe = flat_n(0.3);
        // Read within a few ms of the step: (1 + a)·F_e, decayed by at most a few %.
        assert!(
            f0 > fe * 1.15 && f0 <= fe * 1.2 + 1e-12,
            "right after the step {f0} N vs elastic {fe} N"
        );
        std::thread::sleep(std::time::Duration::from_millis(400));
        let f1 = w.wrench().force_n[2];
        // 8 τ later the excess is below e^-8 ≈ 3e-4 of 0.2·F_e.
        assert!((f1 - fe).abs() < 1e-3 * fe, "relaxed {f1} N vs {fe} N");
        // Unloading relaxes the other way: the force undershoots.
        w.set_stage_mm([29.0, 36.75, 5.1]);
        let f2 = w.wrench().force_n[2];
        assert!(f2 < flat_n(0.1), "{f2} N after unloading");
    }

    #[test]
    fn ft_noise_has_the_listed_sigma_and_is_reproducible() {
        let n = FtNoise {
            sigma_n: 0.01,
            seed: 7,
        };
        let fx = BenchEffects {
            ft_noise: Some(n),
            ..BenchEffects::default()
        };
        let a = world(fx);
        let b = world(fx);
        a.set_stage_mm([29.0, 36.75, 5.3]);
        b.set_stage_mm([29.0, 36.75, 5.3]);
        let fe = flat_n(0.3);
        let xs: Vec<f64> = (0..4000).map(|_| a.wrench().force_n[2] - fe).collect();
        let ys: Vec<f64> = (0..4000).map(|_| b.wrench().force_n[2] - fe).collect();
        assert_eq!(xs, ys, "same seed, same stream");
        let m = xs.iter().sum::<f64>() / xs.len() as f64;
        let sd = (xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (xs.len() - 1) as f64).sqrt();
        // 4000 samples: SE of the mean 1.6e-4, of the SD ~1.1 %.
        assert!(m.abs() < 6e-4, "mean {m}");
        assert!((sd - 0.01).abs() < 0.0006, "sd {sd}");
    }

    #[test]
    fn a_carried_sensor_shifts_the_image_by_the_stage_travel_and_keeps_the_contact() {
        let w = world(BenchEffects {
            carry_zero_mm: Some([9.0, 6.75]),
            ..BenchEffects::default()
        });
        w.set_stage_mm([29.15, 36.75, 0.0]);
        let c = w.contact();
        assert_eq!(c.tip_in_sensor_mm, [9.0, 6.75]);
        assert_eq!(w.carry_shift_mm(&c), [29.15 - 20.0 - 9.0, 0.0]);
        let plain = world(BenchEffects::default());
        plain.set_stage_mm([29.15, 36.75, 0.0]);
        assert_eq!(plain.carry_shift_mm(&plain.contact()), [0.0, 0.0]);
    }

    /// The scale of the rendered displacement field against the ideal world's at the
    /// same stage position (largest displacement component).
    fn field_scale(w: &World, ideal: &World) -> f64 {
        let mut a = w.blank_frame();
        let mut b = ideal.blank_frame();
        let ua = w.render(&mut a).unwrap().elastic_u_mm;
        let ub = ideal.render(&mut b).unwrap().elastic_u_mm;
        let k = (0..ub.len())
            .max_by(|&i, &j| ub[i].abs().total_cmp(&ub[j].abs()))
            .unwrap();
        ua[k] / ub[k]
    }

    fn visco(creep: f64, time_constant_s: f64, hysteresis: f64) -> Arc<World> {
        world(BenchEffects {
            viscoelastic: Some(Viscoelastic {
                creep,
                time_constant_s,
                hysteresis,
            }),
            ..BenchEffects::default()
        })
    }

    #[test]
    fn without_the_viscoelastic_effect_the_field_has_no_creep_and_no_hysteresis() {
        let (w, ideal) = (
            world(BenchEffects::default()),
            world(BenchEffects::default()),
        );
        for z in [5.4, 5.2, 5.4, 5.1] {
            w.set_stage_mm([29.0, 36.75, z]);
            ideal.set_stage_mm([29.0, 36.75, z]);
            std::thread::sleep(std::time::Duration::from_millis(5));
            assert_eq!(field_scale(&w, &ideal), 1.0, "exact at z = {z}");
        }
        // Released: nothing left.
        w.set_stage_mm([29.0, 36.75, 0.0]);
        let mut img = w.blank_frame();
        assert!(w
            .render(&mut img)
            .unwrap()
            .elastic_u_mm
            .iter()
            .all(|u| *u == 0.0));
    }

    #[test]
    fn hysteresis_widens_the_unloading_field_by_the_configured_lens() {
        let h = 0.1;
        let (w, ideal) = (visco(0.0, 1.0, h), world(BenchEffects::default()));
        let at = |z: f64| {
            w.set_stage_mm([29.0, 36.75, z]);
            ideal.set_stage_mm([29.0, 36.75, z]);
            field_scale(&w, &ideal)
        };
        // Loading: on the elastic curve.
        assert!((at(5.2) - 1.0).abs() < 1e-12);
        assert!((at(5.4) - 1.0).abs() < 1e-12, "peak P = flat_n(0.4)");
        // Unloading to P/2 (flat punch: force ∝ depth): F + 4hF(P−F)/P = F(1 + 2h).
        assert!((at(5.2) - (1.0 + 2.0 * h)).abs() < 1e-12);
        // To P/4: 1 + 4h·3/4.
        assert!((at(5.1) - (1.0 + 3.0 * h)).abs() < 1e-12);
        // Back to the peak closes the loop; a release resets it.
        assert!((at(5.4) - 1.0).abs() < 1e-12);
        at(0.0);
        assert!((at(5.2) - 1.0).abs() < 1e-12, "a new contact loads afresh");
    }

    #[test]
    fn creep_grows_the_field_towards_one_plus_a_and_recovers_after_unloading() {
        let (a, tau) = (0.2, 0.02);
        let (w, ideal) = (visco(a, tau, 0.0), world(BenchEffects::default()));
        w.set_stage_mm([29.0, 36.75, 5.3]);
        ideal.set_stage_mm([29.0, 36.75, 5.3]);
        let s0 = field_scale(&w, &ideal);
        assert!((1.0..=1.0 + a).contains(&s0), "right after the step: {s0}");
        std::thread::sleep(std::time::Duration::from_millis(300));
        // 15 τ later: within a·e^-15 of 1 + a (a longer wait only comes closer).
        let s1 = field_scale(&w, &ideal);
        assert!((s1 - (1.0 + a)).abs() < 1e-6 * a, "{s1}");
        // Released: the last contact's field, scaled to the creep left, decays with τ.
        w.set_stage_mm([29.0, 36.75, 0.0]);
        let mut img = w.blank_frame();
        let u = w.render(&mut img).unwrap().elastic_u_mm;
        let residual = u.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(
            residual > 0.0,
            "creep recovery is visible right after unloading"
        );
        std::thread::sleep(std::time::Duration::from_millis(400));
        let u = w.render(&mut img).unwrap().elastic_u_mm;
        let later = u.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(
            later < residual * 1e-6,
            "recovered: {later} mm vs {residual} mm"
        );
        // The F/T side is untouched by this effect.
        w.set_stage_mm([29.0, 36.75, 5.3]);
        assert!((w.wrench().force_n[2] - flat_n(0.3)).abs() < 1e-12);
    }
}

#[cfg(test)]
mod mounting_tests {
    use super::*;
    use crate::sensor::paper_sensor;
    use crate::sim::effects::Pipeline;
    use crate::sim::render::to_rgb8;
    use crate::vision::{detect, DetectConfig, FrameView, MarkerStatus, TrackConfig, Tracker};

    fn world(indenter: Indenter, effects: BenchEffects) -> Arc<World> {
        let sim = Simulation::new(paper_sensor(), indenter, Pipeline::ideal());
        let g = WorldGeometry {
            sensor_origin_in_stage_mm: [20.0, 30.0],
            surface_z_mm: 5.0,
            friction: 1.0,
            ..WorldGeometry::default()
        };
        World::with_effects(sim, indenter, g, [29.0, 36.75, 0.0], effects)
    }

    const FLAT: Indenter = Indenter::Flat { diameter_mm: 5.0 };

    /// Presses to 0.3 mm at sensor point (9, 6.75) and travels 0.02 mm along +x and
    /// 0.01 mm along +y while stuck.
    fn press_and_shear(w: &World) -> Wrench {
        w.set_stage_mm([29.0, 36.75, 5.3]);
        w.set_stage_mm([29.02, 36.76, 5.3]);
        w.wrench()
    }

    #[test]
    fn a_rotated_ft_sensor_reports_the_transposed_rotation_of_the_force_and_torque() {
        let plain = press_and_shear(&world(FLAT, BenchEffects::default()));
        // Closed form of the plain world: Mindlin k = 8 G a / (2 − ν), G = 1/3 N/mm²,
        // a = 2.5 mm; P = 2 a E* δ with E* = 4/3 N/mm².
        let k = 8.0 / 3.0 * 2.5 / 1.5;
        let f = [k * 0.02, k * 0.01, 2.0 * 2.5 * (4.0 / 3.0) * 0.3];
        for (got, want) in plain.force_n.iter().zip(f) {
            assert!((got - want).abs() < 1e-9, "{plain:?}");
        }
        for theta in [90.0f64, 7.0, -30.0] {
            let w = press_and_shear(&world(
                FLAT,
                BenchEffects {
                    ft_rotation_deg: Some(theta),
                    ..BenchEffects::default()
                },
            ));
            // R(θ)ᵀ F written out: (c fx + s fy, −s fx + c fy, fz).
            let (s, c) = theta.to_radians().sin_cos();
            let want = [c * f[0] + s * f[1], -s * f[0] + c * f[1], f[2]];
            for (got, want) in w.force_n.iter().zip(want) {
                assert!((got - want).abs() < 1e-9, "θ = {theta}: {w:?}");
            }
            // Torque of the force at the tip 50 mm below the F/T origin, F/T axes.
            let l = 0.05;
            let m = [-l * want[1], l * want[0], 0.0];
            for (got, want) in w.torque_nm.iter().zip(m) {
                assert!((got - want).abs() < 1e-12, "θ = {theta}: {w:?}");
            }
            // The fit's convention undoes it.
            let mut p = crate::fit::ModelParams::nominal(&paper_sensor(), 5.0);
            p.ft_rotation_deg = theta;
            let back = p.ft_to_sensor(w.force_n);
            for (got, want) in back.iter().zip(f) {
                assert!((got - want).abs() < 1e-9, "θ = {theta}: {back:?}");
            }
        }
        // 90°: sensor +x reads as F/T −y.
        let w = press_and_shear(&world(
            FLAT,
            BenchEffects {
                ft_rotation_deg: Some(90.0),
                ..BenchEffects::default()
            },
        ));
        assert!((w.force_n[1] + k * 0.02).abs() < 1e-9, "{w:?}");
    }

    #[test]
    fn a_stage_offset_moves_the_contact_not_the_stage_or_the_force() {
        let offset = [0.4, -0.3];
        let w = world(
            FLAT,
            BenchEffects {
                stage_offset_mm: Some(offset),
                ..BenchEffects::default()
            },
        );
        let plain = world(FLAT, BenchEffects::default());
        for x in [&w, &plain] {
            x.set_stage_mm([29.0, 36.75, 5.3]);
        }
        assert_eq!(w.stage_mm(), [29.0, 36.75, 5.3]);
        assert_eq!(w.contact().tip_in_sensor_mm, [9.0 + 0.4, 6.75 - 0.3]);
        assert_eq!(w.wrench(), plain.wrench(), "the force law does not move");
    }

    /// The centre of a radial displacement field: the point `c` minimising
    /// `Σ (u × (x − c))²` (every tracked vector points along the line through `c`;
    /// Boussinesq's in-plane field at depth is radial about the load).
    fn radial_centre(points: &[([f64; 2], [f64; 2])]) -> [f64; 2] {
        // u_x c_y − u_y c_x = u_x y − u_y x per marker: normal equations of a 2×2.
        let (mut a, mut b) = ([[0.0; 2]; 2], [0.0; 2]);
        for (x, u) in points {
            let row = [-u[1], u[0]];
            let rhs = u[0] * x[1] - u[1] * x[0];
            for i in 0..2 {
                for j in 0..2 {
                    a[i][j] += row[i] * row[j];
                }
                b[i] += row[i] * rhs;
            }
        }
        let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
        [
            (b[0] * a[1][1] - a[0][1] * b[1]) / det,
            (a[0][0] * b[1] - a[1][0] * b[0]) / det,
        ]
    }

    /// Tracks the frame rendered at the world's current contact against its
    /// reference and returns the centre of the tracked field, sensor frame, mm.
    fn tracked_centre(w: &World) -> [f64; 2] {
        let sensor = paper_sensor();
        let mut img = w.blank_frame();
        w.render_reference(&mut img).unwrap();
        let reference = to_rgb8(&img);
        w.render(&mut img).unwrap();
        let loaded = to_rgb8(&img);
        let r = detect(
            &FrameView::rgb8(&reference),
            &sensor,
            &DetectConfig::default(),
        )
        .unwrap();
        let mut t = Tracker::new(r, TrackConfig::default());
        let tracks = t.track(&FrameView::rgb8(&loaded)).unwrap().to_vec();
        let records = t.displacement_records(&tracks, &sensor.camera);
        let ok = tracks
            .iter()
            .filter(|t| t.status == MarkerStatus::Ok)
            .count();
        assert!(ok > tracks.len() / 2, "{ok} of {} ok", tracks.len());
        // Markers with a clear signal (near-field markers under the punch's edge
        // move most; the far field is tracking noise).
        let field: Vec<([f64; 2], [f64; 2])> = records
            .iter()
            .filter_map(|r| Some((r.position_mm, r.u_mm?)))
            .filter(|(_, u)| u[0].hypot(u[1]) > 0.01)
            .collect();
        assert!(field.len() > 20, "{} markers with signal", field.len());
        radial_centre(&field)
    }

    #[test]
    fn the_tracked_field_is_centred_on_the_stage_notion_plus_the_offset() {
        let hemi = Indenter::Hemisphere { radius_mm: 2.5 };
        let offset = [0.4, -0.3];
        let w = world(
            hemi,
            BenchEffects {
                stage_offset_mm: Some(offset),
                ..BenchEffects::default()
            },
        );
        let plain = world(hemi, BenchEffects::default());
        for x in [&w, &plain] {
            x.set_stage_mm([29.0, 36.75, 5.6]);
        }
        let c0 = tracked_centre(&plain);
        let c1 = tracked_centre(&w);
        // The stage's notion is (9, 6.75); tracking and rendering error well under
        // a tenth of the offset.
        assert!(
            (c0[0] - 9.0).abs() < 0.03 && (c0[1] - 6.75).abs() < 0.03,
            "no offset: centre {c0:?}"
        );
        assert!(
            (c1[0] - 9.4).abs() < 0.03 && (c1[1] - 6.45).abs() < 0.03,
            "offset {offset:?}: centre {c1:?}"
        );
    }
}

#[cfg(test)]
mod body_tests {
    use super::*;
    use crate::model::indentation::reduced_modulus;
    use crate::sim::scene::Scene;

    /// The world of a scene file under experiments/scenes/misbuilt, its tip over
    /// sensor point (9, 6.75), the surface at stage z = 5.
    fn scene_world(name: &str) -> (Arc<World>, Scene) {
        let path = format!(
            "{}/experiments/scenes/misbuilt/{name}",
            env!("CARGO_MANIFEST_DIR")
        );
        let scene = Scene::from_path(&path).expect("the misbuilt scenes parse");
        let g = WorldGeometry {
            sensor_origin_in_stage_mm: [20.0, 30.0],
            surface_z_mm: 5.0,
            ..WorldGeometry::default()
        };
        let sim = Simulation::from_scene(&scene);
        let w = World::with_effects(sim, scene.indenter, g, [29.0, 36.75, 0.0], scene.bench);
        (w, scene)
    }

    #[test]
    fn a_bonded_6mm_scene_presses_with_the_layer_law_and_harder_than_the_half_space() {
        let (w, scene) = scene_world("bonded_6mm.toml");
        let e = &scene.sensor.elastomer;
        assert_eq!(e.model, ModelKind::BondedLayer);
        assert_eq!(e.thickness_mm, 6.0);
        let e_star = reduced_modulus(e.young_modulus_n_per_mm2(), e.poisson_ratio);
        let shape = Shape::Hemisphere { radius_mm: 2.5 };
        let layer = Body::BondedLayer { thickness_mm: 6.0 };
        for depth in [0.2, 0.5, 1.0] {
            w.set_stage_mm([29.0, 36.75, 5.0 + depth]);
            // The depth the world sees, rounded through the stage z.
            let d = (5.0 + depth) - 5.0;
            let fz = w.wrench_without_noise().force_n[2];
            let want = indentation_force(shape, layer, e_star, d).force_n;
            let half = indentation_force(shape, Body::HalfSpace, e_star, d).force_n;
            assert_eq!(fz, want, "depth {d} mm");
            // The rigid plate 6 mm down stiffens the contact well beyond the noise.
            assert!(
                fz > 1.1 * half,
                "depth {d} mm: layer {fz} N, half-space {half} N"
            );
        }
    }

    #[test]
    fn a_half_space_scene_presses_with_hertz_exactly() {
        let (w, scene) = scene_world("e_minus30.toml");
        let e = &scene.sensor.elastomer;
        assert_eq!(e.model, ModelKind::HalfSpace);
        let e_star = e.young_modulus_n_per_mm2() / (1.0 - e.poisson_ratio * e.poisson_ratio);
        for depth in [0.2, 0.5, 1.0, 3.0] {
            w.set_stage_mm([29.0, 36.75, 5.0 + depth]);
            let d = (5.0 + depth) - 5.0;
            let fz = w.wrench_without_noise().force_n[2];
            // Closed form as written before the layer law existed (past the
            // equator at 2.5 mm the flank presses like a punch).
            let want = if d <= 2.5 {
                4.0 / 3.0 * e_star * 2.5f64.sqrt() * d.powf(1.5)
            } else {
                4.0 / 3.0 * e_star * 2.5f64.sqrt() * 2.5f64.powf(1.5)
                    + 2.0 * 2.5 * e_star * (d - 2.5)
            };
            assert_eq!(fz, want, "depth {d} mm");
        }
    }
}
