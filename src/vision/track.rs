//! Tracking markers frame by frame against a [`Reference`] (paper Section II-A).
//!
//! * [`TrackMode::PerWindow`] — the paper's method: every frame is measured on its
//!   own, each marker in a window starting at its reference position. Valid while a
//!   marker stays within about its search radius (half the marker spacing) of rest.
//! * [`TrackMode::FrameToFrame`] (default) — the paper's "tracking" for larger
//!   motion: each window starts at the marker's last position plus its last
//!   velocity, so markers can travel 40 px and more over a sequence of frames. When
//!   that pass leaves a marker unfound or farther than a quarter of its local spacing
//!   from its reference position, the frame is measured again per window from the
//!   reference and the two passes are combined per marker (`Tracker::combine`:
//!   markers both passes put on one blob seed it; the others take, in rounds from
//!   the seeds, the candidate nearer their decided neighbours' median displacement,
//!   within half a local spacing, else `outlier`; what no seed reaches takes the
//!   pass with more ok markers). So independent frames (contacts at unrelated
//!   poses, issue 29) never depend on the unrelated frame before them, and a
//!   sequence keeps its last positions.
//!
//! Per marker: iterated window centroid (`window.rs`) from the start — the predicted
//! position (reference, or last position plus velocity) moved by the nearest
//! already-measured same-layer neighbour's correction of its own prediction, which
//! usually leaves one pass per marker (when that finds nothing acceptable, again from
//! the prediction itself); when that finds
//! no marker (too weak or nothing there), the paper's window search (centre of mass of
//! the score above 40 % of the marker's reference peak within the search radius)
//! acquires it and the window centroid refines it. Then, per frame:
//! * **lost** — nothing found, signal below `min_signal_ratio` of the reference
//!   signal, the dot (radius + 1 px) crossing the image edge in the frame or the
//!   reference (a window cut by the edge around a dot inside is measured on its part
//!   inside the image, `window::clipped`), or the result farther than search radius
//!   + aperture from the start;
//! * **overlap** — a marker whose aperture another layer's marker reaches (layers
//!   at different depths slide over one another) is measured again with that
//!   marker's disc left out, together with its images under the disc's point, axis
//!   and diagonal reflections (`Window::locate_masked`), two sweeps so both use each
//!   other's corrected positions;
//! * **one blob, one marker** (global matching) — when two same-layer markers'
//!   windows end on the same blob (closer than `merge_distance`, default the marker
//!   radius), the blob is given to the marker whose field-corrected prediction (its
//!   window start: the prediction moved by the nearest measured neighbour's
//!   correction) is nearer by at least a quarter of the local spacing (mutual nearest
//!   neighbours), and the other is **lost**: a neighbour's position is never reported
//!   as a marker's own. When the blob carries more than 1.2 markers' signal, or is
//!   about as near to both predictions, both are **merged**;
//! * **merged** — also a signal above `merge_signal_ratio` × reference, or a marker
//!   of another layer closer than 0.8 × the sum of the radii (or hiding over 80 % of
//!   the aperture);
//! * **outlier** — displacement farther than `tol + 3·spread` from the median of its
//!   (ok) neighbours' displacements, where `spread` is the median distance of the
//!   neighbours' displacements from that median (needs ≥ 3 neighbours) and `tol` is
//!   `outlier_px`, at most a quarter of the local spacing (a marker matched to its
//!   neighbour's blob is off by a whole spacing, whatever the spacing);
//! * **outlier** (swap bound) — an ok marker whose displacement is farther than half
//!   its local spacing from the median of its ok neighbours' (one or more), whatever
//!   their spread: it sits on a neighbour's blob, or they do;
//! * **outlier** (appearance changed, issue 24) — an ok marker whose signal relative
//!   to the median of its ok neighbours' signals (relative to their reference
//!   signals) differs from 1 by more than `appearance_tolerance` (6 %), or by more
//!   than 5 robust SDs of the frame's relative signals in its layer when those vary
//!   more: part of it is covered (dust, a shadow, the edge of a patch), or it is a
//!   blob of another size or contrast than in the reference; its centroid may carry
//!   a false displacement. Markers measured with another layer's marker masked out
//!   are not judged. Uniform or smooth illumination changes move the neighbours'
//!   signals too and flag nothing.
//! * **outlier** (specular highlight) — an ok `dark` marker with a saturated pixel
//!   within 60 % of its radius of its centroid, in the reference or in this frame: a
//!   reflection of the light hides part of it and stays where the light is while
//!   the marker moves, so its centroid may be off by pixels with an unchanged signal.
//!   A `bright` marker (which may saturate by itself) is flagged when its saturated
//!   pixels on the dot changed against its reference's (count, or their offset from
//!   the centroid) while none of its neighbours shows saturation (broad light, which
//!   moves no centroid, saturates neighbours too).
//!
//! **Any layout.** Every scale is per marker, from the reference layout around it:
//! its local spacing is the distance to its nearest same-layer marker at rest; the
//! search square's half-size is half of it, the acceptance radius that plus the
//! aperture, and a marker found farther than 0.6 local spacings from both its
//! prediction and its field-corrected start is lost (the local-spacing gate of the
//! matching: it sits on a neighbour's blob), the neighbours those within 1.6 local spacings (a square grid's
//! diagonals, a hexagonal packing's first ring). So hexagonal, perspective-distorted
//! and irregular layouts of hundreds of markers, found in the reference frame without
//! a grid in the sensor file, are tracked like the grids: displacements up to about
//! half the local spacing from the reference alone (per window), larger ones over a
//! sequence (frame to frame).
//!
//! Only ok markers' displacements are meant for the solver. In frame-to-frame mode,
//! lost and merged markers keep their last good position for the next frame.
//! [`Tracker::track`] allocates nothing: all buffers are sized in [`Tracker::new`].

use super::camera::PixelMapping;
use super::detect::{
    highlight_radius_px, highlight_within, saturation_within, with_raw, Reference, Saturation,
};
use super::image::{check_layers, FrameView};
use super::window::{dot_inside, score_bias, search, Foreign, Located, Raw, Sample, Window};
use super::{MarkerStatus, Pixels, VisionError};
use crate::formats::DisplacementRecord;
use crate::sensor::{CameraMapping, MarkerColor};

/// Where [`Tracker::measure_layer`] starts each marker's window in one pass.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Start {
    /// At the reference position (per window).
    Reference,
    /// At the last position plus the last velocity (the sequence's pass).
    Last,
    /// At the reference position, copying the sequence pass's measurement where it
    /// lies near the reference position (the re-acquisition pass).
    Reacquire,
}

/// Which pass [`Tracker::combine`] gives a marker to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pick {
    Undecided,
    /// The sequence's pass (from the last positions).
    A,
    /// The reference's pass.
    B,
    /// The sequence pass's result, flagged `outlier` (inconsistent with the decided
    /// neighbours).
    RejectedA,
    /// The reference pass's result, flagged `outlier`.
    RejectedB,
}

impl Pick {
    fn rejected(self) -> Pick {
        match self {
            Pick::A => Pick::RejectedA,
            Pick::B => Pick::RejectedB,
            other => other,
        }
    }

    fn is_rejected(self) -> bool {
        matches!(self, Pick::RejectedA | Pick::RejectedB)
    }

    /// Taken from the reference's pass.
    fn is_b(self) -> bool {
        matches!(self, Pick::B | Pick::RejectedB)
    }
}

/// How windows are placed in each frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrackMode {
    /// Start at the reference position (paper: squares centred on the rest position).
    PerWindow,
    /// Start at the last position plus the last velocity (large motion, sequences).
    FrameToFrame,
}

/// Options of the [`Tracker`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackConfig {
    /// Window placement.
    pub mode: TrackMode,
    /// Maximum window re-centrings per marker (default 8).
    pub max_iterations: u32,
    /// Below this fraction of its reference signal a marker is lost (default 0.3).
    pub min_signal_ratio: f64,
    /// Above this multiple of its reference signal a marker is merged (default 1.6).
    pub merge_signal_ratio: f64,
    /// Neighbours closer than this are merged, px (default: the marker radius).
    pub merge_distance_px: Option<f64>,
    /// Base tolerance of the neighbour-consistency check, px (default 3).
    pub outlier_px: f64,
    /// Half-size of the acquisition search square, px (default: half the marker's
    /// local spacing, the distance to its nearest same-layer marker at rest).
    pub search_half_px: Option<f64>,
    /// A marker whose signal differs from its neighbours' by more than this fraction
    /// (after the frame's own spread, see the module docs) changed appearance (part of
    /// it covered, a blob of another size or contrast) and is flagged `outlier`
    /// (default 0.06; `f64::INFINITY` turns the check off).
    pub appearance_tolerance: f64,
}

