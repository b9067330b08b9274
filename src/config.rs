//! What the TOML file formats (sensor.toml, experiment plans) share: one error type
//! that names the file, the key, the value with its unit and what is allowed, and the
//! range checks that produce it. Raw TOML is parsed once (serde, unknown keys denied)
//! and then validated into typed values through a [`Checker`].
//!
//! **Fixed-length arrays** (`position_mm = [x, y]`, `max_force = [fx, fy, fz]`, …) are
//! read through [`exact`], [`exact_opt`] and [`exact_each`] (`#[serde(deserialize_with
//! = …)]`): serde's own `[T; N]` takes the first N elements and silently drops the
//! rest, so `[9.0, 6.75, 2.0]` would be read as `[9.0, 6.75]`. These refuse extra
//! elements as well as missing ones, and [`parse_toml`] turns the refusal into an
//! [`ConfigError::Invalid`] naming the key (dotted path, array indices included), the
//! length given, the length expected and the line.

use std::fmt;
use std::path::{Path, PathBuf};

use serde::de::{self, DeserializeOwned, IgnoredAny, SeqAccess, Visitor};
use serde::{Deserialize, Deserializer};
use thiserror::Error;

/// An error reading or validating a configuration file. Every variant names the file.
#[derive(Debug, Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read {what} {path}: {source}")]
    Io {
        /// What the file is (`sensor file`, `plan`).
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// Not valid TOML for the schema (syntax, unknown key, wrong type), with line and
    /// column.
    #[error("{path}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// The parser's message.
        message: String,
    },
    /// A value is out of its allowed range.
    #[error("{path}: {key} = {value} is invalid: {allowed}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// The offending key, e.g. `elastomer.poisson_ratio` or `layers[1].depth_mm`.
        key: String,
        /// The offending value as written, with its unit.
        value: String,
        /// What is allowed, with units.
        allowed: String,
    },
}

/// Reads a file as text; `what` names it in the error.
pub fn read_text(path: &Path, what: &'static str) -> Result<String, ConfigError> {
    std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
        what,
        path: path.to_path_buf(),
        source,
    })
}

/// Parses TOML text into the raw schema type; `path` names the file in errors. A
/// fixed-length array of the wrong length (see [`exact`]) is an
/// [`ConfigError::Invalid`] naming its key; every other schema error is a
/// [`ConfigError::Parse`] with the parser's message (line, column, the line itself).
pub fn parse_toml<T: DeserializeOwned>(text: &str, path: &Path) -> Result<T, ConfigError> {
    let parse_error = |e: toml::de::Error| ConfigError::Parse {
        path: path.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    };
    let de = toml::de::Deserializer::parse(text).map_err(parse_error)?;
    serde_path_to_error::deserialize(de).map_err(|e| {
        let key = e.path().to_string();
        let inner = e.into_inner();
        match LengthMismatch::from_message(inner.message()) {
            Some(m) => m.error(path, &key, text, inner.span()),
            None => parse_error(inner),
        }
    })
}

/// A fixed-length array with another number of elements, carried through serde's
/// string-only custom errors from the visitor to [`parse_toml`] (which alone knows the
/// key); the message is also readable where it is shown as is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct LengthMismatch {
    given: usize,
    expected: usize,
}

impl LengthMismatch {
    const PREFIX: &'static str = "an array of ";
    const MIDDLE: &'static str = " elements where exactly ";
    const SUFFIX: &'static str = " are expected";

    fn message(self) -> String {
        format!(
            "{}{}{}{}{}",
            Self::PREFIX,
            self.given,
            Self::MIDDLE,
            self.expected,
            Self::SUFFIX
        )
    }

    fn from_message(m: &str) -> Option<Self> {
        let rest = m.strip_prefix(Self::PREFIX)?.strip_suffix(Self::SUFFIX)?;
        let (given, expected) = rest.split_once(Self::MIDDLE)?;
        Some(LengthMismatch {
            given: given.parse().ok()?,
            expected: expected.parse().ok()?,
        })
    }

