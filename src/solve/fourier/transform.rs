//! The FFT pipelines of the `fourier` solver: packing displacements and forces into
//! spectra, the per-block gathers and scatters, and the transforms back.

use std::sync::Arc;

use rustfft::num_complex::Complex64;
use rustfft::{Fft, FftPlanner};

pub(super) type C64 = Complex64;

/// One marker layer that carries data.
#[derive(Debug, Clone, Copy)]
pub(super) struct LayerPlan {
    /// Markers per axis.
    pub(super) nm: [usize; 2],
}

/// Everything fixed after precompute: sizes, index maps, FFT plans.
pub(super) struct Plan {
    pub(super) a: usize,
    pub(super) b: usize,
    /// Blocks per axis.
    pub(super) m: [usize; 2],
    /// Marker lattice period per axis (`a·m`).
    pub(super) mm: [usize; 2],
    /// Force lattice period per axis (`b·m`).
    pub(super) mf: [usize; 2],
    /// Force grid size per axis.
    pub(super) nf: [usize; 2],
    pub(super) layers: Vec<LayerPlan>,
    pub(super) rows: usize,
    pub(super) cols: usize,
    /// Processed blocks (`c_x ≤ M_x/2`).
    pub(super) blocks: Vec<[usize; 2]>,
    /// For each input marker: (layer slot, row-major index `iy·mm_x + ix` in its buffer).
    pub(super) site_map: Vec<(usize, usize)>,
    /// Per layer, edge-bridge weights of the padding columns / rows.
    pub(super) bridge_x: Vec<Vec<f64>>,
    pub(super) bridge_y: Vec<Vec<f64>>,
    /// `1/√(#marker lattice · #force lattice)`: the DFT normalisation of both pipelines.
    pub(super) scale: f64,
    pub(super) fwd_mx: Arc<dyn Fft<f64>>,
    pub(super) fwd_my: Arc<dyn Fft<f64>>,
    pub(super) inv_mx: Arc<dyn Fft<f64>>,
    pub(super) inv_my: Arc<dyn Fft<f64>>,
    pub(super) fwd_fx: Arc<dyn Fft<f64>>,
    pub(super) fwd_fy: Arc<dyn Fft<f64>>,
    pub(super) inv_fx: Arc<dyn Fft<f64>>,
    pub(super) inv_fy: Arc<dyn Fft<f64>>,
}

/// Per-frame buffers, allocated once.
#[derive(Clone)]
pub(super) struct Work {
    pub(super) scratch: Vec<C64>,
    /// Per layer: `nm_y × mm_x`, row-major (the rows of the marker lattice that hold data).
    pub(super) z: Vec<Vec<C64>>,
    /// Per layer: spectrum `mm_x × mm_y` (transposed layout `[px][py]`).
    pub(super) spec: Vec<Vec<C64>>,
    /// Force spectra `mf_x × mf_y` (`[qx][qy]`) of `fx + i·fy` and `fz`.
    pub(super) gxy: Vec<C64>,
    pub(super) gz: Vec<C64>,
    /// Force-grid rows `nf_y × mf_x` of `fx + i·fy` and `fz`.
    pub(super) hxy: Vec<C64>,
    pub(super) hz: Vec<C64>,
    /// Output spectra of the preconditioner (`mf_x × mf_y`).
    pub(super) gtmp_xy: Vec<C64>,
    pub(super) gtmp_z: Vec<C64>,
    /// One block's input and output.
    pub(super) vin: Vec<C64>,
    pub(super) vout: Vec<C64>,
    /// CGLS vectors: markers (`r`, `q`) and forces (`s`, `p`).
    pub(super) r: Vec<f64>,
    pub(super) q: Vec<f64>,
    pub(super) s: Vec<f64>,
    pub(super) p: Vec<f64>,
    /// Preconditioned gradient `M s` (forces).
    pub(super) zf: Vec<f64>,
}

/// Index of `−i` modulo `n` for `i < n` (no integer division in the hot loops).
#[inline(always)]
pub(super) fn neg(i: usize, n: usize) -> usize {
    if i == 0 {
        0
    } else {
        n - i
    }
}

