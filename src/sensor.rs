//! `sensor.toml`: the sensor's elastomer, marker layers, force grid and camera mapping.
//!
//! The file is parsed once into [`Sensor`], whose fields have all been checked
//! (ranges, non-empty grids, unique layer names, known colours); everything downstream
//! trusts it. The schema is a public contract (see DESIGN.md and the README):
//!
//! ```toml
//! draft = true                 # optional: a draft (`sensor init`); needs `placeholders`
//! placeholders = ["elastomer.young_modulus_kpa"]  # keys whose values are not measured
//!
//! [elastomer]
//! young_modulus_kpa = 1000.0   # > 0
//! poisson_ratio = 0.5          # in [0, 0.5]
//! thickness_mm = 40.0          # > 0, deeper than every layer
//! model = "half-space"         # optional: "half-space" (default, paper Eq. 1–2) or
//!                              # "bonded-layer" (layer of thickness_mm on a rigid plate)
//!
//! [[layers]]                   # one per marker layer, at least one
//! name = "blue"                # unique
//! color = "blue"               # blue | red | green | dark | bright
//! depth_mm = 3.0               # > 0
//! [layers.markers]             # optional regular grid of this layer
//! nx = 13
//! ny = 10
//! pitch_mm = 1.5
//! origin_mm = [0.0, 0.0]
//! diameter_mm = 0.6
//!
//! [force_grid]
//! nx = 10
//! ny = 8
//! pitch_mm = 2.2
//! origin_mm = [-0.9, -0.95]
//!
//! [camera]
//! mm_per_px = 0.05
//! origin_px = [25.0, 25.0]     # pixel position of the sensor-frame origin
//! width_px = 430
//! height_px = 340
//! roi_px = { center = [215.0, 170.0], radius = 160.0 }  # optional: markers sought only
//!                              # inside; or { min = [x0, y0], max = [x1, y1] } (px)
//! ```
//!
//! **Plausible ranges.** Beyond the schema's ranges every length, the modulus and the
//! camera's scale must lie in the range a real tactile sensor has ([`KeyRange`], the
//! constants [`YOUNG_MODULUS_KPA`] … [`MM_PER_PX`]; the reasoning is in
//! docs/limits.md), so that a file typed in metres, Pa or MPa is refused with the
//! likely slip named instead of giving newtons off by 10³–10⁹; and the force grid must
//! lie over the markers ([`MIN_FORCE_NODES_OVER_MARKERS`]).
//!
//! **Drafts.** `draft = true` marks a file `sensor init` wrote; `placeholders` lists
//! the keys whose values are placeholders, not measurements. A draft loads (so `track`
//! can use its geometry); commands that turn displacements into newtons refuse it
//! while it has placeholders ([`Sensor::refuse_draft`]) unless asked to go on.
//! [`mark_measured`] removes keys from the list in the file's text (comments kept) and
//! the draft keys with the last one.
//!
//! Grids are row-major: node `(ix, iy)` has index `iy * nx + ix` and sits at
//! `origin + pitch * (ix, iy)`. The camera maps pixels to the sensor frame by
//! `x_mm = (x_px - origin_px.x) * mm_per_px` (likewise for y): image columns grow
//! with sensor x and image rows with sensor y.

use std::collections::HashSet;
use std::fmt;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use thiserror::Error;

use crate::config::{self, Checker, ConfigError};
use crate::units;

/// An error reading or validating a sensor file (file, key, value, allowed range).
pub type SensorError = ConfigError;

/// Appearance of a marker layer (`[[layers]] color`), used by the tracker and the
/// renderer: a colour (`blue`, `red`, `green`: markers told apart from each other and
/// from grey light by their colour), or a brightness (`dark`: dark markers on a lit
/// gel, as GelSight-type sensors; `bright`: light markers or pins on a dark skin, as
/// the TacTip). Dark and bright layers are found by their contrast against the local
/// illumination (see `vision::window`), not by colour.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MarkerColor {
    /// Blue markers.
    Blue,
    /// Red markers.
    Red,
    /// Green markers.
    Green,
    /// Dark markers on a brighter, possibly unevenly lit background.
    Dark,
    /// Bright markers on a darker background.
    Bright,
}

impl MarkerColor {
    /// All appearances, in the order used by the tracker's channel separation and the
    /// error messages.
    pub const ALL: [MarkerColor; 5] = [
        MarkerColor::Blue,
        MarkerColor::Red,
        MarkerColor::Green,
        MarkerColor::Dark,
        MarkerColor::Bright,
    ];

    /// The name used in sensor files.
    pub fn name(self) -> &'static str {
        match self {
            MarkerColor::Blue => "blue",
            MarkerColor::Red => "red",
            MarkerColor::Green => "green",
            MarkerColor::Dark => "dark",
            MarkerColor::Bright => "bright",
        }
    }

    /// True for `dark` and `bright`: markers told apart from the background by
    /// brightness (measured against the local illumination), not by colour.
    pub fn is_brightness(self) -> bool {
        matches!(self, MarkerColor::Dark | MarkerColor::Bright)
    }

    /// Parses a colour name as written in sensor files.
    pub fn parse(name: &str) -> Option<Self> {
        MarkerColor::ALL.into_iter().find(|c| c.name() == name)
    }
}

impl fmt::Display for MarkerColor {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// The elastomer's material and thickness.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Elastomer {
    /// Young's modulus in kPa, as written in the file.
    pub young_modulus_kpa: f64,
    /// Poisson ratio, in [0, 0.5].
    pub poisson_ratio: f64,
    /// Thickness in mm (the half-space model ignores it; layers must lie within it).
    pub thickness_mm: f64,
    /// The elastic model the solvers invert (`[elastomer] model`).
    pub model: ModelKind,
}

/// The elastic model of `[elastomer] model` (see [`crate::model`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ModelKind {
    /// `"half-space"`: paper Eq. 1–2 (the default).
    #[default]
    HalfSpace,
    /// `"bonded-layer"`: a layer of `thickness_mm` bonded to a rigid plate.
    BondedLayer,
}

impl ModelKind {
    /// Every kind, in the order of the docs.
    pub const ALL: [ModelKind; 2] = [ModelKind::HalfSpace, ModelKind::BondedLayer];

    /// The name used in sensor.toml and scene.toml.
    pub fn name(&self) -> &'static str {
        match self {
            ModelKind::HalfSpace => "half-space",
            ModelKind::BondedLayer => "bonded-layer",
        }
    }

    /// Parses a name of [`ModelKind::name`].
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }
}

impl fmt::Display for ModelKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl Elastomer {
    /// Young's modulus in the internal unit, N/mm².
    pub fn young_modulus_n_per_mm2(&self) -> f64 {
        units::kpa_to_n_per_mm2(self.young_modulus_kpa)
    }
}

/// A regular rectangular grid in the sensor plane (row-major node order).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Grid {
    /// Nodes along x.
    pub nx: usize,
    /// Nodes along y.
    pub ny: usize,
    /// Spacing in mm (same along x and y).
    pub pitch_mm: f64,
    /// Position of node (0, 0) in the sensor frame, mm.
    pub origin_mm: [f64; 2],
}

impl Grid {
    /// Number of nodes.
    pub fn len(&self) -> usize {
        self.nx * self.ny
    }

    /// True when the grid has no nodes (never for a validated sensor).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Position of node `(ix, iy)` in mm.
    pub fn node_mm(&self, ix: usize, iy: usize) -> [f64; 2] {
        [
            self.origin_mm[0] + self.pitch_mm * ix as f64,
            self.origin_mm[1] + self.pitch_mm * iy as f64,
        ]
    }

    /// Positions of all nodes, row-major (`index = iy * nx + ix`).
    pub fn nodes_mm(&self) -> Vec<[f64; 2]> {
        let mut out = Vec::with_capacity(self.len());
        for iy in 0..self.ny {
            for ix in 0..self.nx {
                out.push(self.node_mm(ix, iy));
            }
        }
        out
    }

