//! The forward models: marker displacements from surface forces.
//!
//! Two elastic models implement [`ElasticModel`]:
//!
//! - [`HalfSpace`] ([`half_space`]): the paper's model, Eq. 1–2 (Boussinesq + Cerruti),
//!   closed form, plus the vertical components `u_z`;
//! - [`BondedLayer`] ([`layer`]): an elastic layer of finite thickness `h` whose bottom
//!   face is bonded to a rigid plate (the real sensor's acrylic), solved in 2D Fourier
//!   space and brought to real space once per sensor by Hankel quadrature.
//!
//! [`ForwardModel`] is the enum a sensor file selects (`[elastomer] model =
//! "half-space" | "bonded-layer"`, see [`crate::sensor::ModelKind`]);
//! [`ForwardModel::from_elastomer`] builds it. Everything that builds `H` or renders
//! displacements is generic over [`ElasticModel`], so existing callers passing a
//! `&HalfSpace` keep their exact arithmetic.
//!
//! By linearity, markers `k` and force points `j` give `u = H f` (paper Eq. 4, 5). The
//! row/column order is a project-wide convention (DESIGN.md): rows `2k` (u_x) and
//! `2k+1` (u_y) for marker `k`; columns `3j` (f_x), `3j+1` (f_y), `3j+2` (f_z) for force
//! point `j`. Markers may sit anywhere (their positions come from data), at any depth
//! `> 0` (and `≤ h` for the layer), in any number of layers. The transfer matrix and the
//! solvers use `(u_x, u_y)` only, as the paper does; [`forward3`] also gives `u_z`
//! (z positive into the elastomer) for scenes and the renderer.

use nalgebra::DMatrix;
use thiserror::Error;

use crate::sensor::{Elastomer, ModelKind, Sensor};

pub mod half_space;
pub mod indentation;
pub mod layer;

pub use half_space::HalfSpace;
pub use layer::{layer_kernel, layer_kernel3, BondedLayer};

/// An error building the forward model.
#[derive(Debug, Error, PartialEq)]
pub enum ModelError {
    /// A marker is not strictly below the surface, where Eq. 1–2 are singular.
    #[error("marker {index} at depth {depth_mm} mm: depth must be a finite number > 0 mm")]
    BadDepth {
        /// Marker index in the set.
        index: usize,
        /// Its depth.
        depth_mm: f64,
    },
    /// A position is NaN or infinite.
    #[error("{what} {index} has a non-finite position ({x_mm}, {y_mm}) mm")]
    NonFinitePosition {
        /// `marker` or `force point`.
        what: &'static str,
        /// Index in its set.
        index: usize,
        /// x in mm.
        x_mm: f64,
        /// y in mm.
        y_mm: f64,
    },
    /// Material constants outside the model's domain.
    #[error("material out of range: E = {young_n_per_mm2} N/mm² must be > 0 and σ = {poisson} in [0, 0.5]")]
    BadMaterial {
        /// Young's modulus.
        young_n_per_mm2: f64,
        /// Poisson ratio.
        poisson: f64,
    },
    /// A marker lies below the bonded layer's rigid bottom face.
    #[error("marker {index} at depth {depth_mm} mm lies below the bonded layer (thickness {thickness_mm} mm)")]
    BelowLayer {
        /// Marker index in the set.
        index: usize,
        /// Its depth.
        depth_mm: f64,
        /// The layer thickness.
        thickness_mm: f64,
    },
    /// The force vector does not have three components per force point.
    #[error("forces have {got} values, expected {expected} (fx, fy, fz per force point)")]
    ForceLength {
        /// `3 × force points`.
        expected: usize,
        /// The length given.
        got: usize,
    },
    /// Layer thickness not a finite positive number.
    #[error("layer thickness {thickness_mm} mm must be a finite number > 0 mm")]
    BadThickness {
        /// The thickness given.
        thickness_mm: f64,
    },
    /// The bonded layer is too thin for the distances asked: its real-space tables
    /// would exceed [`layer::MAX_TABLE_EVALUATIONS`] / [`layer::MAX_TABLE_BYTES`].
    #[error(
        "bonded layer of thickness {} mm with markers at depth {} mm: distances up to {} mm \
         (the largest marker-force-point distance) would need tables of {} Bessel evaluations \
         and {} bytes, past the limit of {:e} evaluations and {:e} bytes; this layer allows \
         distances up to {} mm. Thicknesses and depths are in mm: \
         check `thickness_mm` and `depth_mm` (metres typed in?), or use `model = \"half-space\"`",
        crate::units::fmt_num(*thickness_mm),
        crate::units::fmt_num(*depth_mm),
        crate::units::fmt_num(*reach_mm),
        crate::units::fmt_num(*evaluations),
        crate::units::fmt_num(*bytes),
        layer::MAX_TABLE_EVALUATIONS,
        layer::MAX_TABLE_BYTES,
        crate::units::fmt_num(*max_reach_mm)
    )]
    LayerTooThin {
        /// The layer thickness, mm.
        thickness_mm: f64,
        /// The marker depth whose table is too large, mm.
        depth_mm: f64,
        /// The largest horizontal marker–force-point distance asked for, mm.
        reach_mm: f64,
        /// Bessel evaluations the table would take.
        evaluations: f64,
        /// Bytes it would take.
        bytes: f64,
        /// The largest distance this thickness and depth allow, mm.
        max_reach_mm: f64,
    },
}

