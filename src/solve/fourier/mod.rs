//! `fourier`: regularised inversion on regular grids by per-frequency solves, `O(N log N)`
//! per frame.
//!
//! # Model
//!
//! The half-space response (Eq. 1–2, [`HalfSpace::point_response`]) depends only on the
//! horizontal offset between marker and force point, so on regular grids `u = H f` is a
//! (multi-channel, multi-rate) convolution. Force nodes sit at `x_j = o_f + p_f·j`
//! (`sensor.force_grid`), markers of layer `ℓ` at `y_i = o_ℓ + p_m·i` (the layer's marker
//! grid; all layers share one pitch `p_m`, origins are arbitrary). With a fine pitch `h`,
//! `p_f = a·h`, `p_m = b·h` (`a`, `b` coprime, `a·b ≤` [`MAX_LCM`]):
//!
//! ```text
//! u_ℓ[i] = Σ_j k_ℓ[b·i − a·j] f[j],     k_ℓ[t] = K(o_ℓ − o_f + h·t, depth_ℓ)      (per axis)
//!        = down_b( k_ℓ ∗ up_a(f) )[i]
//! ```
//!
//! Any sub-pitch offset between a layer and the force grid is absorbed exactly into the
//! sampled kernel `k_ℓ`.
//!
//! The kernel `K` is the sensor's model (`[elastomer] model`, [`crate::model::ForwardModel`]).
//! For the half-space, `k_ℓ` samples Eq. 1–2 on the kernel window. For the bonded layer
//! the direct solve uses the layer's closed-form Fourier kernel
//! ([`crate::model::layer_kernel`]) directly in frequency space: per fine frequency the
//! 2 × 3 block of each layer at its depth, aliases folded in, with the in-plane phase
//! `exp(i k·(o_ℓ − o_f))` of the layer offset, and the finite `k = 0` term of the
//! uniform-traction layer (`kernel.rs`); the refinement's exact operator `H` samples
//! the layer's real-space responses through the same [`crate::model::ElasticModel`]
//! trait the dense solvers build `H` with, so it converges to their solution. On a periodic fine grid of `N` nodes per axis (`N` a multiple of
//! `L = a·b`, 2-3-5-7-smooth) the DFT turns this into (per axis, unnormalised DFTs, `M = N/L`,
//! marker lattice period `N/b = a·M`, force lattice period `N/a = b·M`):
//!
//! ```text
//! U_ℓ[c + s'M] = (1/b) Σ_{t=0}^{L−1, t ≡ s' (mod a)} K̂_ℓ[c + tM] · F[c + (t mod b)M]
//! ```
//!
//! so the operator is block-diagonal: block `c = (c_x, c_y)` couples `b²` force
//! frequencies (3 unknowns each) with `a²` marker frequencies (2 values per layer). In the
//! unitary scaling (`Ũ = U/√(#markers of the lattice)`, `F̃ = F/√(#force nodes)`) the block
//! entries are `K̂_ℓ/(a·b)` and the block singular values are exactly the singular values
//! of the periodic operator. Each block is solved by Tikhonov regularisation from its SVD
//! `A_c = U Σ Vᴴ`: `P_c = V diag(σ/(σ²+λ²)) Uᴴ` (λ = 0: `1/σ` above the cut-off
//! `rcond·σ_max`, else 0, so null blocks such as the uniform normal load stay finite).
//! λ is fixed or chosen by GCV / L-curve on the given frame, evaluated in the Fourier
//! domain (Hansen, *Rank-Deficient and Discrete Ill-Posed Problems*, SIAM 1998, §7),
//! which is exact for the periodic operator because the transform is unitary.
//!
//! # Boundaries
//!
//! `N ≥ b(n_m − 1) + a(n_f − 1) + 1 + padding`, where the padding is
//! `fourier_padding × (larger of the force and marker grid extents)` per axis, so circular
//! convolution equals linear convolution for every (marker, force node) pair of the real
//! grids: the kernel window contains every offset that occurs. The periodic *model*,
//! however, has markers in the padding, which are not measured, and forces on the whole
//! periodic force lattice, which are cropped to the force grid afterwards:
//!
//! - by default ([`FourierSolver::bridge_edges`]) each padding marker gets a raised-cosine
//!   blend of the two opposite edge markers of its row / column, so the periodic
//!   displacement field has no jump at the grid boundary; with `bridge_edges = false` the
//!   padding counts as measured zero displacement (the textbook periodic model);
//! - λ selection (GCV, L-curve) and the diagnostics use the zero-padded periodic model.
//!   The L-curve corner works well there; GCV under-regularises, because the padding rows
//!   look like noise-free measurements (16×16 grid, 0.005 mm noise: GCV picks λ ≈ 10×
//!   too small, force error 1.7 vs 0.55 with the L-curve). Prefer `lcurve` or a fixed λ.
//!
//! Real displacements do not vanish (nor follow the bridge) outside the marker area: they
//! decay like `1/r`. The direct solve therefore has a boundary error, and on the small
//! grids of issue 12 it is not a small edge effect but the whole answer: on
//! `grid_sensor(16,16,1.1,1.1)` (layers at 3 and 6 mm, the second offset by half a pitch)
//! with a centred 2 mm Gaussian shear load (fx only, 2.08 N) at λ = 1e-2·σ₁ (σ₁ of the
//! dense `H`) it returns F_sum = (1.09, 0.002, −2.16) N where dense Tikhonov gives
//! (2.09, 0.000, −0.002) N.
//!
//! **Cause** (issue 12). The periodic problem, where the method is exact, is solved
//! exactly: the unit tests below compare the per-frequency solve with dense Tikhonov on
//! the periodised `H` (every marker of the periodic lattice against every force node,
//! kernel sampled on the documented window) to 1e-10, for a half-pitch layer offset and
//! for multi-rate grids with arbitrary offsets, so the kernel, the sign of the Cerruti
//! coupling, the sub-pitch phase and the transform convention are right (the exact
//! operator `H` built from the same spectra also matches direct summation of Eq. 1–2 to
//! 1e-12). The error is the periodic model of the boundary: the padding markers count as
//! data (zeros or the bridge) and forces live on the whole periodic lattice. fz is told
//! apart from fx only by how the displacement changes with depth, i.e. by the ratio of
//! the two layers; the padded fields of the two layers (each bridged or zeroed on its
//! own, the second one half a pitch further out) are not the field of any surface load at
//! those depths, and the per-frequency solve explains the mismatch with fz (the false
//! −2.16 N) and explains part of the shear by forces in the padding, which the crop
//! drops (fx 1.09 of 2.09 N). Measured, direct solve against dense Tikhonov at
//! λ = 1e-2·σ₁ on five loads (centred fx, fz, mixed; off-centre fy, mixed): force sums off
//! by 9–125 % of the applied total, field 13–72 % overall, 7–39 % on the interior
//! (≥ 4 mm from the edges); with other paddings (0, 0.25) or without the bridge the
//! worst of the five loads is still off by 64–135 % in the force sums.
//!
//! **Fix: the two-level solve** (`coarse.rs`, the default). The direct solve's error is
//! mostly smooth (force sums, a broad false normal load), so it is removed by a
//! correction precomputed once per marker set: the Galerkin projection of the remaining
//! error onto a coarse space `Φ` of the force grid (bilinear hats every `s` force nodes)
//! in the norm of the normal equations, `f = f_d + Φ C u`, and the force sums are then
//! set to those of dense Tikhonov exactly (`ΣF_a = w_aᵀu`, `w_a = H N⁻¹ 1_a` from three
//! converged CG solves). `C` (`k × n_in`) is built from `k` applications of the exact
//! normal operator and of the transposed direct solve; `s` is the smallest spacing that
//! keeps `k·n_in` within [`coarse::COARSE_BUDGET`] (on small grids `Φ = I`, and the
//! two-level solve *is* dense Tikhonov). Measured against dense Tikhonov at λ = 2e-3 of
//! the periodic σ_max on the five acceptance loads (worst): 16×16 exact to 1.3e-7 (`s = 1`);
//! 32×32 (`s = 3`, `k = 432`) force sums to 1e-8, field 3.0 % / 1.6 % interior; 64×64
//! (`s = 11`, `k = 147`) force sums to 1e-8, field 3.6 % / 2.1 %; 1.2 ms per frame at
//! 64×64 against 0.69 ms for the direct solve alone (README *Performance*).
//! [`FourierSolver::coarse_correction`] `= false` (CLI `--coarse-correction off`) is the
//! direct solve alone, where speed matters more than accuracy.
//!
//! Refinement iterations (opt-in, [`FourierSolver::refine_iterations`]) converge further
//! to dense Tikhonov from the two-level (or direct) solve.
//!
//! Refinement: preconditioned CGLS (conjugate gradients on the normal equations of
//! `min ‖H f − u‖² + λ²‖f‖²`, Björck, *Numerical Methods for Least Squares Problems*,
//! SIAM 1996, §7.4) on the exact operator `H` restricted to the measured markers and the
//! force grid, applied by the same FFTs (exact: the kernel window holds every offset),
//! warm-started from the two-level (or direct) solve and preconditioned by the periodic block inverse
//! `M = (AᴴA + λ²I)⁻¹` (a block circulant preconditioner, T. Chan 1988). Each iteration
//! costs about three direct solves. It stops when the preconditioned gradient
//! `z = M(Hᵀ(u − Hf) − λ²f)` has `‖z‖ ≤ tol·‖f‖` (`z ≈` the remaining correction, so
//! this estimates the relative distance to dense Tikhonov), at the cap, or when the
//! gradient has fallen to rounding (CGLS run on past that point diverged). Measured at
//! λ ≈ 1e-2·σ₁ on the five acceptance loads, from the direct solve: 16×16, tolerance
//! 0.02 → 22 iterations, ΣF within 0.4 % and field within 1.9 % of dense Tikhonov;
//! 32×32 → 22 iterations, 0.7 % / 1.3 %. From the two-level solve far fewer are needed
//! (32×32: 5 iterations to field 1.0 %; README *Performance* has the whole table). The preconditioner is exact for the
//! periodic problem but not for the measured one (no markers in the padding, no forces
//! outside the grid): the mismatch lives on the boundary and grows with the grid, so
//! the iterations needed grow with it. For small λ (≲ 1e-3·σ_max) convergence is slower
//! and the first iterates can be worse than the direct solve (CGLS minimises the
//! residual, not the force error).
//!
//! # Per frame
//!
//! `ux + i·uy` of each layer goes through one complex 2-D FFT (x then y; the x pass runs
//! on the marker rows only: padding rows are zero or, with the bridge, blends of two
//! transformed rows, since the transform is linear); the real spectra are separated by conjugate symmetry; the
//! blocks with `c_x ≤ M_x/2` are applied (the others follow by Hermitian symmetry);
//! `fx + i·fy` and `fz` are transformed back (only the rows of the force grid in the last
//! pass) and cropped. Plans, scratch and all buffers live in the struct: no allocation.
//!
//! # Refused geometries
//!
//! [`SolveError::Incompatible`] when a marker is not on its layer's regular grid (more
//! than `1e-3` pitch off, e.g. a rotated grid), when markers of a layer grid are missing
//! (lost markers: use a dense solver), when layers have different pitches or a layer has
//! no regular grid, or when `p_f/p_m` is not a ratio of small integers (the paper's
//! 2.2 mm / 1.5 mm = 22/15 is refused; markers every 1.1 mm or 2.2 mm would work).

