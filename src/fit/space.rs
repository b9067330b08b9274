//! The parameters a fit can free, by name: [`ParamId`] reads and writes one value of
//! [`ModelParams`], knows its unit, the scale the engine works in, the interval width
//! beyond which the run is said not to determine it, and what kind of setpoint would.
//!
//! **Identifiability thresholds** (a parameter whose 95 % interval half-width, expected
//! or obtained, exceeds its threshold is reported `identifiable: false` and held at its
//! nominal value): E ±50 % of nominal; ν ±0.1; thickness ±50 % of nominal; a layer
//! depth ±50 % of its nominal depth; the image scale ±10 %; the F/T rotation ±10°; a
//! contact offset ±1 mm; the contact z ±1 mm. They say "the run pins this parameter
//! down to within a range a build could plausibly be off by": a wider interval means
//! the number would be chosen by the noise, not by the gel.

use super::{FitError, ModelParams};
use crate::sensor::{ModelKind, Sensor};

/// One free parameter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum ParamId {
    /// `young_modulus_kpa`.
    YoungModulus,
    /// `poisson_ratio`.
    Poisson,
    /// `thickness_mm` (bonded layer).
    Thickness,
    /// `depth_mm.<layer>`.
    Depth(usize),
    /// `mm_per_px` shared by every layer.
    MmPerPx,
    /// `mm_per_px.<layer>`.
    MmPerPxLayer(usize),
    /// `ft_rotation_deg`.
    FtRotation,
    /// `contact_offset_x_mm`.
    OffsetX,
    /// `contact_offset_y_mm`.
    OffsetY,
    /// `contact_z_mm`.
    ContactZ,
}

/// Which route's residuals a parameter enters.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Enters {
    /// Stage depth against normal force.
    pub indentation: bool,
    /// Forward model against tracked displacements.
    pub displacement: bool,
}

impl ParamId {
    /// The parameter's name in `fit.json`, `--params` and acceptance files.
    pub fn name(self, layers: &[String]) -> String {
        let layer = |l: usize| layers.get(l).cloned().unwrap_or_else(|| l.to_string());
        match self {
            ParamId::YoungModulus => "young_modulus_kpa".into(),
            ParamId::Poisson => "poisson_ratio".into(),
            ParamId::Thickness => "thickness_mm".into(),
            ParamId::Depth(l) => format!("depth_mm.{}", layer(l)),
            ParamId::MmPerPx => "mm_per_px".into(),
            ParamId::MmPerPxLayer(l) => format!("mm_per_px.{}", layer(l)),
            ParamId::FtRotation => "ft_rotation_deg".into(),
            ParamId::OffsetX => "contact_offset_x_mm".into(),
            ParamId::OffsetY => "contact_offset_y_mm".into(),
            ParamId::ContactZ => "contact_z_mm".into(),
        }
    }

    /// Parses a name of [`ParamId::name`]'s form against the sensor's layers.
    pub fn parse(name: &str, layers: &[String]) -> Option<ParamId> {
        let layer = |l: &str| layers.iter().position(|n| n == l);
        Some(match name {
            "young_modulus_kpa" => ParamId::YoungModulus,
            "poisson_ratio" => ParamId::Poisson,
            "thickness_mm" => ParamId::Thickness,
            "mm_per_px" => ParamId::MmPerPx,
            "ft_rotation_deg" => ParamId::FtRotation,
            "contact_offset_x_mm" => ParamId::OffsetX,
            "contact_offset_y_mm" => ParamId::OffsetY,
            "contact_z_mm" => ParamId::ContactZ,
            _ => {
                if let Some(l) = name.strip_prefix("depth_mm.") {
                    ParamId::Depth(layer(l)?)
                } else if let Some(l) = name.strip_prefix("mm_per_px.") {
                    ParamId::MmPerPxLayer(layer(l)?)
                } else {
                    return None;
                }
            }
        })
    }