/// Cache-friendly out-of-place transpose: `dst[c·dst_stride + r] = src[r·src_stride + c]`
/// for `r < rows`, `c < cols`.
pub(super) fn transpose(
    src: &[C64],
    src_stride: usize,
    dst: &mut [C64],
    dst_stride: usize,
    rows: usize,
    cols: usize,
) {
    const T: usize = 16;
    for r0 in (0..rows).step_by(T) {
        let r1 = (r0 + T).min(rows);
        for c0 in (0..cols).step_by(T) {
            let c1 = (c0 + T).min(cols);
            for r in r0..r1 {
                let row = &src[r * src_stride..];
                for c in c0..c1 {
                    dst[c * dst_stride + r] = row[c];
                }
            }
        }
    }
}

/// Unnormalised forward 2-D DFT of a row-major `ny × nx` array; returns the spectrum in
/// transposed layout `[qx][qy]` (precompute only: allocates).
pub(super) fn fft2_transposed(
    planner: &mut FftPlanner<f64>,
    data: &mut [C64],
    nx: usize,
    ny: usize,
) -> Vec<C64> {
    let fx = planner.plan_fft_forward(nx);
    let fy = planner.plan_fft_forward(ny);
    let mut scratch = vec![
        C64::default();
        fx.get_inplace_scratch_len()
            .max(fy.get_inplace_scratch_len())
    ];
    fx.process_with_scratch(data, &mut scratch);
    let mut out = vec![C64::default(); nx * ny];
    transpose(data, nx, &mut out, ny, ny, nx);
    fy.process_with_scratch(&mut out, &mut scratch);
    out
}

/// Scatters a displacement vector (times `in_scale`) into the layer buffers and
/// transforms it: afterwards `w.spec[slot]` holds the unnormalised DFT of `ux + i·uy`.
pub(super) fn markers_to_spectra(
    plan: &Plan,
    w: &mut Work,
    u: &[f64],
    in_scale: f64,
    bridge: bool,
) {
    let [mmx, mmy] = plan.mm;
    for (z, lp) in w.z.iter_mut().zip(&plan.layers) {
        z[..lp.nm[1] * mmx].fill(C64::default());
    }
    for (k, &(slot, idx)) in plan.site_map.iter().enumerate() {
        w.z[slot][idx] = C64::new(u[2 * k] * in_scale, u[2 * k + 1] * in_scale);
    }
    for (slot, lp) in plan.layers.iter().enumerate() {
        let [nmx, nmy] = lp.nm;
        let z = &mut w.z[slot];
        if bridge {
            // Along x in space, row by row.
            let wx = &plan.bridge_x[slot];
            for row in z[..nmy * mmx].chunks_exact_mut(mmx) {
                let (first, last) = (row[0], row[nmx - 1]);
                for (v, &s) in row[nmx..].iter_mut().zip(wx) {
                    *v = last * (1.0 - s) + first * s;
                }
            }
        }
        plan.fwd_mx
            .process_with_scratch(&mut z[..nmy * mmx], &mut w.scratch);
        let rows = if bridge {
            // Along y: the padding rows are blends of the first and last data row, and
            // the row transform is linear, so blend the transformed rows (saves the FFTs).
            let wy = &plan.bridge_y[slot];
            let (data, pad) = z.split_at_mut(nmy * mmx);
            let (first, last) = (&data[..mmx], &data[(nmy - 1) * mmx..]);
            for (row, &s) in pad.chunks_exact_mut(mmx).zip(wy) {
                for ((v, f), l) in row.iter_mut().zip(first).zip(last) {
                    *v = l * (1.0 - s) + f * s;
                }
            }
            mmy
        } else {
            nmy
        };
        let spec = &mut w.spec[slot];
        transpose(z, mmx, spec, mmy, rows, mmx);
        // Rows of the lattice beyond the used rows are zero.
        if rows < mmy {
            for px in 0..mmx {
                spec[px * mmy + rows..(px + 1) * mmy].fill(C64::default());
            }
        }
        plan.fwd_my.process_with_scratch(spec, &mut w.scratch);
    }
}

/// Raised-cosine weights of the opposite edge for the `gap` padding nodes between the
/// last data node and the first one (periodically): 0 at the last node, 1 at the first.
pub(super) fn bridge_weights(gap: usize) -> Vec<f64> {
    (1..=gap)
        .map(|k| 0.5 * (1.0 - (std::f64::consts::PI * k as f64 / (gap + 1) as f64).cos()))
        .collect()
}