    fn error(
        self,
        path: &Path,
        key: &str,
        text: &str,
        span: Option<std::ops::Range<usize>>,
    ) -> ConfigError {
        let line = span
            .map(|s| {
                text.as_bytes()[..s.start.min(text.len())]
                    .iter()
                    .filter(|&&b| b == b'\n')
                    .count()
                    + 1
            })
            .map_or(String::new(), |l| format!(" (line {l})"));
        ConfigError::Invalid {
            path: path.to_path_buf(),
            key: key.to_string(),
            value: format!("an array of {} elements{line}", self.given),
            allowed: format!(
                "{} elements given, exactly {} expected",
                self.given, self.expected
            ),
        }
    }
}

/// Visits a sequence of exactly `N` elements (see [`exact`]).
struct ExactVisitor<T, const N: usize>(std::marker::PhantomData<T>);

impl<'de, T: Deserialize<'de>, const N: usize> Visitor<'de> for ExactVisitor<T, N> {
    type Value = [T; N];

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "an array of {N} elements")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<[T; N], A::Error> {
        let mut out = Vec::with_capacity(N);
        while out.len() < N {
            match seq.next_element()? {
                Some(v) => out.push(v),
                None => break,
            }
        }
        // Count what is left without keeping it (any type: the length is the error).
        let mut given = out.len();
        while seq.next_element::<IgnoredAny>()?.is_some() {
            given += 1;
        }
        if given != N {
            return Err(de::Error::custom(
                LengthMismatch { given, expected: N }.message(),
            ));
        }
        out.try_into()
            .map_err(|_| de::Error::custom("array length changed while reading"))
    }
}

/// A fixed-length array `[T; N]` that must have exactly `N` elements, for
/// `#[serde(deserialize_with = "crate::config::exact")]`.
pub fn exact<'de, D, T, const N: usize>(d: D) -> Result<[T; N], D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    d.deserialize_seq(ExactVisitor::<T, N>(std::marker::PhantomData))
}

/// An optional [`exact`] array (`#[serde(default, deserialize_with =
/// "crate::config::exact_opt")]`: absent is `None`).
pub fn exact_opt<'de, D, T, const N: usize>(d: D) -> Result<Option<[T; N]>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    Ok(Some(exact(d)?))
}

/// A list of [`exact`] arrays (`positions_mm = [[x, y], …]`); the key of a wrong
/// element carries its index.
pub fn exact_each<'de, D, T, const N: usize>(d: D) -> Result<Vec<[T; N]>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    struct Element<T, const N: usize>([T; N]);
    impl<'de, T: Deserialize<'de>, const N: usize> Deserialize<'de> for Element<T, N> {
        fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
            exact(d).map(Element)
        }
    }
    let v: Vec<Element<T, N>> = Vec::deserialize(d)?;
    Ok(v.into_iter().map(|e| e.0).collect())
}

/// An optional [`exact_each`] list.
pub fn exact_each_opt<'de, D, T, const N: usize>(d: D) -> Result<Option<Vec<[T; N]>>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    Ok(Some(exact_each(d)?))
}

/// Range checks for one file; every error names the file, key, value and unit.
#[derive(Debug, Clone, Copy)]
pub struct Checker<'a> {
    /// The file being validated.
    pub path: &'a Path,
}

