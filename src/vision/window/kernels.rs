//! The linear kernel's weight layout and its SIMD variants: the row sums
//! `[Σs, Σs·dx, Σs·dy]` of the aperture and of the background ring (see the parent
//! module's docs for what they measure) as integer dot products of whole window rows
//! with precomputed per-sample weights.
//!
//! One scalar kernel and four explicit x86-64 ones, chosen at run time from the CPU's
//! features ([`Window::new`] detects them): AVX2 (16 samples per `vpmaddwd`), AVX-512
//! F+BW on 16-bit lanes (32 per `vpmaddwd`), AVX-512 on bytes (64 per `vpmaddubsw`,
//! when every weight fits a byte of at most ±[`MAX_BYTE_WEIGHT`]) and AVX-512 VNNI
//! (64 per `vpdpbusd`). All sums are integers and every path gives the scalar
//! kernel's sums bit for bit (the tests below compare them window by window). The
//! window's geometry, its plane fit and its re-centring stay in the parent module;
//! this file only adds up samples.

use super::{Raw, Sample, Window};

/// One row of the linear kernel: samples `[start, start + len)` of the row `dy`,
/// beginning at pixel `dx = lo`; weights at `offset` in the weight arrays.
#[derive(Debug, Clone, Copy)]
struct LinearRow {
    dy: i32,
    lo: i32,
    offset: usize,
    len: usize,
    /// Start of this row's blocks in [`LinearWeights::blocks`].
    block_offset: usize,
    /// Blocks of [`LANES`] samples covering `len` (the last one zero-padded).
    blocks: usize,
    /// Start of this row's blocks in [`LinearWeights::blocks512`].
    block512_offset: usize,
    /// Blocks of [`LANES512`] samples covering `len` (the last one zero-padded).
    blocks512: usize,
    /// Start of this row's blocks in [`LinearWeights::bytes512`].
    byte_block_offset: usize,
    /// Blocks of [`BYTES512`] samples covering `len` (the last one zero-padded).
    byte_blocks: usize,
}

/// The index in [`Window::linear`] of the weights for `channels` samples per pixel.
#[inline(always)]
pub(super) const fn layout(channels: usize) -> usize {
    match channels {
        1 => 2,
        4 => 1,
        _ => 0,
    }
}

/// Samples per block of the SIMD kernel (one 256-bit register of 16-bit lanes).
const LANES: usize = 16;

/// Samples per block of the AVX-512 kernel (one 512-bit register of 16-bit lanes).
const LANES512: usize = 32;

/// Samples per block of the AVX-512 byte kernel (one 512-bit register of 8-bit lanes).
const BYTES512: usize = 64;

/// Largest |weight| the byte kernel takes: `vpmaddubsw` adds two `u8 × i8` products
/// into an i16 with saturation, and 2 × 255 × 64 = 32640 stays below 2¹⁵.
const MAX_BYTE_WEIGHT: i16 = 64;

/// Per-sample weights of the linear kernel for one pixel layout and colour: the score
/// `3·I_c − (R + G + B)` times aperture / ring membership, and times `dx`. Summing
/// `sample × weight` over whole contiguous rows is a plain integer dot product that
/// the compiler vectorises, with no de-interleaving of the RGB samples.
#[derive(Debug, Clone, Default)]
pub(super) struct LinearWeights {
    rows: Vec<LinearRow>,
    ap: Vec<i16>,
    ap_dx: Vec<i16>,
    ring: Vec<i16>,
    ring_dx: Vec<i16>,
    /// The same weights for the SIMD kernel: per block of [`LANES`] samples, the
    /// `ap`, `ap_dx`, `ring`, `ring_dx` weights of those samples one after the other
    /// (`4 × LANES` values), zero beyond the row's end.
    blocks: Vec<i16>,
    /// As `blocks`, in blocks of [`LANES512`] samples for the AVX-512 kernel.
    blocks512: Vec<i16>,
    /// As `blocks`, as bytes, in blocks of [`BYTES512`] samples for the AVX-512 byte
    /// kernel; empty when a weight exceeds [`MAX_BYTE_WEIGHT`] (windows wider than
    /// 2 × 32 px with colour weight 2), which then take the 16-bit kernel.
    bytes512: Vec<ByteBlock>,
    /// [`sums_u8_vnni`] may take these byte weights: the rows are consecutive (`dy`
    /// one apart, which its running sums for `Σ s·dy` need) and no lane of its i32
    /// accumulators can overflow (checked in [`Window::linear_weights`]).
    vnni: bool,
}

