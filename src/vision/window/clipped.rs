//! Windows cut by the image edge: the moments of [`Window::moments`] over the part
//! of the window that lies inside the image.
//!
//! A marker near the edge of the image whose dot lies inside it but whose window
//! (aperture, gap and background ring) does not is measured on the pixels the image
//! has. The ring is no longer symmetric about the centre, so the background plane
//! `b(dx, dy) = a + gx·dx + gy·dy` is fitted by the full 3 × 3 normal equations on the
//! ring's pixels inside the image, and the plane is subtracted from each aperture
//! pixel inside the image:
//!
//! ```text
//! M0 = Σ_ap (s − b),   Mx = Σ_ap (s − b)·dx,   My = Σ_ap (s − b)·dy
//! ```
//!
//! The aperture pixels beyond the edge are missing from these sums; they hold
//! background only (their `s − b` is noise around 0) as long as the dot itself is
//! inside, which the tracker checks ([`super::super::track`]). Scalar code: only the
//! few windows at the edge take it.

use super::{linear_score, score, Moments, Raw, Sample, Window};

/// Below this fraction of its pixels inside the image, the ring's plane fit is not
/// trusted (a corner cuts away more than a half of the ring on two sides).
const MIN_RING_FRACTION: f64 = 0.4;

/// How far beyond its radius a marker's dot must stay inside the image for a window
/// cut by the edge to measure it, px: the renderer's and a real camera's soft edge
/// (anti-aliasing, defocus) reaches about a pixel beyond the radius the detector
/// measures (`detect`: the blob's area above half contrast); a dot whose soft edge is
/// cut has lost part of its signal on one side. With it, cut windows measure as well
/// as whole ones on rendered frames (`tests/vision_tracking.rs`,
/// `windows_cut_by_the_image_edge_…`: the largest displacement error of cut windows
/// stays within the whole windows' at every clearance from 1 to 5 px).
pub(crate) const DOT_MARGIN_PX: f64 = 1.0;

/// Whether the dot of radius `radius_px` (plus [`DOT_MARGIN_PX`]) centred on
/// `centre_px` lies inside a `width` × `height` image (pixel edges at −½ and
/// `width − ½`). A dot crossing the edge has lost part of itself: its centroid is
/// biased towards the inside, and it is not measured.
pub(crate) fn dot_inside(centre_px: [f64; 2], radius_px: f64, width: usize, height: usize) -> bool {
    let r = radius_px + DOT_MARGIN_PX;
    let [x, y] = centre_px;
    x - r >= -0.5 && y - r >= -0.5 && x + r <= width as f64 - 0.5 && y + r <= height as f64 - 0.5
}

impl Window {
    /// Whether the window centred on `(cx, cy)` lies wholly inside the image.
    #[cfg(test)]
    pub(crate) fn fits<T, const C: usize>(&self, img: Raw<'_, T, C>, cx: i32, cy: i32) -> bool {
        let h = self.half;
        cx >= h && cy >= h && cx + h < img.width as i32 && cy + h < img.height as i32
    }

    /// Background-corrected moments of the window centred on `(cx, cy)` from its
    /// pixels inside the image (see the module docs); `None` when the centre pixel is
    /// outside the image, less than [`MIN_RING_FRACTION`] of the ring is inside, or the
    /// plane fit is singular. Equal to [`Window::moments`] (up to rounding) when the
    /// window fits.
    pub(crate) fn moments_clipped<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        cx: i32,
        cy: i32,
        clamped: bool,
    ) -> Option<Moments> {
        let (w, h) = (img.width as i32, img.height as i32);
        if cx < 0 || cy < 0 || cx >= w || cy >= h {
            return None;
        }
        let half = self.half;
        let wt = &self.weights;
        // Per region (0 aperture, 1 ring): n, Σx, Σy, Σxx, Σxy, Σyy, Σs, Σs·x, Σs·y.
        let mut acc = [[0.0f64; 9]; 2];
        for (k, row) in self.rows.iter().enumerate() {
            if row.outer < 0 {
                continue;
            }
            let dy = k as i32 - half;
            let y = cy + dy;
            if y < 0 || y >= h {
                continue;
            }
            let lo = (-row.outer).max(-cx);
            let hi = row.outer.min(w - 1 - cx);
            for dx in lo..=hi {
                let adx = dx.abs();
                let region = if adx <= row.ap {
                    0
                } else if adx > row.inner {
                    1
                } else {
                    continue;
                };
                let i = ((y * w + cx + dx) as usize) * C;
                let px = &img.data[i..i + C];
                let s = if clamped {
                    score::<T, C>(px, wt)
                } else {
                    linear_score::<T, C>(px, wt)
                } as f64;
                let (x, yy) = (dx as f64, dy as f64);
                let a = &mut acc[region];
                a[0] += 1.0;
                a[1] += x;
                a[2] += yy;
                a[3] += x * x;
                a[4] += x * yy;
                a[5] += yy * yy;
                a[6] += s;
                a[7] += s * x;
                a[8] += s * yy;
            }
        }
        let [ap, ring] = acc;
        if ring[0] < MIN_RING_FRACTION * self.n_bg || ap[0] == 0.0 {
            return None;
        }
        let [a, gx, gy] = solve3(
            [
                [ring[0], ring[1], ring[2]],
                [ring[1], ring[3], ring[4]],
                [ring[2], ring[4], ring[5]],
            ],
            [ring[6], ring[7], ring[8]],
        )?;
        let m0 = ap[6] - (a * ap[0] + gx * ap[1] + gy * ap[2]);
        let mx = ap[7] - (a * ap[1] + gx * ap[3] + gy * ap[4]);
        let my = ap[8] - (a * ap[2] + gx * ap[4] + gy * ap[5]);
        Some(Moments::new(m0, [mx, my], a, [gx, gy]))
    }
}