mod build;
mod coarse;
mod grid;
mod kernel;
mod lambda;
mod refine;
mod transform;
mod uncertainty;

use std::sync::OnceLock;

use rustfft::FftPlanner;

use super::{
    check_input, check_output, Diagnostics, FrameSolver, Problem, SolveError, SolverConfig,
};

pub use grid::{MAX_LCM, OFF_GRID_TOLERANCE};
use transform::{markers_to_forces, Plan, Work, C64};

/// Largest accepted `fourier_padding`: beyond it the FFTs grow without improving the
/// periodic model noticeably.
const MAX_PADDING: f64 = 8.0;

/// Cap on the CGLS refinement iterations a new [`FourierSolver`] runs after the
/// two-level solve: none. The two-level solve (direct periodic solve + coarse correction,
/// `coarse.rs`) already meets issue 12's bounds against dense Tikhonov (force sums exact,
/// field within 3.6 % / 2.1 % interior on the 64×64 acceptance loads) in 1.2 ms at 64×64;
/// refinement iterations converge further to dense Tikhonov at ~3 direct solves each.
pub const DEFAULT_REFINE_ITERATIONS: usize = 0;

/// Default stopping tolerance of the refinement ([`FourierSolver::refine_tolerance`]):
/// the largest that meets issue 12's bounds (ΣF within 2 %, field within 10 % / 5 %
/// interior of dense Tikhonov) on the 16×16 and 32×32 acceptance loads with a margin
/// (measured at the issue's λ: 16×16 22 iterations, ΣF 0.4 %, field 1.9 %; 32×32 22
/// iterations, 0.7 % / 1.3 %; README *Performance* has the trade-off table).
pub const DEFAULT_REFINE_TOLERANCE: f64 = 2e-2;