impl Default for TrackConfig {
    fn default() -> Self {
        TrackConfig {
            mode: TrackMode::FrameToFrame,
            max_iterations: 8,
            min_signal_ratio: 0.3,
            merge_signal_ratio: 1.6,
            merge_distance_px: None,
            outlier_px: 3.0,
            search_half_px: None,
            appearance_tolerance: DEFAULT_APPEARANCE_TOLERANCE,
        }
    }
}

/// One marker in one frame. Indexes match [`Reference::markers`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarkerTrack {
    /// Measured centroid, px (NaN when lost).
    pub centroid_px: [f64; 2],
    /// Centroid minus reference centroid, px (NaN when lost).
    pub displacement_px: [f64; 2],
    /// Status.
    pub status: MarkerStatus,
    /// Signal relative to the reference (0 when lost with nothing found).
    pub signal_ratio: f64,
}

impl MarkerTrack {
    const LOST: MarkerTrack = MarkerTrack {
        centroid_px: [f64::NAN; 2],
        displacement_px: [f64::NAN; 2],
        status: MarkerStatus::Lost,
        signal_ratio: 0.0,
    };
}

/// Counts of each status in one frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StatusCounts {
    /// Ok markers.
    pub ok: usize,
    /// Lost markers (reference-missing ones included).
    pub lost: usize,
    /// Merged markers.
    pub merged: usize,
    /// Outliers.
    pub outlier: usize,
}

impl StatusCounts {
    /// Counts the statuses of `tracks`, plus `missing` always-lost markers.
    pub fn of(tracks: &[MarkerTrack], missing: usize) -> StatusCounts {
        let mut c = StatusCounts {
            lost: missing,
            ..Default::default()
        };
        for t in tracks {
            match t.status {
                MarkerStatus::Ok => c.ok += 1,
                MarkerStatus::Lost => c.lost += 1,
                MarkerStatus::Merged => c.merged += 1,
                MarkerStatus::Outlier => c.outlier += 1,
            }
        }
        c
    }

    /// Counts over several frames of the same markers: each marker counts once, with
    /// its worst status (lost, then merged, then outlier, then ok: ok only when ok in
    /// every frame), plus `missing` always-lost markers.
    pub fn of_frames<'a>(
        frames: impl IntoIterator<Item = &'a [MarkerTrack]>,
        missing: usize,
    ) -> StatusCounts {
        let rank = |s: MarkerStatus| match s {
            MarkerStatus::Ok => 0,
            MarkerStatus::Outlier => 1,
            MarkerStatus::Merged => 2,
            MarkerStatus::Lost => 3,
        };
        let mut worst: Vec<u8> = Vec::new();
        for tracks in frames {
            if worst.len() < tracks.len() {
                worst.resize(tracks.len(), 0);
            }
            for (w, t) in worst.iter_mut().zip(tracks) {
                *w = (*w).max(rank(t.status));
            }
        }
        let mut c = StatusCounts {
            lost: missing,
            ..Default::default()
        };
        for w in worst {
            match w {
                0 => c.ok += 1,
                1 => c.outlier += 1,
                2 => c.merged += 1,
                _ => c.lost += 1,
            }
        }
        c
    }
}

const MAX_NEIGHBOURS: usize = 8;

/// Other-layer markers checked for overlap per marker (the nearest at rest).
const MAX_FOREIGN: usize = 4;

/// Below this fraction of its aperture left visible by other layers' markers (with
/// the mirror images of the hidden part), a marker is merged.
const MIN_VISIBLE: f64 = 0.2;

/// Markers of two layers closer than this fraction of the sum of their radii are
/// merged (9.6 px for two discs of radius 6 px). On the `sim` renders (`tests/vision.rs`,
/// overlapping layers, five sub-pixel phases) the masked centroid errs by ≤ 0.027 px
/// noise-free above that, but by up to 0.053 px at 8–9.5 px apart, and with σ = 2
/// noise in 8 bits by 0.11 px (mean 0.033 px) at 9 px: not accurate enough to report.
const MIN_CROSS_LAYER_DISTANCE: f64 = 0.8;

/// Default of [`TrackConfig::appearance_tolerance`].
pub const DEFAULT_APPEARANCE_TOLERANCE: f64 = 0.06;

/// Two markers on one blob whose signal is at least this multiple of a marker's are
/// merged in the image (two markers' worth of colour), whoever is nearer.
const SHARED_BLOB_MERGE_RATIO: f64 = 1.2;

/// A window's result farther than this many local spacings from where the attempt
/// expected the marker is rejected (matching gate: a neighbour's blob lies about one
/// spacing away, the marker's own within about half of one).
const GATE_FRACTION: f64 = 0.6;

/// Two claimants of one blob whose distances from their own predictions differ by
/// less than this fraction of the local spacing cannot be told apart: both merged.
const CLAIM_MARGIN: f64 = 0.25;

/// The neighbour-consistency tolerance is at most this fraction of the local spacing
/// (a marker matched to its neighbour's blob is off by a whole spacing).
const OUTLIER_SPACING_FRACTION: f64 = 0.25;

/// The appearance check's tolerance is at least this many robust SDs (1.4826 · MAD)
/// of the frame's relative signals: frames whose markers vary more by nature (real
/// skins, pins that tilt) are not flagged wholesale.
const APPEARANCE_SPREAD_FACTOR: f64 = 5.0;

/// A `bright` marker's saturated pixels may change by this share of the larger count
/// between reference and frame before it counts as a highlight (sub-pixel motion
/// moves pixels of a saturated core's rim across the threshold).
const SATURATION_COUNT_CHANGE: f64 = 0.3;

/// ... and by at least this many pixels.
const SATURATION_MIN_PX: f64 = 4.0;

/// The mean offset of a `bright` marker's saturated pixels from its centroid may move
/// by this much between reference and frame, px.
const SATURATION_SHIFT_PX: f64 = 0.5;

/// A marker the sequence's pass found within this many local spacings of its
/// reference position is where a window from the reference would find it too: the
/// re-acquisition pass copies it (and is skipped when every marker is so).
const COPY_FRACTION: f64 = 0.25;

/// Swap bound: an ok marker whose displacement is farther than this many local
/// spacings from the median of its neighbours' displacements sits on a neighbour's
/// blob (or its neighbours on others'): `outlier`, whatever their spread.
const SWAP_FRACTION: f64 = 0.5;

/// Per-marker scales taken from the reference layout around that marker, so layouts
/// that are perspective-distorted, irregular or hexagonal get the right scale
/// everywhere (a layer-wide median would be too large on one side of the image and
/// too small on the other).
#[derive(Debug, Clone, Copy)]
struct Local {
    /// Distance to the nearest same-layer marker at rest, px.
    spacing_px: f64,
    /// Half-size of the acquisition search square, px.
    search_half: i32,
    /// Square of the farthest accepted distance from the window's start, px².
    max_jump2: f64,
    /// Base tolerance of the neighbour-consistency check, px.
    outlier_px: f64,
}

struct LayerState {
    window: Window,
    weights: [i32; 3],
    merge_distance_px: f64,
    /// Aperture radius, px: a marker of this layer colours at most this far.
    aperture_px: f64,
    /// Marker radius, px.
    marker_radius_px: f64,
    /// Square of the distance within which another layer's marker may reach into
    /// this layer's aperture, px² (see [`Tracker::resolve_overlaps`]).
    overlap_reach2_px: f64,
    /// The layer's background score in the reference's levels (search threshold base).
    background_score: f64,
    /// A brightness layer (`dark`/`bright`): the illumination varies over the image,
    /// so the search threshold starts from each marker's own ring level instead of
    /// the layer's median score.
    local_background: bool,
    /// This layer's markers in `Reference::markers`.
    markers: std::ops::Range<usize>,
}

impl LayerState {
    /// How far a marker of this layer colours another layer's window, px: its
    /// measured extent (the aperture less its 1.5 px margin, see `detect`) plus 1 px,
    /// so that no pixel whose gradient stencil (±1 px) touches it is used — the edge
    /// a covering marker draws does not move with the covered one.
    fn foreign_support_px(&self) -> f64 {
        self.aperture_px - 1.5 + 1.0 + 0.5
    }
}