    /// Unit of the value (`fit.json` `unit`).
    pub fn unit(self) -> &'static str {
        match self {
            ParamId::YoungModulus => "kPa",
            ParamId::Poisson => "1",
            ParamId::MmPerPx | ParamId::MmPerPxLayer(_) => "mm/px",
            ParamId::FtRotation => "deg",
            _ => "mm",
        }
    }

    /// The value in `p`.
    pub fn get(self, p: &ModelParams) -> f64 {
        match self {
            ParamId::YoungModulus => p.young_modulus_kpa,
            ParamId::Poisson => p.poisson_ratio,
            ParamId::Thickness => p.thickness_mm,
            ParamId::Depth(l) => p.depth_mm[l],
            ParamId::MmPerPx => p.mm_per_px[0],
            ParamId::MmPerPxLayer(l) => p.mm_per_px[l],
            ParamId::FtRotation => p.ft_rotation_deg,
            ParamId::OffsetX => p.contact_offset_mm[0],
            ParamId::OffsetY => p.contact_offset_mm[1],
            ParamId::ContactZ => p.contact_z_mm,
        }
    }

    /// Sets the value in `p` (the shared scale sets every layer's).
    pub fn set(self, p: &mut ModelParams, v: f64) {
        match self {
            ParamId::YoungModulus => p.young_modulus_kpa = v,
            ParamId::Poisson => p.poisson_ratio = v,
            ParamId::Thickness => p.thickness_mm = v,
            ParamId::Depth(l) => p.depth_mm[l] = v,
            ParamId::MmPerPx => p.mm_per_px.iter_mut().for_each(|m| *m = v),
            ParamId::MmPerPxLayer(l) => p.mm_per_px[l] = v,
            ParamId::FtRotation => p.ft_rotation_deg = v,
            ParamId::OffsetX => p.contact_offset_mm[0] = v,
            ParamId::OffsetY => p.contact_offset_mm[1] = v,
            ParamId::ContactZ => p.contact_z_mm = v,
        }
    }

    /// The unit the engine measures this parameter in (its steps and its scaled
    /// Jacobian column): the nominal value for E, h and the image scale, 1 mm for
    /// lengths, 1° for the rotation, 0.1 for ν.
    pub fn scale(self, nominal: &ModelParams) -> f64 {
        let v = self.get(nominal).abs();
        match self {
            ParamId::YoungModulus | ParamId::Thickness => v.max(1e-9),
            ParamId::MmPerPx | ParamId::MmPerPxLayer(_) => v.max(1e-9),
            ParamId::Poisson => 0.1,
            ParamId::FtRotation => 1.0,
            _ => 1.0,
        }
    }

    /// The largest 95 % half-width at which the run still determines the parameter
    /// (module docs).
    pub fn threshold(self, nominal: &ModelParams) -> f64 {
        let v = self.get(nominal).abs();
        match self {
            ParamId::YoungModulus | ParamId::Thickness => 0.5 * v,
            ParamId::Depth(_) => (0.5 * v).max(0.25),
            ParamId::MmPerPx | ParamId::MmPerPxLayer(_) => 0.1 * v,
            ParamId::Poisson => 0.1,
            ParamId::FtRotation => 10.0,
            ParamId::OffsetX | ParamId::OffsetY | ParamId::ContactZ => 1.0,
        }
    }

    /// The routes whose residuals depend on the parameter.
    pub fn enters(self) -> Enters {
        let (indentation, displacement) = match self {
            ParamId::YoungModulus | ParamId::Poisson | ParamId::Thickness => (true, true),
            ParamId::ContactZ => (true, false),
            _ => (false, true),
        };
        Enters {
            indentation,
            displacement,
        }
    }

    /// What kind of setpoint would determine the parameter (for a parameter the run
    /// does not determine).
    pub fn needs(self) -> &'static str {
        match self {
            ParamId::YoungModulus => {
                "normal setpoints at several depths with the F/T force and the stage z recorded, or loaded setpoints with tracked displacements"
            }
            ParamId::Poisson => {
                "shear and normal setpoints at several positions with tracked displacements in both layers (nu shapes the ratio of tangential to normal response)"
            }
            ParamId::Thickness => {
                "normal setpoints with a contact radius that is a sizeable fraction of the thickness (a larger indenter or deeper indentation); a gel much thicker than the contact behaves as a half-space and its thickness cannot be measured this way"
            }
            ParamId::Depth(_) => {
                "loaded setpoints at several positions and loads whose field this layer's markers surround (the width of the field fixes the depth)"
            }
            ParamId::MmPerPx | ParamId::MmPerPxLayer(_) => {
                "normal setpoints at several positions with the stage depth recorded (the indentation route fixes E, the field then fixes the scale)"
            }
            ParamId::FtRotation => {
                "shear setpoints (a tangential target) in at least one direction, with tracked displacements"
            }
            ParamId::OffsetX | ParamId::OffsetY => {
                "loaded setpoints whose field the markers surround on every side"
            }
            ParamId::ContactZ => {
                "normal setpoints at three or more depths with the stage z recorded"
            }
        }
    }
}