impl Checker<'_> {
    /// An `Invalid` error for `key`.
    pub fn invalid(
        &self,
        key: &str,
        value: impl fmt::Display,
        allowed: impl Into<String>,
    ) -> ConfigError {
        ConfigError::Invalid {
            path: self.path.to_path_buf(),
            key: key.to_string(),
            value: value.to_string(),
            allowed: allowed.into(),
        }
    }

    /// `v` finite and > 0 (in `unit`).
    pub fn positive(&self, key: &str, v: f64, unit: &str) -> Result<f64, ConfigError> {
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(self.invalid(
                key,
                with_unit(v, unit),
                format!("must be a finite number > 0 {unit}"),
            ))
        }
    }

    /// `v` finite and ≥ 0 (in `unit`).
    pub fn non_negative(&self, key: &str, v: f64, unit: &str) -> Result<f64, ConfigError> {
        if v.is_finite() && v >= 0.0 {
            Ok(v)
        } else {
            Err(self.invalid(
                key,
                with_unit(v, unit),
                format!("must be a finite number >= 0 {unit}"),
            ))
        }
    }

    /// `v` finite (in `unit`).
    pub fn finite(&self, key: &str, v: f64, unit: &str) -> Result<f64, ConfigError> {
        if v.is_finite() {
            Ok(v)
        } else {
            Err(self.invalid(
                key,
                with_unit(v, unit),
                format!("must be a finite number ({unit})"),
            ))
        }
    }

    /// An integer count in `[1, max]`.
    pub fn count(&self, key: &str, v: i64, max: i64) -> Result<usize, ConfigError> {
        if (1..=max).contains(&v) {
            Ok(v as usize)
        } else {
            Err(self.invalid(key, v, format!("must be an integer in [1, {max}]")))
        }
    }
}