/// Tracks the markers of a [`Reference`] in frames of the same size.
pub struct Tracker {
    reference: Reference,
    config: TrackConfig,
    layers: Vec<LayerState>,
    /// Per-marker scales from the reference layout.
    local: Vec<Local>,
    neighbours: Vec<[u32; MAX_NEIGHBOURS]>,
    neighbour_count: Vec<u8>,
    /// The nearest other-layer markers at rest, for the overlap check.
    foreign: Vec<[u32; MAX_FOREIGN]>,
    foreign_count: Vec<u8>,
    last_px: Vec<[f64; 2]>,
    velocity_px: Vec<[f64; 2]>,
    /// Each marker's window start of the current frame before the neighbour hint
    /// (reference or last position plus velocity), px.
    predicted_px: Vec<[f64; 2]>,
    out: Vec<MarkerTrack>,
    /// Each marker's first window start of the current frame: the prediction moved
    /// by the nearest measured neighbour's correction (the displacement field's local
    /// estimate), px.
    field_start_px: Vec<[f64; 2]>,
    /// Per marker, this frame: measured with other layers' markers masked out.
    masked: Vec<bool>,
    /// Per marker, this frame: a `dark` marker with a saturated pixel on its disc
    /// (a specular highlight, see [`Tracker::find_highlights`]).
    highlight: Vec<bool>,
    /// Per marker, this frame: a `bright` marker's saturated pixels.
    saturation: Vec<Saturation>,
    /// Per marker, this frame: the verdict of [`Tracker::resolve_claims`].
    claim: Vec<Claim>,
    /// Scratch, one value per marker (relative signals of the appearance check).
    relative: Vec<f64>,
    /// Scratch, one value per marker (medians and spreads).
    scratch: Vec<f64>,
    /// Frame to frame: the sequence pass's measurements before any rule (what the
    /// re-acquisition pass copies).
    raw: Vec<MarkerTrack>,
    /// Frame to frame: the sequence pass's results while the re-acquisition pass
    /// runs ([`Tracker::combine`]).
    out_last: Vec<MarkerTrack>,
    /// Per marker, this frame: the pass [`Tracker::combine`] took it from, and the
    /// next round's.
    pick: Vec<Pick>,
    next_pick: Vec<Pick>,
    /// The current frame's sample levels per reference level: 1, or 257 / (1/257)
    /// when the frame's bit depth differs from the reference image's.
    level_scale: f64,
}

impl Tracker {
    /// Prepares windows, neighbour lists and buffers for `reference`. Its markers are
    /// kept sorted by layer, then id (as [`super::detect`] returns them): track results
    /// are indexed like [`Tracker::reference`]'s markers.
    pub fn new(mut reference: Reference, config: TrackConfig) -> Tracker {
        reference.markers.sort_by_key(|m| (m.layer, m.id));
        let mut layers: Vec<LayerState> = reference
            .layers
            .iter()
            .enumerate()
            .map(|(li, l)| LayerState {
                window: Window::new(l.aperture_radius_px, l.score_weights),
                weights: l.score_weights,
                merge_distance_px: config.merge_distance_px.unwrap_or(l.marker_radius_px),
                aperture_px: l.aperture_radius_px,
                marker_radius_px: l.marker_radius_px,
                overlap_reach2_px: 0.0,
                background_score: l.background_score,
                local_background: l.color.is_brightness(),
                markers: {
                    let m = &reference.markers;
                    let lo = m.partition_point(|r| r.layer < li);
                    lo..lo + m[lo..].partition_point(|r| r.layer == li)
                },
            })
            .collect();
        let max_support = layers
            .iter()
            .map(LayerState::foreign_support_px)
            .fold(0.0, f64::max);
        for l in &mut layers {
            l.overlap_reach2_px = (l.aperture_px + max_support).powi(2);
        }
        let m = &reference.markers;
        let mut neighbours = vec![[0u32; MAX_NEIGHBOURS]; m.len()];
        let mut neighbour_count = vec![0u8; m.len()];
        let mut local = Vec::with_capacity(m.len());
        for (i, a) in m.iter().enumerate() {
            let mut near: Vec<(f64, usize)> = m
                .iter()
                .enumerate()
                .filter(|(j, b)| *j != i && b.layer == a.layer)
                .map(|(j, b)| {
                    let d = (a.centroid_px[0] - b.centroid_px[0])
                        .hypot(a.centroid_px[1] - b.centroid_px[1]);
                    (d, j)
                })
                .collect();
            near.sort_by(|x, y| x.0.total_cmp(&y.0));
            let l = &reference.layers[a.layer];
            // The nearest same-layer marker sets this marker's scale; a marker alone
            // in its layer takes the layer's (or four apertures).
            let spacing = near
                .first()
                .map(|n| n.0)
                .filter(|d| d.is_finite() && *d > 0.0)
                .or_else(|| l.spacing_px.is_finite().then_some(l.spacing_px))
                .unwrap_or(4.0 * l.aperture_radius_px);
            let search_half = config
                .search_half_px
                .unwrap_or(0.5 * spacing)
                .max(l.aperture_radius_px);
            let max_jump = search_half + l.aperture_radius_px;
            local.push(Local {
                spacing_px: spacing,
                search_half: search_half.round() as i32,
                max_jump2: max_jump * max_jump,
                outlier_px: config.outlier_px.min(OUTLIER_SPACING_FRACTION * spacing),
            });
            // Neighbours: within 1.6 local spacings (a square grid's diagonals, a
            // hexagonal packing's first ring), the nearest first.
            let radius = 1.6 * spacing;
            for (k, (_, j)) in near
                .iter()
                .take_while(|(d, _)| *d <= radius)
                .take(MAX_NEIGHBOURS)
                .enumerate()
            {
                neighbours[i][k] = *j as u32;
                neighbour_count[i] = k as u8 + 1;
            }
        }
        let mut foreign = vec![[0u32; MAX_FOREIGN]; m.len()];
        let mut foreign_count = vec![0u8; m.len()];
        for (i, a) in m.iter().enumerate() {
            let mut near: Vec<(f64, usize)> = m
                .iter()
                .enumerate()
                .filter(|(_, b)| b.layer != a.layer)
                .map(|(j, b)| (dist2(a.centroid_px, b.centroid_px), j))
                .collect();
            near.sort_by(|x, y| x.0.total_cmp(&y.0));
            for (k, (_, j)) in near.iter().take(MAX_FOREIGN).enumerate() {
                foreign[i][k] = *j as u32;
                foreign_count[i] = k as u8 + 1;
            }
        }
        let last_px = m.iter().map(|r| r.centroid_px).collect();
        Tracker {
            velocity_px: vec![[0.0; 2]; m.len()],
            predicted_px: vec![[0.0; 2]; m.len()],
            out: vec![MarkerTrack::LOST; m.len()],
            field_start_px: vec![[0.0; 2]; m.len()],
            masked: vec![false; m.len()],
            highlight: vec![false; m.len()],
            claim: vec![Claim::Keep; m.len()],
            saturation: vec![Saturation::default(); m.len()],
            relative: vec![0.0; m.len()],
            scratch: vec![0.0; m.len()],
            raw: vec![MarkerTrack::LOST; m.len()],
            out_last: vec![MarkerTrack::LOST; m.len()],
            pick: vec![Pick::Undecided; m.len()],
            next_pick: vec![Pick::Undecided; m.len()],
            local,
            reference,
            config,
            layers,
            neighbours,
            neighbour_count,
            foreign,
            foreign_count,
            last_px,
            level_scale: 1.0,
        }
    }

    /// The reference being tracked.
    pub fn reference(&self) -> &Reference {
        &self.reference
    }

    /// The configuration.
    pub fn config(&self) -> &TrackConfig {
        &self.config
    }

    /// Forgets the sequence: the next frame starts from the reference positions.
    pub fn reset(&mut self) {
        for (l, r) in self.last_px.iter_mut().zip(&self.reference.markers) {
            *l = r.centroid_px;
        }
        for v in &mut self.velocity_px {
            *v = [0.0; 2];
        }
    }