/// 64 byte weights on a cache line of their own: a 512-bit load of a block never
/// straddles two lines (a split load costs two L1 accesses).
#[derive(Debug, Clone, Copy)]
#[repr(C, align(64))]
struct ByteBlock([i8; BYTES512]);

impl Window {
    pub(super) fn linear_weights(&self, channels: usize) -> LinearWeights {
        let mut lw = LinearWeights::default();
        // The byte kernel's weights, packed as i16 first (all rows), kept when they fit.
        let mut byte_weights: Vec<i16> = Vec::new();
        let h = self.half;
        for (k, row) in self.rows.iter().enumerate() {
            if row.outer < 0 {
                continue;
            }
            let lo = -row.outer;
            let offset = lw.ap.len();
            for dx in lo..=row.outer {
                let adx = dx.abs();
                let in_ap = adx <= row.ap;
                let in_ring = adx > row.inner && adx <= row.outer;
                for c in 0..channels {
                    // A grey sample stands for (g, g, g): the weights' sum.
                    let cw = match (channels, c) {
                        (1, _) => self.weights.iter().sum::<i32>() as i16,
                        (_, 0..=2) => self.weights[c] as i16,
                        _ => 0,
                    };
                    let (a, r) = (cw * in_ap as i16, cw * in_ring as i16);
                    lw.ap.push(a);
                    lw.ap_dx.push(a * dx as i16);
                    lw.ring.push(r);
                    lw.ring_dx.push(r * dx as i16);
                }
            }
            let len = lw.ap.len() - offset;
            // Per block of `lanes` samples: the four weight vectors one after the other.
            let pack = |lanes: usize, out: &mut Vec<i16>| -> (usize, usize) {
                let (start, blocks) = (out.len(), len.div_ceil(lanes));
                for b in 0..blocks {
                    for arr in [&lw.ap, &lw.ap_dx, &lw.ring, &lw.ring_dx] {
                        for l in 0..lanes {
                            let i = b * lanes + l;
                            out.push(if i < len { arr[offset + i] } else { 0 });
                        }
                    }
                }
                (start, blocks)
            };
            let mut packed = std::mem::take(&mut lw.blocks);
            let (block_offset, blocks) = pack(LANES, &mut packed);
            let mut packed512 = std::mem::take(&mut lw.blocks512);
            let (block512_offset, blocks512) = pack(LANES512, &mut packed512);
            let (byte_block_offset, byte_blocks) = pack(BYTES512, &mut byte_weights);
            lw.blocks = packed;
            lw.blocks512 = packed512;
            lw.rows.push(LinearRow {
                dy: k as i32 - h,
                lo,
                offset,
                len,
                block_offset,
                blocks,
                block512_offset,
                blocks512,
                byte_block_offset,
                byte_blocks,
            });
        }
        if byte_weights.iter().all(|w| w.abs() <= MAX_BYTE_WEIGHT) {
            // `byte_weights` holds whole blocks (4 × 64 weights each).
            lw.bytes512 = byte_weights
                .chunks_exact(BYTES512)
                .map(|c| ByteBlock(std::array::from_fn(|k| c[k] as i8)))
                .collect();
            // Per lane, a block adds at most 4 × 255 × max|w| to a row sum; the running
            // sum of the rows' prefix sums reaches n(n + 1)/2 row sums.
            let max_w = byte_weights.iter().map(|w| w.unsigned_abs() as u64).max();
            let max_blocks = lw.rows.iter().map(|r| r.byte_blocks as u64).max();
            let n = lw.rows.len() as u64;
            let consecutive = lw.rows.windows(2).all(|p| p[1].dy == p[0].dy + 1);
            lw.vnni = consecutive
                && max_w
                    .zip(max_blocks)
                    .is_some_and(|(w, b)| n * (n + 1) / 2 * b * 4 * 255 * w <= i32::MAX as u64);
        }
        lw
    }