    /// The node nearest to `p_mm` and its distance in mm, or `None` when the point
    /// lies more than half a pitch outside the grid.
    pub fn nearest_node(&self, p_mm: [f64; 2]) -> Option<((usize, usize), f64)> {
        let fx = (p_mm[0] - self.origin_mm[0]) / self.pitch_mm;
        let fy = (p_mm[1] - self.origin_mm[1]) / self.pitch_mm;
        if !fx.is_finite() || !fy.is_finite() {
            return None;
        }
        let ix = fx.round();
        let iy = fy.round();
        if ix < 0.0 || iy < 0.0 || ix >= self.nx as f64 || iy >= self.ny as f64 {
            return None;
        }
        let (ix, iy) = (ix as usize, iy as usize);
        let n = self.node_mm(ix, iy);
        let d = ((p_mm[0] - n[0]).powi(2) + (p_mm[1] - n[1]).powi(2)).sqrt();
        Some(((ix, iy), d))
    }
}

/// A layer's regular marker grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarkerGrid {
    /// Grid of marker centres.
    pub grid: Grid,
    /// Marker diameter in mm.
    pub diameter_mm: f64,
}

/// One layer of markers at a fixed depth.
#[derive(Debug, Clone, PartialEq)]
pub struct Layer {
    /// Unique name, used in displacement CSVs.
    pub name: String,
    /// Marker colour.
    pub color: MarkerColor,
    /// Depth below the surface in mm (> 0).
    pub depth_mm: f64,
    /// Regular marker grid, when the file gives one.
    pub markers: Option<MarkerGrid>,
}

/// Pixel <-> sensor-frame mapping of the camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraMapping {
    /// Size of one pixel in mm (square pixels).
    pub mm_per_px: f64,
    /// Pixel position of the sensor-frame origin.
    pub origin_px: [f64; 2],
    /// Image width in pixels.
    pub width_px: u32,
    /// Image height in pixels.
    pub height_px: u32,
    /// Where markers are sought (`[camera] roi_px`); `None`: the whole image.
    pub roi_px: Option<Roi>,
}

/// The region of interest of `[camera] roi_px`, in pixels (pixel `(i, j)` is centred
/// on `(i, j)`): markers are sought only inside it, and a marker whose tracking window
/// crosses its border is not trusted (see `vision`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Roi {
    /// `{ center = [x, y], radius = r }`.
    Circle {
        /// Centre, px.
        center_px: [f64; 2],
        /// Radius, px (> 0).
        radius_px: f64,
    },
    /// `{ min = [x0, y0], max = [x1, y1] }`, `x0 < x1`, `y0 < y1`.
    Rect {
        /// Corner with the smallest coordinates, px.
        min_px: [f64; 2],
        /// Corner with the largest coordinates, px.
        max_px: [f64; 2],
    },
}

impl Roi {
    /// Whether the point lies inside (border included).
    pub fn contains(&self, p: [f64; 2]) -> bool {
        self.inset_contains(p, 0.0)
    }

    /// Whether the whole disc of radius `r` around `c` lies inside.
    pub fn contains_disc(&self, c: [f64; 2], r: f64) -> bool {
        self.inset_contains(c, r)
    }

    /// Distance from `p` to the border, px: positive inside, negative outside.
    pub fn depth(&self, p: [f64; 2]) -> f64 {
        match *self {
            Roi::Circle {
                center_px,
                radius_px,
            } => radius_px - (p[0] - center_px[0]).hypot(p[1] - center_px[1]),
            Roi::Rect { min_px, max_px } => (p[0] - min_px[0])
                .min(max_px[0] - p[0])
                .min(p[1] - min_px[1])
                .min(max_px[1] - p[1]),
        }
    }

    fn inset_contains(&self, p: [f64; 2], inset: f64) -> bool {
        self.depth(p) >= inset
    }

    /// The bounding box `(min, max)`, px.
    pub fn bounds(&self) -> ([f64; 2], [f64; 2]) {
        match *self {
            Roi::Circle {
                center_px: c,
                radius_px: r,
            } => ([c[0] - r, c[1] - r], [c[0] + r, c[1] + r]),
            Roi::Rect { min_px, max_px } => (min_px, max_px),
        }
    }

    /// Checks that the ROI has a positive size and lies inside a `width × height` px
    /// image (within [`ROI_IMAGE_MARGIN_PX`] of the outer pixel centres); the error
    /// says what is allowed, in px.
    pub fn check_in_image(&self, width: u32, height: u32) -> Result<(), String> {
        let size_ok = match *self {
            Roi::Circle { radius_px, .. } => radius_px.is_finite() && radius_px > 0.0,
            Roi::Rect { min_px, max_px } => max_px[0] > min_px[0] && max_px[1] > min_px[1],
        };
        if !size_ok {
            return Err("zero or negative size: a circle needs radius > 0 px, a rectangle max > min along x and y".to_string());
        }
        let (lo, hi) = self.bounds();
        let m = ROI_IMAGE_MARGIN_PX;
        let (xmax, ymax) = (width as f64 - 1.0 + m, height as f64 - 1.0 + m);
        let inside = |v: f64, top: f64| v.is_finite() && v >= -m && v <= top;
        if inside(lo[0], xmax) && inside(hi[0], xmax) && inside(lo[1], ymax) && inside(hi[1], ymax)
        {
            Ok(())
        } else {
            Err(format!(
                "must lie inside the {width}×{height} px image (x in [{}, {xmax}] px, y in [{}, {ymax}] px)",
                -m, -m
            ))
        }
    }

    /// The inline TOML table of `roi_px`.
    pub fn to_toml(&self) -> String {
        match self {
            Roi::Circle {
                center_px,
                radius_px,
            } => format!(
                "{{ center = [{:?}, {:?}], radius = {:?} }}",
                center_px[0], center_px[1], radius_px
            ),
            Roi::Rect { min_px, max_px } => format!(
                "{{ min = [{:?}, {:?}], max = [{:?}, {:?}] }}",
                min_px[0], min_px[1], max_px[0], max_px[1]
            ),
        }
    }
}

impl fmt::Display for Roi {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.to_toml())
    }
}

/// How far an ROI may reach past the image's pixel centres, px: pixel `(i, j)` covers
/// `[i − ½, i + ½]`, so a rectangle `max = [width, height]` (the image's size) is the
/// whole image.
pub const ROI_IMAGE_MARGIN_PX: f64 = 1.0;

impl CameraMapping {
    /// Pixel position to sensor-frame position in mm.
    pub fn px_to_mm(&self, p_px: [f64; 2]) -> [f64; 2] {
        [
            (p_px[0] - self.origin_px[0]) * self.mm_per_px,
            (p_px[1] - self.origin_px[1]) * self.mm_per_px,
        ]
    }

    /// Sensor-frame position in mm to pixel position.
    pub fn mm_to_px(&self, p_mm: [f64; 2]) -> [f64; 2] {
        [
            p_mm[0] / self.mm_per_px + self.origin_px[0],
            p_mm[1] / self.mm_per_px + self.origin_px[1],
        ]
    }
}

/// A validated sensor description.
#[derive(Debug, Clone, PartialEq)]
pub struct Sensor {
    /// Material and thickness.
    pub elastomer: Elastomer,
    /// Marker layers, at least one, unique names.
    pub layers: Vec<Layer>,
    /// Where surface forces are reconstructed.
    pub force_grid: Grid,
    /// Camera mapping.
    pub camera: CameraMapping,
    /// `Some` for a draft (`draft = true`): the keys that still hold placeholders.
    pub draft: Option<Draft>,
}

/// A draft's state (`draft = true`, `placeholders = [...]`, written by `sensor init`).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Draft {
    /// Keys whose values are placeholders (as written: `elastomer.young_modulus_kpa`,
    /// `layers[0].depth_mm`, `camera.mm_per_px`, …), in the file's order.
    pub placeholders: Vec<String>,
}

/// A draft with placeholders given to a command that computes forces
/// ([`Sensor::refuse_draft`]).
#[derive(Debug, Error)]
#[error(
    "{path} is a draft sensor file (draft = true) whose placeholder values were never measured: {list}; \
     forces computed with them are not measurements. Measure each value and remove its key from \
     `placeholders` (remove `draft` and `placeholders` when none is left), or pass --allow-draft \
     to compute with the placeholders anyway",
    list = placeholder_list(.placeholders)
)]
pub struct UnmeasuredDraft {
    /// The sensor file.
    pub path: PathBuf,
    /// `(key, value with unit)` of every placeholder.
    pub placeholders: Vec<(String, String)>,
}

