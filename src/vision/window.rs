//! The per-marker window kernel: colour score, local background plane and
//! background-corrected centre of mass, iterated with re-centring.
//!
//! **Colour score.** A layer of colour `c` scores a pixel by a fixed linear
//! combination `s = w · (R, G, B)` whose weights sum to zero ([`score_weights`]):
//! `B − G` and `R − G` for a blue+red sensor (green, used by no layer, is the
//! reference), `2·I_c − I_o1 − I_o2` when every channel is used. Grey light, including
//! uneven grey illumination, scores 0; another layer's markers score near 0; a marker
//! of the layer's colour scores its colour excess. The score is *linear* in the pixel
//! values, so a blend `α·marker + (1 − α)·background` at a soft or anti-aliased edge
//! scores linearly in `α` and the centre of mass stays unbiased (a `max()` of channels
//! would be piecewise linear in `α` and bias sub-pixel centroids by ~0.003 px).
//!
//! Two kernels compute the same moments: the *linear* one (default) sums
//! `sample × weight` over whole rows with precomputed per-sample weights — a plain
//! integer dot product, with no de-interleaving (for 8-bit frames on a CPU with AVX2,
//! detected at run time, an explicit kernel does it 16 samples per `vpmaddwd`: the
//! compiler alone uses 4 lanes on baseline x86-64; with AVX-512 F+BW a 512-bit variant
//! takes 32 samples per `vpmaddwd`, so a paper-sensor window row is two blocks instead
//! of four, and, when every weight fits a byte of at most ±64, 64 samples per
//! `vpmaddubsw` on byte weights: one block per paper-sensor row; the sums are
//! bit-identical on every path; the weights' layout and the kernels are in
//! [`kernels`]); the
//! *clamped* one scores `max(0, s + 2K)` per pixel (`K` = 8 levels of 8 bits, so the
//! background noise is not clipped) and is used by the tracker when the ring's
//! background plane moved away from the reference's: a strongly negative foreign blob
//! in the window then clips to background.
//!
//! **Window.** Centred on an integer pixel `(cx, cy)`: an aperture disc of radius
//! `Ra` (the marker plus its soft edge), a one-pixel gap, and a background ring
//! `Ra + 1 < r ≤ Ra + 3`. The ring's scores are fitted by a plane
//! `b(dx, dy) = a + gx·dx + gy·dy`; because the ring is symmetric about the centre the
//! least-squares fit decouples into `a = Σs/N`, `gx = Σs·dx/Σdx²`, `gy = Σs·dy/Σdy²`.
//! The aperture's moments minus the plane's moments over the aperture (again by
//! symmetry only `a·N_ap` and `g·Σdx²_ap` survive) give the marker's centre of mass
//! (paper Section II-A) without the background:
//!
//! ```text
//! M0 = Σ_ap s − a·N_ap,   Mx = Σ_ap s·dx − gx·Σ_ap dx²,   My = Σ_ap s·dy − gy·Σ_ap dy²
//! centroid = (cx + Mx/M0, cy + My/M0)
//! ```
//!
//! **Overlaps.** [`Window::locate_masked`] measures a marker that another layer's
//! marker partly covers (or that partly covers one). A disc is symmetric under every
//! symmetry of the pixel grid that fixes its centre; five of them map the window's
//! pixels onto pixels: the point reflection `S₀ = −I`, the reflections about the two
//! axes and about the two diagonals. For each `S`, the pixels `p` with both `p` and
//! `S·p` clear of the foreign discs form a set `K_S` that `S` maps onto itself, and the
//! moment `N_S = Σ_{K_S} ½(p − S·p)·s'(p)` vanishes when the marker sits at the window
//! centre. The offset solves `Σ_S N_S = 0` by a Gauss–Newton step with the measured
//! Jacobian `J = −Σ_S Σ_{K_S} ½(p − S·p)·∇s'(p)ᵀ` (equal to `3·M0·I`, i.e. the plain
//! centroid, when nothing is left out). With the point mirror alone, the far edge of a
//! marker covered on one side is left out with its hidden partner, and the offset
//! along the line of centres rests on the thin band of edge across it; the reflections
//! pair that far edge with visible parts of the sides.
//!
//! *Measured limits* (`tests/vision.rs`, overlap renders: two layers of 12 px discs,
//! the deeper one drawn over the other, 16-bit noise-free, all gaps in 0.1 px steps at
//! five sub-pixel phases of the layers): worst error ≤ 0.027 px for centre gaps
//! 9.6–13 px (point mirror alone: 0.054 px), up to 0.053 px at 8–9.5 px (was 0.16 px),
//! with σ = 2 noise in 8 bits 0.11 px worst and a mean of 0.033 px at 9 px — so the
//! tracker still flags gaps below 0.8 × the sum of the radii merged. The remaining
//! error is systematic, proportional to the marker's offset from the window's centre
//! pixel and of a sign that depends on the phase: the truncated sets cut the
//! anti-aliased edge, whose pixels are piecewise linear in the marker's position, so
//! `N` is not linear over the ±0.5 px an integer window leaves (neither the
//! midpoint-corrected Jacobian nor a secant across neighbouring windows removed it).
//!
//! **Re-centring.** The window is moved to the rounded centroid and the moments taken
//! again until the rounded centroid stays put (or a two-cycle is detected). At the
//! fixed point the aperture is centred within half a pixel of the marker, so a 3 px
//! motion is measured with the whole marker inside a symmetric aperture and no
//! truncation by the window edge. Everything is integer arithmetic over the raw
//! interleaved samples: no allocation, no whole-image conversion.

use crate::sensor::MarkerColor;

mod clipped;
mod kernels;
pub(crate) use clipped::dot_inside;
use kernels::{layout, LinearWeights};

/// Samples the kernel can read (8- and 16-bit).
pub(crate) trait Sample: Copy {
    /// Score offset `K` (see the module docs): 8 levels of an 8-bit image.
    const OFFSET: i32;
    /// Full scale: 255 or 65535.
    const MAX: i32;
    fn value(self) -> i32;
    /// The samples as bytes when they are 8-bit (the SIMD kernel reads only those).
    #[inline(always)]
    fn as_bytes(_data: &[Self]) -> Option<&[u8]> {
        None
    }
}

impl Sample for u8 {
    const OFFSET: i32 = 8;
    const MAX: i32 = 255;
    #[inline(always)]
    fn value(self) -> i32 {
        self as i32
    }
    #[inline(always)]
    fn as_bytes(data: &[u8]) -> Option<&[u8]> {
        Some(data)
    }
}

impl Sample for u16 {
    const OFFSET: i32 = 8 * 257;
    const MAX: i32 = 65535;
    #[inline(always)]
    fn value(self) -> i32 {
        self as i32
    }
}