/// The parameters a run can hold by default: E; the thickness of a bonded layer;
/// every marker layer's depth; the shared image scale; the F/T rotation and the
/// contact offset; the contact z when the indentation route has data. ν only when
/// listed.
pub fn default_params(sensor: &Sensor, indentation: bool, displacement: bool) -> Vec<ParamId> {
    let mut v = vec![ParamId::YoungModulus];
    if sensor.elastomer.model == ModelKind::BondedLayer {
        v.push(ParamId::Thickness);
    }
    if displacement {
        v.extend((0..sensor.layers.len()).map(ParamId::Depth));
        v.extend([
            ParamId::MmPerPx,
            ParamId::FtRotation,
            ParamId::OffsetX,
            ParamId::OffsetY,
        ]);
    }
    if indentation {
        v.push(ParamId::ContactZ);
    }
    v
}

/// Parses `--params a,b,c` against the sensor's layers; unknown names are an error
/// naming the value and listing the names there are.
pub fn parse_list(list: &str, sensor: &Sensor) -> Result<Vec<ParamId>, FitError> {
    let layers: Vec<String> = sensor.layers.iter().map(|l| l.name.clone()).collect();
    let mut out = Vec::new();
    for name in list.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let Some(id) = ParamId::parse(name, &layers) else {
            let mut known: Vec<String> = super::PARAMETER_NAMES
                .iter()
                .map(|s| s.to_string())
                .collect();
            known.extend(layers.iter().map(|l| format!("depth_mm.{l}")));
            known.extend(layers.iter().map(|l| format!("mm_per_px.{l}")));
            return Err(FitError::Input {
                path: "--params".into(),
                message: format!(
                    "unknown parameter {name:?}; the parameters of this sensor are: {}",
                    known.join(", ")
                ),
            });
        };
        if id == ParamId::Thickness && sensor.elastomer.model != ModelKind::BondedLayer {
            return Err(FitError::Input {
                path: "--params".into(),
                message: "thickness_mm: the sensor's [elastomer] model is the half-space, whose field does not depend on a thickness; set model = \"bonded-layer\" to fit it".into(),
            });
        }
        if !out.contains(&id) {
            out.push(id);
        }
    }
    let shared = out.contains(&ParamId::MmPerPx);
    if shared && out.iter().any(|p| matches!(p, ParamId::MmPerPxLayer(_))) {
        return Err(FitError::Input {
            path: "--params".into(),
            message: "mm_per_px and mm_per_px.<layer> together: give the shared scale or the per-layer ones".into(),
        });
    }
    if out.is_empty() {
        return Err(FitError::Input {
            path: "--params".into(),
            message: "no parameter named".into(),
        });
    }
    Ok(out)
}

/// The range a value may take: the sensor file's plausible ranges
/// ([`crate::sensor::YOUNG_MODULUS_KPA`], [`crate::sensor::DEPTH_MM`] below the
/// thickness, [`crate::sensor::THICKNESS_MM`] beyond the deepest layer,
/// [`crate::sensor::MM_PER_PX`]; ν in [0, 0.5]), so a fitted file always loads;
/// unbounded for the bench's mounting.
pub fn bounds(id: ParamId, p: &ModelParams) -> (f64, f64) {
    use crate::sensor::{DEPTH_MM, MM_PER_PX, THICKNESS_MM, YOUNG_MODULUS_KPA};
    let deepest = p.depth_mm.iter().cloned().fold(0.0, f64::max);
    match id {
        ParamId::YoungModulus => (YOUNG_MODULUS_KPA.lo, YOUNG_MODULUS_KPA.hi),
        ParamId::Poisson => (0.0, 0.5),
        ParamId::Thickness => (THICKNESS_MM.lo.max(deepest), THICKNESS_MM.hi),
        ParamId::Depth(_) => (DEPTH_MM.lo, DEPTH_MM.hi.min(p.thickness_mm)),
        ParamId::MmPerPx | ParamId::MmPerPxLayer(_) => (MM_PER_PX.lo, MM_PER_PX.hi),
        _ => (f64::NEG_INFINITY, f64::INFINITY),
    }
}