    /// Measures one frame; the result's indexes match [`Reference::markers`].
    /// Fails only when the frame size differs from the reference's.
    ///
    /// 8- and 16-bit frames are both accepted whatever the reference's depth: the
    /// reference's signals and background scores are compared in the frame's levels
    /// (× 257 from 8 to 16 bits, ÷ 257 the other way, exact for PNG-widened samples),
    /// so a mixed pair tracks like a matched one. A greyscale frame is read as
    /// `(g, g, g)`; it fails when a layer is coloured ([`check_layers`]).
    pub fn track(&mut self, frame: &FrameView<'_>) -> Result<&[MarkerTrack], VisionError> {
        check_layers(
            frame,
            self.reference
                .layers
                .iter()
                .map(|l| (l.name.as_str(), l.color)),
        )?;
        if frame.width_px() != self.reference.width_px
            || frame.height_px() != self.reference.height_px
        {
            return Err(VisionError::FrameSize {
                found: [frame.width_px(), frame.height_px()],
                expected: [self.reference.width_px, self.reference.height_px],
            });
        }
        self.level_scale = level_scale(self.reference.bit_depth, frame.bit_depth());
        if self.config.mode == TrackMode::PerWindow {
            self.pass(frame, Start::Reference);
            return Ok(&self.out);
        }
        self.pass(frame, Start::Last);
        let reacquire = self.reacquire_needed();
        if reacquire {
            // The sequence's pass is kept aside; the reference's pass measures what
            // it did not find near the reference (the rest is copied from `raw`).
            std::mem::swap(&mut self.out, &mut self.out_last);
            self.pass(frame, Start::Reacquire);
            self.combine();
        }
        for i in 0..self.out.len() {
            let t = &self.out[i];
            match t.status {
                // A marker re-acquired from its reference jumped: no velocity.
                MarkerStatus::Ok | MarkerStatus::Outlier if reacquire && self.pick[i].is_b() => {
                    self.velocity_px[i] = [0.0; 2];
                    self.last_px[i] = t.centroid_px;
                }
                MarkerStatus::Ok | MarkerStatus::Outlier => {
                    let l = self.last_px[i];
                    self.velocity_px[i] = [t.centroid_px[0] - l[0], t.centroid_px[1] - l[1]];
                    self.last_px[i] = t.centroid_px;
                }
                MarkerStatus::Lost | MarkerStatus::Merged => self.velocity_px[i] = [0.0; 2],
            }
        }
        Ok(&self.out)
    }

    /// One full pass over a frame into `out`: every marker measured from `start`
    /// (with the sequence's start, the measurements are also kept in `raw` for a
    /// reference pass to reuse), then the overlap, claim, outlier, appearance and
    /// highlight rules.
    fn pass(&mut self, frame: &FrameView<'_>, start: Start) {
        with_raw!(frame, img => {
            self.measure_all(img, start);
            if start == Start::Last {
                self.raw.copy_from_slice(&self.out);
            }
            self.resolve_overlaps(img);
            self.find_highlights(img);
        });
        self.flag_outside_roi();
        self.flag_reference_dot_outside();
        self.resolve_claims();
        self.flag_outliers();
        self.flag_swaps();
        self.flag_appearance();
        self.flag_highlights();
    }

    /// Whether the sequence's pass left a marker that a window from its reference
    /// position might find elsewhere: one not found, or found farther than
    /// [`COPY_FRACTION`] local spacings from its reference position. When none is,
    /// a pass from the reference would find the same blobs: it is skipped.
    fn reacquire_needed(&self) -> bool {
        (0..self.raw.len()).any(|i| !self.copyable(i))
    }

    /// Whether the sequence pass's raw measurement of marker `i` is what a window
    /// from its reference position finds too (found within [`COPY_FRACTION`] local
    /// spacings of it: no other blob is nearer to that start).
    fn copyable(&self, i: usize) -> bool {
        let t = &self.raw[i];
        t.status == MarkerStatus::Ok
            && dist2(t.centroid_px, self.reference.markers[i].centroid_px)
                <= (COPY_FRACTION * self.local[i].spacing_px).powi(2)
    }

    /// Keeps, per marker, the result of the sequence's pass (`out_last`, A) or of
    /// the reference's pass (`out`, B) that agrees with its neighbours, so that a
    /// frame unrelated to the one before it (an independent contact) is tracked as
    /// from the reference, and a sequence as from the last positions:
    ///
    /// 1. both ok on one blob (closer than the merge distance): A (seeds);
    /// 2. the rest with a candidate (A or B ok), in rounds from the seeds: the
    ///    candidate whose displacement is nearer the median of the already decided
    ///    ok neighbours' displacements, when within [`SWAP_FRACTION`] local spacings
    ///    of it; a nearest candidate beyond that is `outlier` (on a neighbour's blob);
    /// 3. markers no decided neighbour reaches: the pass with more ok markers in this
    ///    frame (ties: A), then the other when that one is not ok there;
    /// 4. markers with no candidate: that pass's status.
    ///
    /// Then two ok markers of a layer on one blob are both `merged`, and the
    /// neighbour-consistency check runs on the combined field.
    fn combine(&mut self) {
        let n = self.out.len();
        let ok = |t: &MarkerTrack| t.status == MarkerStatus::Ok;
        let ok_a = self.out_last.iter().filter(|t| ok(t)).count();
        let ok_b = self.out.iter().filter(|t| ok(t)).count();
        let prefer_b = ok_b > ok_a;
        for i in 0..n {
            let (a, b) = (&self.out_last[i], &self.out[i]);
            let md = self.layers[self.reference.markers[i].layer].merge_distance_px;
            self.pick[i] = match (ok(a), ok(b)) {
                (true, true) if dist2(a.centroid_px, b.centroid_px) < md * md => Pick::A,
                (false, false) if prefer_b => Pick::B,
                (false, false) => Pick::A,
                _ => Pick::Undecided,
            };
        }
        loop {
            let mut progress = false;
            for i in 0..n {
                self.next_pick[i] = self.pick[i];
                if self.pick[i] != Pick::Undecided {
                    continue;
                }
                let (mut ux, mut uy) = ([0.0f64; MAX_NEIGHBOURS], [0.0f64; MAX_NEIGHBOURS]);
                let mut k = 0;
                for &j in &self.neighbours[i][..self.neighbour_count[i] as usize] {
                    if let Some(t) = self.picked(j as usize).filter(|t| ok(t)) {
                        ux[k] = t.displacement_px[0];
                        uy[k] = t.displacement_px[1];
                        k += 1;
                    }
                }
                if k == 0 {
                    continue;
                }
                let m = [median(&mut ux[..k]), median(&mut uy[..k])];
                let da = ok(&self.out_last[i]).then(|| dist2(self.out_last[i].displacement_px, m));
                let db = ok(&self.out[i]).then(|| dist2(self.out[i].displacement_px, m));
                let (pick, d2) = match (da, db) {
                    (Some(da), Some(db)) if db < da => (Pick::B, db),
                    (Some(da), _) => (Pick::A, da),
                    (None, Some(db)) => (Pick::B, db),
                    // Undecided markers have a candidate (see above).
                    (None, None) => continue,
                };
                let bound = SWAP_FRACTION * self.local[i].spacing_px;
                self.next_pick[i] = if d2 <= bound * bound {
                    pick
                } else {
                    pick.rejected()
                };
                progress = true;
            }
            std::mem::swap(&mut self.pick, &mut self.next_pick);
            if !progress {
                break;
            }
        }
        for i in 0..n {
            if self.pick[i] == Pick::Undecided {
                let b_first = if prefer_b {
                    ok(&self.out[i])
                } else {
                    !ok(&self.out_last[i])
                };
                self.pick[i] = if b_first { Pick::B } else { Pick::A };
            }
        }
        for i in 0..n {
            let t = match self.pick[i] {
                Pick::A | Pick::RejectedA => self.out_last[i],
                Pick::B | Pick::RejectedB | Pick::Undecided => self.out[i],
            };
            self.out[i] = if self.pick[i].is_rejected() {
                MarkerTrack {
                    status: MarkerStatus::Outlier,
                    ..t
                }
            } else {
                t
            };
        }
        self.merge_shared_blobs();
        self.flag_outliers();
        self.flag_swaps();
    }

    /// The track marker `j` was given in [`Tracker::combine`] so far (`None` while
    /// undecided).
    fn picked(&self, j: usize) -> Option<&MarkerTrack> {
        match self.pick[j] {
            Pick::Undecided => None,
            Pick::A => Some(&self.out_last[j]),
            Pick::B => Some(&self.out[j]),
            // Flagged: not ok, so never used as a neighbour.
            Pick::RejectedA | Pick::RejectedB => None,
        }
    }