/// Largest accepted refinement count ([`SolverConfig::fourier_refine_iterations`]):
/// 80 iterations already agree with dense Tikhonov to 1e-6.
pub const MAX_REFINE_ITERATIONS: usize = 1000;

/// The fine-grid geometry a [`FourierSolver`] found for its problem.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FourierGeometry {
    /// `a` in `p_f = a·h`.
    pub force_factor: usize,
    /// `b` in `p_m = b·h`.
    pub marker_factor: usize,
    /// The fine pitch `h`, mm.
    pub fine_pitch_mm: f64,
    /// Fine period `N` per axis (x, y), nodes.
    pub period: [usize; 2],
    /// Number of frequency blocks per axis (`N / (a·b)`).
    pub blocks: [usize; 2],
    /// Rows × columns of one frequency block (`2·layers·a²`, `3·b²`).
    pub block_shape: (usize, usize),
}

/// The `fourier` solver: precomputed per-frequency Tikhonov solutions.
pub struct FourierSolver {
    /// The two-level correction of the bridged direct solve (`coarse.rs`); `None` for
    /// λ = 0 or when it could not be built (the reason is in the diagnostics' notes).
    coarse: Option<coarse::Coarse>,
    /// Per-node SDs of the two-level map, computed on first use.
    noise_twolevel_force: OnceLock<Vec<f64>>,
    /// Force-sum SDs (per unit σ) of the bridged direct map, exact.
    noise_bridged_sum: [f64; 3],
    /// Noise figures of the zero-padded direct map (exact; [`uncertainty`]).
    noise_direct: uncertainty::NoiseFigures,
    /// Force-sum SDs of the converged refined map (dense Tikhonov), λ > 0 only.
    noise_refined_sum: Option<[f64; 3]>,
    /// Per-node SDs of the converged refined map and of the bridged direct map, each
    /// computed by probing on first use ([`uncertainty::probe_force_sd`]).
    noise_refined_force: OnceLock<Option<Vec<f64>>>,
    noise_bridged_force: OnceLock<Vec<f64>>,
    plan: Plan,
    work: Work,
    /// Per processed block, `cols × rows` solution operator (unitary scaling).
    p: Vec<C64>,
    /// Per processed block, `rows × cols` forward operator (unitary scaling).
    a: Vec<C64>,
    /// Per processed block, `cols × cols` preconditioner `(AᴴA + λ²I)⁻¹` (λ > 0 only).
    q: Vec<C64>,
    lambda: f64,
    geometry: FourierGeometry,
    diag: Diagnostics,
    n_in: usize,
    n_out: usize,
    /// Cap on the CGLS iterations on the exact (non-periodic) operator after the direct
    /// periodic solve ([`DEFAULT_REFINE_ITERATIONS`]); 0 is the plain direct solve. Each
    /// iteration costs about three direct solves; see the module docs.
    pub refine_iterations: usize,
    /// The refinement stops before the cap once its estimate of the relative distance
    /// to dense Tikhonov, `‖M·gradient‖/‖f‖`, is at most this ([`DEFAULT_REFINE_TOLERANCE`];
    /// 0 = always run the cap; λ > 0 only).
    pub refine_tolerance: f64,
    /// Refinement iterations run by the last [`FrameSolver::apply`].
    last_refine_iterations: usize,
    /// Precondition the refinement with the periodic block inverse `(AᴴA + λ²I)⁻¹`
    /// (default true; ignored for λ = 0).
    pub refine_preconditioned: bool,
    /// Fill the padding with a smooth bridge between opposite edges of each marker grid
    /// instead of zeros before the direct solve (default true; see the module docs).
    pub bridge_edges: bool,
    /// Add the precomputed coarse-space correction with exact force sums to the bridged
    /// direct solve (default true; `coarse.rs`). It applies only with `bridge_edges`.
    pub coarse_correction: bool,
}