fn placeholder_list(p: &[(String, String)]) -> String {
    p.iter()
        .map(|(k, v)| format!("{k} = {v}"))
        .collect::<Vec<_>>()
        .join(", ")
}

impl Sensor {
    /// Reads and validates a sensor file.
    pub fn from_path(path: impl AsRef<Path>) -> Result<Sensor, SensorError> {
        let path = path.as_ref();
        let text = config::read_text(path, "sensor file")?;
        Sensor::from_toml_str(&text, path)
    }

    /// Parses and validates sensor TOML; `path` is used in error messages only.
    pub fn from_toml_str(text: &str, path: impl AsRef<Path>) -> Result<Sensor, SensorError> {
        let path = path.as_ref();
        let raw: RawSensor = config::parse_toml(text, path)?;
        raw.validate(path)
    }

    /// The keys that hold placeholders (empty unless the file is a draft with
    /// placeholders left).
    pub fn placeholders(&self) -> &[String] {
        self.draft.as_ref().map_or(&[], |d| &d.placeholders)
    }

    /// `(key, value with unit)` of every placeholder.
    pub fn placeholder_values(&self) -> Vec<(String, String)> {
        self.placeholders()
            .iter()
            .map(|k| {
                let v = self.value_text(k).unwrap_or_else(|| "?".to_string());
                (k.clone(), v)
            })
            .collect()
    }

    /// One line naming the placeholders, for the outputs of a command run on a draft
    /// with `--allow-draft` (`None` when there are none).
    pub fn draft_warning(&self, path: &Path) -> Option<String> {
        let p = self.placeholder_values();
        (!p.is_empty()).then(|| {
            format!(
                "DRAFT sensor file {}: computed with placeholder values that were never measured: {}",
                path.display(),
                placeholder_list(&p)
            )
        })
    }

    /// Refuses a draft that still has placeholders: commands that turn displacements
    /// into newtons (`reconstruct`, `run`, `report`) call this unless `--allow-draft`.
    pub fn refuse_draft(&self, path: &Path) -> Result<(), UnmeasuredDraft> {
        let placeholders = self.placeholder_values();
        if placeholders.is_empty() {
            Ok(())
        } else {
            Err(UnmeasuredDraft {
                path: path.to_path_buf(),
                placeholders,
            })
        }
    }

    /// Removes `keys` from the draft's placeholders in memory; the draft state goes
    /// when the last one does. Keys that are not placeholders are left alone and
    /// returned. (For the file's text, keeping its comments: [`mark_measured`].)
    pub fn mark_measured(&mut self, keys: &[&str]) -> Vec<String> {
        let mut unknown = Vec::new();
        if let Some(d) = &mut self.draft {
            for k in keys {
                match d.placeholders.iter().position(|p| p == k) {
                    Some(i) => {
                        d.placeholders.remove(i);
                    }
                    None => unknown.push(k.to_string()),
                }
            }
            if d.placeholders.is_empty() {
                self.draft = None;
            }
        } else {
            unknown.extend(keys.iter().map(|k| k.to_string()));
        }
        unknown
    }

    /// The value of a numeric key as written in the file (`elastomer.young_modulus_kpa`,
    /// `layers[0].depth_mm`, `layers[0].markers.pitch_mm`, `force_grid.origin_mm`,
    /// `camera.mm_per_px`, …), with its unit; `None` for a key the file does not have.
    pub fn value_text(&self, key: &str) -> Option<String> {
        let num = |v: f64, unit: &str| format!("{} {unit}", fmt_value(v));
        let pair =
            |v: [f64; 2], unit: &str| format!("[{}, {}] {unit}", fmt_value(v[0]), fmt_value(v[1]));
        let grid = |g: &Grid, field: &str| match field {
            "nx" => Some(g.nx.to_string()),
            "ny" => Some(g.ny.to_string()),
            "pitch_mm" => Some(num(g.pitch_mm, "mm")),
            "origin_mm" => Some(pair(g.origin_mm, "mm")),
            _ => None,
        };
        let e = &self.elastomer;
        let c = &self.camera;
        match key {
            "elastomer.young_modulus_kpa" => return Some(num(e.young_modulus_kpa, "kPa")),
            "elastomer.poisson_ratio" => return Some(fmt_value(e.poisson_ratio)),
            "elastomer.thickness_mm" => return Some(num(e.thickness_mm, "mm")),
            "camera.mm_per_px" => return Some(num(c.mm_per_px, "mm/px")),
            "camera.origin_px" => return Some(pair(c.origin_px, "px")),
            "camera.width_px" => return Some(format!("{} px", c.width_px)),
            "camera.height_px" => return Some(format!("{} px", c.height_px)),
            _ => {}
        }
        if let Some(field) = key.strip_prefix("force_grid.") {
            return grid(&self.force_grid, field);
        }
        let rest = key.strip_prefix("layers[")?;
        let (index, field) = rest.split_once("].")?;
        let layer = self.layers.get(index.parse::<usize>().ok()?)?;
        match field {
            "depth_mm" => Some(num(layer.depth_mm, "mm")),
            _ => {
                let m = layer.markers.as_ref()?;
                match field.strip_prefix("markers.")? {
                    "diameter_mm" => Some(num(m.diameter_mm, "mm")),
                    f => grid(&m.grid, f),
                }
            }
        }
    }

    /// An upper bound of the load the elastomer can carry on the force grid, N: the
    /// modulus times the grid's area (`nx · ny · pitch²`, each node's cell). A field
    /// whose total `Σ |f|` exceeds it needs a mean stress beyond `E` over the whole
    /// grid, a strain near 100 %: no elastomer sensor carries that (docs/limits.md).
    pub fn max_load_n(&self) -> f64 {
        self.elastomer.young_modulus_n_per_mm2() * self.force_grid_area_mm2()
    }

    /// Area of the force grid's cells, `nx · ny · pitch²`, mm².
    pub fn force_grid_area_mm2(&self) -> f64 {
        let g = &self.force_grid;
        g.len() as f64 * g.pitch_mm * g.pitch_mm
    }

    /// What the loader checked beyond the schema, one line per check, with the values
    /// and the ranges (the `[ok]` lines of `run --dry-run`).
    pub fn plausibility_lines(&self) -> Vec<String> {
        let e = &self.elastomer;
        let r = |v: f64, k: &KeyRange| {
            format!(
                "{} {} (range {} … {})",
                fmt_value(v),
                k.unit,
                fmt_value(k.lo),
                fmt_value(k.hi)
            )
        };
        let depths: Vec<String> = self
            .layers
            .iter()
            .map(|l| format!("{} {}", l.name, fmt_value(l.depth_mm)))
            .collect();
        let mut lines = vec![
            format!(
                "sensor units plausible (docs/limits.md): young_modulus_kpa {}, thickness_mm {}, mm_per_px {}",
                r(e.young_modulus_kpa, &YOUNG_MODULUS_KPA),
                r(e.thickness_mm, &THICKNESS_MM),
                r(self.camera.mm_per_px, &MM_PER_PX)
            ),
            format!(
                "sensor lengths plausible: layer depths {} mm (range {} … {} mm, < thickness), force pitch {}",
                depths.join(", "),
                fmt_value(DEPTH_MM.lo),
                fmt_value(DEPTH_MM.hi),
                r(self.force_grid.pitch_mm, &FORCE_PITCH_MM)
            ),
        ];
        for (i, l) in self.layers.iter().enumerate() {
            if let Some(m) = &l.markers {
                lines.push(format!(
                    "layers[{i}] ({}) markers plausible: pitch {}, diameter {}",
                    l.name,
                    r(m.grid.pitch_mm, &MARKER_PITCH_MM),
                    r(m.diameter_mm, &MARKER_DIAMETER_MM)
                ));
            }
        }
        let cover = ForceCover::of(self);
        lines.push(format!(
            "force grid over the markers: {} of {} nodes within {} mm of the marker area {} (at least {:.0} % needed)",
            cover.near,
            cover.total,
            fmt_value(cover.margin_mm),
            cover.area_text(),
            100.0 * MIN_FORCE_NODES_OVER_MARKERS
        ));
        lines.push(format!(
            "elastomer load bound: |F| <= E x force-grid area = {} N (a force field past it is flagged)",
            fmt_value(self.max_load_n())
        ));
        lines
    }

    /// Index of the layer with this name.
    pub fn layer_index(&self, name: &str) -> Option<usize> {
        self.layers.iter().position(|l| l.name == name)
    }