    /// Aperture and ring sums `[Σs, Σs·dx, Σs·dy]` ×2 with the linear score
    /// `3·I_c − (R + G + B)`, as dot products of whole rows with precomputed weights.
    #[inline]
    pub(super) fn sums_linear<T: Sample, const C: usize>(
        &self,
        img: Raw<'_, T, C>,
        cx: i32,
        cy: i32,
    ) -> [i64; 6] {
        let lw = &self.linear[layout(C)];
        // The last block of the window's last row may read past the row's end
        // (weights 0 there) but must stay inside the buffer.
        let last_read = |lanes: usize, blocks: fn(&LinearRow) -> usize| {
            lw.rows.last().map_or(0, |r| {
                ((cy + r.dy) as usize * img.width + (cx + r.lo) as usize) * C + blocks(r) * lanes
            })
        };
        #[cfg(target_arch = "x86_64")]
        if self.vnni && self.byte_kernel && lw.vnni {
            if let Some(bytes) = T::as_bytes(img.data) {
                if last_read(BYTES512, |r| r.byte_blocks) <= bytes.len() {
                    // SAFETY: AVX-512 F/BW/VNNI were detected at run time
                    // (`Window::new`), every block read lies inside `bytes` (checked just
                    // above), and `lw.vnni` holds (consecutive rows, no overflow).
                    return unsafe { sums_u8_vnni::<C>(lw, bytes, img.width, cx, cy) };
                }
            }
        }
        #[cfg(target_arch = "x86_64")]
        if self.avx512 && self.byte_kernel && !lw.bytes512.is_empty() {
            if let Some(bytes) = T::as_bytes(img.data) {
                if last_read(BYTES512, |r| r.byte_blocks) <= bytes.len() {
                    // SAFETY: AVX-512 F/BW were detected at run time (`Window::new`),
                    // and every block read lies inside `bytes` (checked just above).
                    return unsafe { sums_u8_avx512_bytes::<C>(lw, bytes, img.width, cx, cy) };
                }
            }
        }
        #[cfg(target_arch = "x86_64")]
        if self.avx512 {
            if let Some(bytes) = T::as_bytes(img.data) {
                if last_read(LANES512, |r| r.blocks512) <= bytes.len() {
                    // SAFETY: AVX-512 F/BW were detected at run time (`Window::new`),
                    // and every block read lies inside `bytes` (checked just above).
                    return unsafe { sums_u8_avx512::<C>(lw, bytes, img.width, cx, cy) };
                }
            }
        }
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            if let Some(bytes) = T::as_bytes(img.data) {
                if last_read(LANES, |r| r.blocks) <= bytes.len() {
                    // SAFETY: AVX2 was detected at run time (`Window::new`), and every
                    // block read lies inside `bytes` (checked just above: rows are in
                    // increasing address order, the last ends furthest).
                    return unsafe { sums_u8_avx2::<C>(lw, bytes, img.width, cx, cy) };
                }
            }
        }
        let mut t = [0i64; 6];
        for r in &lw.rows {
            let start = ((cy + r.dy) as usize * img.width + (cx + r.lo) as usize) * C;
            let data = &img.data[start..start + r.len];
            let w = r.offset..r.offset + r.len;
            let (mut a0, mut a1, mut b0, mut b1) = (0i32, 0i32, 0i32, 0i32);
            for ((((v, &wa), &wax), &wb), &wbx) in data
                .iter()
                .zip(&lw.ap[w.clone()])
                .zip(&lw.ap_dx[w.clone()])
                .zip(&lw.ring[w.clone()])
                .zip(&lw.ring_dx[w])
            {
                let v = v.value();
                a0 += v * wa as i32;
                a1 += v * wax as i32;
                b0 += v * wb as i32;
                b1 += v * wbx as i32;
            }
            let dy = r.dy as i64;
            t[0] += a0 as i64;
            t[1] += a1 as i64;
            t[2] += a0 as i64 * dy;
            t[3] += b0 as i64;
            t[4] += b1 as i64;
            t[5] += b0 as i64 * dy;
        }
        t
    }
}