impl std::fmt::Debug for FourierSolver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FourierSolver")
            .field("geometry", &self.geometry)
            .field("lambda", &self.lambda)
            .field("refine_iterations", &self.refine_iterations)
            .finish_non_exhaustive()
    }
}

impl FourierSolver {
    /// Precomputes the solver for `problem` (see the module docs). `frame` (mm, the order
    /// of `problem.sites`) is needed for automatic λ (GCV, L-curve) and ignored for a
    /// fixed λ.
    pub fn precompute(
        problem: &Problem<'_>,
        config: &SolverConfig,
        frame: Option<&[f64]>,
    ) -> Result<FourierSolver, SolveError> {
        let sizes = build::check_options(problem, config, frame)?;
        let (sensor, sites) = (problem.sensor, problem.sites);
        // Sites to (layer slot, lattice node) on the commensurate fine grid.
        let slots = build::layer_slots(sensor, sites)?;
        let fine = build::fine_grid(sensor, &slots, config.fourier_padding)?;
        let site_map = build::site_map(sensor, sites, &slots, &fine)?;
        // Kernel spectra, then every frequency block and its SVD.
        let mut planner = FftPlanner::<f64>::new();
        let (exact, periodic) = build::kernel_spectra(
            &problem.forward_model(),
            sensor,
            &slots,
            &fine,
            &mut planner,
        )?;
        let blocks = build::frequency_blocks(fine.m);
        let svds = build::block_svds(&fine, &blocks, &exact, &periodic)?;
        drop((exact, periodic));
        let (h, period, m) = (fine.h, fine.period, fine.m);
        let plan = build::make_plan(fine, &svds, blocks, site_map, &mut planner);
        let mut work = build::make_work(&plan, sizes.0, sizes.1);
        // λ, then the solution operators and the refinement preconditioner.
        let mut notes = Vec::new();
        let lambda = build::select_lambda(config, frame, &plan, &mut work, &svds, &mut notes)?;
        let filter = build::Filter {
            lambda,
            cutoff: build::cutoff(&plan, &svds, config),
        };
        let nb = plan.blocks.len();
        let pmat = build::solution_operators(&svds, nb, filter);
        let qmat = build::preconditioner(&svds, nb, lambda);
        let mut diag = build::diagnostics(&plan, &svds, filter, h, period, sizes, notes);
        let geometry = FourierGeometry {
            force_factor: plan.a,
            marker_factor: plan.b,
            fine_pitch_mm: h,
            period,
            blocks: m,
            block_shape: (plan.rows, plan.cols),
        };
        let amat = svds.amat;
        let noise = build::noise_and_coarse(
            &plan,
            &mut work,
            (&pmat, &amat, &qmat),
            lambda,
            config.fourier_coarse,
            sizes,
            &mut planner,
            &mut diag,
        );
        Ok(FourierSolver {
            coarse: noise.coarse,
            noise_twolevel_force: OnceLock::new(),
            noise_bridged_sum: noise.noise_bridged_sum,
            noise_direct: noise.noise_direct,
            noise_refined_sum: noise.noise_refined_sum,
            noise_refined_force: OnceLock::new(),
            noise_bridged_force: OnceLock::new(),
            plan,
            work,
            p: pmat,
            a: amat,
            q: qmat,
            lambda,
            geometry,
            diag,
            n_in: sizes.0,
            n_out: sizes.1,
            refine_iterations: config.fourier_refine_iterations,
            refine_tolerance: config.fourier_refine_tolerance,
            last_refine_iterations: 0,
            refine_preconditioned: true,
            bridge_edges: true,
            coarse_correction: config.fourier_coarse,
        })
    }