/// Per-channel weights `w` of a layer's colour score `w · (R, G, B)`.
///
/// For colour `c`, with `U` the channels that no coloured layer of the sensor uses:
/// `w = |U|·e_c − Σ_{u∈U} e_u` when `U` is not empty, else `2·e_c − Σ_{o≠c} e_o`.
/// The weights sum to zero, so grey light (and uneven grey illumination) scores 0.
/// Subtracting an unused channel makes the other layers' markers score near 0
/// instead of strongly negative (a blue+red sensor scores `B − G` and `R − G`): their
/// pixels then look like background when they come near a window.
///
/// Brightness layers score the brightness: `bright` `R + G + B`, `dark`
/// `−(R + G + B)` (so a dark marker is a positive signal, like every other marker).
/// Their weights do not sum to zero: the illumination is *not* cancelled by the score
/// but by the background estimate (the window's ring plane, the detector's local
/// top-hat; see `detect.rs`). They use no colour channel, so they leave the colour
/// layers' weights as they were.
pub(crate) fn score_weights(color: MarkerColor, used: &[MarkerColor]) -> [i32; 3] {
    let idx = |c: MarkerColor| match c {
        MarkerColor::Red => Some(0),
        MarkerColor::Green => Some(1),
        MarkerColor::Blue => Some(2),
        MarkerColor::Dark | MarkerColor::Bright => None,
    };
    let ci = match color {
        MarkerColor::Dark => return [-1; 3],
        MarkerColor::Bright => return [1; 3],
        c => idx(c).unwrap_or(0),
    };
    let unused: Vec<usize> = (0..3)
        .filter(|&k| !used.iter().any(|&u| idx(u) == Some(k)))
        .collect();
    let mut w = [0i32; 3];
    if unused.is_empty() {
        w = [-1; 3];
        w[ci] = 2;
    } else {
        for &u in &unused {
            w[u] = -1;
        }
        w[ci] = unused.len() as i32;
    }
    w
}

/// The constant added to the linear score before clamping: `2K`, plus `−Σw · max`
/// when the weights sum below zero (`dark`), so that every pixel of a dark layer
/// scores in `[0, 3·max + 2K]` instead of clamping to 0. Colour weights sum to 0
/// and bright weights above it: their bias is the `2K` of the module docs.
#[inline(always)]
pub(crate) fn score_bias<T: Sample>(w: &[i32; 3]) -> i32 {
    let sum = w[0] + w[1] + w[2];
    2 * T::OFFSET + if sum < 0 { -sum * T::MAX } else { 0 }
}

/// The linear colour score `w · (R, G, B)` of one pixel of `C` samples. A greyscale
/// pixel (`C = 1`) reads as `(g, g, g)`: `(w₀ + w₁ + w₂)·g`, exactly the score of the
/// grey image widened to RGB (`∓3g` for dark and bright, 0 for colour weights).
#[inline(always)]
pub(crate) fn linear_score<T: Sample, const C: usize>(px: &[T], w: &[i32; 3]) -> i32 {
    if C == 1 {
        (w[0] + w[1] + w[2]) * px[0].value()
    } else {
        w[0] * px[0].value() + w[1] * px[1].value() + w[2] * px[2].value()
    }
}

/// The clamped colour score of one pixel of `C` samples: `max(0, w · (R, G, B) +
/// bias)`, the bias of [`score_bias`] (`2K` for colour layers).
#[inline(always)]
pub(crate) fn score<T: Sample, const C: usize>(px: &[T], w: &[i32; 3]) -> i32 {
    (linear_score::<T, C>(px, w) + score_bias::<T>(w)).max(0)
}

/// `(Σ s, Σ s·i)` over consecutive pixels, `i` counted from 0.
#[inline(always)]
fn span_sums<T: Sample, const C: usize>(samples: &[T], w: &[i32; 3]) -> (i32, i32) {
    let mut rs = 0i32;
    let mut rx = 0i32;
    for (i, px) in samples.chunks_exact(C).enumerate() {
        let s = score::<T, C>(px, w);
        rs += s;
        rx += s * i as i32;
    }
    (rs, rx)
}

/// A borrowed image as the kernel reads it.
#[derive(Clone, Copy)]
pub(crate) struct Raw<'a, T, const C: usize> {
    pub data: &'a [T],
    pub width: usize,
    pub height: usize,
}

#[derive(Debug, Clone, Copy)]
struct Row {
    /// Aperture half-width (`|dx| ≤ ap`), or −1 when the row misses the aperture.
    ap: i32,
    /// Background ring: `inner < |dx| ≤ outer`; `inner = −1` means the whole `[−outer, outer]`.
    inner: i32,
    /// Outer half-width, or −1 when the row misses the ring.
    outer: i32,
}

/// Precomputed geometry of the window for one aperture radius.
#[derive(Debug, Clone)]
pub(crate) struct Window {
    half: i32,
    rows: Vec<Row>,
    n_ap: f64,
    sxx_ap: f64,
    syy_ap: f64,
    n_bg: f64,
    sxx_bg: f64,
    syy_bg: f64,
    radius_px: f64,
    /// Colour weights of the score.
    weights: [i32; 3],
    /// Linear-kernel weights, `[RGB, RGBA, grey]` (see [`layout`]).
    linear: [LinearWeights; 3],
    /// The CPU has AVX2: 8-bit frames take the SIMD kernel [`kernels::sums_u8_avx2`].
    avx2: bool,
    /// The CPU has AVX-512 F and BW: 8-bit frames take [`kernels::sums_u8_avx512_bytes`]
    /// (preferred, when the weights fit bytes) or [`kernels::sums_u8_avx512`].
    avx512: bool,
    /// The CPU has AVX-512 VNNI: the byte kernel is [`kernels::sums_u8_vnni`] (one
    /// `vpdpbusd` per block and moment) when its sums fit (see
    /// [`LinearWeights::vnni`]).
    vnni: bool,
    /// Whether the AVX-512 byte kernel may be used (tests turn it off to compare).
    byte_kernel: bool,
}

/// Background-corrected moments of one window.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Moments {
    /// Net signal (score units × pixels).
    pub m0: f64,
    /// Centroid offset from the window centre, px.
    pub offset: [f64; 2],
    /// Background score at the window centre (the ring's plane fit).
    pub background: f64,
    /// Background plane slope, score per px.
    pub slope: [f64; 2],
}

impl Moments {
    /// From the background-corrected net signal `m0` and first moments `m1`, the
    /// ring plane's level `background` and `slope`: the centroid offset is `m1 / m0`
    /// (0 when there is no positive signal).
    #[inline(always)]
    pub(crate) fn new(m0: f64, m1: [f64; 2], background: f64, slope: [f64; 2]) -> Moments {
        let offset = if m0 > 0.0 {
            [m1[0] / m0, m1[1] / m0]
        } else {
            [0.0, 0.0]
        };
        Moments {
            m0,
            offset,
            background,
            slope,
        }
    }
}