    /// Two ok same-layer neighbours closer than the merge distance (one blob, after
    /// [`Tracker::combine`] took them from different passes) are both `merged`.
    fn merge_shared_blobs(&mut self) {
        for i in 0..self.out.len() {
            if self.out[i].status != MarkerStatus::Ok {
                continue;
            }
            let md = self.layers[self.reference.markers[i].layer].merge_distance_px;
            for &j in &self.neighbours[i][..self.neighbour_count[i] as usize] {
                let j = j as usize;
                if matches!(self.out[j].status, MarkerStatus::Ok | MarkerStatus::Merged)
                    && dist2(self.out[i].centroid_px, self.out[j].centroid_px) < md * md
                {
                    self.out[i].status = MarkerStatus::Merged;
                    self.out[j].status = MarkerStatus::Merged;
                }
            }
        }
    }

    /// Displacement rows for the solver (`formats` types), reference-missing markers
    /// included: only ok markers carry a displacement (mm), the others are `None`.
    pub fn displacement_records(
        &self,
        tracks: &[MarkerTrack],
        camera: &CameraMapping,
    ) -> Vec<DisplacementRecord> {
        self.displacement_records_mapped(tracks, &PixelMapping::Linear(*camera))
    }

    /// As [`Tracker::displacement_records`], converting pixels with `mapping` (e.g. a
    /// camera calibration).
    pub fn displacement_records_mapped(
        &self,
        tracks: &[MarkerTrack],
        mapping: &PixelMapping,
    ) -> Vec<DisplacementRecord> {
        let mut rows: Vec<DisplacementRecord> = self
            .reference
            .markers
            .iter()
            .zip(tracks)
            .map(|(r, t)| DisplacementRecord {
                layer: r.layer,
                marker: r.id,
                position_mm: r.position_mm,
                u_mm: (t.status == MarkerStatus::Ok)
                    .then(|| mapping.displacement_mm(r.layer, r.centroid_px, t.displacement_px)),
                line: 0,
            })
            .chain(self.reference.missing.iter().map(|m| DisplacementRecord {
                layer: m.layer,
                marker: m.id,
                position_mm: m.node_mm,
                u_mm: None,
                line: 0,
            }))
            .collect();
        rows.sort_by_key(|r| (r.layer, r.marker));
        rows
    }

    fn measure_all<T: Sample, const C: usize>(&mut self, img: Raw<'_, T, C>, start: Start) {
        for layer in 0..self.layers.len() {
            self.measure_layer::<T, C>(img, layer, start);
        }
    }

    /// Measures the markers of one layer (a contiguous range: markers are sorted by layer).
    fn measure_layer<T: Sample, const C: usize>(
        &mut self,
        img: Raw<'_, T, C>,
        layer: usize,
        from: Start,
    ) {
        let cfg = self.config;
        let k = self.level_scale;
        let ls = &self.layers[layer];
        let range = ls.markers.clone();
        for i in range {
            let r = &self.reference.markers[i];
            let local = self.local[i];
            let search_half2 = (local.search_half * local.search_half) as f64;
            self.masked[i] = false;
            let start = match from {
                Start::Reference | Start::Reacquire => r.centroid_px,
                Start::Last => [
                    self.last_px[i][0] + self.velocity_px[i][0],
                    self.last_px[i][1] + self.velocity_px[i][1],
                ],
            };
            self.predicted_px[i] = start;
            // Where the nearest already-measured neighbour ended up relative to its own
            // prediction, this marker probably did too (displacement fields are smooth):
            // starting the window there usually saves a re-centring pass. Only the
            // first window moves; acceptance stays relative to `start`. (A mean of
            // the measured neighbours' corrections, 1/d²-weighted, saved 7 % of the
            // windows on the paper frame but carried one bad neighbour's correction
            // into all of its neighbours' starts: on the striped bright GelSight
            // frame, tracked against itself, the fringe dot 13 px off dragged its
            // neighbour onto the next stripe.)
            let hint = self.neighbours[i][..self.neighbour_count[i] as usize]
                .iter()
                .map(|&j| j as usize)
                .find(|&j| j < i && self.out[j].status == MarkerStatus::Ok)
                .map(|j| {
                    let (c, p) = (self.out[j].centroid_px, self.predicted_px[j]);
                    [c[0] - p[0], c[1] - p[1]]
                })
                .filter(|d| d[0] * d[0] + d[1] * d[1] <= search_half2)
                .map(|d| [start[0] + d[0], start[1] + d[1]]);
            // The reference's levels in the frame's (k = 1 for a matched bit depth).
            let (signal, peak, background) = (r.signal * k, r.peak * k, r.background * k);
            let slope = [r.background_slope[0] * k, r.background_slope[1] * k];
            let min_signal = cfg.min_signal_ratio * signal;
            let max_jump2 = local.max_jump2;
            let max_background_change = 0.05 * peak;
            let ring_px = ls.window.ring_radius_px();
            // Linear score first (fast); when the ring's background plane moved away
            // from the reference's (another layer's marker entering the window), again
            // from there with the clamped score, which ignores other colours.
            let locate = |from: [f64; 2]| {
                let loc = ls
                    .window
                    .locate_clipped::<T, C>(img, from, cfg.max_iterations, false);
                match loc {
                    Located::Found {
                        centroid_px,
                        background: loc_background,
                        slope: loc_slope,
                        ..
                    } if (loc_background - background).abs()
                        + ring_px
                            * ((loc_slope[0] - slope[0]).abs()
                                + (loc_slope[1] - slope[1]).abs())
                        > max_background_change =>
                    {
                        ls.window
                            .locate_clipped::<T, C>(img, centroid_px, cfg.max_iterations, true)
                    }
                    other => other,
                }
            };
            // A window cut by the image edge counts only when the dot is inside.
            let (radius, width, height) = (ls.marker_radius_px, img.width, img.height);
            let accept = |loc: Located| match loc {
                Located::Found {
                    centroid_px,
                    m0,
                    clipped,
                    ..
                } if m0 >= min_signal
                    && dist2(centroid_px, start) <= max_jump2
                    && (!clipped || dot_inside(centroid_px, radius, width, height)) =>
                {
                    Some((centroid_px, m0))
                }
                _ => None,
            };
            self.field_start_px[i] = hint.unwrap_or(start);
            let mut found = None;
            if let Some(h) = hint {
                found = accept(locate(h));
            }
            if found.is_none() && hint.is_none_or(|h| !same_pixel(h, start)) {
                found = accept(locate(start));
            }
            if found.is_none() {
                let base = if ls.local_background {
                    // The window's ring level is the linear score; the search reads
                    // the clamped one, which adds the bias.
                    (background + score_bias::<T>(&ls.weights) as f64).round() as i32
                } else {
                    (ls.background_score * k).round() as i32
                };
                let threshold = base + (0.4 * peak).round() as i32;
                if let Some(seed) =
                    search::<T, C>(img, &ls.weights, start, local.search_half, threshold)
                {
                    found = accept(locate(seed));
                }
            }
            self.out[i] = match found {
                Some((c, m0)) => MarkerTrack {
                    centroid_px: c,
                    displacement_px: [c[0] - r.centroid_px[0], c[1] - r.centroid_px[1]],
                    status: MarkerStatus::Ok,
                    signal_ratio: m0 / signal,
                },
                None => MarkerTrack::LOST,
            };
        }
    }