/// Horizontal displacement response of one point to unit forces: `h[a][b]` is the
/// displacement along axis `a` (0 = x, 1 = y) per newton along axis `b`
/// (0 = x, 1 = y, 2 = z), in mm/N.
pub type PointResponse = [[f64; 3]; 2];

/// Full displacement response of one point to unit forces: `h[a][b]` is the
/// displacement along axis `a` (0 = x, 1 = y, 2 = z, z positive into the elastomer)
/// per newton along axis `b` (0 = x, 1 = y, 2 = z), in mm/N.
pub type PointResponse3 = [[f64; 3]; 3];

/// A linear elastic model of the elastomer: the response of an interior point to a
/// unit surface point force at a horizontal offset.
pub trait ElasticModel: Send + Sync {
    /// Response `h[a][b]` (mm/N) at offset `(dx, dy)` mm from the force point, depth
    /// `z` mm; `a` ∈ {x, y}, `b` ∈ {x, y, z}.
    fn point_response(&self, dx: f64, dy: f64, z: f64) -> PointResponse {
        let r = self.point_response3(dx, dy, z);
        [r[0], r[1]]
    }

    /// Response with the vertical row: `a, b` ∈ {x, y, z}.
    fn point_response3(&self, dx: f64, dy: f64, z: f64) -> PointResponse3;

    /// Displacement `(u_x, u_y)` in mm from a force `f` in N.
    fn displacement(&self, dx: f64, dy: f64, z: f64, f: [f64; 3]) -> [f64; 2] {
        let h = self.point_response(dx, dy, z);
        [
            h[0][0] * f[0] + h[0][1] * f[1] + h[0][2] * f[2],
            h[1][0] * f[0] + h[1][1] * f[1] + h[1][2] * f[2],
        ]
    }

    /// The deepest admissible marker depth, mm (∞ for the half-space).
    fn max_depth_mm(&self) -> f64;

    /// Prepares whatever the model caches for these depths and horizontal distances
    /// up to `rho_max_mm` (the layer's real-space tables). Optional: a model computes
    /// what it lacks on first use.
    fn prepare(&self, _depths_mm: &[f64], _rho_max_mm: f64) {}

    /// Checks, before any work, that the model can answer for these depths and
    /// horizontal distances up to `rho_max_mm` within its caps (the layer's tables;
    /// the half-space has none).
    fn check_reach(&self, _depths_mm: &[f64], _rho_max_mm: f64) -> Result<(), ModelError> {
        Ok(())
    }
}