/// Solves the symmetric 3 × 3 system `m · p = b` by Cramer's rule; `None` when `m` is
/// (nearly) singular.
fn solve3(m: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(&m);
    let scale = m[0][0] * m[1][1] * m[2][2];
    if !(d.is_finite() && scale > 0.0 && d.abs() > 1e-9 * scale) {
        return None;
    }
    let mut p = [0.0; 3];
    for (k, pk) in p.iter_mut().enumerate() {
        let mut mk = m;
        for r in 0..3 {
            mk[r][k] = b[r];
        }
        *pk = det(&mk) / d;
    }
    Some(p)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A dark disc (radius 5 px, 16×16 supersampled) on a tilted background plane,
    /// 8-bit RGB: `(w, h)` image with the disc at `c`.
    fn frame(w: usize, h: usize, c: [f64; 2]) -> Vec<u8> {
        let mut d = vec![0u8; w * h * 3];
        for y in 0..h {
            for x in 0..w {
                let mut cov = 0.0;
                for sy in 0..16 {
                    for sx in 0..16 {
                        let px = x as f64 + (sx as f64 + 0.5) / 16.0 - 0.5 - c[0];
                        let py = y as f64 + (sy as f64 + 0.5) / 16.0 - 0.5 - c[1];
                        if px * px + py * py <= 25.0 {
                            cov += 1.0 / 256.0;
                        }
                    }
                }
                let bg = 180.0 + 1.5 * x as f64 - 0.8 * y as f64;
                let v = (bg - 120.0 * cov).round() as u8;
                d[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&[v; 3]);
            }
        }
        d
    }

    #[test]
    fn clipped_moments_equal_the_full_window_s_when_it_fits() {
        let win = Window::new(6.5, [-1; 3]);
        let (w, h) = (40, 40);
        let data = frame(w, h, [20.3, 19.6]);
        let img = Raw::<u8, 3> {
            data: &data,
            width: w,
            height: h,
        };
        for clamped in [false, true] {
            let a = win.moments::<u8, 3>(img, 20, 20, clamped).unwrap();
            let b = win.moments_clipped::<u8, 3>(img, 20, 20, clamped).unwrap();
            assert!((a.m0 - b.m0).abs() < 1e-6 * a.m0.abs(), "{a:?} {b:?}");
            for k in 0..2 {
                assert!((a.offset[k] - b.offset[k]).abs() < 1e-9, "{a:?} {b:?}");
                assert!((a.slope[k] - b.slope[k]).abs() < 1e-9, "{a:?} {b:?}");
            }
            assert!((a.background - b.background).abs() < 1e-9, "{a:?} {b:?}");
        }
    }

    /// A disc 7 px from the left edge on a tilted plane: the window (half-size 9) is
    /// cut by 2–3 px, the plane is extrapolated exactly (it is a plane), and the
    /// centroid is right to a few hundredths of a pixel.
    #[test]
    fn a_window_cut_by_the_edge_measures_a_dot_inside_on_a_plane() {
        let win = Window::new(6.5, [-1; 3]);
        let (w, h) = (40, 40);
        for c in [[7.0, 20.0], [7.4, 19.7], [6.6, 20.2], [20.0, 6.8]] {
            let data = frame(w, h, c);
            let img = Raw::<u8, 3> {
                data: &data,
                width: w,
                height: h,
            };
            let (cx, cy) = (c[0].round() as i32, c[1].round() as i32);
            assert!(!win.fits(img, cx, cy));
            assert!(win.moments::<u8, 3>(img, cx, cy, false).is_none());
            let m = win.moments_clipped::<u8, 3>(img, cx, cy, false).unwrap();
            let got = [cx as f64 + m.offset[0], cy as f64 + m.offset[1]];
            let e = (got[0] - c[0]).hypot(got[1] - c[1]);
            assert!(e < 0.05, "{c:?}: {got:?}, error {e:.3} px");
        }
    }
}