/// Outcome of an iterated measurement.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Located {
    /// Converged: sub-pixel centroid, net signal, background score and slope.
    Found {
        centroid_px: [f64; 2],
        m0: f64,
        background: f64,
        slope: [f64; 2],
        /// The last window was cut by the image edge (measured by
        /// [`Window::locate_clipped`] on its pixels inside the image).
        clipped: bool,
    },
    /// The window left the image.
    OutOfImage,
    /// No positive signal in the aperture.
    NoSignal,
}

/// Another layer's marker that a window must leave out: its centre and the square
/// of the radius it may colour, px.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Foreign {
    pub centre_px: [f64; 2],
    pub radius2_px: f64,
}

/// Outcome of [`Window::locate_masked`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct MaskedFound {
    /// Sub-pixel centroid, px.
    pub centroid_px: [f64; 2],
    /// Net signal of the pixels used (score units × pixels).
    pub m0: f64,
    /// Fraction of the aperture's pixels used.
    pub visible: f64,
}

impl Window {
    /// Window with aperture radius `radius_px` (gap 1 px, background ring 2 px wide)
    /// for the colour score with weights `weights` (see [`score_weights`]).
    pub fn new(radius_px: f64, weights: [i32; 3]) -> Window {
        let ra = radius_px.max(1.0);
        let rb = ra + 1.0;
        let rc = ra + 3.0;
        let half = rc.floor() as i32;
        let hw = |r: f64, dy: i32| -> i32 {
            let d = r * r - (dy * dy) as f64;
            if d >= 0.0 {
                d.sqrt().floor() as i32
            } else {
                -1
            }
        };
        let mut w = Window {
            half,
            rows: Vec::with_capacity(2 * half as usize + 1),
            n_ap: 0.0,
            sxx_ap: 0.0,
            syy_ap: 0.0,
            n_bg: 0.0,
            sxx_bg: 0.0,
            syy_bg: 0.0,
            radius_px: ra,
            weights,
            linear: Default::default(),
            #[cfg(target_arch = "x86_64")]
            avx2: std::is_x86_feature_detected!("avx2"),
            #[cfg(not(target_arch = "x86_64"))]
            avx2: false,
            #[cfg(target_arch = "x86_64")]
            avx512: std::is_x86_feature_detected!("avx512f")
                && std::is_x86_feature_detected!("avx512bw"),
            #[cfg(not(target_arch = "x86_64"))]
            avx512: false,
            #[cfg(target_arch = "x86_64")]
            vnni: std::is_x86_feature_detected!("avx512f")
                && std::is_x86_feature_detected!("avx512bw")
                && std::is_x86_feature_detected!("avx512vnni"),
            #[cfg(not(target_arch = "x86_64"))]
            vnni: false,
            byte_kernel: true,
        };
        for dy in -half..=half {
            let row = Row {
                ap: hw(ra, dy),
                inner: hw(rb, dy),
                outer: hw(rc, dy),
            };
            let dy2 = (dy * dy) as f64;
            for dx in -half..=half {
                let dx2 = (dx * dx) as f64;
                let adx = dx.abs();
                if adx <= row.ap {
                    w.n_ap += 1.0;
                    w.sxx_ap += dx2;
                    w.syy_ap += dy2;
                } else if adx > row.inner && adx <= row.outer {
                    w.n_bg += 1.0;
                    w.sxx_bg += dx2;
                    w.syy_bg += dy2;
                }
            }
            w.rows.push(row);
        }
        for channels in [3usize, 4, 1] {
            w.linear[layout(channels)] = w.linear_weights(channels);
        }
        w
    }

    /// Mid-radius of the background ring, px.
    pub fn ring_radius_px(&self) -> f64 {
        self.radius_px + 2.0
    }

    /// Half-size of the square the window reads, px.
    #[cfg(test)]
    pub fn half_px(&self) -> i32 {
        self.half
    }

