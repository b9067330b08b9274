//! The per-marker window kernel: colour score, local background plane and
//! background-corrected centre of mass, iterated with re-centring.
//!
//! **Colour score.** For a layer of colour `c` the score of a pixel is
//! `s = max(0, 2·I_c − I_o1 − I_o2 + 2K)`, twice the colour's excess over the mean of
//! the other two channels, lifted by a small offset `K` (8 levels of 8 bits): grey
//! light (equal channels, including uneven grey illumination) scores the constant
//! `2K`, which the background plane removes; a marker of the layer's colour scores its
//! colour excess; markers of another colour are strongly negative and clip to 0, so
//! they never look like this layer. The score is *linear* in the pixel values wherever
//! it matters (markers of this colour, background with noise): a blend `α·marker +
//! (1 − α)·background` at a soft or anti-aliased edge scores linearly in `α`, which
//! keeps the centre of mass unbiased. (`I_c − max(I_o1, I_o2)` would be piecewise
//! linear in `α` and bias sub-pixel centroids by ~0.003 px; clipping at 0 without
//! the offset would clip the background noise.)
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
//! **Re-centring.** The window is moved to the rounded centroid and the moments taken
//! again until the rounded centroid stays put (or a two-cycle is detected). At the
//! fixed point the aperture is centred within half a pixel of the marker, so a 3 px
//! motion is measured with the whole marker inside a symmetric aperture and no
//! truncation by the window edge. Everything is integer arithmetic over the raw
//! interleaved samples: no allocation, no whole-image conversion.

/// Samples the kernel can read (8- and 16-bit).
pub(crate) trait Sample: Copy {
    /// Score offset `K` (see the module docs): 8 levels of an 8-bit image.
    const OFFSET: i32;
    fn value(self) -> i32;
}

impl Sample for u8 {
    const OFFSET: i32 = 8;
    #[inline(always)]
    fn value(self) -> i32 {
        self as i32
    }
}

impl Sample for u16 {
    const OFFSET: i32 = 8 * 257;
    #[inline(always)]
    fn value(self) -> i32 {
        self as i32
    }
}

/// Channel indices `[colour, other, other]` of an RGB pixel for a layer colour.
pub(crate) fn channels(color: crate::sensor::MarkerColor) -> [usize; 3] {
    use crate::sensor::MarkerColor::*;
    match color {
        Red => [0, 1, 2],
        Green => [1, 0, 2],
        Blue => [2, 0, 1],
    }
}

/// The colour score of one pixel (see the module docs).
#[inline(always)]
pub(crate) fn score<T: Sample>(px: &[T], ch: [usize; 3]) -> i32 {
    let c = px[ch[0]].value();
    (2 * c - px[ch[1]].value() - px[ch[2]].value() + 2 * T::OFFSET).max(0)
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
}

/// Background-corrected moments of one window.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Moments {
    /// Net signal (score units × pixels).
    pub m0: f64,
    /// Centroid offset from the window centre, px.
    pub offset: [f64; 2],
}

/// Outcome of an iterated measurement.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Located {
    /// Converged: sub-pixel centroid and net signal.
    Found { centroid_px: [f64; 2], m0: f64 },
    /// The window left the image.
    OutOfImage,
    /// No positive signal in the aperture.
    NoSignal,
}

impl Window {
    /// Window with aperture radius `radius_px` (gap 1 px, background ring 2 px wide).
    pub fn new(radius_px: f64) -> Window {
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
        w
    }

    /// Half-size of the square the window reads, px.
    #[cfg(test)]
    pub fn half_px(&self) -> i32 {
        self.half
    }