    /// The fine-grid geometry in use.
    pub fn geometry(&self) -> FourierGeometry {
        self.geometry
    }

    /// λ in use, mm/N.
    pub fn lambda(&self) -> f64 {
        self.lambda
    }

    /// Sets the cap on the CGLS refinement iterations (builder style).
    pub fn with_refinement(mut self, iterations: usize) -> Self {
        self.refine_iterations = iterations;
        self
    }

    /// Sets the refinement's stopping tolerance (builder style; 0 = run the cap).
    pub fn with_refine_tolerance(mut self, tolerance: f64) -> Self {
        self.refine_tolerance = tolerance;
        self
    }

    /// Refinement iterations the last [`FrameSolver::apply`] ran (0 for the direct solve).
    pub fn last_refine_iterations(&self) -> usize {
        self.last_refine_iterations
    }

    /// Whether [`FrameSolver::apply`] adds the two-level correction: it was built
    /// (λ > 0), [`FourierSolver::coarse_correction`] is on and the padding is bridged.
    pub fn two_level(&self) -> bool {
        self.coarse.is_some() && self.coarse_correction && self.bridge_edges
    }

    /// `(k, coarse spacing in force nodes)` of the two-level correction, if built.
    pub fn coarse_space(&self) -> Option<(usize, usize)> {
        self.coarse.as_ref().map(|c| (c.len(), c.shape().0))
    }