    /// Re-measures markers that overlap another layer's marker in this frame with
    /// [`Window::locate_masked`] (the other markers' discs and their symmetric images left
    /// out), or flags them merged when too little of them is visible. Two sweeps: the
    /// second uses the other layer's corrected positions.
    fn resolve_overlaps<T: Sample, const C: usize>(&mut self, img: Raw<'_, T, C>) {
        for _sweep in 0..2 {
            let mut any = false;
            for i in 0..self.out.len() {
                if self.out[i].status != MarkerStatus::Ok {
                    continue;
                }
                let r = &self.reference.markers[i];
                let signal = r.signal * self.level_scale;
                let ls = &self.layers[r.layer];
                let c = self.out[i].centroid_px;
                // Cheap test first (the usual case: no other-layer marker near);
                // a lost marker's NaN centroid compares false.
                if !self.foreign[i][..self.foreign_count[i] as usize]
                    .iter()
                    .any(|&j| dist2(c, self.out[j as usize].centroid_px) < ls.overlap_reach2_px)
                {
                    continue;
                }
                let reach = ls.window.ring_radius_px() + 1.0;
                let mut masks = [Foreign {
                    centre_px: [0.0; 2],
                    radius2_px: 0.0,
                }; MAX_FOREIGN];
                let (mut n, mut overlap, mut too_close) = (0, false, false);
                for &j in &self.foreign[i][..self.foreign_count[i] as usize] {
                    let (j, fl) = (j as usize, self.reference.markers[j as usize].layer);
                    if self.out[j].status == MarkerStatus::Lost {
                        continue;
                    }
                    let support = self.layers[fl].foreign_support_px();
                    let d2 = dist2(c, self.out[j].centroid_px);
                    if d2 < (reach + support) * (reach + support) {
                        masks[n] = Foreign {
                            centre_px: self.out[j].centroid_px,
                            radius2_px: support * support,
                        };
                        n += 1;
                        overlap |= d2 < (ls.aperture_px + support) * (ls.aperture_px + support);
                        let close = MIN_CROSS_LAYER_DISTANCE
                            * (ls.marker_radius_px + self.layers[fl].marker_radius_px);
                        too_close |= d2 < close * close;
                    }
                }
                if !overlap {
                    continue;
                }
                any = true;
                let found = if too_close {
                    None
                } else {
                    ls.window
                        .locate_masked::<T, C>(img, c, self.config.max_iterations, &masks[..n])
                };
                let start = self.predicted_px[i];
                let max_jump2 = self.local[i].max_jump2;
                self.masked[i] = true;
                self.out[i] = match found {
                    Some(f)
                        if !too_close
                            && f.visible >= MIN_VISIBLE
                            && f.m0 >= self.config.min_signal_ratio * f.visible * signal
                            && dist2(f.centroid_px, start) <= max_jump2 =>
                    {
                        let c = f.centroid_px;
                        MarkerTrack {
                            centroid_px: c,
                            displacement_px: [c[0] - r.centroid_px[0], c[1] - r.centroid_px[1]],
                            status: MarkerStatus::Ok,
                            signal_ratio: f.m0 / (f.visible * signal),
                        }
                    }
                    // Too much of it hidden or mirrored away: its position is not
                    // measurable, it merged with the other layer's marker.
                    _ => MarkerTrack {
                        status: MarkerStatus::Merged,
                        ..self.out[i]
                    },
                };
            }
            if !any {
                break;
            }
        }
    }

    /// Marks the markers with a specular highlight on them in this frame: for `dark`
    /// ones, a saturated pixel within [`highlight_radius_px`] of the measured centroid
    /// ([`highlight_within`]); for `bright` ones, which may saturate by themselves,
    /// saturated pixels on the dot that changed against the marker's own reference
    /// ([`saturation_changed`]) while none of its neighbours shows saturation, in the
    /// frame or the reference: a specular highlight is the small reflection of a light
    /// on one marker, where broad light (a glare, pins that saturate by themselves)
    /// saturates neighbours alike and, being smooth over a window, moves no centroid
    /// (`tests/vision_tracking.rs`, `table_i_bright_*`). Colour layers are not
    /// searched.
    fn find_highlights<T: Sample, const C: usize>(&mut self, img: Raw<'_, T, C>) {
        for (li, ls) in self.layers.iter().enumerate() {
            let color = self.reference.layers[li].color;
            let r = highlight_radius_px(ls.marker_radius_px);
            if color == MarkerColor::Bright {
                // Saturated pixels on each dot in this frame (0 when lost).
                for i in ls.markers.clone() {
                    let t = &self.out[i];
                    self.saturation[i] = if t.status == MarkerStatus::Lost {
                        Saturation::default()
                    } else {
                        saturation_within(&img, t.centroid_px, ls.marker_radius_px)
                    };
                }
            }
            for i in ls.markers.clone() {
                let t = &self.out[i];
                self.highlight[i] = t.status != MarkerStatus::Lost
                    && match color {
                        MarkerColor::Dark => highlight_within(&img, t.centroid_px, r),
                        MarkerColor::Bright => {
                            saturation_changed(
                                &self.reference.markers[i].saturation,
                                &self.saturation[i],
                            ) && !self.neighbours[i][..self.neighbour_count[i] as usize]
                                .iter()
                                .any(|&j| {
                                    let j = j as usize;
                                    self.saturation[j].count as f64 >= SATURATION_MIN_PX
                                        || self.reference.markers[j].saturation.count as f64
                                            >= SATURATION_MIN_PX
                                })
                        }
                        _ => false,
                    };
            }
        }
    }

    /// An ok marker with a specular highlight on it is an `outlier`: the highlight
    /// hides part of it (or adds to it) and stays with the light while the marker
    /// moves, so its centroid carries a false displacement (on the simulated Table I
    /// bench: a `dark` marker 2.15 px off on a 30 px pitch, below the neighbour
    /// check's tolerance, with its signal barely changed when the highlight is on it in
    /// both frames; a `bright` one 0.42 px off). `dark`: a highlight in the reference
    /// or in this frame; `bright`: saturation on the dot changed against the
    /// reference's (see [`Tracker::find_highlights`]).
    fn flag_highlights(&mut self) {
        for i in 0..self.out.len() {
            if self.out[i].status == MarkerStatus::Ok
                && (self.highlight[i] || self.reference.markers[i].highlight)
            {
                self.out[i].status = MarkerStatus::Outlier;
            }
        }
    }

    /// A marker whose dot crossed the image edge in the reference is `lost` in every
    /// frame: its reference position is its blob's centroid, not a window's (see
    /// `detect`), so a displacement from it would carry the difference of the two.
    /// (A dot crossing the edge in this frame was not accepted in `measure_layer`;
    /// a dot inside, its window cut by the edge, is measured on the window's part
    /// inside the image, as well as a whole window: see `window::clipped`.)
    fn flag_reference_dot_outside(&mut self) {
        let (w, h) = (
            self.reference.width_px as usize,
            self.reference.height_px as usize,
        );
        for i in 0..self.out.len() {
            let r = &self.reference.markers[i];
            if self.out[i].status != MarkerStatus::Lost
                && !dot_inside(r.centroid_px, self.layers[r.layer].marker_radius_px, w, h)
            {
                self.out[i] = MarkerTrack {
                    signal_ratio: self.out[i].signal_ratio,
                    ..MarkerTrack::LOST
                };
            }
        }
    }

    /// A marker whose window (aperture and background ring) crosses the border of the
    /// reference's ROI is `lost`: part of what it measured lies where the sensor file
    /// says nothing is to be trusted (LEDs, the gel's edge, glare).
    fn flag_outside_roi(&mut self) {
        let Some(roi) = self.reference.roi_px else {
            return;
        };
        for i in 0..self.out.len() {
            if self.out[i].status == MarkerStatus::Lost {
                continue;
            }
            let ls = &self.layers[self.reference.markers[i].layer];
            let reach = ls.window.ring_radius_px() + 1.0;
            if !roi.contains_disc(self.out[i].centroid_px, reach) {
                self.out[i] = MarkerTrack {
                    signal_ratio: self.out[i].signal_ratio,
                    ..MarkerTrack::LOST
                };
            }
        }
    }