    /// Background-corrected moments of the window centred on `(cx, cy)`, or `None` when
    /// the window does not fit in the image.
    #[inline]
    pub fn moments<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        ch: [usize; 3],
        cx: i32,
        cy: i32,
    ) -> Option<Moments> {
        let h = self.half;
        if cx < h || cy < h || cx + h >= img.width as i32 || cy + h >= img.height as i32 {
            return None;
        }
        let (mut s0, mut sx, mut sy) = (0i64, 0i64, 0i64);
        let (mut b0, mut bx, mut by) = (0i64, 0i64, 0i64);
        for (k, row) in self.rows.iter().enumerate() {
            let dy = k as i32 - h;
            let centre = (cy + dy) as usize * img.width + cx as usize;
            // Sum of s and of s·i over the pixels [lo, hi] of this row (i from 0).
            let span = |lo: i32, hi: i32| -> (i32, i32) {
                let start = (centre as isize + lo as isize) as usize * C;
                let end = (centre as isize + hi as isize + 1) as usize * C;
                let mut rs = 0i32;
                let mut rx = 0i32;
                for (i, px) in img.data[start..end].chunks_exact(C).enumerate() {
                    let s = score(px, ch);
                    rs += s;
                    rx += s * i as i32;
                }
                // Σ s·dx with dx = lo + i.
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
        let a = b0 as f64 / self.n_bg;
        let gx = bx as f64 / self.sxx_bg;
        let gy = by as f64 / self.syy_bg;
        let m0 = s0 as f64 - a * self.n_ap;
        let mx = sx as f64 - gx * self.sxx_ap;
        let my = sy as f64 - gy * self.syy_ap;
        if !(m0 > 0.0) {
            return Some(Moments {
                m0,
                offset: [0.0, 0.0],
            });
        }
        Some(Moments {
            m0,
            offset: [mx / m0, my / m0],
        })
    }

    /// Iterates [`Self::moments`] with re-centring from `start_px` (see module docs).
    pub fn locate<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        ch: [usize; 3],
        start_px: [f64; 2],
        max_iterations: u32,
    ) -> Located {
        if !(start_px[0].is_finite() && start_px[1].is_finite()) {
            return Located::OutOfImage;
        }
        let mut c = [start_px[0].round() as i32, start_px[1].round() as i32];
        let mut prev = [i32::MIN, i32::MIN];
        let mut last = Located::NoSignal;
        for _ in 0..max_iterations.max(1) {
            let Some(m) = self.moments(img, ch, c[0], c[1]) else {
                return Located::OutOfImage;
            };
            if !(m.m0 > 0.0) {
                return Located::NoSignal;
            }
            let est = [c[0] as f64 + m.offset[0], c[1] as f64 + m.offset[1]];
            last = Located::Found {
                centroid_px: est,
                m0: m.m0,
            };
            let next = [est[0].round() as i32, est[1].round() as i32];
            // Converged, or a two-cycle between neighbouring pixels (centroid on a
            // half-pixel boundary): either window is centred within ~0.5 px.
            if next == c || next == prev {
                return last;
            }
            prev = c;
            c = next;
        }
        last
    }

    /// Largest colour score inside the aperture centred on `(cx, cy)`.
    pub fn peak<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        ch: [usize; 3],
        cx: i32,
        cy: i32,
    ) -> Option<i32> {
        let h = self.half;
        if cx < h || cy < h || cx + h >= img.width as i32 || cy + h >= img.height as i32 {
            return None;
        }
        let mut best = 0;
        for (k, row) in self.rows.iter().enumerate() {
            if row.ap < 0 {
                continue;
            }
            let y = (cy + k as i32 - h) as usize;
            let start = (y * img.width + (cx - row.ap) as usize) * C;
            let end = (y * img.width + (cx + row.ap) as usize + 1) * C;
            for px in img.data[start..end].chunks_exact(C) {
                best = best.max(score(px, ch));
            }
        }
        Some(best)
    }
}

/// The paper's window search: centre of mass of `max(0, s − threshold)` over the square
/// of half-size `half_px` around `centre_px` (clipped to the image). Used to acquire a
/// marker that the aperture does not see. `None` when nothing exceeds the threshold.
pub(crate) fn search<T: Sample, const C: usize>(
    img: Raw<'_, T, C>,
    ch: [usize; 3],
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
            let s = (score(px, ch) - threshold).max(0) as i64;
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
    fn disc(w: usize, h: usize, c: [f64; 2], r: f64, amp: f64, bg: f64) -> Vec<u16> {
        let mut d = vec![0u16; w * h * 3];
        for y in 0..h {
            for x in 0..w {
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
                let i = (y * w + x) * 3;
                d[i] = bg as u16;
                d[i + 1] = bg as u16;
                d[i + 2] = (bg + amp * cov).round() as u16;
            }
        }
        d
    }

    #[test]
    fn window_regions_are_symmetric_and_disjoint() {
        let w = Window::new(8.0);
        assert_eq!(w.half_px(), 11);
        assert_eq!(w.sxx_ap, w.syy_ap);
        assert_eq!(w.sxx_bg, w.syy_bg);
        // Disc area within a few pixels of π r².
        assert!((w.n_ap - std::f64::consts::PI * 64.0).abs() < 12.0, "{}", w.n_ap);
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
            let w = Window::new(8.0);
            match w.locate(img, [2, 0, 1], [c[0] + 2.6, c[1] - 2.2], 10) {
                Located::Found { centroid_px, .. } => {
                    assert!((centroid_px[0] - c[0]).abs() < 0.01, "{centroid_px:?} vs {c:?}");
                    assert!((centroid_px[1] - c[1]).abs() < 0.01, "{centroid_px:?} vs {c:?}");
                }
                other => panic!("not found: {other:?}"),
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
        let w = Window::new(6.0);
        assert!(matches!(
            w.locate(img, [2, 0, 1], [20.0, 20.0], 5),
            Located::NoSignal
        ));
        assert!(matches!(
            w.locate(img, [2, 0, 1], [3.0, 20.0], 5),
            Located::OutOfImage
        ));
        assert!(matches!(
            w.locate(img, [2, 0, 1], [f64::NAN, 20.0], 5),
            Located::OutOfImage
        ));
    }
}