/// Whether a fitted value ran to the edge of its range (within 0.5 % of the nominal
/// value, or of the range where the nominal is 0): the data pushed it there, so the
/// model does not describe them for this parameter. ν at 0.5 is a legitimate
/// (incompressible) value and is not flagged.
pub fn at_bound(id: ParamId, p: &ModelParams, nominal: &ModelParams) -> bool {
    if id == ParamId::Poisson {
        return false;
    }
    let (lo, hi) = bounds(id, p);
    let v = id.get(p);
    let margin = 0.005 * id.get(nominal).abs().max(1e-9);
    v - lo <= margin || hi - v <= margin
}

/// Whether `p` is a valid parameter set for the model: finite, every parameter inside
/// [`bounds`] (a bonded layer, and the half-space's nominal thickness, beyond the
/// deepest layer).
pub fn check_valid(p: &ModelParams, kind: ModelKind) -> Result<(), String> {
    let _ = kind;
    let mut ids = vec![ParamId::YoungModulus, ParamId::Poisson, ParamId::Thickness];
    ids.extend((0..p.depth_mm.len()).map(ParamId::Depth));
    ids.extend((0..p.mm_per_px.len()).map(ParamId::MmPerPxLayer));
    ids.extend([
        ParamId::FtRotation,
        ParamId::OffsetX,
        ParamId::OffsetY,
        ParamId::ContactZ,
    ]);
    for id in ids {
        let v = id.get(p);
        let (lo, hi) = bounds(id, p);
        if !v.is_finite() || v < lo || v > hi {
            return Err(format!(
                "{} = {v} {} outside [{lo}, {hi}]",
                id.name(&[]),
                id.unit()
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::paper_sensor;

    #[test]
    fn every_name_parses_back_to_its_parameter() {
        let s = paper_sensor();
        let layers: Vec<String> = s.layers.iter().map(|l| l.name.clone()).collect();
        for id in [
            ParamId::YoungModulus,
            ParamId::Poisson,
            ParamId::Thickness,
            ParamId::Depth(1),
            ParamId::MmPerPx,
            ParamId::MmPerPxLayer(0),
            ParamId::FtRotation,
            ParamId::OffsetX,
            ParamId::OffsetY,
            ParamId::ContactZ,
        ] {
            let name = id.name(&layers);
            assert!(super::super::is_parameter_name(&name), "{name}");
            assert_eq!(ParamId::parse(&name, &layers), Some(id), "{name}");
        }
        assert_eq!(ParamId::parse("depth_mm.green", &layers), None);
    }

    #[test]
    fn an_unknown_parameter_name_is_an_error_listing_the_known_ones() {
        let e = parse_list("young_modulus_kpa,stiffness", &paper_sensor())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("\"stiffness\"") && e.contains("depth_mm.blue"),
            "{e}"
        );
        let e = parse_list("thickness_mm", &paper_sensor())
            .unwrap_err()
            .to_string();
        assert!(e.contains("half-space"), "{e}");
    }

    #[test]
    fn a_shared_scale_sets_every_layer() {
        let mut p = ModelParams::nominal(&paper_sensor(), 0.0);
        ParamId::MmPerPx.set(&mut p, 0.06);
        assert_eq!(p.mm_per_px, vec![0.06, 0.06]);
        assert!(check_valid(&p, ModelKind::HalfSpace).is_ok());
        ParamId::Depth(0).set(&mut p, -1.0);
        assert!(check_valid(&p, ModelKind::HalfSpace).is_err());
    }
}