    /// Background-corrected moments of the window centred on `(cx, cy)`, or `None` when
    /// the window does not fit in the image. `clamped` selects the clamped score
    /// (robust to other-colour markers inside the window, scalar) instead of the
    /// linear score (vectorised; the default).
    #[inline]
    pub fn moments<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        cx: i32,
        cy: i32,
        clamped: bool,
    ) -> Option<Moments> {
        let h = self.half;
        if cx < h || cy < h || cx + h >= img.width as i32 || cy + h >= img.height as i32 {
            return None;
        }
        let [s0, sx, sy, b0, bx, by] = if clamped {
            self.sums_clamped::<T, C>(img, cx, cy)
        } else {
            self.sums_linear::<T, C>(img, cx, cy)
        };
        let a = b0 as f64 / self.n_bg;
        let gx = bx as f64 / self.sxx_bg;
        let gy = by as f64 / self.syy_bg;
        let m0 = s0 as f64 - a * self.n_ap;
        let mx = sx as f64 - gx * self.sxx_ap;
        let my = sy as f64 - gy * self.syy_ap;
        Some(Moments::new(m0, [mx, my], a, [gx, gy]))
    }

    /// As [`Self::sums_linear`] with the clamped score `max(0, 3·I_c − (R+G+B) + 2K)`.
    fn sums_clamped<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        cx: i32,
        cy: i32,
    ) -> [i64; 6] {
        let h = self.half;
        let (mut s0, mut sx, mut sy) = (0i64, 0i64, 0i64);
        let (mut b0, mut bx, mut by) = (0i64, 0i64, 0i64);
        for (k, row) in self.rows.iter().enumerate() {
            let dy = k as i32 - h;
            let centre = (cy + dy) as usize * img.width + cx as usize;
            // Sum of s and of s·dx over the pixels dx in [lo, hi] of this row.
            let span = |lo: i32, hi: i32| -> (i32, i32) {
                let start = (centre as isize + lo as isize) as usize * C;
                let end = (centre as isize + hi as isize + 1) as usize * C;
                let (rs, rx) = span_sums::<T, C>(&img.data[start..end], &self.weights);
                (rs, rx + lo * rs)
            };
            if row.ap >= 0 {
                let (rs, rx) = span(-row.ap, row.ap);
                s0 += rs as i64;
                sx += rx as i64;
                sy += rs as i64 * dy as i64;
            }
            if row.outer >= 0 {
                let mut add = |(rs, rx): (i32, i32)| {
                    b0 += rs as i64;
                    bx += rx as i64;
                    by += rs as i64 * dy as i64;
                };
                if row.inner < 0 {
                    add(span(-row.outer, row.outer));
                } else {
                    add(span(-row.outer, -row.inner - 1));
                    add(span(row.inner + 1, row.outer));
                }
            }
        }
        [s0, sx, sy, b0, bx, by]
    }

    /// Iterates [`Self::moments`] with re-centring from `start_px` (see module docs).
    pub fn locate<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        start_px: [f64; 2],
        max_iterations: u32,
        clamped: bool,
    ) -> Located {
        self.locate_impl::<T, C>(img, start_px, max_iterations, clamped, false)
    }

    /// As [`Self::locate`], measuring a window cut by the image edge on its pixels
    /// inside the image ([`Self::moments_clipped`]) instead of giving up: the result
    /// says whether the last window was cut; whether its dot lies inside the image is
    /// for the caller to check.
    pub fn locate_clipped<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        start_px: [f64; 2],
        max_iterations: u32,
        clamped: bool,
    ) -> Located {
        self.locate_impl::<T, C>(img, start_px, max_iterations, clamped, true)
    }

    #[inline(always)]
    fn locate_impl<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        start_px: [f64; 2],
        max_iterations: u32,
        clamped: bool,
        clip: bool,
    ) -> Located {
        if !(start_px[0].is_finite() && start_px[1].is_finite()) {
            return Located::OutOfImage;
        }
        let mut c = [round_px(start_px[0]), round_px(start_px[1])];
        let mut prev = [i32::MIN, i32::MIN];
        let mut last = Located::NoSignal;
        // The previous window's result and how far its centroid lay from its centre.
        let mut prev_found = (Located::NoSignal, f64::INFINITY);
        for _ in 0..max_iterations.max(1) {
            let (m, cut) = match self.moments::<T, C>(img, c[0], c[1], clamped) {
                Some(m) => (m, false),
                None if clip => match self.moments_clipped::<T, C>(img, c[0], c[1], clamped) {
                    Some(m) => (m, true),
                    None => return Located::OutOfImage,
                },
                None => return Located::OutOfImage,
            };
            // NaN-safe: anything but a positive signal is no signal.
            if m.m0.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                return Located::NoSignal;
            }
            let est = [c[0] as f64 + m.offset[0], c[1] as f64 + m.offset[1]];
            last = Located::Found {
                centroid_px: est,
                m0: m.m0,
                background: m.background,
                slope: m.slope,
                clipped: cut,
            };
            let next = [round_px(est[0]), round_px(est[1])];
            if next == c {
                return last;
            }
            let off2 = m.offset[0] * m.offset[0] + m.offset[1] * m.offset[1];
            // A two-cycle between neighbouring pixels (centroid on a half-pixel
            // boundary): either window is centred within ~0.5 px. The one whose
            // centroid lies nearer its centre is kept (on a tie, the upper-left one),
            // so the result does not depend on which of the two the search met first
            // — nor on the start window.
            if next == prev {
                let keep_prev = prev_found.1 < off2
                    || (prev_found.1 == off2 && (prev[1], prev[0]) < (c[1], c[0]));
                return if keep_prev { prev_found.0 } else { last };
            }
            prev_found = (last, off2);
            prev = c;
            c = next;
        }
        last
    }

    /// Linear colour score `w · (R, G, B)` of pixel `(x, y)` (not clamped).
    #[inline(always)]
    fn linear_score<T: Sample, const C: usize>(&self, img: Raw<'_, T, C>, x: i32, y: i32) -> i32 {
        let i = (y as usize * img.width + x as usize) * C;
        linear_score::<T, C>(&img.data[i..i + C], &self.weights)
    }

    /// Offset, net signal and visible fraction of the window centred on `(cx, cy)`
    /// with the pixels of `foreign` discs — and their mirror images through the
    /// centre — left out (see [`Self::locate_masked`]). `None` when the window does not
    /// fit, too little ring or signal is left, or the Jacobian is singular.
    ///
    /// Steps: the pixels' scores and the foreign mask ([`MaskedPixels`]), the
    /// background plane over the kept ring ([`Self::masked_plane`]), the aperture's
    /// moments per symmetry ([`Self::masked_aperture`]), their Gauss–Newton offset
    /// ([`masked_offset`]).
    fn masked_moments<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        cx: i32,
        cy: i32,
        foreign: &[Foreign],
    ) -> Option<([f64; 2], f64, f64)> {
        let h = self.half;
        if cx <= h || cy <= h || cx + h + 1 >= img.width as i32 || cy + h + 1 >= img.height as i32 {
            return None;
        }
        let px = MaskedPixels::new(self, img, [cx, cy], foreign);
        let plane = self.masked_plane(&px)?;
        let ap = self.masked_aperture(&px, plane);
        // NaN-safe: anything but a positive signal is no measurement.
        if ap.m0.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let offset = masked_offset(&ap.t)?;
        Some((offset, ap.m0, ap.kept / self.n_ap))
    }

    /// Background plane `[a, gx, gy]` over the kept ring pixels (both a pixel and its
    /// mirror through the centre clear). The kept set is point-symmetric, so the level
    /// decouples from the slopes, but the slopes couple through Σdx·dy. `None` when
    /// fewer than a quarter of the ring's pixels are kept or the slopes are singular.
    fn masked_plane<T: Sample, const C: usize>(
        &self,
        px: &MaskedPixels<'_, '_, T, C>,
    ) -> Option<[f64; 3]> {
        let h = self.half;
        let (mut n, mut s0, mut sx, mut sy) = (0.0, 0.0, 0.0, 0.0);
        let (mut xx, mut xy, mut yy) = (0.0, 0.0, 0.0);
        for (k, row) in self.rows.iter().enumerate() {
            let dy = k as i32 - h;
            for dx in -row.outer..=row.outer {
                if dx.abs() <= row.inner || !px.keep(dx, dy) {
                    continue;
                }
                let (s, fx, fy) = (px.score(dx, dy), dx as f64, dy as f64);
                n += 1.0;
                s0 += s;
                sx += s * fx;
                sy += s * fy;
                xx += fx * fx;
                xy += fx * fy;
                yy += fy * fy;
            }
        }
        let det_bg = xx * yy - xy * xy;
        if n < 0.25 * self.n_bg || det_bg <= 0.0 {
            return None;
        }
        let a = s0 / n;
        let gx = (sx * yy - sy * xy) / det_bg;
        let gy = (sy * xx - sx * xy) / det_bg;
        Some([a, gx, gy])
    }

    /// The aperture's moments `N = Σ_S Σ_{K_S} w_S s'` of the background-corrected
    /// score `s'` (`w_S = ½(p − S·p)`, `K_S` the pixels with `p` and `S·p` both clear)
    /// and the Jacobian `J = −Σ_S Σ_{K_S} w_S ∇s'ᵀ` (central differences) of `N` with
    /// respect to a shift, with its first-order change when `∇s'` is sampled `h` px
    /// away: `J(h) = J + hx·Kx + hy·Ky`, `Kx = −Σ w_S ∂x∇s'ᵀ`, `Ky = −Σ w_S ∂y∇s'ᵀ`
    /// (all in [`MaskedSums::t`]). `kept` / `m0` count the point-symmetric set
    /// (visible fraction, signal check).
    ///
    /// Every symmetry uses a pixel whose images are all clear, with total weight
    /// `Σ_S W_S = 3·I`: such sums are taken once (`all`), and per symmetry only the
    /// pixels it drops (`dropped[S]`) are subtracted. Columns: `s'`, `∂x s'`, `∂y s'`,
    /// `∂xx s'`, `∂xy s'`, `∂yy s'`; rows: times `dx`, times `dy`.
    fn masked_aperture<T: Sample, const C: usize>(
        &self,
        px: &MaskedPixels<'_, '_, T, C>,
        [a, gx, gy]: [f64; 3],
    ) -> MaskedSums {
        let h = self.half;
        let score = |dx: i32, dy: i32| px.score(dx, dy);
        let (mut kept, mut m0) = (0.0, 0.0);
        let mut all = [[0.0f64; 6]; 2];
        let mut dropped = [[[0.0f64; 6]; 2]; 5];
        let sym = symmetries();
        for (k, row) in self.rows.iter().enumerate() {
            let dy = k as i32 - h;
            for dx in -row.ap..=row.ap {
                if px.hidden(dx, dy) {
                    continue;
                }
                let (fx, fy) = (dx as f64, dy as f64);
                let s_c = score(dx, dy);
                let (s_l, s_r) = (score(dx - 1, dy), score(dx + 1, dy));
                let (s_u, s_d) = (score(dx, dy - 1), score(dx, dy + 1));
                let q = [
                    s_c - (a + gx * fx + gy * fy),
                    0.5 * (s_r - s_l) - gx,
                    0.5 * (s_d - s_u) - gy,
                    s_r - 2.0 * s_c + s_l,
                    0.25 * (score(dx + 1, dy + 1) - score(dx + 1, dy - 1) - score(dx - 1, dy + 1)
                        + score(dx - 1, dy - 1)),
                    s_d - 2.0 * s_c + s_u,
                ];
                if !px.hidden(-dx, -dy) {
                    kept += 1.0;
                    m0 += q[0];
                }
                for c in 0..6 {
                    all[0][c] += fx * q[c];
                    all[1][c] += fy * q[c];
                }
                for (si, (sm, _)) in sym.iter().enumerate() {
                    let (ix, iy) = (sm[0][0] * dx + sm[0][1] * dy, sm[1][0] * dx + sm[1][1] * dy);
                    if px.hidden(ix, iy) {
                        for c in 0..6 {
                            dropped[si][0][c] += fx * q[c];
                            dropped[si][1][c] += fy * q[c];
                        }
                    }
                }
            }
        }
        // T = Σ_S W_S·(all − dropped_S) = 3·all − Σ_S W_S·dropped_S.
        let mut t = [[0.0f64; 6]; 2];
        for r in 0..2 {
            for c in 0..6 {
                t[r][c] = 3.0 * all[r][c];
                for (si, (_, wm)) in sym.iter().enumerate() {
                    t[r][c] -= wm[r][0] * dropped[si][0][c] + wm[r][1] * dropped[si][1][c];
                }
            }
        }
        MaskedSums { kept, m0, t }
    }

    /// Centroid of a marker partly covered by, or covering, other layers' markers
    /// `foreign` (each a disc that may hold any colour).
    ///
    /// A disc of any radial profile is symmetric about its centre under the point
    /// reflection and the reflections about the axes and diagonals, so for each such
    /// symmetry `S` a set of pixels around the window centre `c` that `S` maps onto
    /// itself keeps the moment `N_S(δ) = Σ ½(p − S·p)·s'(p)` (`p` relative to `c`) zero
    /// when the marker sits at `c` (`δ = 0`). Per `S`, the pixels whose own or
    /// `S`-image position falls in a foreign disc are left out; the rest is used as in
    /// [`Self::moments`] (ring plane fit, background-corrected score `s'`). The
    /// full-window centroid would be biased by the missing pixels, so the offset is the
    /// Gauss–Newton step `δ = J⁻¹·N` for `N = Σ_S N_S` with the measured
    /// `J = ∂N/∂δ = −Σ_S Σ ½(p − S·p)·∇s'(p)ᵀ` (central differences, midpoint-corrected
    /// with the second differences). With nothing left out `J = 3·M0·I` (summation by
    /// parts) and `δ` is the plain centroid. Re-centred on the rounded estimate like
    /// [`Self::locate`]; `m0` and `visible` are the net signal and the aperture fraction
    /// of the point-symmetric set. `None` when nothing usable is left. Accuracy: see
    /// the module docs.
    pub fn locate_masked<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        start_px: [f64; 2],
        max_iterations: u32,
        foreign: &[Foreign],
    ) -> Option<MaskedFound> {
        if !(start_px[0].is_finite() && start_px[1].is_finite()) {
            return None;
        }
        let mut c = [round_px(start_px[0]), round_px(start_px[1])];
        let mut prev = [i32::MIN, i32::MIN];
        let mut last = None;
        for _ in 0..max_iterations.max(1) {
            let (offset, m0, visible) = self.masked_moments::<T, C>(img, c[0], c[1], foreign)?;
            let est = [c[0] as f64 + offset[0], c[1] as f64 + offset[1]];
            last = Some(MaskedFound {
                centroid_px: est,
                m0,
                visible,
            });
            let next = [round_px(est[0]), round_px(est[1])];
            if next == c || next == prev {
                break;
            }
            prev = c;
            c = next;
        }
        last
    }

    /// Largest colour score inside the aperture centred on `(cx, cy)` (its part inside
    /// the image); `None` when the centre pixel is outside the image.
    pub fn peak<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        cx: i32,
        cy: i32,
    ) -> Option<i32> {
        let h = self.half;
        let (w, ht) = (img.width as i32, img.height as i32);
        if cx < 0 || cy < 0 || cx >= w || cy >= ht {
            return None;
        }
        let mut best = 0;
        for (k, row) in self.rows.iter().enumerate() {
            let y = cy + k as i32 - h;
            if row.ap < 0 || y < 0 || y >= ht {
                continue;
            }
            let y = y as usize;
            let (x0, x1) = (
                (cx - row.ap).max(0) as usize,
                (cx + row.ap).min(w - 1) as usize,
            );
            let start = (y * img.width + x0) * C;
            let end = (y * img.width + x1 + 1) * C;
            for px in img.data[start..end].chunks_exact(C) {
                best = best.max(score::<T, C>(px, &self.weights));
            }
        }
        Some(best)
    }
}