    fn active_coarse(&mut self) -> Option<&mut coarse::Coarse> {
        if self.coarse_correction && self.bridge_edges {
            self.coarse.as_mut()
        } else {
            None
        }
    }
}

impl FourierSolver {
    /// Per-node SDs per unit σ of the map the current settings apply (module docs of
    /// [`uncertainty`]): the converged refined map when refining with λ > 0, else the
    /// direct map with or without the edge bridge. Computed on first use, then cached.
    fn force_sd_unit(&self) -> &[f64] {
        let (plan, n_in, n_out) = (&self.plan, self.n_in, self.n_out);
        let spacing = uncertainty::PROBE_SPACING;
        // The zero-padded direct map, probed with the same probes: a control variate.
        let direct_probed = |w: &mut Work| {
            uncertainty::probe_force_var(plan, spacing, n_out, |z, f| {
                markers_to_forces(plan, w, &self.p, false, z, 1.0, false, f)
            })
        };
        let combine = |probed: Vec<f64>, control: Vec<f64>| -> Vec<f64> {
            probed
                .iter()
                .zip(&control)
                .zip(&self.noise_direct.force)
                .map(|((p, c), d)| (p - c + d * d).max(0.0).sqrt())
                .collect()
        };
        if self.refine_iterations > 0 {
            let refined = self.noise_refined_force.get_or_init(|| {
                let mut w = self.work.clone();
                let probed = uncertainty::converged_force_sd(
                    plan,
                    &mut w,
                    &self.a,
                    &self.q,
                    self.coarse.as_ref().map(|c| c.space()),
                    self.lambda,
                    spacing,
                    n_in,
                    n_out,
                )?;
                Some(combine(probed, direct_probed(&mut w)))
            });
            if let Some(v) = refined {
                return v;
            }
        }
        if let (true, Some(c)) = (self.two_level(), &self.coarse) {
            // The two-level map D + ΦC, probed like the others (its coarse part is smooth:
            // the cross terms it adds average out like those of the direct part).
            return self.noise_twolevel_force.get_or_init(|| {
                let mut w = self.work.clone();
                let mut c = c.clone();
                let probed = uncertainty::probe_force_var(plan, spacing, n_out, |z, f| {
                    markers_to_forces(plan, &mut w, &self.p, false, z, 1.0, true, f);
                    c.apply(z, 1.0, f);
                });
                combine(probed, direct_probed(&mut w))
            });
        }
        if self.bridge_edges {
            return self.noise_bridged_force.get_or_init(|| {
                let mut w = self.work.clone();
                let probed = uncertainty::probe_force_var(plan, spacing, n_out, |z, f| {
                    markers_to_forces(plan, &mut w, &self.p, false, z, 1.0, true, f)
                });
                combine(probed, direct_probed(&mut w))
            });
        }
        &self.noise_direct.force
    }
}

/// The noise level of the uncertainty figures must be a finite number ≥ 0.
fn check_sigma(sigma_mm: f64) -> Result<(), SolveError> {
    if sigma_mm.is_finite() && sigma_mm >= 0.0 {
        Ok(())
    } else {
        Err(SolveError::InvalidOption(format!(
            "displacement noise σ = {sigma_mm} mm must be a finite number >= 0"
        )))
    }
}

impl FrameSolver for FourierSolver {
    fn n_inputs(&self) -> usize {
        self.n_in
    }

    fn n_outputs(&self) -> usize {
        self.n_out
    }