/// Gathers the marker values of block `c` as `(Ux, Uy)` per (layer, s'y, s'x), separated
/// from the packed spectra by conjugate symmetry (unnormalised DFT scale).
#[inline]
pub(super) fn gather_marker_block(plan: &Plan, spec: &[Vec<C64>], c: [usize; 2], out: &mut [C64]) {
    let (a, [mx, my], [mmx, mmy]) = (plan.a, plan.m, plan.mm);
    let mut r = 0;
    for sp in spec {
        for sy in 0..a {
            let py = c[1] + sy * my;
            let ny = neg(py, mmy);
            for sx in 0..a {
                let px = c[0] + sx * mx;
                let nx = neg(px, mmx);
                let s = sp[px * mmy + py];
                let sn = sp[nx * mmy + ny].conj();
                out[r] = (s + sn) * 0.5;
                let d = (s - sn) * 0.5;
                out[r + 1] = C64::new(d.im, -d.re); // −i·d
                r += 2;
            }
        }
    }
}

/// Markers → forces through per-block matrices: `P` (`cols × rows`, direct solve) or the
/// adjoint of `A` (`rows × cols`, for `Hᵀ`).
#[allow(clippy::too_many_arguments)]
pub(super) fn markers_to_forces(
    plan: &Plan,
    w: &mut Work,
    mats: &[C64],
    adjoint: bool,
    u: &[f64],
    in_scale: f64,
    bridge: bool,
    f: &mut [f64],
) {
    markers_to_spectra(plan, w, u, in_scale, bridge);
    let (rows, cols) = (plan.rows, plan.cols);
    for (bi, &c) in plan.blocks.iter().enumerate() {
        gather_marker_block(plan, &w.spec, c, &mut w.vin);
        let mat = &mats[bi * rows * cols..(bi + 1) * rows * cols];
        let vin = &w.vin[..rows];
        let vout = &mut w.vout[..cols];
        if adjoint {
            vout.fill(C64::default());
            for (r, &v) in vin.iter().enumerate() {
                let row = &mat[r * cols..(r + 1) * cols];
                for (o, m) in vout.iter_mut().zip(row) {
                    *o += m.conj() * v;
                }
            }
        } else {
            for (j, o) in vout.iter_mut().enumerate() {
                let row = &mat[j * rows..(j + 1) * rows];
                *o = row.iter().zip(vin).map(|(m, v)| m * v).sum();
            }
        }
        scatter_force_block(plan, c, &w.vout[..cols], &mut w.gxy, &mut w.gz);
    }
    let ForceBufs {
        gxy,
        gz,
        hxy,
        hz,
        scratch,
    } = w.force_bufs();
    spectra_to_forces(plan, gxy, gz, hxy, hz, scratch, plan.scale, f);
}

/// Borrowed force-side buffers (split borrows of [`Work`]).
pub(super) struct ForceBufs<'a> {
    pub(super) gxy: &'a mut [C64],
    pub(super) gz: &'a mut [C64],
    pub(super) hxy: &'a mut [C64],
    pub(super) hz: &'a mut [C64],
    pub(super) scratch: &'a mut [C64],
}

impl Work {
    fn force_bufs(&mut self) -> ForceBufs<'_> {
        ForceBufs {
            gxy: &mut self.gxy,
            gz: &mut self.gz,
            hxy: &mut self.hxy,
            hz: &mut self.hz,
            scratch: &mut self.scratch,
        }
    }
}

/// Writes one block's force spectrum `(Fx, Fy, Fz)` per (s_y, s_x) into the packed
/// spectra of `fx + i·fy` and `fz`, and its Hermitian partner at `−q`.
#[inline]
pub(super) fn scatter_force_block(
    plan: &Plan,
    c: [usize; 2],
    v: &[C64],
    gxy: &mut [C64],
    gz: &mut [C64],
) {
    let (b, [mx, my], [mfx, mfy]) = (plan.b, plan.m, plan.mf);
    let mut j = 0;
    for sy in 0..b {
        let qy = c[1] + sy * my;
        let ny = neg(qy, mfy);
        for sx in 0..b {
            let qx = c[0] + sx * mx;
            let nx = neg(qx, mfx);
            let (fx, fy, fz) = (v[j], v[j + 1], v[j + 2]);
            let q = qx * mfy + qy;
            let nq = nx * mfy + ny;
            gxy[q] = fx + C64::new(-fy.im, fy.re); // Fx + i·Fy
            gz[q] = fz;
            gxy[nq] = fx.conj() + C64::new(fy.im, fy.re); // conj(Fx) + i·conj(Fy)
            gz[nq] = fz.conj();
            j += 3;
        }
    }
}