/// Largest window half-size whose scores and foreign-disc mask
/// [`Window::locate_masked`] tabulates on the stack (a 33 × 33 score table, 4.4 kB,
/// zeroed per call: the paper sensor's windows have half-size 10–11).
const MAX_TABLE_HALF: i32 = 15;

/// A pixel-grid symmetry `S` (integer matrix) and its moment weight `W_S = (I − S)/2`.
type Symmetry = ([[i32; 2]; 2], [[f64; 2]; 2]);

/// The pixel-grid symmetries `S` a disc shares (point reflection, reflections about
/// the axes and the diagonals) with the weights `(p − S·p)/2` of their moments.
#[inline(always)]
fn symmetries() -> [Symmetry; 5] {
    [
        ([[-1, 0], [0, -1]], [[1.0, 0.0], [0.0, 1.0]]),
        ([[-1, 0], [0, 1]], [[1.0, 0.0], [0.0, 0.0]]),
        ([[1, 0], [0, -1]], [[0.0, 0.0], [0.0, 1.0]]),
        ([[0, 1], [1, 0]], [[0.5, -0.5], [-0.5, 0.5]]),
        ([[0, -1], [-1, 0]], [[0.5, 0.5], [0.5, 0.5]]),
    ]
}

/// Width of the score table of [`MaskedPixels`]: the largest tabulated window ± 1 px
/// for the gradient stencils.
const TABLE_SIDE: usize = 2 * MAX_TABLE_HALF as usize + 3;

