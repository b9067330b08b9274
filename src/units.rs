//! Units and their conversions, in one place.
//!
//! Internally tactbench works in millimetres, newtons and N/mm² (= MPa). The paper
//! reports forces in gram-force (gf); plans and reports may use gf, and every
//! conversion goes through this module so there is exactly one definition of a gf.

use std::fmt;
use std::str::FromStr;

/// One gram-force in newtons (standard gravity, 9.80665 m/s², times 1 g).
pub const NEWTONS_PER_GF: f64 = 9.806_65e-3;

/// One kilopascal in N/mm² (1 kPa = 1e3 N/m² = 1e-3 N/mm²).
pub const N_PER_MM2_PER_KPA: f64 = 1e-3;

/// Gram-force to newtons.
pub fn gf_to_n(gf: f64) -> f64 {
    gf * NEWTONS_PER_GF
}

/// Newtons to gram-force.
pub fn n_to_gf(n: f64) -> f64 {
    n / NEWTONS_PER_GF
}

/// Kilopascal (the unit of `young_modulus_kpa`) to N/mm², the internal modulus unit.
pub fn kpa_to_n_per_mm2(kpa: f64) -> f64 {
    kpa * N_PER_MM2_PER_KPA
}

/// The force unit a plan or report is written in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ForceUnit {
    /// Newtons, the internal unit.
    #[default]
    Newton,
    /// Gram-force, the paper's unit.
    GramForce,
}

impl ForceUnit {
    /// Converts a value in this unit to newtons.
    pub fn to_newtons(self, value: f64) -> f64 {
        match self {
            ForceUnit::Newton => value,
            ForceUnit::GramForce => gf_to_n(value),
        }
    }

    /// Converts a value in newtons to this unit.
    pub fn from_newtons(self, newtons: f64) -> f64 {
        match self {
            ForceUnit::Newton => newtons,
            ForceUnit::GramForce => n_to_gf(newtons),
        }
    }

    /// The unit's symbol as written in files and reports.
    pub fn symbol(self) -> &'static str {
        match self {
            ForceUnit::Newton => "N",
            ForceUnit::GramForce => "gf",
        }
    }
}

impl fmt::Display for ForceUnit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.symbol())
    }
}

impl FromStr for ForceUnit {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "N" | "n" | "newton" | "newtons" => Ok(ForceUnit::Newton),
            "gf" | "gram-force" | "gramforce" => Ok(ForceUnit::GramForce),
            other => Err(format!(
                "unknown force unit `{other}`: expected `N` or `gf`"
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gf_round_trips_through_newtons() {
        assert_eq!(gf_to_n(1000.0), 9.806_65);
        assert!((n_to_gf(gf_to_n(750.0)) - 750.0).abs() < 1e-12);
        assert_eq!(ForceUnit::GramForce.to_newtons(50.0), gf_to_n(50.0));
        assert_eq!("gf".parse::<ForceUnit>(), Ok(ForceUnit::GramForce));
        assert!("lbf".parse::<ForceUnit>().is_err());
    }

    #[test]
    fn kpa_is_one_thousandth_of_n_per_mm2() {
        assert_eq!(kpa_to_n_per_mm2(1000.0), 1.0);
    }
}