/// [`Window::sums_linear`] for 8-bit samples with AVX2: per block of 16 samples, one
/// widening load and four `vpmaddwd` (16 × i16·i16 → 8 × i32) against the block's
/// four weight vectors. Per-row sums of the `Σs` terms are multiplied by `dy` in
/// vector registers, so there is a single horizontal reduction per window. The integer
/// sums are exactly those of the scalar kernel (no overflow: |sample × weight| ≤
/// 255 × 3 × 18 per lane, < 2³¹ summed over a window), so results are bit-identical.
///
/// # Safety
/// The CPU must support AVX2, and for every row `r` of `lw` the `r.blocks × 16` bytes
/// from the row's start `((cy + r.dy)·width + cx + r.lo)·C` must lie inside `data`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn sums_u8_avx2<const C: usize>(
    lw: &LinearWeights,
    data: &[u8],
    width: usize,
    cx: i32,
    cy: i32,
) -> [i64; 6] {
    use std::arch::x86_64::*;
    let z = _mm256_setzero_si256();
    let (mut a0, mut a1, mut a0y, mut b0, mut b1, mut b0y) = (z, z, z, z, z, z);
    let w = lw.blocks.as_ptr();
    for r in &lw.rows {
        let start = ((cy + r.dy) as usize * width + (cx + r.lo) as usize) * C;
        let p = data.as_ptr().add(start);
        let (mut ra0, mut rb0) = (z, z);
        for b in 0..r.blocks {
            let v = _mm256_cvtepu8_epi16(_mm_loadu_si128(p.add(b * LANES) as *const __m128i));
            let wb = w.add(r.block_offset + b * 4 * LANES) as *const __m256i;
            ra0 = _mm256_add_epi32(ra0, _mm256_madd_epi16(v, _mm256_loadu_si256(wb)));
            a1 = _mm256_add_epi32(a1, _mm256_madd_epi16(v, _mm256_loadu_si256(wb.add(1))));
            rb0 = _mm256_add_epi32(rb0, _mm256_madd_epi16(v, _mm256_loadu_si256(wb.add(2))));
            b1 = _mm256_add_epi32(b1, _mm256_madd_epi16(v, _mm256_loadu_si256(wb.add(3))));
        }
        let dy = _mm256_set1_epi32(r.dy);
        a0 = _mm256_add_epi32(a0, ra0);
        a0y = _mm256_add_epi32(a0y, _mm256_mullo_epi32(ra0, dy));
        b0 = _mm256_add_epi32(b0, rb0);
        b0y = _mm256_add_epi32(b0y, _mm256_mullo_epi32(rb0, dy));
    }
    let hsum = |v: __m256i| -> i64 {
        let mut lanes = [0i32; 8];
        _mm256_storeu_si256(lanes.as_mut_ptr() as *mut __m256i, v);
        lanes.iter().map(|&x| x as i64).sum()
    };
    [hsum(a0), hsum(a1), hsum(a0y), hsum(b0), hsum(b1), hsum(b0y)]
}

/// [`sums_u8_avx2`] with 512-bit registers: 32 samples per block (one widening
/// 256-bit load, four `vpmaddwd` of 32 × i16), so a window row of the paper sensor
/// (≤ 19 px × 3 samples) takes two blocks instead of four. Same integer sums, bit-identical.
///
/// # Safety
/// The CPU must support AVX-512 F and BW, and for every row `r` of `lw` the
/// `r.blocks512 × 32` bytes from the row's start must lie inside `data`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw")]
unsafe fn sums_u8_avx512<const C: usize>(
    lw: &LinearWeights,
    data: &[u8],
    width: usize,
    cx: i32,
    cy: i32,
) -> [i64; 6] {
    use std::arch::x86_64::*;
    let z = _mm512_setzero_si512();
    let (mut a0, mut a1, mut a0y, mut b0, mut b1, mut b0y) = (z, z, z, z, z, z);
    let w = lw.blocks512.as_ptr();
    for r in &lw.rows {
        let start = ((cy + r.dy) as usize * width + (cx + r.lo) as usize) * C;
        let p = data.as_ptr().add(start);
        let (mut ra0, mut rb0) = (z, z);
        for b in 0..r.blocks512 {
            let v = _mm512_cvtepu8_epi16(_mm256_loadu_si256(p.add(b * LANES512) as *const __m256i));
            let wb = w.add(r.block512_offset + b * 4 * LANES512) as *const __m512i;
            ra0 = _mm512_add_epi32(ra0, _mm512_madd_epi16(v, _mm512_loadu_si512(wb)));
            a1 = _mm512_add_epi32(a1, _mm512_madd_epi16(v, _mm512_loadu_si512(wb.add(1))));
            rb0 = _mm512_add_epi32(rb0, _mm512_madd_epi16(v, _mm512_loadu_si512(wb.add(2))));
            b1 = _mm512_add_epi32(b1, _mm512_madd_epi16(v, _mm512_loadu_si512(wb.add(3))));
        }
        let dy = _mm512_set1_epi32(r.dy);
        a0 = _mm512_add_epi32(a0, ra0);
        a0y = _mm512_add_epi32(a0y, _mm512_mullo_epi32(ra0, dy));
        b0 = _mm512_add_epi32(b0, rb0);
        b0y = _mm512_add_epi32(b0y, _mm512_mullo_epi32(rb0, dy));
    }
    let hsum = |v: __m512i| -> i64 { _mm512_reduce_add_epi32(v) as i64 };
    [hsum(a0), hsum(a1), hsum(a0y), hsum(b0), hsum(b1), hsum(b0y)]
}