/// The pixels a masked window reads, relative to its centre: their colour scores and
/// whether a foreign disc hides them. Both are tabulated once per window when it is
/// small enough (every window of the paper sensor, half-size ≤ [`MAX_TABLE_HALF`]):
/// each pixel is read by up to nine stencils and tested by up to six symmetries.
/// Larger windows compute them on demand.
struct MaskedPixels<'a, 'f, T, const C: usize> {
    window: &'a Window,
    img: Raw<'a, T, C>,
    /// The window's centre pixel `(cx, cy)`.
    centre: [i32; 2],
    foreign: &'f [Foreign],
    tabulated: bool,
    /// Scores of the window ± 1 px, row-major, `2·half + 3` per row (when tabulated).
    scores: [i32; TABLE_SIDE * TABLE_SIDE],
    /// Per window row, bit `dx + half` set when a foreign disc hides that pixel.
    hidden_rows: [u64; 2 * MAX_TABLE_HALF as usize + 1],
}

impl<'a, 'f, T: Sample, const C: usize> MaskedPixels<'a, 'f, T, C> {
    /// The window of `window` centred on `centre` in `img` (which must contain it ±
    /// 1 px), with the pixels of `foreign` discs hidden.
    fn new(
        window: &'a Window,
        img: Raw<'a, T, C>,
        centre: [i32; 2],
        foreign: &'f [Foreign],
    ) -> Self {
        let mut px = MaskedPixels {
            window,
            img,
            centre,
            foreign,
            tabulated: window.half <= MAX_TABLE_HALF,
            scores: [0i32; TABLE_SIDE * TABLE_SIDE],
            hidden_rows: [0u64; 2 * MAX_TABLE_HALF as usize + 1],
        };
        if px.tabulated {
            px.tabulate();
        }
        px
    }

    /// Side of the score table: the window ± 1 px.
    #[inline(always)]
    fn side(&self) -> usize {
        (2 * self.window.half + 3) as usize
    }

    /// Fills the score table and the hidden-pixel rows.
    fn tabulate(&mut self) {
        let h = self.window.half;
        let [cx, cy] = self.centre;
        let side = self.side();
        for (k, v) in self.scores[..side * side].iter_mut().enumerate() {
            let (dx, dy) = ((k % side) as i32 - h - 1, (k / side) as i32 - h - 1);
            *v = self.window.linear_score::<T, C>(self.img, cx + dx, cy + dy);
        }
        // Per row, each foreign disc hides one run of pixels.
        for (k, bits) in self.hidden_rows[..(2 * h + 1) as usize]
            .iter_mut()
            .enumerate()
        {
            let y = (cy + k as i32 - h) as f64;
            for f in self.foreign {
                let d = f.radius2_px - (y - f.centre_px[1]) * (y - f.centre_px[1]);
                // NaN-safe: as in `hidden_at`, a NaN centre hides nothing.
                if d.is_nan() || d < 0.0 {
                    continue;
                }
                let r = d.sqrt();
                let lo = ((f.centre_px[0] - r).ceil() - cx as f64).max(-h as f64) as i32;
                let hi = ((f.centre_px[0] + r).floor() - cx as f64).min(h as f64) as i32;
                if lo > hi {
                    continue;
                }
                let n = (hi - lo + 1) as u32;
                let run = if n >= 64 { u64::MAX } else { (1u64 << n) - 1 };
                *bits |= run << (lo + h) as u32;
            }
        }
    }

    /// Whether image pixel `(x, y)` lies in a foreign disc.
    fn hidden_at(&self, x: i32, y: i32) -> bool {
        self.foreign.iter().any(|f| {
            let (dx, dy) = (x as f64 - f.centre_px[0], y as f64 - f.centre_px[1]);
            dx * dx + dy * dy <= f.radius2_px
        })
    }

    /// Whether pixel `(cx + dx, cy + dy)`, `|dx|, |dy| ≤ half`, lies in a foreign disc.
    #[inline(always)]
    fn hidden(&self, dx: i32, dy: i32) -> bool {
        let h = self.window.half;
        if self.tabulated {
            (self.hidden_rows[(dy + h) as usize] >> (dx + h) as u32) & 1 == 1
        } else {
            self.hidden_at(self.centre[0] + dx, self.centre[1] + dy)
        }
    }

    /// Whether both the pixel at `(dx, dy)` and its mirror through the centre are clear.
    #[inline(always)]
    fn keep(&self, dx: i32, dy: i32) -> bool {
        !self.hidden(dx, dy) && !self.hidden(-dx, -dy)
    }

    /// Colour score of the pixel at `(dx, dy)` from the centre, `|dx|, |dy| ≤ half + 1`.
    #[inline(always)]
    fn score(&self, dx: i32, dy: i32) -> f64 {
        let h = self.window.half;
        if self.tabulated {
            self.scores[(dy + h + 1) as usize * self.side() + (dx + h + 1) as usize] as f64
        } else {
            let [cx, cy] = self.centre;
            self.window.linear_score::<T, C>(self.img, cx + dx, cy + dy) as f64
        }
    }
}

/// What [`Window::masked_aperture`] sums over the aperture.
struct MaskedSums {
    /// Pixels of the point-symmetric set (both a pixel and its mirror clear).
    kept: f64,
    /// Net signal of the point-symmetric set.
    m0: f64,
    /// `T = Σ_S W_S·Σ_{K_S} (dx, dy)ᵀ·(s', ∂x s', ∂y s', ∂xx s', ∂xy s', ∂yy s')`:
    /// column 0 is the moment `N`, columns 1–2 give `−J`, 3–5 its changes `−Kx`, `−Ky`.
    t: [[f64; 6]; 2],
}