/// The forward model a sensor file selects.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ForwardModel {
    /// Paper Eq. 1–2.
    HalfSpace(HalfSpace),
    /// A finite layer bonded to a rigid plate.
    BondedLayer(BondedLayer),
}

impl ForwardModel {
    /// The model an elastomer section names (`model`, material, thickness).
    pub fn from_elastomer(e: &Elastomer) -> Self {
        Self::of_kind(e.model, e)
    }

    /// The model of the given kind on an elastomer's material and thickness (a scene
    /// may render with a different model from the one its sensor file names).
    pub fn of_kind(kind: ModelKind, e: &Elastomer) -> Self {
        Self::with_material(kind, HalfSpace::from_elastomer(e), e.thickness_mm)
    }

    /// The model of the given kind with a material (E, ν) and a thickness, mm (the
    /// half-space ignores the thickness). The thickness of a validated sensor is
    /// finite and positive; anything else falls back to the half-space.
    pub fn with_material(kind: ModelKind, material: HalfSpace, thickness_mm: f64) -> Self {
        match kind {
            ModelKind::HalfSpace => ForwardModel::HalfSpace(material),
            ModelKind::BondedLayer => {
                match BondedLayer::new(material.young_n_per_mm2, material.poisson, thickness_mm) {
                    Ok(l) => ForwardModel::BondedLayer(l),
                    Err(_) => ForwardModel::HalfSpace(material),
                }
            }
        }
    }

    /// Which kind this is.
    pub fn kind(&self) -> ModelKind {
        match self {
            ForwardModel::HalfSpace(_) => ModelKind::HalfSpace,
            ForwardModel::BondedLayer(_) => ModelKind::BondedLayer,
        }
    }

    /// The material constants (E, ν) as a [`HalfSpace`].
    pub fn material(&self) -> HalfSpace {
        match self {
            ForwardModel::HalfSpace(m) => *m,
            ForwardModel::BondedLayer(l) => HalfSpace {
                poisson: l.poisson,
                young_n_per_mm2: l.young_n_per_mm2,
            },
        }
    }
}

impl ElasticModel for ForwardModel {
    #[inline]
    fn point_response(&self, dx: f64, dy: f64, z: f64) -> PointResponse {
        match self {
            ForwardModel::HalfSpace(m) => m.point_response(dx, dy, z),
            ForwardModel::BondedLayer(m) => ElasticModel::point_response(m, dx, dy, z),
        }
    }

    #[inline]
    fn point_response3(&self, dx: f64, dy: f64, z: f64) -> PointResponse3 {
        match self {
            ForwardModel::HalfSpace(m) => m.point_response3(dx, dy, z),
            ForwardModel::BondedLayer(m) => m.point_response3(dx, dy, z),
        }
    }

    #[inline]
    fn displacement(&self, dx: f64, dy: f64, z: f64, f: [f64; 3]) -> [f64; 2] {
        match self {
            ForwardModel::HalfSpace(m) => m.displacement(dx, dy, z, f),
            ForwardModel::BondedLayer(m) => ElasticModel::displacement(m, dx, dy, z, f),
        }
    }

    fn max_depth_mm(&self) -> f64 {
        match self {
            ForwardModel::HalfSpace(m) => m.max_depth_mm(),
            ForwardModel::BondedLayer(m) => m.max_depth_mm(),
        }
    }

    fn prepare(&self, depths_mm: &[f64], rho_max_mm: f64) {
        if let ForwardModel::BondedLayer(m) = self {
            m.prepare(depths_mm, rho_max_mm)
        }
    }

    fn check_reach(&self, depths_mm: &[f64], rho_max_mm: f64) -> Result<(), ModelError> {
        match self {
            ForwardModel::HalfSpace(_) => Ok(()),
            ForwardModel::BondedLayer(m) => m.check_reach(depths_mm, rho_max_mm),
        }
    }
}

/// A marker of the system: its reference position in the sensor frame and its depth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarkerSite {
    /// Index of its layer in the sensor's layer list.
    pub layer: usize,
    /// Reference (unloaded) position, mm.
    pub position_mm: [f64; 2],
    /// Depth below the surface, mm.
    pub depth_mm: f64,
}