/// [`sums_u8_avx512`] on bytes: 64 samples per block, one plain 512-bit load and
/// four `vpmaddubsw` (64 × u8·i8 → 32 × i16, pairs added) against the block's four
/// byte-weight vectors, each widened and pair-added into i32 lanes by `vpmaddwd` with
/// ones. A window row of the paper sensor (≤ 63 samples) is one block instead of two,
/// with no widening load. The i16 pair sums cannot saturate (|weight| ≤
/// [`MAX_BYTE_WEIGHT`]), so the integer sums are those of the other kernels,
/// bit-identical.
///
/// # Safety
/// The CPU must support AVX-512 F and BW, `lw.bytes512` must hold the byte weights,
/// and for every row `r` of `lw` the `r.byte_blocks × 64` bytes from the row's start
/// must lie inside `data`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw")]
unsafe fn sums_u8_avx512_bytes<const C: usize>(
    lw: &LinearWeights,
    data: &[u8],
    width: usize,
    cx: i32,
    cy: i32,
) -> [i64; 6] {
    use std::arch::x86_64::*;
    let z = _mm512_setzero_si512();
    let ones = _mm512_set1_epi16(1);
    let (mut a0, mut a1, mut a0y, mut b0, mut b1, mut b0y) = (z, z, z, z, z, z);
    let w = lw.bytes512.as_ptr() as *const i8;
    for r in &lw.rows {
        let start = ((cy + r.dy) as usize * width + (cx + r.lo) as usize) * C;
        let p = data.as_ptr().add(start);
        let (mut ra0, mut rb0) = (z, z);
        for b in 0..r.byte_blocks {
            let v = _mm512_loadu_si512(p.add(b * BYTES512) as *const __m512i);
            let wb = w.add(r.byte_block_offset + b * 4 * BYTES512) as *const __m512i;
            let dot = |k: usize| {
                _mm512_madd_epi16(_mm512_maddubs_epi16(v, _mm512_loadu_si512(wb.add(k))), ones)
            };
            ra0 = _mm512_add_epi32(ra0, dot(0));
            a1 = _mm512_add_epi32(a1, dot(1));
            rb0 = _mm512_add_epi32(rb0, dot(2));
            b1 = _mm512_add_epi32(b1, dot(3));
        }
        let dy = _mm512_set1_epi32(r.dy);
        a0 = _mm512_add_epi32(a0, ra0);
        a0y = _mm512_add_epi32(a0y, _mm512_mullo_epi32(ra0, dy));
        b0 = _mm512_add_epi32(b0, rb0);
        b0y = _mm512_add_epi32(b0y, _mm512_mullo_epi32(rb0, dy));
    }
    let hsum = |v: __m512i| -> i64 { _mm512_reduce_add_epi32(v) as i64 };
    [hsum(a0), hsum(a1), hsum(a0y), hsum(b0), hsum(b1), hsum(b0y)]
}