    /// Force-grid node positions, row-major.
    pub fn force_points_mm(&self) -> Vec<[f64; 2]> {
        self.force_grid.nodes_mm()
    }

    /// Serialises back to TOML in the schema of the module docs.
    pub fn to_toml_string(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        if let Some(d) = &self.draft {
            let keys: Vec<String> = d.placeholders.iter().map(|k| format!("{k:?}")).collect();
            let _ = writeln!(s, "draft = true\nplaceholders = [{}]\n", keys.join(", "));
        }
        let e = &self.elastomer;
        let _ = writeln!(
            s,
            "[elastomer]\nyoung_modulus_kpa = {:?}\npoisson_ratio = {:?}\nthickness_mm = {:?}\n",
            e.young_modulus_kpa, e.poisson_ratio, e.thickness_mm
        );
        if e.model != ModelKind::HalfSpace {
            // Inserted before the blank line ending the section.
            s.pop();
            let _ = writeln!(s, "model = \"{}\"\n", e.model);
        }
        for l in &self.layers {
            let _ = writeln!(
                s,
                "[[layers]]\nname = {:?}\ncolor = \"{}\"\ndepth_mm = {:?}",
                l.name, l.color, l.depth_mm
            );
            if let Some(m) = &l.markers {
                let _ = writeln!(
                    s,
                    "[layers.markers]\nnx = {}\nny = {}\npitch_mm = {:?}\norigin_mm = [{:?}, {:?}]\ndiameter_mm = {:?}",
                    m.grid.nx, m.grid.ny, m.grid.pitch_mm, m.grid.origin_mm[0], m.grid.origin_mm[1], m.diameter_mm
                );
            }
            s.push('\n');
        }
        let g = &self.force_grid;
        let _ = writeln!(
            s,
            "[force_grid]\nnx = {}\nny = {}\npitch_mm = {:?}\norigin_mm = [{:?}, {:?}]\n",
            g.nx, g.ny, g.pitch_mm, g.origin_mm[0], g.origin_mm[1]
        );
        let c = &self.camera;
        let _ = writeln!(
            s,
            "[camera]\nmm_per_px = {:?}\norigin_px = [{:?}, {:?}]\nwidth_px = {}\nheight_px = {}",
            c.mm_per_px, c.origin_px[0], c.origin_px[1], c.width_px, c.height_px
        );
        if let Some(roi) = &c.roi_px {
            let _ = writeln!(s, "roi_px = {roi}");
        }
        s
    }
}

// ---- plausible ranges -----------------------------------------------------------------

/// What a key measures, for the likely slip an error names.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quantity {
    /// A length in mm (metres or micrometres are the slips).
    Length,
    /// A modulus in kPa (Pa, MPa or GPa are the slips).
    Modulus,
    /// The camera's scale in mm/px (m/px, µm/px or px/mm are the slips).
    Scale,
}

/// The plausible range of one sensor-file key: what every real vision-based tactile
/// sensor we have figures for lies in, with a margin (docs/limits.md gives the figures
/// and the reasoning), and what a unit slip does not.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeyRange {
    /// Smallest plausible value.
    pub lo: f64,
    /// Largest plausible value.
    pub hi: f64,
    /// The key's unit.
    pub unit: &'static str,
    /// What the key is, for messages.
    pub what: &'static str,
    /// What kind of slip to suspect.
    pub quantity: Quantity,
}

/// `[elastomer] young_modulus_kpa`: 2 kPa … 20 MPa. Tactile gels span ~10 kPa (soft
/// silicone gels) to a few MPa (Sylgard 184, 3D-printed rubber-like skins); Pa typed
/// for kPa multiplies any modulus from 20 kPa up by 1000 past the top, MPa typed for
/// kPa divides any modulus under 2 MPa (the paper's 1 MPa as `1.0`) below the bottom.
pub const YOUNG_MODULUS_KPA: KeyRange = KeyRange {
    lo: 2.0,
    hi: 20_000.0,
    unit: "kPa",
    what: "an elastomer's Young's modulus",
    quantity: Quantity::Modulus,
};

/// `[elastomer] thickness_mm`: 0.2 … 1000 mm (gels are 1–40 mm thick; metres typed
/// for mm put any gel under 200 mm below 0.2).
pub const THICKNESS_MM: KeyRange = KeyRange {
    lo: 0.2,
    hi: 1000.0,
    unit: "mm",
    what: "an elastomer's thickness",
    quantity: Quantity::Length,
};

/// `[[layers]] depth_mm`: 0.05 mm … (and below the thickness): markers lie under at
/// least a coating; metres typed for mm put any depth under 50 mm below 0.05.
pub const DEPTH_MM: KeyRange = KeyRange {
    lo: 0.05,
    hi: 1000.0,
    unit: "mm",
    what: "a marker layer's depth",
    quantity: Quantity::Length,
};

/// `[layers.markers] pitch_mm`: 0.1 … 50 mm (real marker pitches 0.5–5 mm).
pub const MARKER_PITCH_MM: KeyRange = KeyRange {
    lo: 0.1,
    hi: 50.0,
    unit: "mm",
    what: "a marker pitch",
    quantity: Quantity::Length,
};

/// `[layers.markers] diameter_mm`: 0.01 … 20 mm (real markers 0.1–2 mm).
pub const MARKER_DIAMETER_MM: KeyRange = KeyRange {
    lo: 0.01,
    hi: 20.0,
    unit: "mm",
    what: "a marker diameter",
    quantity: Quantity::Length,
};

/// `[force_grid] pitch_mm`: 0.05 … 1000 mm. The top is loose on purpose: a
/// `sensor init` draft without a scale writes its force grid in pixels at the
/// placeholder `mm_per_px = 1`; a grid in the wrong unit is caught by the markers
/// check ([`MIN_FORCE_NODES_OVER_MARKERS`]), not by its pitch.
pub const FORCE_PITCH_MM: KeyRange = KeyRange {
    lo: 0.05,
    hi: 1000.0,
    unit: "mm",
    what: "a force-grid pitch",
    quantity: Quantity::Length,
};

/// `[camera] mm_per_px`: 0.001 … 1 mm/px (real sensors 0.01–0.2 mm/px; 1 is the
/// placeholder of a `sensor init` draft without a scale).
pub const MM_PER_PX: KeyRange = KeyRange {
    lo: 0.001,
    hi: 1.0,
    unit: "mm/px",
    what: "a camera's scale",
    quantity: Quantity::Scale,
};

/// Largest `[camera] width_px × height_px`: the decoded-frame cap
/// ([`crate::frame_size::MAX_FRAME_PIXELS`]).
pub const MAX_CAMERA_PIXELS: u64 = crate::frame_size::MAX_FRAME_PIXELS;

/// Share of the force-grid nodes that must lie over the markers (within the margin
/// of [`ForceCover`]): forces are reconstructed where markers see them.
pub const MIN_FORCE_NODES_OVER_MARKERS: f64 = 0.5;

impl KeyRange {
    /// `Err(why)`: outside the range (with the likely slip when one explains the value).
    /// `v` must be finite and > 0 (checked before).
    pub fn check(&self, v: f64) -> Result<(), String> {
        if (self.lo..=self.hi).contains(&v) {
            return Ok(());
        }
        let inside = |x: f64| (self.lo..=self.hi).contains(&x);
        let hint = match (self.quantity, v < self.lo) {
            (Quantity::Length, true) if inside(v * 1e3) => format!(
                "; looks like metres: {} m = {} mm (every `_mm` key is in millimetres)",
                fmt_value(v),
                fmt_value(v * 1e3)
            ),
            (Quantity::Length, false) if inside(v * 1e-3) => format!(
                "; looks like micrometres: {} µm = {} mm (every `_mm` key is in millimetres)",
                fmt_value(v),
                fmt_value(v * 1e-3)
            ),
            (Quantity::Modulus, false) if inside(v * 1e-3) => format!(
                "; looks like Pa: {} Pa = {} kPa (the key is in kPa)",
                fmt_value(v),
                fmt_value(v * 1e-3)
            ),
            (Quantity::Modulus, true) if inside(v * 1e3) => format!(
                "; looks like MPa: {} MPa = {} kPa (the key is in kPa)",
                fmt_value(v),
                fmt_value(v * 1e3)
            ),
            (Quantity::Modulus, true) if inside(v * 1e6) => format!(
                "; looks like GPa: {} GPa = {} kPa (the key is in kPa)",
                fmt_value(v),
                fmt_value(v * 1e6)
            ),
            (Quantity::Scale, true) if inside(v * 1e3) => format!(
                "; looks like metres per pixel: {} m/px = {} mm/px",
                fmt_value(v),
                fmt_value(v * 1e3)
            ),
            (Quantity::Scale, false) if inside(1.0 / v) => format!(
                "; looks like pixels per mm (the inverse): {} px/mm = {} mm/px",
                fmt_value(v),
                fmt_value(1.0 / v)
            ),
            (Quantity::Scale, false) if inside(v * 1e-3) => format!(
                "; looks like micrometres per pixel: {} µm/px = {} mm/px",
                fmt_value(v),
                fmt_value(v * 1e-3)
            ),
            _ => format!("; is the unit {}?", self.unit),
        };
        Err(format!(
            "outside the plausible range {} … {} {} of {} (docs/limits.md){hint}",
            fmt_value(self.lo),
            fmt_value(self.hi),
            self.unit,
            self.what
        ))
    }
}