    fn apply(&mut self, u_mm: &[f64], f_n: &mut [f64]) -> Result<(), SolveError> {
        check_input(u_mm, self.n_in)?;
        check_output(f_n, self.n_out)?;
        // The operator is linear: rescale huge inputs so intermediate sums cannot overflow.
        let umax = super::max_abs(u_mm);
        let in_scale = if umax > 1e100 { 1.0 / umax } else { 1.0 };
        markers_to_forces(
            &self.plan,
            &mut self.work,
            &self.p,
            false,
            u_mm,
            in_scale,
            self.bridge_edges,
            f_n,
        );
        if let Some(c) = self.active_coarse() {
            c.apply(u_mm, in_scale, f_n);
        }
        self.last_refine_iterations = if self.refine_iterations > 0 {
            self.refine(u_mm, in_scale, f_n)
        } else {
            0
        };
        if in_scale != 1.0 {
            for v in f_n.iter_mut() {
                *v /= in_scale;
            }
        }
        Ok(())
    }

    fn diagnostics(&self) -> &Diagnostics {
        &self.diag
    }

    fn force_sd(&self, sigma_mm: f64, out: &mut [f64]) -> Result<(), SolveError> {
        check_sigma(sigma_mm)?;
        check_output(out, self.n_out)?;
        let unit = self.force_sd_unit();
        for (o, s) in out.iter_mut().zip(unit) {
            *o = sigma_mm * s;
        }
        Ok(())
    }

    fn sum_sd(&self, sigma_mm: f64) -> Result<[f64; 3], SolveError> {
        check_sigma(sigma_mm)?;
        // The refined and the two-level solves have the force sums of dense Tikhonov.
        let unit = match self.noise_refined_sum {
            Some(s) if self.refine_iterations > 0 || self.two_level() => s,
            _ if self.bridge_edges => self.noise_bridged_sum,
            _ => self.noise_direct.sum,
        };
        Ok(unit.map(|s| sigma_mm * s))
    }
}

#[cfg(test)]
mod tests {
    //! The periodic problem, where the Fourier method is exact: separates kernel, sign,
    //! phase and transform errors from the boundary model.
    use super::transform::fft2_transposed;
    use super::*;
    use crate::model::MarkerSite;
    use crate::sensor::grid_sensor;
    use crate::solve::{Lambda, Method};
    use nalgebra::{DMatrix, DVector};

    /// Deterministic values in [-0.5, 0.5) (an LCG), shared by the Fourier tests.
    pub(super) fn pseudo_random(n: usize, seed: u64) -> Vec<f64> {
        let mut x = seed;
        (0..n)
            .map(|_| {
                x = x
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (x >> 11) as f64 / (1u64 << 53) as f64 - 0.5
            })
            .collect()
    }

    /// The periodic exactness check shared by the half-space and bonded-layer tests:
    /// dense Tikhonov with the periodised transfer matrix `c` (rows: the `nl` marker
    /// lattices of `solver.plan.mm`, columns: the force lattice) against the solver's
    /// per-frequency solve of the same whole-lattice data. Returns the largest
    /// difference and the solution's scale.
    pub(super) fn periodic_solve_error(
        solver: &FourierSolver,
        c: &DMatrix<f64>,
        lambda: f64,
        nl: usize,
    ) -> (f64, f64) {
        let mm = solver.plan.mm;
        let (nrow, ncol) = c.shape();
        let u = pseudo_random(nrow, 11);
        let ct = c.transpose();
        let lhs = &ct * c + DMatrix::<f64>::identity(ncol, ncol) * (lambda * lambda);
        let want = lhs
            .lu()
            .solve(&(&ct * DVector::from_column_slice(&u)))
            .unwrap();
        let mut planner = FftPlanner::<f64>::new();
        let spec: Vec<Vec<C64>> = (0..nl)
            .map(|li| {
                let base = li * mm[0] * mm[1] * 2;
                let mut z: Vec<C64> = (0..mm[0] * mm[1])
                    .map(|k| C64::new(u[base + 2 * k], u[base + 2 * k + 1]))
                    .collect();
                fft2_transposed(&mut planner, &mut z, mm[0], mm[1])
            })
            .collect();
        let got = uncertainty::solve_lattice(&solver.plan, &spec, &solver.p, &mut planner);
        let got: Vec<f64> = got.iter().flatten().copied().collect();
        let scale = want.amax();
        let err = got
            .iter()
            .zip(want.iter())
            .map(|(g, w)| (g - w).abs())
            .fold(0.0, f64::max);
        (err, scale)
    }