impl MarkerSite {
    /// Every marker of every layer grid of a sensor, layer by layer, row-major within
    /// a layer. Layers without a `[layers.markers]` grid contribute nothing.
    pub fn from_sensor_grids(sensor: &Sensor) -> Vec<MarkerSite> {
        let mut out = Vec::new();
        for (li, layer) in sensor.layers.iter().enumerate() {
            if let Some(m) = &layer.markers {
                out.extend(m.grid.nodes_mm().into_iter().map(|p| MarkerSite {
                    layer: li,
                    position_mm: p,
                    depth_mm: layer.depth_mm,
                }));
            }
        }
        out
    }
}

/// Transfer matrix `H` (paper Eq. 5) with `2 × markers` rows and `3 × force points`
/// columns, in the order of the module docs. Unit: mm/N.
pub fn transfer_matrix<M: ElasticModel + ?Sized>(
    model: &M,
    markers: &[MarkerSite],
    force_points_mm: &[[f64; 2]],
) -> Result<DMatrix<f64>, ModelError> {
    check_geometry(model, markers, force_points_mm)?;
    prepare_for(model, markers, force_points_mm)?;
    let mut h = DMatrix::<f64>::zeros(2 * markers.len(), 3 * force_points_mm.len());
    for (j, fp) in force_points_mm.iter().enumerate() {
        for (k, m) in markers.iter().enumerate() {
            let r = model.point_response(
                m.position_mm[0] - fp[0],
                m.position_mm[1] - fp[1],
                m.depth_mm,
            );
            for b in 0..3 {
                h[(2 * k, 3 * j + b)] = r[0][b];
                h[(2 * k + 1, 3 * j + b)] = r[1][b];
            }
        }
    }
    Ok(h)
}

/// Forward model without building `H`: displacements (interleaved `ux, uy` per marker,
/// mm) for forces (interleaved `fx, fy, fz` per force point, N).
pub fn forward<M: ElasticModel + ?Sized>(
    model: &M,
    markers: &[MarkerSite],
    force_points_mm: &[[f64; 2]],
    forces_n: &[f64],
) -> Result<Vec<f64>, ModelError> {
    superpose(model, markers, force_points_mm, forces_n, |dx, dy, z| {
        model.point_response(dx, dy, z)
    })
}

/// Forward model with the vertical component: displacements interleaved
/// `ux, uy, uz` per marker (mm, z positive into the elastomer) for forces interleaved
/// `fx, fy, fz` per force point (N).
pub fn forward3<M: ElasticModel + ?Sized>(
    model: &M,
    markers: &[MarkerSite],
    force_points_mm: &[[f64; 2]],
    forces_n: &[f64],
) -> Result<Vec<f64>, ModelError> {
    superpose(model, markers, force_points_mm, forces_n, |dx, dy, z| {
        model.point_response3(dx, dy, z)
    })
}

/// The one loop of [`forward`] and [`forward3`]: checks the geometry and the length of
/// `forces_n`, then sums the `R`-row responses over the force points, marker by
/// marker (`R` values per marker in the output).
fn superpose<M: ElasticModel + ?Sized, const R: usize>(
    model: &M,
    markers: &[MarkerSite],
    force_points_mm: &[[f64; 2]],
    forces_n: &[f64],
    response: impl Fn(f64, f64, f64) -> [[f64; 3]; R],
) -> Result<Vec<f64>, ModelError> {
    check_geometry(model, markers, force_points_mm)?;
    if forces_n.len() != 3 * force_points_mm.len() {
        return Err(ModelError::ForceLength {
            expected: 3 * force_points_mm.len(),
            got: forces_n.len(),
        });
    }
    prepare_for(model, markers, force_points_mm)?;
    let mut u = vec![0.0; R * markers.len()];
    for (m, out) in markers.iter().zip(u.chunks_exact_mut(R)) {
        for (fp, f) in force_points_mm.iter().zip(forces_n.chunks_exact(3)) {
            let h = response(
                m.position_mm[0] - fp[0],
                m.position_mm[1] - fp[1],
                m.depth_mm,
            );
            for (o, row) in out.iter_mut().zip(&h) {
                *o += row[0] * f[0] + row[1] * f[1] + row[2] * f[2];
            }
        }
    }
    Ok(u)
}