/// A number as people read it: plain from 1e-4 to 1e6, scientific outside (so
/// `1e308` is not 309 digits).
pub fn fmt_value(v: f64) -> String {
    let a = v.abs();
    if v == 0.0 || !v.is_finite() || (1e-4..1e6).contains(&a) {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// `v` finite, > 0 and within `r`; the error names the file, key, value, unit, the
/// range and the likely slip.
fn plausible(c: &Checker<'_>, key: &str, v: f64, r: &KeyRange) -> Result<f64, SensorError> {
    let v = c.positive(key, v, r.unit)?;
    r.check(v)
        .map(|()| v)
        .map_err(|why| c.invalid(key, format!("{} {}", fmt_value(v), r.unit), why))
}

/// How much of the force grid lies over the markers: the marker area is the
/// bounding box of every layer's grid (the camera's whole field for a layer without
/// one), grown by a margin of the deepest layer's depth and the largest marker pitch
/// (markers feel forces that far beyond them).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ForceCover {
    /// Marker area `[x_min, y_min, x_max, y_max]`, mm (before the margin).
    pub area_mm: [f64; 4],
    /// The margin, mm.
    pub margin_mm: f64,
    /// Force nodes within the grown area.
    pub near: usize,
    /// Force nodes.
    pub total: usize,
}

impl ForceCover {
    fn compute(layers: &[Layer], force: &Grid, camera: &CameraMapping) -> Self {
        let mut a = [
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ];
        let mut grow = |p: [f64; 2]| {
            a = [
                a[0].min(p[0]),
                a[1].min(p[1]),
                a[2].max(p[0]),
                a[3].max(p[1]),
            ];
        };
        let mut margin: f64 = 0.0;
        for l in layers {
            margin = margin.max(l.depth_mm);
            match &l.markers {
                Some(m) => {
                    margin = margin.max(m.grid.pitch_mm);
                    grow(m.grid.node_mm(0, 0));
                    grow(m.grid.node_mm(m.grid.nx - 1, m.grid.ny - 1));
                }
                None => {
                    // Pixel (i, j) covers [i − ½, i + ½]: the whole field.
                    grow(camera.px_to_mm([-0.5, -0.5]));
                    grow(
                        camera.px_to_mm([
                            camera.width_px as f64 - 0.5,
                            camera.height_px as f64 - 0.5,
                        ]),
                    );
                }
            }
        }
        let near = force
            .nodes_mm()
            .iter()
            .filter(|p| {
                p[0] >= a[0] - margin
                    && p[0] <= a[2] + margin
                    && p[1] >= a[1] - margin
                    && p[1] <= a[3] + margin
            })
            .count();
        ForceCover {
            area_mm: a,
            margin_mm: margin,
            near,
            total: force.len(),
        }
    }

    /// The cover of a validated sensor.
    pub fn of(sensor: &Sensor) -> Self {
        Self::compute(&sensor.layers, &sensor.force_grid, &sensor.camera)
    }

    /// `x a … b mm, y c … d mm`.
    pub fn area_text(&self) -> String {
        let a = self.area_mm;
        format!(
            "(x {} … {} mm, y {} … {} mm)",
            fmt_value(a[0]),
            fmt_value(a[2]),
            fmt_value(a[1]),
            fmt_value(a[3])
        )
    }

    /// Whether enough nodes lie over the markers.
    pub fn ok(&self) -> bool {
        self.near as f64 >= MIN_FORCE_NODES_OVER_MARKERS * self.total as f64
    }
}

/// The force grid must lie over the markers ([`ForceCover`]).
fn check_force_cover(
    c: &Checker<'_>,
    layers: &[Layer],
    force: &Grid,
    camera: &CameraMapping,
) -> Result<(), SensorError> {
    let cover = ForceCover::compute(layers, force, camera);
    if cover.ok() {
        return Ok(());
    }
    let last = force.node_mm(force.nx - 1, force.ny - 1);
    let span_grid = (last[0] - force.origin_mm[0]).max(last[1] - force.origin_mm[1]);
    let span_markers =
        (cover.area_mm[2] - cover.area_mm[0]).max(cover.area_mm[3] - cover.area_mm[1]);
    let cause = if span_grid > 5.0 * span_markers.max(camera.mm_per_px) {
        format!(
            "the force grid spans {}× the marker area: its pitch_mm and origin_mm look like pixels or another unit (every `_mm` key is in millimetres; a `sensor init` draft without a scale writes its force grid in pixels: multiply both by mm_per_px)",
            fmt_value((span_grid / span_markers.max(f64::MIN_POSITIVE)).round())
        )
    } else {
        "move force_grid.origin_mm over the markers (or check the layers' origin_mm and [camera] origin_px)".to_string()
    };
    Err(c.invalid(
        "force_grid",
        format!(
            "{} × {} nodes every {} mm from [{}, {}] mm (to [{}, {}] mm)",
            force.nx,
            force.ny,
            fmt_value(force.pitch_mm),
            fmt_value(force.origin_mm[0]),
            fmt_value(force.origin_mm[1]),
            fmt_value(last[0]),
            fmt_value(last[1])
        ),
        format!(
            "the force grid must lie over the markers: only {} of its {} nodes lie within {} mm of the marker area {} (the layers' grids, or the camera's field for a layer without one), at least {:.0} % must; {cause}",
            cover.near,
            cover.total,
            fmt_value(cover.margin_mm),
            cover.area_text(),
            100.0 * MIN_FORCE_NODES_OVER_MARKERS
        ),
    ))
}

/// Every key `placeholders` may name (`layers[i]` for any layer index).
fn check_placeholders(
    c: &Checker<'_>,
    draft: Option<bool>,
    placeholders: Option<Vec<String>>,
    sensor: &Sensor,
) -> Result<Option<Draft>, SensorError> {
    match (draft, placeholders) {
        (None | Some(false), None) => Ok(None),
        (None | Some(false), Some(p)) => Err(c.invalid(
            "placeholders",
            format!("{p:?}"),
            "only a draft has placeholders: add `draft = true`, or remove `placeholders` once every value is measured",
        )),
        (Some(true), None) => Err(c.invalid(
            "draft",
            "true",
            "a draft must list the keys whose values are placeholders: `placeholders = [\"elastomer.young_modulus_kpa\", …]` (`[]` when none is left)",
        )),
        (Some(true), Some(p)) => {
            let mut keys: Vec<String> = Vec::with_capacity(p.len());
            for (i, k) in p.into_iter().enumerate() {
                if sensor.value_text(&k).is_none() {
                    return Err(c.invalid(
                        &format!("placeholders[{i}]"),
                        format!("{k:?}"),
                        "not a key of this sensor file: name a numeric key as `elastomer.young_modulus_kpa`, `layers[0].depth_mm`, `layers[0].markers.pitch_mm`, `force_grid.origin_mm` or `camera.mm_per_px`",
                    ));
                }
                if !keys.contains(&k) {
                    keys.push(k);
                }
            }
            Ok(Some(Draft { placeholders: keys }))
        }
    }
}

/// Removes `keys` from the `placeholders` of a draft's text, keeping everything else
/// (comments, layout); when none is left, removes the `draft` and `placeholders` lines.
/// For the `fit` command that turns a draft into a measured file. Errors: the text is
/// not a valid sensor file, not a draft, or a key is not one of its placeholders.
pub fn mark_measured(text: &str, path: &Path, keys: &[&str]) -> Result<String, SensorError> {
    let sensor = Sensor::from_toml_str(text, path)?;
    let c = Checker { path };
    let Some(draft) = &sensor.draft else {
        return Err(c.invalid(
            "draft",
            "(absent)",
            "not a draft: it has no placeholders to clear",
        ));
    };
    for k in keys {
        if !draft.placeholders.iter().any(|p| p == k) {
            return Err(c.invalid(
                "placeholders",
                format!("{k:?}"),
                format!(
                    "not a placeholder of this draft (placeholders: {:?})",
                    draft.placeholders
                ),
            ));
        }
    }
    let left: Vec<&String> = draft
        .placeholders
        .iter()
        .filter(|p| !keys.contains(&p.as_str()))
        .collect();
    let spans = top_level_spans(text);
    let (Some(draft_span), Some(list_span)) = (spans.draft, spans.placeholders) else {
        return Err(c.invalid(
            "placeholders",
            "(not found)",
            "the `draft` and `placeholders` keys must be at the top of the file, before the first table",
        ));
    };
    let mut out = String::with_capacity(text.len());
    if left.is_empty() {
        // Remove both entries (the later one first keeps the earlier span valid).
        let (first, second) = if draft_span.start < list_span.start {
            (draft_span, list_span)
        } else {
            (list_span, draft_span)
        };
        out.push_str(&text[..first.start]);
        out.push_str(&text[first.end..second.start]);
        out.push_str(&text[second.end..]);
    } else {
        let list: Vec<String> = left.iter().map(|k| format!("{k:?}")).collect();
        out.push_str(&text[..list_span.start]);
        out.push_str(&format!("placeholders = [{}]\n", list.join(", ")));
        out.push_str(&text[list_span.end..]);
    }
    // The result must load and say what was asked.
    let again = Sensor::from_toml_str(&out, path)?;
    debug_assert_eq!(again.placeholders().len(), left.len());
    Ok(out)
}

/// Byte spans (whole lines, newline included) of the top-level `draft` and
/// `placeholders` entries.
#[derive(Default)]
struct TopLevelSpans {
    draft: Option<std::ops::Range<usize>>,
    placeholders: Option<std::ops::Range<usize>>,
}

fn top_level_spans(text: &str) -> TopLevelSpans {
    let mut spans = TopLevelSpans::default();
    let mut pos = 0;
    while pos < text.len() {
        let line_end = text[pos..].find('\n').map_or(text.len(), |i| pos + i + 1);
        let line = text[pos..line_end].trim_start();
        if line.starts_with('[') {
            break; // the first table: no top-level keys after it
        }
        let key_is = |k: &str| {
            line.strip_prefix(k)
                .is_some_and(|rest| rest.trim_start().starts_with('='))
        };
        if key_is("draft") {
            spans.draft = Some(pos..line_end);
        } else if key_is("placeholders") {
            // The array may span lines: find its closing bracket outside strings.
            let end = array_end(text, pos).unwrap_or(line_end);
            let end = text[end..].find('\n').map_or(text.len(), |i| end + i + 1);
            spans.placeholders = Some(pos..end);
            pos = end;
            continue;
        }
        pos = line_end;
    }
    spans
}

/// Byte offset just past the `]` closing the first array that starts after `from`.
fn array_end(text: &str, from: usize) -> Option<usize> {
    let mut depth = 0usize;
    let mut in_str = false;
    let mut escaped = false;
    let mut comment = false;
    for (i, ch) in text[from..].char_indices() {
        if comment {
            comment = ch != '\n';
            continue;
        }
        if in_str {
            match (escaped, ch) {
                (true, _) => escaped = false,
                (false, '\\') => escaped = true,
                (false, '"') => in_str = false,
                _ => {}
            }
            continue;
        }
        match ch {
            '"' => in_str = true,
            '#' => comment = true,
            '[' => depth += 1,
            ']' => {
                depth = depth.checked_sub(1)?;
                if depth == 0 {
                    return Some(from + i + 1);
                }
            }
            _ => {}
        }
    }
    None
}

// ---- raw (unvalidated) schema -------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSensor {
    draft: Option<bool>,
    placeholders: Option<Vec<String>>,
    elastomer: RawElastomer,
    layers: Vec<RawLayer>,
    force_grid: RawGrid,
    camera: RawCamera,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawElastomer {
    young_modulus_kpa: f64,
    poisson_ratio: f64,
    thickness_mm: f64,
    model: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLayer {
    name: String,
    color: String,
    depth_mm: f64,
    markers: Option<RawMarkerGrid>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMarkerGrid {
    nx: i64,
    ny: i64,
    pitch_mm: f64,
    #[serde(deserialize_with = "crate::config::exact")]
    origin_mm: [f64; 2],
    diameter_mm: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawGrid {
    nx: i64,
    ny: i64,
    pitch_mm: f64,
    #[serde(deserialize_with = "crate::config::exact")]
    origin_mm: [f64; 2],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCamera {
    mm_per_px: f64,
    #[serde(deserialize_with = "crate::config::exact")]
    origin_px: [f64; 2],
    width_px: i64,
    height_px: i64,
    roi_px: Option<RawRoi>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRoi {
    center: Option<[f64; 2]>,
    radius: Option<f64>,
    min: Option<[f64; 2]>,
    max: Option<[f64; 2]>,
}

impl RawRoi {
    /// Validates the ROI against the image of `width × height` px.
    fn validate(&self, c: &Checker<'_>, width: u32, height: u32) -> Result<Roi, SensorError> {
        const KEY: &str = "camera.roi_px";
        let roi = match (self.center, self.radius, self.min, self.max) {
            (Some(center), Some(radius), None, None) => {
                let center_px = [
                    c.finite(&format!("{KEY}.center[0]"), center[0], "px")?,
                    c.finite(&format!("{KEY}.center[1]"), center[1], "px")?,
                ];
                let radius_px = c.positive(&format!("{KEY}.radius"), radius, "px")?;
                Roi::Circle {
                    center_px,
                    radius_px,
                }
            }
            (None, None, Some(min), Some(max)) => {
                for (i, axis) in ["x", "y"].into_iter().enumerate() {
                    c.finite(&format!("{KEY}.min[{i}]"), min[i], "px")?;
                    c.finite(&format!("{KEY}.max[{i}]"), max[i], "px")?;
                    if max[i] <= min[i] {
                        return Err(c.invalid(
                            &format!("{KEY}.max[{i}]"),
                            format!("{} px", max[i]),
                            format!(
                                "zero or negative size: max must exceed min = {} px along {axis}",
                                min[i]
                            ),
                        ));
                    }
                }
                Roi::Rect {
                    min_px: min,
                    max_px: max,
                }
            }
            _ => {
                let given: Vec<&str> = [
                    ("center", self.center.is_some()),
                    ("radius", self.radius.is_some()),
                    ("min", self.min.is_some()),
                    ("max", self.max.is_some()),
                ]
                .into_iter()
                .filter(|(_, g)| *g)
                .map(|(k, _)| k)
                .collect();
                return Err(c.invalid(
                    KEY,
                    format!("{{ {} }}", given.join(", ")),
                    "must be a circle { center = [x, y], radius = r } or a rectangle { min = [x0, y0], max = [x1, y1] } (px)",
                ));
            }
        };
        if let Err(allowed) = roi.check_in_image(width, height) {
            let (lo, hi) = roi.bounds();
            return Err(c.invalid(
                KEY,
                format!(
                    "{roi} (spans x {}..{} px, y {}..{} px)",
                    lo[0], hi[0], lo[1], hi[1]
                ),
                allowed,
            ));
        }
        Ok(roi)
    }
}

/// A regular grid's keys, checked; its pitch within `pitch_range`.
fn check_grid(
    c: &Checker<'_>,
    key: &str,
    nx: i64,
    ny: i64,
    pitch: f64,
    origin: [f64; 2],
    pitch_range: &KeyRange,
) -> Result<Grid, SensorError> {
    const MAX_NODES: i64 = 4096;
    Ok(Grid {
        nx: c.count(&format!("{key}.nx"), nx, MAX_NODES)?,
        ny: c.count(&format!("{key}.ny"), ny, MAX_NODES)?,
        pitch_mm: plausible(c, &format!("{key}.pitch_mm"), pitch, pitch_range)?,
        origin_mm: [
            c.finite(&format!("{key}.origin_mm[0]"), origin[0], "mm")?,
            c.finite(&format!("{key}.origin_mm[1]"), origin[1], "mm")?,
        ],
    })
}

impl RawSensor {
    /// The validated sensor: the elastomer, the layers, the force grid, the camera
    /// mapping, then the checks across them (the force grid covers the markers, the
    /// draft's placeholders).
    fn validate(self, path: &Path) -> Result<Sensor, SensorError> {
        let c = Checker { path };
        let elastomer = self.elastomer.validate(&c)?;
        let layers = validate_layers(&c, self.layers, elastomer.thickness_mm)?;
        let g = &self.force_grid;
        let force_grid = check_grid(
            &c,
            "force_grid",
            g.nx,
            g.ny,
            g.pitch_mm,
            g.origin_mm,
            &FORCE_PITCH_MM,
        )?;
        let camera = self.camera.validate(&c)?;
        check_force_cover(&c, &layers, &force_grid, &camera)?;
        let mut sensor = Sensor {
            elastomer,
            layers,
            force_grid,
            camera,
            draft: None,
        };
        sensor.draft = check_placeholders(&c, self.draft, self.placeholders, &sensor)?;
        Ok(sensor)
    }
}

impl RawElastomer {
    /// Young's modulus, Poisson's ratio and thickness in their plausible ranges, and
    /// the forward model (default: the half-space).
    fn validate(&self, c: &Checker<'_>) -> Result<Elastomer, SensorError> {
        let young = plausible(
            c,
            "elastomer.young_modulus_kpa",
            self.young_modulus_kpa,
            &YOUNG_MODULUS_KPA,
        )?;
        let nu = self.poisson_ratio;
        if !(nu.is_finite() && (0.0..=0.5).contains(&nu)) {
            return Err(c.invalid(
                "elastomer.poisson_ratio",
                nu,
                "must be in [0, 0.5] (0.5 = incompressible)",
            ));
        }
        let thickness = plausible(
            c,
            "elastomer.thickness_mm",
            self.thickness_mm,
            &THICKNESS_MM,
        )?;
        let model = match &self.model {
            None => ModelKind::HalfSpace,
            Some(name) => ModelKind::from_name(name).ok_or_else(|| {
                c.invalid(
                    "elastomer.model",
                    format!("{name:?}"),
                    "must be \"half-space\" or \"bonded-layer\"",
                )
            })?,
        };
        Ok(Elastomer {
            young_modulus_kpa: young,
            poisson_ratio: nu,
            thickness_mm: thickness,
            model,
        })
    }
}

/// At least one layer, each with a unique name ([`RawLayer::validate`]).
fn validate_layers(
    c: &Checker<'_>,
    raw: Vec<RawLayer>,
    thickness_mm: f64,
) -> Result<Vec<Layer>, SensorError> {
    if raw.is_empty() {
        return Err(c.invalid("layers", "[]", "at least one [[layers]] table is required"));
    }
    let mut names = HashSet::new();
    let mut layers = Vec::with_capacity(raw.len());
    for (i, l) in raw.into_iter().enumerate() {
        let key = format!("layers[{i}]");
        if l.name.trim().is_empty() || l.name.contains(',') {
            return Err(c.invalid(
                &format!("{key}.name"),
                format!("{:?}", l.name),
                "must be a non-empty name without commas",
            ));
        }
        if !names.insert(l.name.clone()) {
            return Err(c.invalid(
                &format!("{key}.name"),
                format!("{:?}", l.name),
                "duplicate layer name: every layer needs a unique name",
            ));
        }
        layers.push(l.validate(c, &key, thickness_mm)?);
    }
    Ok(layers)
}

impl RawLayer {
    /// The layer at `key` (its name already checked): colour, depth inside the
    /// elastomer (`thickness_mm`), the optional marker grid.
    fn validate(self, c: &Checker<'_>, key: &str, thickness_mm: f64) -> Result<Layer, SensorError> {
        let color = MarkerColor::parse(&self.color).ok_or_else(|| {
            c.invalid(
                &format!("{key}.color"),
                format!("{:?}", self.color),
                "unknown colour: expected one of blue, red, green, dark, bright",
            )
        })?;
        let depth = plausible(c, &format!("{key}.depth_mm"), self.depth_mm, &DEPTH_MM)?;
        if depth >= thickness_mm {
            return Err(c.invalid(
                &format!("{key}.depth_mm"),
                depth,
                format!("must be less than elastomer.thickness_mm = {thickness_mm} mm"),
            ));
        }
        let markers = match self.markers {
            None => None,
            Some(m) => {
                let mkey = format!("{key}.markers");
                let grid = check_grid(
                    c,
                    &mkey,
                    m.nx,
                    m.ny,
                    m.pitch_mm,
                    m.origin_mm,
                    &MARKER_PITCH_MM,
                )?;
                let d = plausible(
                    c,
                    &format!("{mkey}.diameter_mm"),
                    m.diameter_mm,
                    &MARKER_DIAMETER_MM,
                )?;
                Some(MarkerGrid {
                    grid,
                    diameter_mm: d,
                })
            }
        };
        Ok(Layer {
            name: self.name,
            color,
            depth_mm: depth,
            markers,
        })
    }
}

impl RawCamera {
    /// The linear camera mapping: image size (within the decoded-frame cap), scale,
    /// origin and the optional region of interest.
    fn validate(&self, c: &Checker<'_>) -> Result<CameraMapping, SensorError> {
        let width_px = c.count("camera.width_px", self.width_px, 65_535)? as u32;
        let height_px = c.count("camera.height_px", self.height_px, 65_535)? as u32;
        let pixels = width_px as u64 * height_px as u64;
        if pixels > MAX_CAMERA_PIXELS {
            return Err(c.invalid(
                "camera.width_px × camera.height_px",
                format!("{width_px} × {height_px} px = {pixels} px"),
                format!(
                    "at most {MAX_CAMERA_PIXELS} px ({} megapixels): the decoded-frame cap (docs/limits.md)",
                    MAX_CAMERA_PIXELS / 1_000_000
                ),
            ));
        }
        Ok(CameraMapping {
            mm_per_px: plausible(c, "camera.mm_per_px", self.mm_per_px, &MM_PER_PX)?,
            origin_px: [
                c.finite("camera.origin_px[0]", self.origin_px[0], "px")?,
                c.finite("camera.origin_px[1]", self.origin_px[1], "px")?,
            ],
            width_px,
            height_px,
            roi_px: match &self.roi_px {
                Some(r) => Some(r.validate(c, width_px, height_px)?),
                None => None,
            },
        })
    }
}

/// The paper's sensor (Section III, Fig. 6 set-up): markers every 1.5 mm at 3 mm
/// (blue) and 6 mm (red), a 10×8 force grid every 2.2 mm, E = 1 MPa, ν = 0.5.
/// Also shipped as `experiments/paper_sensor.toml`.
pub const PAPER_SENSOR_TOML: &str = include_str!("../experiments/paper_sensor.toml");

/// The paper's sensor, parsed (see [`PAPER_SENSOR_TOML`]).
pub fn paper_sensor() -> Sensor {
    // The file is part of the crate and covered by a test; failing here is a build defect.
    Sensor::from_toml_str(PAPER_SENSOR_TOML, "experiments/paper_sensor.toml")
        .expect("bundled paper sensor is valid")
}

/// A synthetic sensor with regular, mutually compatible grids, used by benchmarks,
/// tests and the accuracy-vs-time study: an `force_nx × force_ny` force grid every
/// `force_pitch_mm` from the origin, and two marker layers (blue at 3 mm, red at 6 mm,
/// the paper's depths) every `marker_pitch_mm` covering the same extent, the red grid
/// offset by half a marker pitch. Material as the paper (E = 1000 kPa, ν = 0.5); the
/// camera frames the marker area at 0.05 mm/px with a 1 mm margin.
pub fn grid_sensor(
    force_nx: usize,
    force_ny: usize,
    force_pitch_mm: f64,
    marker_pitch_mm: f64,
) -> Sensor {
    let span = [
        force_pitch_mm * (force_nx.max(1) - 1) as f64,
        force_pitch_mm * (force_ny.max(1) - 1) as f64,
    ];
    let mnx = (span[0] / marker_pitch_mm).round() as usize + 1;
    let mny = (span[1] / marker_pitch_mm).round() as usize + 1;
    let layer = |name: &str, color, depth_mm, offset: f64| Layer {
        name: name.to_string(),
        color,
        depth_mm,
        markers: Some(MarkerGrid {
            grid: Grid {
                nx: mnx,
                ny: mny,
                pitch_mm: marker_pitch_mm,
                origin_mm: [offset, offset],
            },
            diameter_mm: 0.4 * marker_pitch_mm,
        }),
    };
    let mm_per_px = 0.05;
    Sensor {
        elastomer: Elastomer {
            young_modulus_kpa: 1000.0,
            poisson_ratio: 0.5,
            thickness_mm: 40.0,
            model: ModelKind::HalfSpace,
        },
        layers: vec![
            layer("blue", MarkerColor::Blue, 3.0, 0.0),
            layer("red", MarkerColor::Red, 6.0, 0.5 * marker_pitch_mm),
        ],
        force_grid: Grid {
            nx: force_nx,
            ny: force_ny,
            pitch_mm: force_pitch_mm,
            origin_mm: [0.0, 0.0],
        },
        camera: CameraMapping {
            mm_per_px,
            origin_px: [1.0 / mm_per_px, 1.0 / mm_per_px],
            width_px: ((span[0] + marker_pitch_mm + 2.0) / mm_per_px).ceil() as u32,
            height_px: ((span[1] + marker_pitch_mm + 2.0) / mm_per_px).ceil() as u32,
            roi_px: None,
        },
        draft: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Sensor, SensorError> {
        Sensor::from_toml_str(text, "s.toml")
    }

    fn err(text: &str) -> String {
        parse(text).expect_err("should be rejected").to_string()
    }

    #[test]
    fn bundled_paper_sensor_parses_with_design_values() {
        let s = paper_sensor();
        assert_eq!(s.layers.len(), 2);
        assert_eq!(s.layers[0].name, "blue");
        assert_eq!(s.layers[1].depth_mm, 6.0);
        assert_eq!(s.force_grid.len(), 80);
        assert_eq!(s.elastomer.young_modulus_n_per_mm2(), 1.0);
        assert_eq!(s.camera.width_px, 430);
        let m = s.layers[0].markers.unwrap();
        assert_eq!((m.grid.nx, m.grid.ny), (13, 10));
    }

    #[test]
    fn grid_sensor_is_valid_and_covers_the_force_grid() {
        let s = grid_sensor(32, 32, 1.1, 1.1);
        let again = parse(&s.to_toml_string()).unwrap();
        assert_eq!(s, again);
        let m = s.layers[1].markers.unwrap().grid;
        assert_eq!((m.nx, m.ny), (32, 32));
        assert_eq!(m.origin_mm, [0.55, 0.55]);
        let s = grid_sensor(10, 8, 2.2, 1.1);
        assert_eq!(s.layers[0].markers.unwrap().grid.nx, 19);
    }

    #[test]
    fn round_trips_through_toml() {
        let s = paper_sensor();
        let again = parse(&s.to_toml_string()).unwrap();
        assert_eq!(s, again);
    }

    #[test]
    fn rejects_poisson_ratio_outside_range_naming_key_and_range() {
        let t = PAPER_SENSOR_TOML.replace("poisson_ratio = 0.5", "poisson_ratio = 0.7");
        let e = err(&t);
        assert!(e.contains("s.toml"), "{e}");
        assert!(e.contains("elastomer.poisson_ratio = 0.7"), "{e}");
        assert!(e.contains("[0, 0.5]"), "{e}");
    }

    #[test]
    fn rejects_non_positive_depth_and_modulus() {
        let t = PAPER_SENSOR_TOML.replacen("depth_mm = 3.0", "depth_mm = 0.0", 1);
        assert!(err(&t).contains("layers[0].depth_mm = 0"));
        let t = PAPER_SENSOR_TOML.replace("young_modulus_kpa = 1000.0", "young_modulus_kpa = -5.0");
        let e = err(&t);
        assert!(
            e.contains("elastomer.young_modulus_kpa = -5") && e.contains("kPa"),
            "{e}"
        );
    }

    #[test]
    fn rejects_empty_grids() {
        let t = PAPER_SENSOR_TOML.replace("nx = 10", "nx = 0");
        let e = err(&t);
        assert!(e.contains("force_grid.nx = 0"), "{e}");
        let t = PAPER_SENSOR_TOML.replacen("ny = 10", "ny = 0", 1);
        assert!(err(&t).contains("layers[0].markers.ny = 0"));
    }

    #[test]
    fn rejects_unknown_colour_and_duplicate_names() {
        let t = PAPER_SENSOR_TOML.replacen("color = \"red\"", "color = \"purple\"", 1);
        let e = err(&t);
        assert!(
            e.contains("layers[1].color = \"purple\"") && e.contains("blue, red, green"),
            "{e}"
        );
        let t = PAPER_SENSOR_TOML.replacen("name = \"red\"", "name = \"blue\"", 1);
        assert!(err(&t).contains("duplicate layer name"));
    }

    #[test]
    fn rejects_unknown_keys_with_location() {
        let t =
            PAPER_SENSOR_TOML.replace("thickness_mm = 40.0", "thickness_mm = 40.0\nstiffness = 3");
        let e = err(&t);
        assert!(e.contains("s.toml") && e.contains("stiffness"), "{e}");
        assert!(e.contains("line"), "{e}");
    }

    #[test]
    fn rejects_layer_deeper_than_elastomer() {
        let t = PAPER_SENSOR_TOML.replace("thickness_mm = 40.0", "thickness_mm = 5.0");
        assert!(err(&t).contains("layers[1].depth_mm = 6"));
    }

    #[test]
    fn grid_nearest_node_and_camera_mapping_invert() {
        let s = paper_sensor();
        let g = s.layers[0].markers.unwrap().grid;
        assert_eq!(
            g.nearest_node([1.5 * 3.0 + 0.1, 1.5 * 2.0]).unwrap().0,
            (3, 2)
        );
        assert!(g.nearest_node([-5.0, 0.0]).is_none());
        let p = [3.3, -1.25];
        let back = s.camera.px_to_mm(s.camera.mm_to_px(p));
        assert!((back[0] - p[0]).abs() < 1e-12 && (back[1] - p[1]).abs() < 1e-12);
    }

    #[test]
    fn elastomer_model_defaults_to_half_space_and_parses_bonded_layer() {
        let s = Sensor::from_toml_str(PAPER_SENSOR_TOML, Path::new("s.toml")).unwrap();
        assert_eq!(s.elastomer.model, ModelKind::HalfSpace);
        // The default writes no key: today's files round-trip unchanged.
        assert!(!s.to_toml_string().contains("model"));
        let t = PAPER_SENSOR_TOML.replace(
            "thickness_mm = 40.0",
            "thickness_mm = 40.0\nmodel = \"bonded-layer\"",
        );
        let s = Sensor::from_toml_str(&t, Path::new("s.toml")).unwrap();
        assert_eq!(s.elastomer.model, ModelKind::BondedLayer);
        let back = Sensor::from_toml_str(&s.to_toml_string(), Path::new("s.toml")).unwrap();
        assert_eq!(back, s);
        let t = PAPER_SENSOR_TOML.replace(
            "thickness_mm = 40.0",
            "thickness_mm = 40.0\nmodel = \"half-space\"",
        );
        let s = Sensor::from_toml_str(&t, Path::new("s.toml")).unwrap();
        assert_eq!(s.elastomer.model, ModelKind::HalfSpace);
    }

    #[test]
    fn rejects_unknown_elastomer_model_naming_file_key_and_value() {
        let t = PAPER_SENSOR_TOML.replace(
            "thickness_mm = 40.0",
            "thickness_mm = 40.0\nmodel = \"layered\"",
        );
        let e = err(&t);
        assert!(
            e.contains("s.toml")
                && e.contains("elastomer.model = \"layered\"")
                && e.contains("bonded-layer"),
            "{e}"
        );
    }
}