/// Reads one block's force spectrum `(Fx, Fy, Fz)` per (s_y, s_x) from the packed spectra.
#[inline]
pub(super) fn gather_force_block(
    plan: &Plan,
    c: [usize; 2],
    gxy: &[C64],
    gz: &[C64],
    out: &mut [C64],
) {
    let (b, [mx, my], [mfx, mfy]) = (plan.b, plan.m, plan.mf);
    let mut j = 0;
    for sy in 0..b {
        let qy = c[1] + sy * my;
        let ny = neg(qy, mfy);
        for sx in 0..b {
            let qx = c[0] + sx * mx;
            let nx = neg(qx, mfx);
            let g = gxy[qx * mfy + qy];
            let gn = gxy[nx * mfy + ny].conj();
            out[j] = (g + gn) * 0.5;
            let d = (g - gn) * 0.5;
            out[j + 1] = C64::new(d.im, -d.re); // −i·d
            out[j + 2] = gz[qx * mfy + qy];
            j += 3;
        }
    }
}

/// Inverse transform of the packed force spectra (along y for every qx, then along x for
/// the force-grid rows only) and crop to the force grid, times `scale`.
#[allow(clippy::too_many_arguments)]
pub(super) fn spectra_to_forces(
    plan: &Plan,
    gxy: &mut [C64],
    gz: &mut [C64],
    hxy: &mut [C64],
    hz: &mut [C64],
    scratch: &mut [C64],
    scale: f64,
    f: &mut [f64],
) {
    let ([nfx, nfy], [mfx, mfy]) = (plan.nf, plan.mf);
    for (g, hbuf) in [(&mut *gxy, &mut *hxy), (&mut *gz, &mut *hz)] {
        plan.inv_fy.process_with_scratch(g, scratch);
        transpose(g, mfy, hbuf, mfx, mfx, nfy);
        plan.inv_fx.process_with_scratch(hbuf, scratch);
    }
    for jy in 0..nfy {
        for jx in 0..nfx {
            let k = jy * nfx + jx;
            let i = jy * mfx + jx;
            f[3 * k] = hxy[i].re * scale;
            f[3 * k + 1] = hxy[i].im * scale;
            f[3 * k + 2] = hz[i].re * scale;
        }
    }
}

/// Scatters a force vector into the force-grid rows and transforms it: afterwards
/// `gxy`, `gz` hold the unnormalised DFTs of `fx + i·fy` and `fz` on the force lattice.
pub(super) fn forces_to_spectra(plan: &Plan, w: &mut Work, f: &[f64]) {
    let ([nfx, nfy], [mfx, mfy]) = (plan.nf, plan.mf);
    for jy in 0..nfy {
        for jx in 0..nfx {
            let k = jy * nfx + jx;
            w.hxy[jy * mfx + jx] = C64::new(f[3 * k], f[3 * k + 1]);
            w.hz[jy * mfx + jx] = C64::new(f[3 * k + 2], 0.0);
        }
        w.hxy[jy * mfx + nfx..(jy + 1) * mfx].fill(C64::default());
        w.hz[jy * mfx + nfx..(jy + 1) * mfx].fill(C64::default());
    }
    for (hbuf, g) in [(&mut w.hxy, &mut w.gxy), (&mut w.hz, &mut w.gz)] {
        plan.fwd_fx.process_with_scratch(hbuf, &mut w.scratch);
        transpose(hbuf, mfx, g, mfy, nfy, mfx);
        for qx in 0..mfx {
            g[qx * mfy + nfy..(qx + 1) * mfy].fill(C64::default());
        }
        plan.fwd_fy.process_with_scratch(g, &mut w.scratch);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transpose_moves_every_element() {
        let src: Vec<C64> = (0..35).map(|i| C64::new(i as f64, 0.0)).collect();
        let mut dst = vec![C64::default(); 35];
        transpose(&src, 7, &mut dst, 5, 5, 7);
        for r in 0..5 {
            for c in 0..7 {
                assert_eq!(dst[c * 5 + r], src[r * 7 + c]);
            }
        }
    }
}