/// [`sums_u8_avx512_bytes`] with VNNI: per block and moment one `vpdpbusd` (64 ×
/// u8·i8, four adjacent products summed into each i32 lane and accumulated, no
/// intermediate saturation) instead of `vpmaddubsw` + `vpmaddwd` + `vpaddd`; and the
/// `Σ s·dy` moments from running sums instead of a multiply per row: with row sums
/// `S_r` (r = 0…n−1, `dy = dy₀ + r`), `A = Σ S_r` and `P = Σ_k Σ_{r≤k} S_r = Σ_r (n −
/// r) S_r`, `Σ dy·S_r = (dy₀ + n)·A − P`. Integer sums, bit-identical to the other
/// kernels.
///
/// # Safety
/// The CPU must support AVX-512 F, BW and VNNI, `lw.bytes512` must hold the byte
/// weights with `lw.vnni` set, and for every row `r` of `lw` the `r.byte_blocks × 64`
/// bytes from the row's start must lie inside `data`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
unsafe fn sums_u8_vnni<const C: usize>(
    lw: &LinearWeights,
    data: &[u8],
    width: usize,
    cx: i32,
    cy: i32,
) -> [i64; 6] {
    use std::arch::x86_64::*;
    let z = _mm512_setzero_si512();
    let (mut a0, mut a1, mut pa, mut b0, mut b1, mut pb) = (z, z, z, z, z, z);
    let w = lw.bytes512.as_ptr() as *const i8;
    for r in &lw.rows {
        let start = ((cy + r.dy) as usize * width + (cx + r.lo) as usize) * C;
        let p = data.as_ptr().add(start);
        // Per-row sums start from zero: no `vpdpbusd` (5-cycle latency) chain runs
        // from row to row, only one-cycle adds.
        let (mut ra0, mut ra1, mut rb0, mut rb1) = (z, z, z, z);
        for b in 0..r.byte_blocks {
            let v = _mm512_loadu_si512(p.add(b * BYTES512) as *const __m512i);
            let wb = w.add(r.byte_block_offset + b * 4 * BYTES512) as *const __m512i;
            ra0 = _mm512_dpbusd_epi32(ra0, v, _mm512_loadu_si512(wb));
            ra1 = _mm512_dpbusd_epi32(ra1, v, _mm512_loadu_si512(wb.add(1)));
            rb0 = _mm512_dpbusd_epi32(rb0, v, _mm512_loadu_si512(wb.add(2)));
            rb1 = _mm512_dpbusd_epi32(rb1, v, _mm512_loadu_si512(wb.add(3)));
        }
        a0 = _mm512_add_epi32(a0, ra0);
        pa = _mm512_add_epi32(pa, a0);
        a1 = _mm512_add_epi32(a1, ra1);
        b0 = _mm512_add_epi32(b0, rb0);
        pb = _mm512_add_epi32(pb, b0);
        b1 = _mm512_add_epi32(b1, rb1);
    }
    // Lane sums widened to i64 before the horizontal add (16 lanes could overflow i32).
    let hsum = |v: __m512i| -> i64 {
        let lo = _mm512_cvtepi32_epi64(_mm512_castsi512_si256(v));
        let hi = _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(v));
        _mm512_reduce_add_epi64(_mm512_add_epi64(lo, hi))
    };
    let (n, dy0) = (
        lw.rows.len() as i64,
        lw.rows.first().map_or(0, |r| r.dy) as i64,
    );
    let (sa, sb) = (hsum(a0), hsum(b0));
    [
        sa,
        hsum(a1),
        (dy0 + n) * sa - hsum(pa),
        sb,
        hsum(b1),
        (dy0 + n) * sb - hsum(pb),
    ]
}

#[cfg(test)]
mod tests {
    use super::super::{Raw, Window};