fn with_unit(v: f64, unit: &str) -> String {
    if unit.is_empty() {
        v.to_string()
    } else {
        format!("{v} {unit}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_name_file_key_value_unit_and_range() {
        let c = Checker {
            path: Path::new("x.toml"),
        };
        let e = c
            .positive("a.pitch_mm", -1.5, "mm")
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "x.toml: a.pitch_mm = -1.5 mm is invalid: must be a finite number > 0 mm"
        );
        assert!(c.finite("b", f64::NAN, "mm").is_err());
        assert_eq!(c.count("n", 3, 4).unwrap(), 3);
        assert!(c
            .count("n", 0, 4)
            .unwrap_err()
            .to_string()
            .contains("[1, 4]"));
        assert_eq!(c.non_negative("z", 0.0, "s").unwrap(), 0.0);
        let e = read_text(Path::new("/nonexistent/s.toml"), "sensor file")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("cannot read sensor file /nonexistent/s.toml"),
            "{e}"
        );
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Arrays {
        #[serde(deserialize_with = "exact")]
        xy: [f64; 2],
        #[serde(default, deserialize_with = "exact_opt")]
        xyz: Option<[i64; 3]>,
        #[serde(default, deserialize_with = "exact_each_opt")]
        list: Option<Vec<[f64; 2]>>,
    }

    fn arrays(text: &str) -> Result<Arrays, ConfigError> {
        parse_toml(text, Path::new("a.toml"))
    }

    #[test]
    fn fixed_length_arrays_take_exactly_their_length() {
        let a =
            arrays("xy = [1.0, 2.0]\nxyz = [1, 2, 3]\nlist = [[1.0, 2.0], [3.0, 4.0]]").unwrap();
        assert_eq!((a.xy, a.xyz), ([1.0, 2.0], Some([1, 2, 3])));
        assert_eq!(a.list.unwrap(), vec![[1.0, 2.0], [3.0, 4.0]]);
        assert!(arrays("xy = [1.0, 2.0]").unwrap().xyz.is_none());
        for (text, key, given, expected, line) in [
            ("xy = [1.0, 2.0, 3.0]", "xy", 3, 2, 1),
            ("xy = [1.0]", "xy", 1, 2, 1),
            ("xy = []", "xy", 0, 2, 1),
            ("xy = [1.0, 2.0]\nxyz = [1, 2, 3, 4]", "xyz", 4, 3, 2),
            (
                "xy = [1.0, 2.0]\n\nlist = [[1.0, 2.0], [3.0, 4.0, 5.0]]",
                "list[1]",
                3,
                2,
                3,
            ),
            // Extra elements of another type are counted, not a type error.
            ("xy = [1.0, 2.0, \"z\"]", "xy", 3, 2, 1),
        ] {
            let e = arrays(text).unwrap_err();
            let ConfigError::Invalid { key: k, .. } = &e else {
                panic!("{text}: {e}")
            };
            assert_eq!(k, key, "{e}");
            assert_eq!(
                e.to_string(),
                format!(
                    "a.toml: {key} = an array of {given} elements (line {line}) is invalid: {given} elements given, exactly {expected} expected"
                )
            );
        }
        // A wrong element type is still the parser's error, with its line.
        let e = arrays("xy = [1.0, \"a\"]").unwrap_err().to_string();
        assert!(e.contains("line 1") && e.contains("xy"), "{e}");
    }

    /// Issue 24, case 7, beyond plans: the sensor, scene, bench and camera files refuse
    /// extra elements in their fixed-length arrays, naming the key.
    #[test]
    fn case7_sensor_scene_bench_and_camera_arrays_with_extra_elements_are_refused() {
        let sensor_text = crate::sensor::PAPER_SENSOR_TOML;
        let e = crate::sensor::Sensor::from_toml_str(
            &sensor_text.replacen(
                "origin_px = [25.0, 25.0]",
                "origin_px = [25.0, 25.0, 1.0]",
                1,
            ),
            "s.toml",
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("camera.origin_px") && e.contains("3 elements given, exactly 2"),
            "{e}"
        );
        let e = crate::sensor::Sensor::from_toml_str(
            &sensor_text.replacen("origin_mm = [0.0, 0.0]", "origin_mm = [0.0, 0.0, 0.0]", 1),
            "s.toml",
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("layers[0].markers.origin_mm") && e.contains("3 elements given"),
            "{e}"
        );

        let sensor = crate::sensor::paper_sensor();
        let scene = "sensor = \"s.toml\"\n[indenter]\nkind = \"hemisphere\"\nradius_mm = 2.5\n[load]\nposition_mm = [9.0, 6.75, 1.0]\nnormal_force_gf = 100.0\n";
        let e = crate::sim::scene::Scene::from_toml_str(scene, "scene.toml", sensor.clone())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("load.position_mm") && e.contains("3 elements given"),
            "{e}"
        );
        let occlusion = scene.replace("[9.0, 6.75, 1.0]", "[9.0, 6.75]")
            + "[[effects]]\nkind = \"occlusion\"\nrect_px = [0.0, 0.0, 10.0, 10.0, 5.0]\n";
        let e = crate::sim::scene::Scene::from_toml_str(&occlusion, "scene.toml", sensor.clone())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("effects") && e.contains("5 elements given, exactly 4"),
            "{e}"
        );

        let bench = "[stage]\nprotocol = \"grbl\"\nport = \"/dev/ttyUSB0\"\n[force_sensor]\nprotocol = \"dynpick\"\nport = \"/dev/ttyUSB1\"\n[camera]\ndevice = 0\n[geometry]\nsensor_origin_in_stage_mm = [-100.0, -100.0, 0.0]\nsurface_z_mm = -30.0\npress_direction = -1\n";
        let e = crate::bench::config::BenchConfig::from_toml_str(bench, "bench.toml")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("geometry.sensor_origin_in_stage_mm") && e.contains("3 elements given"),
            "{e}"
        );

        let camera = crate::vision::camera::CameraCalibration::from_linear(&sensor.camera, &sensor)
            .to_toml_string("s.toml", "reference.png");
        let cut = camera.find("center_px = [").expect("center_px written");
        let end = cut + camera[cut..].find(']').unwrap();
        let bad = format!("{}, 1.0{}", &camera[..end], &camera[end..]);
        let e = crate::vision::camera::CameraCalibration::from_toml_str(
            &bad,
            Path::new("camera.toml"),
            &sensor,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("distortion.center_px") && e.contains("3 elements given"),
            "{e}"
        );
    }
}