/// The marker's offset from the window centre: the Gauss–Newton step `δ = J⁻¹·N`
/// from the aperture sums `t` ([`MaskedSums::t`]), midpoint-corrected. `N(δ) =
/// ∫₀¹ J(tδ) dt · δ` exactly; `J` is measured at the marker's offset `δ`, so `J⁻¹N`
/// has an O(δ²) error. The midpoint rule (`J` sampled at offset `δ/2`, i.e. `∇s'`
/// taken `h = δ/2` px away) leaves O(δ³): two refinements from `J⁻¹N`. `None` when
/// the Jacobian is singular or not positive.
fn masked_offset(t: &[[f64; 6]; 2]) -> Option<[f64; 2]> {
    let (mx, my) = (t[0][0], t[1][0]);
    let j = [[-t[0][1], -t[0][2]], [-t[1][1], -t[1][2]]];
    let kx = [[-t[0][3], -t[0][4]], [-t[1][3], -t[1][4]]];
    let ky = [[-t[0][4], -t[0][5]], [-t[1][4], -t[1][5]]];
    let solve = |hx: f64, hy: f64| -> Option<[f64; 2]> {
        let m = |a: usize, b: usize| j[a][b] + hx * kx[a][b] + hy * ky[a][b];
        let det = m(0, 0) * m(1, 1) - m(0, 1) * m(1, 0);
        (det > 0.0).then(|| {
            [
                (m(1, 1) * mx - m(0, 1) * my) / det,
                (m(0, 0) * my - m(1, 0) * mx) / det,
            ]
        })
    };
    let mut offset = solve(0.0, 0.0)?;
    for _ in 0..2 {
        offset = solve(0.5 * offset[0], 0.5 * offset[1])?;
    }
    Some(offset)
}

/// `x.round() as i32` (half away from zero; NaN → 0) without a call: baseline x86-64
/// has no rounding instruction, so `f64::round` is a libm call, and `locate` rounds
/// twice per pass. Exact for |x| < 2³¹ (the fraction `x − trunc(x)` is exact).
#[inline(always)]
fn round_px(x: f64) -> i32 {
    let t = x as i32;
    let f = x - t as f64;
    t + (f >= 0.5) as i32 - (f <= -0.5) as i32
}