    #[test]
    fn simd_kernel_sums_equal_the_scalar_kernel_exactly() {
        // Pseudo-random 8-bit RGB and RGBA images; windows everywhere they fit,
        // including the image's last rows (where the SIMD kernel must fall back).
        let (wd, ht) = (53, 41);
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 56) as u8
        };
        let d3: Vec<u8> = (0..wd * ht * 3).map(|_| next()).collect();
        let d4: Vec<u8> = (0..wd * ht * 4).map(|_| next()).collect();
        for (radius, weights) in [(6.0, [0, -1, 1]), (8.5, [-1, -1, 2]), (2.0, [1, -1, 0])] {
            let vnni = Window::new(radius, weights);
            let mut simd512 = vnni.clone();
            simd512.vnni = false;
            let mut simd512_words = simd512.clone();
            simd512_words.byte_kernel = false;
            let mut simd = simd512.clone();
            simd.avx512 = false;
            let mut scalar = simd.clone();
            scalar.avx2 = false;
            // Every kernel the CPU has (VNNI, AVX-512 bytes, AVX-512 16-bit, AVX2)
            // against the scalar one.
            let kernels = [
                ("avx-512 vnni", &vnni),
                ("avx-512", &simd512),
                ("avx-512 16-bit", &simd512_words),
                ("avx2", &simd),
            ];
            let i3 = Raw::<u8, 3> {
                data: &d3,
                width: wd,
                height: ht,
            };
            let i4 = Raw::<u8, 4> {
                data: &d4,
                width: wd,
                height: ht,
            };
            let h = simd.half;
            for cy in h..ht as i32 - h {
                for cx in h..wd as i32 - h {
                    let (rgb, rgba) = (
                        scalar.sums_linear::<u8, 3>(i3, cx, cy),
                        scalar.sums_linear::<u8, 4>(i4, cx, cy),
                    );
                    for (name, k) in kernels {
                        assert_eq!(
                            k.sums_linear::<u8, 3>(i3, cx, cy),
                            rgb,
                            "{name} rgb r={radius} at ({cx}, {cy})"
                        );
                        assert_eq!(
                            k.sums_linear::<u8, 4>(i4, cx, cy),
                            rgba,
                            "{name} rgba r={radius} at ({cx}, {cy})"
                        );
                    }
                }
            }
        }
    }

    /// The byte kernels at their limit: weights up to ±64 (half-size 32, colour weight
    /// 2) on saturated and random samples still give the scalar sums (no i16
    /// saturation, no i32 overflow of the VNNI kernel's running sums); one more pixel of half-size and the byte weights are dropped, the
    /// 16-bit kernel takes over.
    #[test]
    fn byte_kernel_is_exact_at_its_weight_limit_and_refused_beyond() {
        let w = Window::new(29.0, [-1, -1, 2]);
        assert_eq!(w.half, 32);
        assert!(!w.linear[0].bytes512.is_empty());
        assert!(Window::new(30.0, [-1, -1, 2]).linear[0].bytes512.is_empty());
        assert!(!Window::new(30.0, [1, 1, 1]).linear[0].bytes512.is_empty());
        // The VNNI kernel's i32 running sums fit up to here; beyond (a 127-row window
        // of weights up to 63), the plain byte kernel takes the window.
        assert!(w.linear[0].vnni && Window::new(30.0, [1, 1, 1]).linear[0].vnni);
        let wide = Window::new(60.0, [1, 1, 1]);
        assert!(!wide.linear[0].bytes512.is_empty() && !wide.linear[0].vnni);
        let mut no_vnni = w.clone();
        no_vnni.vnni = false;
        let mut scalar = w.clone();
        scalar.avx512 = false;
        scalar.avx2 = false;
        let (wd, ht) = (72usize, 70usize);
        let mut state = 0x2545_F491_4F6C_DD1Du64;
        for fill in [Some(255u8), Some(0), None] {
            let d3: Vec<u8> = (0..wd * ht * 3)
                .map(|_| {
                    fill.unwrap_or_else(|| {
                        state ^= state << 13;
                        state ^= state >> 7;
                        state ^= state << 17;
                        (state >> 56) as u8
                    })
                })
                .collect();
            let img = Raw::<u8, 3> {
                data: &d3,
                width: wd,
                height: ht,
            };
            for cy in 32..ht as i32 - 32 {
                for cx in 32..wd as i32 - 32 {
                    let want = scalar.sums_linear::<u8, 3>(img, cx, cy);
                    for (name, k) in [("vnni", &w), ("bytes", &no_vnni)] {
                        assert_eq!(
                            k.sums_linear::<u8, 3>(img, cx, cy),
                            want,
                            "{name}: fill {fill:?} at ({cx}, {cy})"
                        );
                    }
                }
            }
        }
    }
}
