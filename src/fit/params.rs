//! The parameter vector of the sensor model the fit identifies, and what the routes
//! share: [`ModelParams`] (every parameter of issue 30 in its file unit) and
//! [`Residuals`], the interface a route implements for the least-squares engine.

use crate::sensor::Sensor;

/// Every parameter the fit can identify, in the units of the sensor file (kPa, mm,
/// mm/px, degrees). Sign conventions (the simulated bench's `[bench]` table uses the
/// same, so a fit of a simulated mis-mounted bench recovers the scene's numbers):
/// - `ft_rotation_deg` = θ: the F/T sensor is mounted rotated by +θ about z relative to
///   the sensor frame, so it reports `F_ft = R(θ)ᵀ F` for a force `F` in the sensor
///   frame (`R(θ)` the counter-clockwise rotation in the x-y plane); the fit applies
///   `F = R(θ) F_ft`.
/// - `contact_offset_mm` = `[dx, dy]`: the contact happens at the stage's notion of
///   the contact point (the plan's position) plus `[dx, dy]` in the camera's sensor
///   frame.
/// - `contact_z_mm`: the stage z (machine coordinates, as journalled in `stage_z_mm`)
///   at first contact; depth past contact is `press_direction · (z − contact_z_mm)`.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelParams {
    /// Young's modulus E, kPa.
    pub young_modulus_kpa: f64,
    /// Poisson's ratio ν.
    pub poisson_ratio: f64,
    /// Elastomer thickness h, mm (used by the bonded-layer model only).
    pub thickness_mm: f64,
    /// Depth of each layer's markers, mm, in the sensor file's layer order.
    pub depth_mm: Vec<f64>,
    /// Image scale of each layer, mm/px, in layer order (all equal to the sensor file's
    /// `[camera] mm_per_px` unless fitted per layer).
    pub mm_per_px: Vec<f64>,
    /// In-plane rotation of the F/T sensor's axes relative to the sensor frame, degrees.
    pub ft_rotation_deg: f64,
    /// Contact position offset from the stage's notion, mm, sensor frame.
    pub contact_offset_mm: [f64; 2],
    /// Stage z of first contact, mm (machine coordinates).
    pub contact_z_mm: f64,
}

impl ModelParams {
    /// The nominal parameters: the sensor file's values, an F/T mounted as the bench
    /// file says (no rotation), no offset, and the given contact z.
    pub fn nominal(sensor: &Sensor, contact_z_mm: f64) -> ModelParams {
        ModelParams {
            young_modulus_kpa: sensor.elastomer.young_modulus_kpa,
            poisson_ratio: sensor.elastomer.poisson_ratio,
            thickness_mm: sensor.elastomer.thickness_mm,
            depth_mm: sensor.layers.iter().map(|l| l.depth_mm).collect(),
            mm_per_px: vec![sensor.camera.mm_per_px; sensor.layers.len()],
            ft_rotation_deg: 0.0,
            contact_offset_mm: [0.0, 0.0],
            contact_z_mm,
        }
    }

    /// A copy of `nominal` with these elastic and geometric values (E, ν, h, depths;
    /// the camera scale when every layer shares one). Bench parameters (rotation,
    /// offset, contact z) are not part of a sensor file.
    pub fn apply_to(&self, nominal: &Sensor) -> Sensor {
        let mut s = nominal.clone();
        s.elastomer.young_modulus_kpa = self.young_modulus_kpa;
        s.elastomer.poisson_ratio = self.poisson_ratio;
        s.elastomer.thickness_mm = self.thickness_mm;
        for (l, d) in s.layers.iter_mut().zip(&self.depth_mm) {
            l.depth_mm = *d;
        }
        if let Some(first) = self.mm_per_px.first() {
            if self.mm_per_px.iter().all(|m| m == first) {
                s.camera.mm_per_px = *first;
            }
        }
        s
    }

    /// The F/T force rotated into the sensor frame: `F = R(θ) F_ft`.
    pub fn ft_to_sensor(&self, f_ft: [f64; 3]) -> [f64; 3] {
        let (s, c) = self.ft_rotation_deg.to_radians().sin_cos();
        [
            c * f_ft[0] - s * f_ft[1],
            s * f_ft[0] + c * f_ft[1],
            f_ft[2],
        ]
    }
}

/// One route's residuals as a function of the parameters: what the least-squares
/// engine minimises (the sum of squares of `eval`'s output, each residual already
/// divided by its noise so the routes can be stacked).
pub trait Residuals: Sync {
    /// Number of residuals.
    fn len(&self) -> usize;
    /// Whether there are no residuals.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Writes the residuals at `p` into `out` (`out.len() == self.len()`).
    fn eval(&self, p: &ModelParams, out: &mut [f64]) -> Result<(), String>;
    /// The cluster of each residual (the journal's setpoint index: a setpoint's
    /// residuals may be correlated); `usize::MAX` for a residual in no cluster.
    fn groups(&self) -> Vec<usize> {
        vec![usize::MAX; self.len()]
    }
    /// The second cluster key of each residual (the marker it belongs to), or
    /// `usize::MAX` for none.
    fn marker_groups(&self) -> Vec<usize> {
        vec![usize::MAX; self.len()]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::paper_sensor;

    #[test]
    fn nominal_parameters_apply_back_to_the_same_sensor() {
        let s = paper_sensor();
        let p = ModelParams::nominal(&s, -30.0);
        assert_eq!(p.depth_mm, vec![3.0, 6.0]);
        let back = p.apply_to(&s);
        assert_eq!(
            back.elastomer.young_modulus_kpa,
            s.elastomer.young_modulus_kpa
        );
        assert_eq!(back.camera.mm_per_px, s.camera.mm_per_px);
    }

    #[test]
    fn a_rotated_ft_sensor_is_rotated_back_into_the_sensor_frame() {
        let mut p = ModelParams::nominal(&paper_sensor(), 0.0);
        p.ft_rotation_deg = 90.0;
        // Mounted +90°: a force along sensor +x reads along F/T −y; rotating back
        // recovers +x.
        let f = p.ft_to_sensor([0.0, -1.0, 2.0]);
        assert!((f[0] - 1.0).abs() < 1e-12 && f[1].abs() < 1e-12 && f[2] == 2.0);
    }
}