/// The paper's window search: centre of mass of `max(0, s − threshold)` over the square
/// of half-size `half_px` around `centre_px` (clipped to the image). Used to acquire a
/// marker that the aperture does not see. `None` when nothing exceeds the threshold.
pub(crate) fn search<T: Sample, const C: usize>(
    img: Raw<'_, T, C>,
    weights: &[i32; 3],
    centre_px: [f64; 2],
    half_px: i32,
    threshold: i32,
) -> Option<[f64; 2]> {
    if !(centre_px[0].is_finite() && centre_px[1].is_finite()) {
        return None;
    }
    let cx = centre_px[0].round() as i64;
    let cy = centre_px[1].round() as i64;
    let h = half_px as i64;
    let x0 = (cx - h).max(0);
    let x1 = (cx + h).min(img.width as i64 - 1);
    let y0 = (cy - h).max(0);
    let y1 = (cy + h).min(img.height as i64 - 1);
    if x0 > x1 || y0 > y1 {
        return None;
    }
    let (mut s0, mut sx, mut sy) = (0i64, 0i64, 0i64);
    for y in y0..=y1 {
        let start = (y as usize * img.width + x0 as usize) * C;
        let end = (y as usize * img.width + x1 as usize + 1) * C;
        let mut rs = 0i64;
        let mut rx = 0i64;
        for (i, px) in img.data[start..end].chunks_exact(C).enumerate() {
            let s = (score::<T, C>(px, weights) - threshold).max(0) as i64;
            rs += s;
            rx += s * i as i64;
        }
        s0 += rs;
        sx += rx + x0 * rs;
        sy += rs * y;
    }
    if s0 <= 0 {
        return None;
    }
    Some([sx as f64 / s0 as f64, sy as f64 / s0 as f64])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An anti-aliased disc (16×16 supersampled) of colour score `amp` in the blue channel.
    /// Area of pixel `(x, y)` inside the disc of centre `c`, radius `r` (16×16
    /// supersampled).
    fn coverage(x: usize, y: usize, c: [f64; 2], r: f64) -> f64 {
        let mut cov = 0.0;
        for sy in 0..16 {
            for sx in 0..16 {
                let px = x as f64 + (sx as f64 + 0.5) / 16.0 - 0.5 - c[0];
                let py = y as f64 + (sy as f64 + 0.5) / 16.0 - 0.5 - c[1];
                if px * px + py * py <= r * r {
                    cov += 1.0 / 256.0;
                }
            }
        }
        cov
    }

    fn disc(w: usize, h: usize, c: [f64; 2], r: f64, amp: f64, bg: f64) -> Vec<u16> {
        let mut d = vec![0u16; w * h * 3];
        for y in 0..h {
            for x in 0..w {
                let cov = coverage(x, y, c, r);
                let i = (y * w + x) * 3;
                d[i] = bg as u16;
                d[i + 1] = bg as u16;
                d[i + 2] = (bg + amp * cov).round() as u16;
            }
        }
        d
    }

    #[test]
    fn score_weights_subtract_unused_channels_and_sum_to_zero() {
        use MarkerColor::*;
        assert_eq!(score_weights(Blue, &[Blue, Red]), [0, -1, 1]);
        assert_eq!(score_weights(Red, &[Blue, Red]), [1, -1, 0]);
        assert_eq!(score_weights(Blue, &[Blue]), [-1, -1, 2]);
        assert_eq!(score_weights(Green, &[Blue, Red, Green]), [-1, 2, -1]);
        for w in [
            score_weights(Green, &[Green, Red]),
            score_weights(Red, &[Red]),
        ] {
            assert_eq!(w.iter().sum::<i32>(), 0, "{w:?}");
        }
    }

    #[test]
    fn window_regions_are_symmetric_and_disjoint() {
        let w = Window::new(8.0, [-1, -1, 2]);
        assert_eq!(w.half_px(), 11);
        assert_eq!(w.sxx_ap, w.syy_ap);
        assert_eq!(w.sxx_bg, w.syy_bg);
        // Disc area within a few pixels of π r².
        assert!(
            (w.n_ap - std::f64::consts::PI * 64.0).abs() < 12.0,
            "{}",
            w.n_ap
        );
        assert!(w.n_bg > 100.0);
    }

    #[test]
    fn locate_recovers_subpixel_centre_of_a_disc_on_a_sloped_background() {
        let (wd, ht) = (60, 60);
        for &c in &[[30.0, 30.0], [30.37, 29.81], [28.5, 31.25]] {
            let mut d = disc(wd, ht, c, 6.0, 4000.0, 0.0);
            // Add a blue-only linear background gradient (uneven illumination).
            for y in 0..ht {
                for x in 0..wd {
                    d[(y * wd + x) * 3 + 2] += (3.0 * x as f64 + 2.0 * y as f64) as u16;
                }
            }
            let img = Raw::<u16, 3> {
                data: &d,
                width: wd,
                height: ht,
            };
            let w = Window::new(8.0, [-1, -1, 2]);
            for clamped in [false, true] {
                match w.locate::<u16, 3>(img, [c[0] + 2.6, c[1] - 2.2], 10, clamped) {
                    Located::Found { centroid_px, .. } => {
                        assert!(
                            (centroid_px[0] - c[0]).abs() < 0.01,
                            "{centroid_px:?} vs {c:?}"
                        );
                        assert!(
                            (centroid_px[1] - c[1]).abs() < 0.01,
                            "{centroid_px:?} vs {c:?}"
                        );
                    }
                    other => panic!("not found: {other:?}"),
                }
            }
        }
    }

    /// A centroid on a half-pixel boundary can send the search back and forth
    /// between two windows (each one's centroid rounds to the other's centre); the
    /// result then must not depend on which of the two the search met first, i.e. on
    /// the start window. Discs are swept across the boundary x = 30.5 (with a small
    /// blob in one window's ring, so the two windows' estimates differ); every start within
    /// ±3 px must give the same centroid, bit for bit, and the sweep must contain
    /// two-cycles.
    #[test]
    fn two_cycle_result_does_not_depend_on_the_start_window() {
        let (wd, ht) = (60, 60);
        let w = Window::new(6.0, [-1, -1, 2]);
        let mut two_cycles = 0;
        for k in 0..=200 {
            let c = [30.49 + 0.0001 * k as f64, 29.8];
            let mut d = disc(wd, ht, c, 5.0, 4000.0, 100.0);
            // A small blob that only the right-hand window's ring reaches: it lifts
            // that window's background plane and pulls its centroid to the left.
            let spike = disc(wd, ht, [39.8, 30.0], 1.2, 1500.0, 0.0);
            for (v, s) in d.iter_mut().zip(&spike) {
                *v += s;
            }
            let img = Raw::<u16, 3> {
                data: &d,
                width: wd,
                height: ht,
            };
            let est = |cx: i32| {
                let m = w.moments::<u16, 3>(img, cx, 30, false).unwrap();
                round_px(cx as f64 + m.offset[0])
            };
            if est(30) == 31 && est(31) == 30 {
                two_cycles += 1;
            }
            let mut found = Vec::new();
            for dx in -3..=3 {
                for dy in -3..=3 {
                    let start = [c[0] + dx as f64, c[1] + dy as f64];
                    match w.locate::<u16, 3>(img, start, 8, false) {
                        Located::Found { centroid_px, .. } => found.push(centroid_px),
                        other => panic!("not found from {start:?}: {other:?}"),
                    }
                }
            }
            assert!(
                found.iter().all(|f| f == &found[0]),
                "disc at {c:?}: {found:?}"
            );
        }
        assert!(two_cycles > 0, "the sweep met no two-cycle");
    }

    /// A disc (radius `r`) with a neighbour of another colour (radius `r`, `gap` px
    /// away along a diagonal-ish direction) drawn over it: the covered pixels lose
    /// their blue excess (anti-aliased, 16×16 supersampled).
    fn covered_disc(size: usize, c: [f64; 2], r: f64, occluder: [f64; 2]) -> Vec<u16> {
        let mut d = disc(size, size, c, r, 4000.0, 100.0);
        for y in 0..size {
            for x in 0..size {
                let cov = coverage(x, y, occluder, r);
                let i = (y * size + x) * 3;
                // Over-compositing a grey-scoring marker: B − G → (1 − cov)·(B − G).
                let b = d[i + 2] as f64;
                d[i + 2] = (b + cov * (d[i + 1] as f64 - b)).round() as u16;
            }
        }
        d
    }

    #[test]
    fn locate_masked_recovers_a_partly_covered_disc_with_small_and_large_windows() {
        // Scale 1: radius 6 px, the paper's 12 px markers (window half 10, tabulated);
        // scale 4.7: radius 28 px (window half 33, the direct path).
        for (scale, tol) in [(1.0, 0.03), (4.7, 0.03)] {
            let r = 6.0 * scale;
            let size = (60.0 * scale) as usize;
            let mid = size as f64 / 2.0;
            for &(c, dir) in &[
                ([mid + 0.31, mid - 0.22], [0.8, 0.6]),
                ([mid - 0.45, mid + 0.12], [-0.6, 0.8]),
            ] {
                // Centres 10.5 px apart at scale 1 (1.5 px of the 12 px diameters covered).
                let gap = 10.5 * scale;
                let occ = [c[0] + gap * dir[0], c[1] + gap * dir[1]];
                let d = covered_disc(size, c, r, occ);
                let img = Raw::<u16, 3> {
                    data: &d,
                    width: size,
                    height: size,
                };
                let w = Window::new(r + 1.5, [0, -1, 1]);
                let foreign = [Foreign {
                    centre_px: occ,
                    radius2_px: (r + 1.5) * (r + 1.5),
                }];
                let found = w
                    .locate_masked::<u16, 3>(img, [c[0] + 0.6, c[1] - 0.7], 8, &foreign)
                    .expect("measurable");
                let e = [found.centroid_px[0] - c[0], found.centroid_px[1] - c[1]];
                assert!(
                    e[0].abs() <= tol && e[1].abs() <= tol,
                    "scale {scale}: {:?} vs {c:?}",
                    found.centroid_px
                );
                // The plain centroid follows the visible part, well away from the centre.
                let Located::Found { centroid_px, .. } = w.locate::<u16, 3>(img, c, 8, false)
                else {
                    panic!("plain centroid not found");
                };
                assert!(
                    (centroid_px[0] - c[0]).hypot(centroid_px[1] - c[1]) > 0.1 * scale,
                    "scale {scale}: plain {centroid_px:?} vs {c:?}"
                );
            }
        }
    }

    #[test]
    fn locate_reports_no_signal_and_out_of_image() {
        let d = vec![10u8; 40 * 40 * 3];
        let img = Raw::<u8, 3> {
            data: &d,
            width: 40,
            height: 40,
        };
        let w = Window::new(6.0, [-1, -1, 2]);
        assert!(matches!(
            w.locate::<u8, 3>(img, [20.0, 20.0], 5, false),
            Located::NoSignal
        ));
        assert!(matches!(
            w.locate::<u8, 3>(img, [3.0, 20.0], 5, false),
            Located::OutOfImage
        ));
        assert!(matches!(
            w.locate::<u8, 3>(img, [f64::NAN, 20.0], 5, false),
            Located::OutOfImage
        ));
    }

    #[test]
    fn round_px_matches_f64_round() {
        for x in [
            0.0, 0.49, 0.5, 0.51, 1.5, 2.5, -0.5, -0.49, -1.5, -2.51, 123.4999, 429.5, -7.0,
        ] {
            assert_eq!(round_px(x), x.round() as i32, "{x}");
        }
        assert_eq!(round_px(f64::NAN), 0);
    }
}