    /// Dense Tikhonov with the periodised `H` (every marker of the periodic marker
    /// lattice against every node of the periodic force lattice, the kernel sampled at
    /// the lattice offset's representative in the documented window `[lo, lo + N)`),
    /// against the solver's per-frequency solve of the same whole-lattice data.
    fn periodic_case(nx: usize, ny: usize, pf: f64, pm: f64, offset: [f64; 2]) {
        let mut s = grid_sensor(nx, ny, pf, pm);
        s.layers[1].markers.as_mut().unwrap().grid.origin_mm = offset;
        let sites = MarkerSite::from_sensor_grids(&s);
        let p = Problem::new(&s, &sites);
        let lambda = 0.05;
        let cfg = SolverConfig {
            method: Method::Fourier,
            lambda: Lambda::Fixed(lambda),
            fourier_padding: 0.0,
            ..SolverConfig::default()
        };
        let solver = FourierSolver::precompute(&p, &cfg, None).unwrap();
        let g = solver.geometry();
        let (a, b, h, period) = (g.force_factor, g.marker_factor, g.fine_pitch_mm, g.period);
        let (mm, mf) = (solver.plan.mm, solver.plan.mf);
        let fg = s.force_grid;
        let nf = [fg.nx, fg.ny];
        let nl = s.layers.len();
        let (nrow, ncol) = (2 * nl * mm[0] * mm[1], 3 * mf[0] * mf[1]);
        let mut c = DMatrix::<f64>::zeros(nrow, ncol);
        for (li, layer) in s.layers.iter().enumerate() {
            let grid = layer.markers.unwrap().grid;
            let nm = [grid.nx, grid.ny];
            let mut lo = [0i64; 2];
            for ax in 0..2 {
                let span = a * (nf[ax] - 1) + b * (nm[ax] - 1) + 1;
                lo[ax] = -((a * (nf[ax] - 1)) as i64) - ((period[ax] - span) / 2) as i64;
            }
            for iy in 0..mm[1] {
                for ix in 0..mm[0] {
                    for jy in 0..mf[1] {
                        for jx in 0..mf[0] {
                            let t = [
                                (b * ix) as i64 - (a * jx) as i64,
                                (b * iy) as i64 - (a * jy) as i64,
                            ];
                            let w: Vec<f64> = (0..2)
                                .map(|ax| {
                                    (lo[ax] + (t[ax] - lo[ax]).rem_euclid(period[ax] as i64)) as f64
                                })
                                .collect();
                            let dx = grid.origin_mm[0] - fg.origin_mm[0] + h * w[0];
                            let dy = grid.origin_mm[1] - fg.origin_mm[1] + h * w[1];
                            let r = p.model.point_response(dx, dy, layer.depth_mm);
                            let row = ((li * mm[1] + iy) * mm[0] + ix) * 2;
                            let col = (jy * mf[0] + jx) * 3;
                            for i in 0..2 {
                                for k in 0..3 {
                                    c[(row + i, col + k)] = r[i][k];
                                }
                            }
                        }
                    }
                }
            }
        }
        let (err, scale) = periodic_solve_error(&solver, &c, lambda, nl);
        assert!(
            err <= 1e-10 * scale,
            "{nx}x{ny} pitches {pf}/{pm}, layer offset {offset:?}: periodic solve differs \
             from dense periodic Tikhonov by {err:e} (scale {scale:e})"
        );
    }

    #[test]
    fn periodic_problem_is_solved_exactly_with_a_half_pitch_layer_offset() {
        periodic_case(4, 4, 1.1, 1.1, [0.55, 0.55]);
    }

    #[test]
    fn periodic_problem_is_solved_exactly_on_multi_rate_grids() {
        // Forces every 2.2 mm on 1.1 mm markers (a = 2), and markers every 2.2 mm on
        // 1.1 mm forces (b = 2), with arbitrary sub-pitch layer offsets.
        periodic_case(3, 3, 2.2, 1.1, [0.37, -0.21]);
        periodic_case(5, 4, 1.1, 2.2, [0.9, 0.3]);
    }
}