    /// One blob, one marker: finds markers of a layer whose windows converged onto
    /// the same blob (closer than the merge distance) and decides per pair. A blob
    /// with more than one marker's signal (`SHARED_BLOB_MERGE_RATIO`), or one that is
    /// about as near to both markers' field-corrected predictions (within
    /// `CLAIM_MARGIN` local spacings), holds two merged markers; otherwise it belongs
    /// to the marker whose prediction is nearer (mutual nearest neighbours) and the
    /// other one is lost: its own blob was not found, and a neighbour's position is
    /// never reported as its. A signal above `merge_signal_ratio` is merged as before.
    fn resolve_claims(&mut self) {
        let ratio = self.config.merge_signal_ratio;
        for c in &mut self.claim {
            *c = Claim::Keep;
        }
        for i in 0..self.out.len() {
            let a = self.out[i];
            if a.status == MarkerStatus::Lost {
                continue;
            }
            // Local-spacing gate: a blob farther than `GATE_FRACTION` local spacings
            // from both the prediction and the field-corrected start is a
            // neighbour's, not this marker's.
            let gate2 = (GATE_FRACTION * self.local[i].spacing_px).powi(2);
            if dist2(a.centroid_px, self.predicted_px[i]) > gate2
                && dist2(a.centroid_px, self.field_start_px[i]) > gate2
            {
                self.claim[i] = self.claim[i].max(Claim::Lost);
            }
            if a.signal_ratio > ratio {
                self.claim[i] = self.claim[i].max(Claim::Merged);
            }
            let ls = &self.layers[self.reference.markers[i].layer];
            let md2 = ls.merge_distance_px * ls.merge_distance_px;
            for &j in &self.neighbours[i][..self.neighbour_count[i] as usize] {
                let j = j as usize;
                let b = self.out[j];
                if b.status == MarkerStatus::Lost || dist2(a.centroid_px, b.centroid_px) >= md2 {
                    continue;
                }
                let (ci, cj) = self.decide_claim(i, j);
                self.claim[i] = self.claim[i].max(ci);
                self.claim[j] = self.claim[j].max(cj);
            }
        }
        for (t, c) in self.out.iter_mut().zip(&self.claim) {
            match c {
                Claim::Keep => {}
                Claim::Lost => *t = MarkerTrack::LOST,
                Claim::Merged => t.status = MarkerStatus::Merged,
            }
        }
    }

    /// The verdicts for markers `i` and `j` found on one blob (see
    /// [`Tracker::resolve_claims`]); symmetric in `i` and `j`.
    fn decide_claim(&self, i: usize, j: usize) -> (Claim, Claim) {
        let (a, b) = (&self.out[i], &self.out[j]);
        if a.status == MarkerStatus::Merged
            || b.status == MarkerStatus::Merged
            || a.signal_ratio.max(b.signal_ratio) >= SHARED_BLOB_MERGE_RATIO
        {
            return (Claim::Merged, Claim::Merged);
        }
        let blob = [
            0.5 * (a.centroid_px[0] + b.centroid_px[0]),
            0.5 * (a.centroid_px[1] + b.centroid_px[1]),
        ];
        let di = dist2(blob, self.field_start_px[i]).sqrt();
        let dj = dist2(blob, self.field_start_px[j]).sqrt();
        let margin = CLAIM_MARGIN * self.local[i].spacing_px.min(self.local[j].spacing_px);
        if (di - dj).abs() < margin {
            (Claim::Merged, Claim::Merged)
        } else if di < dj {
            (Claim::Keep, Claim::Lost)
        } else {
            (Claim::Lost, Claim::Keep)
        }
    }

    /// Flags `outlier` every ok marker whose signal, relative to the median of its ok
    /// neighbours' (at least 3; else of its layer's), differs from 1 by more than
    /// `appearance_tolerance`, or by more than `APPEARANCE_SPREAD_FACTOR` robust SDs of
    /// the layer's relative signals in this frame when those vary more: the marker
    /// changed appearance against the reference (part of it covered, another size or
    /// contrast), so its centroid may carry a false displacement. Markers measured
    /// with another layer's marker masked out are not judged (their signal counts only
    /// the visible part).
    fn flag_appearance(&mut self) {
        let tol = self.config.appearance_tolerance;
        if tol.is_nan() || tol == f64::INFINITY {
            return;
        }
        for li in 0..self.layers.len() {
            let range = self.layers[li].markers.clone();
            let eligible = |out: &[MarkerTrack], masked: &[bool], i: usize| {
                out[i].status == MarkerStatus::Ok && !masked[i] && out[i].signal_ratio > 0.0
            };
            let mut n = 0;
            for i in range.clone() {
                if eligible(&self.out, &self.masked, i) {
                    self.scratch[n] = self.out[i].signal_ratio;
                    n += 1;
                }
            }
            if n < 3 {
                continue;
            }
            let layer_median = median_select(&mut self.scratch[..n]);
            let mut m = 0;
            for i in range.clone() {
                self.relative[i] = f64::NAN;
                if !eligible(&self.out, &self.masked, i) {
                    continue;
                }
                let mut v = [0.0f64; MAX_NEIGHBOURS];
                let mut k = 0;
                for &j in &self.neighbours[i][..self.neighbour_count[i] as usize] {
                    if eligible(&self.out, &self.masked, j as usize) {
                        v[k] = self.out[j as usize].signal_ratio;
                        k += 1;
                    }
                }
                let typical = if k >= 3 {
                    median(&mut v[..k])
                } else {
                    layer_median
                };
                let rel = self.out[i].signal_ratio / typical - 1.0;
                self.relative[i] = rel;
                self.scratch[m] = rel.abs();
                m += 1;
            }
            let spread = 1.4826 * median_select(&mut self.scratch[..m]);
            let limit = tol.max(APPEARANCE_SPREAD_FACTOR * spread);
            for i in range {
                // NaN (not judged) compares false.
                if self.relative[i].abs() > limit {
                    self.out[i].status = MarkerStatus::Outlier;
                }
            }
        }
    }

    /// The swap bound: an ok marker whose displacement lies farther than
    /// [`SWAP_FRACTION`] local spacings from the median of its ok neighbours' (one or
    /// more) is `outlier`, whatever their spread (the neighbour-consistency check
    /// allows `3·spread`, which a messy neighbourhood makes large). Judged against
    /// the statuses before this check, so the order of markers does not matter.
    fn flag_swaps(&mut self) {
        for i in 0..self.out.len() {
            self.scratch[i] = 0.0;
            if self.out[i].status != MarkerStatus::Ok {
                continue;
            }
            let mut ux = [0.0f64; MAX_NEIGHBOURS];
            let mut uy = [0.0f64; MAX_NEIGHBOURS];
            let mut n = 0;
            let u = self.out[i].displacement_px;
            // The farthest neighbour bounds the distance to the median (which lies in
            // their box): the usual case needs no sort.
            let mut far2 = 0.0f64;
            for &j in &self.neighbours[i][..self.neighbour_count[i] as usize] {
                let t = &self.out[j as usize];
                if t.status == MarkerStatus::Ok {
                    [ux[n], uy[n]] = t.displacement_px;
                    far2 = far2.max(dist2(u, t.displacement_px));
                    n += 1;
                }
            }
            let bound = SWAP_FRACTION * self.local[i].spacing_px;
            if far2 > bound * bound && swapped(u, &ux[..n], &uy[..n], bound) {
                self.scratch[i] = 1.0;
            }
        }
        for i in 0..self.out.len() {
            if self.scratch[i] != 0.0 {
                self.out[i].status = MarkerStatus::Outlier;
            }
        }
    }

    fn flag_outliers(&mut self) {
        for i in 0..self.out.len() {
            if self.out[i].status != MarkerStatus::Ok {
                continue;
            }
            let tol = self.local[i].outlier_px;
            let u = self.out[i].displacement_px;
            let mut ux = [0.0f64; MAX_NEIGHBOURS];
            let mut uy = [0.0f64; MAX_NEIGHBOURS];
            let mut n = 0;
            // Box spanned by `u` and the neighbours' displacements (plain comparisons:
            // the values are finite, `f64::min` would add NaN handling).
            let (mut lo, mut hi) = (u, u);
            for &j in &self.neighbours[i][..self.neighbour_count[i] as usize] {
                let t = &self.out[j as usize];
                // Outliers flagged earlier in this loop still count: the decision must
                // not depend on marker order.
                if matches!(t.status, MarkerStatus::Ok | MarkerStatus::Outlier) {
                    let [x, y] = t.displacement_px;
                    ux[n] = x;
                    uy[n] = y;
                    n += 1;
                    lo = [
                        if x < lo[0] { x } else { lo[0] },
                        if y < lo[1] { y } else { lo[1] },
                    ];
                    hi = [
                        if x > hi[0] { x } else { hi[0] },
                        if y > hi[1] { y } else { hi[1] },
                    ];
                }
            }
            if n < 3 {
                continue;
            }
            // The medians lie in that box: if its farthest corner from `u` is within
            // `tol` (≤ tol + 3·spread), `u` is no outlier whatever the medians. Exact,
            // and the usual case: it skips three small sorts per marker.
            let fx = (u[0] - lo[0]).max(hi[0] - u[0]);
            let fy = (u[1] - lo[1]).max(hi[1] - u[1]);
            if fx * fx + fy * fy <= tol * tol {
                continue;
            }
            if displacement_outlier(u, &ux[..n], &uy[..n], tol) {
                self.out[i].status = MarkerStatus::Outlier;
            }
        }
    }
}