/// Lets a model with tables check their size, then build them once for this
/// geometry (distinct depths and the largest marker–force-point distance).
fn prepare_for<M: ElasticModel + ?Sized>(
    model: &M,
    markers: &[MarkerSite],
    force_points_mm: &[[f64; 2]],
) -> Result<(), ModelError> {
    let Some((depths, reach)) = reach_of(markers, force_points_mm) else {
        return Ok(());
    };
    model.check_reach(&depths, reach)?;
    model.prepare(&depths, reach);
    Ok(())
}

/// Checks, without building anything, that `model` can answer for this geometry
/// within its caps ([`ElasticModel::check_reach`] on the distinct marker depths and
/// the largest marker–force-point distance): what [`transfer_matrix`] and
/// [`forward`] check before they work.
pub fn check_reach_for<M: ElasticModel + ?Sized>(
    model: &M,
    markers: &[MarkerSite],
    force_points_mm: &[[f64; 2]],
) -> Result<(), ModelError> {
    match reach_of(markers, force_points_mm) {
        Some((depths, reach)) => model.check_reach(&depths, reach),
        None => Ok(()),
    }
}

/// The distinct marker depths and the largest horizontal marker–force-point
/// distance (from the two bounding boxes); `None` when either set is empty.
fn reach_of(markers: &[MarkerSite], force_points_mm: &[[f64; 2]]) -> Option<(Vec<f64>, f64)> {
    if markers.is_empty() || force_points_mm.is_empty() {
        return None;
    }
    let mut depths: Vec<f64> = markers.iter().map(|m| m.depth_mm).collect();
    depths.sort_by(f64::total_cmp);
    depths.dedup();
    let bbox = |pts: &mut dyn Iterator<Item = [f64; 2]>| {
        pts.fold([f64::MAX, f64::MAX, f64::MIN, f64::MIN], |b, p| {
            [
                b[0].min(p[0]),
                b[1].min(p[1]),
                b[2].max(p[0]),
                b[3].max(p[1]),
            ]
        })
    };
    let a = bbox(&mut markers.iter().map(|m| m.position_mm));
    let b = bbox(&mut force_points_mm.iter().copied());
    let dx = (a[2] - b[0]).abs().max((b[2] - a[0]).abs());
    let dy = (a[3] - b[1]).abs().max((b[3] - a[1]).abs());
    Some((depths, dx.hypot(dy)))
}

fn check_geometry<M: ElasticModel + ?Sized>(
    model: &M,
    markers: &[MarkerSite],
    force_points_mm: &[[f64; 2]],
) -> Result<(), ModelError> {
    let max_depth = model.max_depth_mm();
    for (index, m) in markers.iter().enumerate() {
        if !(m.depth_mm.is_finite() && m.depth_mm > 0.0) {
            return Err(ModelError::BadDepth {
                index,
                depth_mm: m.depth_mm,
            });
        }
        if m.depth_mm > max_depth {
            return Err(ModelError::BelowLayer {
                index,
                depth_mm: m.depth_mm,
                thickness_mm: max_depth,
            });
        }
        if !(m.position_mm[0].is_finite() && m.position_mm[1].is_finite()) {
            return Err(ModelError::NonFinitePosition {
                what: "marker",
                index,
                x_mm: m.position_mm[0],
                y_mm: m.position_mm[1],
            });
        }
    }
    for (index, p) in force_points_mm.iter().enumerate() {
        if !(p[0].is_finite() && p[1].is_finite()) {
            return Err(ModelError::NonFinitePosition {
                what: "force point",
                index,
                x_mm: p[0],
                y_mm: p[1],
            });
        }
    }
    Ok(())
}
