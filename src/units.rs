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

/// A byte count for a message: `1.5 GB`, `300 MB`, `12 kB` (decimal units, 3
/// significant digits; scientific beyond petabytes).
pub fn fmt_bytes(b: f64) -> String {
    const UNITS: [(f64, &str); 5] = [
        (1e15, "PB"),
        (1e12, "TB"),
        (1e9, "GB"),
        (1e6, "MB"),
        (1e3, "kB"),
    ];
    if !b.is_finite() || b >= 1e18 {
        return format!("{b:.3e} bytes");
    }
    for (scale, unit) in UNITS {
        if b >= scale {
            let v = b / scale;
            return if v >= 100.0 {
                format!("{v:.0} {unit}")
            } else if v >= 10.0 {
                format!("{v:.1} {unit}")
            } else {
                format!("{v:.2} {unit}")
            };
        }
    }
    format!("{b:.0} bytes")
}

/// A number for a message: up to 6 significant digits, plain notation between 1e-4
/// and 1e6, scientific otherwise (never hundreds of digits, never
/// `0.005000000000000001`).
pub fn fmt_num(x: f64) -> String {
    if !x.is_finite() {
        return format!("{x}");
    }
    if x == 0.0 {
        return "0".into();
    }
    let a = x.abs();
    if (1e-4..1e6).contains(&a) {
        let rounded: f64 = format!("{x:.5e}").parse().unwrap_or(x);
        format!("{rounded}")
    } else {
        let s = format!("{x:.5e}");
        // Trim trailing zeros of the mantissa: 5.00000e-7 -> 5e-7.
        match s.split_once('e') {
            Some((m, e)) if m.contains('.') => {
                let m = m.trim_end_matches('0').trim_end_matches('.');
                format!("{m}e{e}")
            }
            _ => s,
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