/// Saturated pixels of a `bright` marker's dot in a frame (`now`) that differ from its
/// reference's (`then`) as a specular highlight's do: their count changed by more
/// than [`SATURATION_COUNT_CHANGE`] (at least [`SATURATION_MIN_PX`] pixels: it
/// appeared, grew, shrank or vanished), or, with both at least that many, their mean
/// offset from the marker's centroid moved by more than [`SATURATION_SHIFT_PX`] (the
/// saturated patch stayed with the light instead of moving with the marker). A
/// marker that saturates by itself keeps its saturated core, centred on it.
fn saturation_changed(then: &Saturation, now: &Saturation) -> bool {
    let (a, b) = (then.count as f64, now.count as f64);
    if (a - b).abs() > SATURATION_MIN_PX.max(SATURATION_COUNT_CHANGE * a.max(b)) {
        return true;
    }
    a >= SATURATION_MIN_PX
        && b >= SATURATION_MIN_PX
        && (now.offset_px[0] - then.offset_px[0]).hypot(now.offset_px[1] - then.offset_px[1])
            > SATURATION_SHIFT_PX
}

/// Frame levels per reference level: samples widen from 8 to 16 bits as `v · 257`.
fn level_scale(reference_bits: u32, frame_bits: u32) -> f64 {
    match (reference_bits, frame_bits) {
        (8, 16) => 257.0,
        (16, 8) => 1.0 / 257.0,
        _ => 1.0,
    }
}

/// Squared distance, px².
#[inline]
fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]) * (a[0] - b[0]) + (a[1] - b[1]) * (a[1] - b[1])
}

/// Whether two positions round to the same pixel (the window would start there).
#[inline]
fn same_pixel(a: [f64; 2], b: [f64; 2]) -> bool {
    a[0].round() == b[0].round() && a[1].round() == b[1].round()
}

/// Median of a slice of any length (reorders it; NaN-free input). Selection, not a
/// sort: one layer's worth of values per frame.
fn median_select(v: &mut [f64]) -> f64 {
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    let (_, hi, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    let hi = *hi;
    if n % 2 == 1 {
        hi
    } else {
        let lo = v[..n / 2].iter().copied().fold(f64::NEG_INFINITY, f64::max);
        0.5 * (lo + hi)
    }
}

/// A frame's verdict on one marker's claim to its blob ([`Tracker::resolve_claims`]),
/// ordered by severity.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Claim {
    Keep,
    Lost,
    Merged,
}

/// Whether displacement `u` is an outlier among its neighbours' displacements
/// `(ux[k], uy[k])` (see the module docs): farther than `tol + 3·spread` from their
/// component-wise median, `spread` being the median distance of the neighbours' own
/// displacements — each neighbour's x with its own y — from that median.
fn displacement_outlier(u: [f64; 2], ux: &[f64], uy: &[f64], tol: f64) -> bool {
    let n = ux.len().min(uy.len()).min(MAX_NEIGHBOURS);
    let (mut x, mut y) = ([0.0f64; MAX_NEIGHBOURS], [0.0f64; MAX_NEIGHBOURS]);
    x[..n].copy_from_slice(&ux[..n]);
    y[..n].copy_from_slice(&uy[..n]);
    let m = [median(&mut x[..n]), median(&mut y[..n])];
    let mut dev = [0.0f64; MAX_NEIGHBOURS];
    for k in 0..n {
        dev[k] = dist2([ux[k], uy[k]], m).sqrt();
    }
    let spread = median(&mut dev[..n]);
    dist2(u, m).sqrt() > tol + 3.0 * spread
}

/// Whether displacement `u` is farther than `bound` from the component-wise median
/// of its neighbours' displacements `(ux[k], uy[k])` (at least one): the swap bound,
/// which holds whatever the neighbours' spread.
fn swapped(u: [f64; 2], ux: &[f64], uy: &[f64], bound: f64) -> bool {
    let n = ux.len().min(uy.len()).min(MAX_NEIGHBOURS);
    let (mut x, mut y) = ([0.0f64; MAX_NEIGHBOURS], [0.0f64; MAX_NEIGHBOURS]);
    x[..n].copy_from_slice(&ux[..n]);
    y[..n].copy_from_slice(&uy[..n]);
    n > 0 && dist2(u, [median(&mut x[..n]), median(&mut y[..n])]) > bound * bound
}

/// Median of a small slice (reorders it). Insertion sort with a plain `>`: the slices
/// hold at most `MAX_NEIGHBOURS` finite values (neighbours' displacements or signal
/// ratios), where this beats the general sort's call and dispatch and `total_cmp`'s
/// bit twiddling (three medians per marker per frame were a third of the
/// frame-to-frame tracking time). Measured slower on the paper frame: a branch-free
/// rank count, and the 19-comparator network for eight inputs (12 → 22 µs per frame
/// for the appearance check's medians).
fn median(v: &mut [f64]) -> f64 {
    for i in 1..v.len() {
        let x = v[i];
        let mut j = i;
        while j > 0 && v[j - 1] > x {
            v[j] = v[j - 1];
            j -= 1;
        }
        v[j] = x;
    }
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

#[cfg(test)]
mod tests {
    use super::{displacement_outlier, median};

    #[test]
    fn median_of_small_slices_matches_the_sorted_middle() {
        let cases: [&[f64]; 5] = [
            &[3.0],
            &[2.0, -1.0],
            &[5.0, 1.0, 4.0, 1.5, 9.0],
            &[0.25, 0.5, -3.0, 8.0, 0.0, 0.125, 7.0, -1.0],
            &[1.0, 1.0, 1.0, 2.0],
        ];
        let expected = [3.0, 0.5, 4.0, 0.1875, 1.0];
        for (c, e) in cases.iter().zip(expected) {
            let mut v = c.to_vec();
            assert_eq!(median(&mut v), e, "{c:?}");
            assert!(v.windows(2).all(|w| w[0] <= w[1]), "{v:?} not sorted");
        }
    }

    /// Regression: the spread of the neighbours' displacements was taken over the
    /// x and y components sorted separately (each median sorted its slice in place),
    /// pairing one neighbour's x with another's y. Three neighbours at rest and one
    /// moved by (4, −4): their spread is 0 (paired) but was 2 px (x sorted
    /// [0, 0, 0, 4], y sorted [−4, 0, 0, 0]: pairs (0, −4) and (4, 0) at 4 px), which
    /// let a marker displaced 2 px against its resting neighbours pass a 1 px tolerance.
    #[test]
    fn outlier_spread_pairs_each_neighbours_x_with_its_own_y() {
        let (ux, uy) = ([0.0, 0.0, 0.0, 4.0], [0.0, 0.0, 0.0, -4.0]);
        assert!(displacement_outlier([2.0, 0.0], &ux, &uy, 1.0));
        assert!(!displacement_outlier([0.5, 0.0], &ux, &uy, 1.0));
        // Order of the neighbours does not matter.
        let (ux, uy) = ([4.0, 0.0, 0.0, 0.0], [-4.0, 0.0, 0.0, 0.0]);
        assert!(displacement_outlier([2.0, 0.0], &ux, &uy, 1.0));
    }

    /// Every slice of length 1–8 (all 0/1 inputs, and random values with ties) comes
    /// out sorted, with the sorted middle as its median.
    #[test]
    fn median_sorts_every_length_up_to_eight() {
        for n in 1..=8usize {
            for bits in 0u32..(1 << n) {
                let mut v: Vec<f64> = (0..n).map(|k| ((bits >> k) & 1) as f64).collect();
                let mut sorted = v.clone();
                sorted.sort_by(f64::total_cmp);
                median(&mut v);
                assert_eq!(v, sorted, "n = {n}, bits = {bits:b}");
            }
        }
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        for _ in 0..2000 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let n = 1 + (state % 8) as usize;
            let mut v: Vec<f64> = (0..n)
                .map(|k| ((state >> (3 * k + 8)) % 5) as f64 - 2.0)
                .collect();
            let mut sorted = v.clone();
            sorted.sort_by(f64::total_cmp);
            let expected = if n % 2 == 1 {
                sorted[n / 2]
            } else {
                0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
            };
            assert_eq!(median(&mut v), expected);
            assert_eq!(v, sorted);
        }
    }
}
