//! A small seeded pseudo-random generator for the simulation's effects.
//!
//! xoshiro256++ (Blackman & Vigna, "Scrambled linear pseudorandom number generators",
//! ACM TOMS 2021) seeded through SplitMix64, as the authors recommend. Every random
//! effect owns its seed, and every frame gets its own stream
//! ([`Rng::stream`]`(seed, frame)`), so a frame can be regenerated alone and adding or
//! removing one effect never changes the draws of another. Written here rather than
//! pulling `rand` + `rand_distr` + `rand_chacha`: the simulation needs three
//! distributions and bit-for-bit reproducibility across dependency upgrades.
//!
//! Distributions: uniform `[0, 1)` from the top 53 bits; standard normal by the
//! Marsaglia polar method; Poisson by multiplication of uniforms (Knuth) for `λ < 30`
//! and by the PTRS transformed rejection of Hörmann ("The transformed rejection method
//! for generating Poisson random variables", Insurance: Mathematics and Economics 12,
//! 1993) above.

/// SplitMix64 step: the seed expander of xoshiro.
fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// xoshiro256++ with a cached second normal deviate.
#[derive(Debug, Clone)]
pub struct Rng {
    s: [u64; 4],
    spare_normal: Option<f64>,
}

impl Rng {
    /// A generator for `seed` (stream 0).
    pub fn new(seed: u64) -> Self {
        Self::stream(seed, 0)
    }

    /// Stream `stream` of `seed`: independent sequences for, e.g., each frame.
    pub fn stream(seed: u64, stream: u64) -> Self {
        // Mix the stream id through SplitMix64 first so that neighbouring (seed, stream)
        // pairs do not give overlapping states.
        let mut t = stream.wrapping_mul(0xD1B5_4A32_D192_ED03);
        let mut st = seed ^ splitmix64(&mut t);
        let s = [
            splitmix64(&mut st),
            splitmix64(&mut st),
            splitmix64(&mut st),
            splitmix64(&mut st),
        ];
        Rng {
            s,
            spare_normal: None,
        }
    }

    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        let s = &mut self.s;
        let result = s[0].wrapping_add(s[3]).rotate_left(23).wrapping_add(s[0]);
        let t = s[1] << 17;
        s[2] ^= s[0];
        s[3] ^= s[1];
        s[1] ^= s[2];
        s[0] ^= s[3];
        s[2] ^= t;
        s[3] = s[3].rotate_left(45);
        result
    }

    /// Uniform in `[0, 1)`.
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Standard normal deviate.
    pub fn normal(&mut self) -> f64 {
        if let Some(z) = self.spare_normal.take() {
            return z;
        }
        loop {
            let u = 2.0 * self.uniform() - 1.0;
            let v = 2.0 * self.uniform() - 1.0;
            let s = u * u + v * v;
            if s > 0.0 && s < 1.0 {
                let m = (-2.0 * s.ln() / s).sqrt();
                self.spare_normal = Some(v * m);
                return u * m;
            }
        }
    }

    /// Poisson deviate with mean `lambda` (≤ 0 or non-finite gives 0).
    pub fn poisson(&mut self, lambda: f64) -> f64 {
        if !(lambda.is_finite() && lambda > 0.0) {
            return 0.0;
        }
        if lambda < 30.0 {
            let limit = (-lambda).exp();
            let mut k = 0.0;
            let mut p = self.uniform();
            while p > limit {
                k += 1.0;
                p *= self.uniform();
            }
            return k;
        }
        // PTRS (Hörmann 1993).
        let slam = lambda.sqrt();
        let loglam = lambda.ln();
        let b = 0.931 + 2.53 * slam;
        let a = -0.059 + 0.02483 * b;
        let inv_alpha = 1.1239 + 1.1328 / (b - 3.4);
        let vr = 0.9277 - 3.6224 / (b - 2.0);
        loop {
            let u = self.uniform() - 0.5;
            let v = self.uniform();
            let us = 0.5 - u.abs();
            let k = ((2.0 * a / us + b) * u + lambda + 0.43).floor();
            if us >= 0.07 && v <= vr {
                return k;
            }
            if k < 0.0 || (us < 0.013 && v > us) {
                continue;
            }
            if (v * inv_alpha / (a / (us * us) + b)).ln() <= -lambda + k * loglam - ln_factorial(k)
            {
                return k;
            }
        }
    }
}

/// `ln(k!)` by Stirling's series (exact table below 10).
fn ln_factorial(k: f64) -> f64 {
    const TABLE: [f64; 10] = [
        0.0,
        0.0,
        std::f64::consts::LN_2,
        1.791_759_469_228_055,
        3.178_053_830_347_146,
        4.787_491_742_782_046,
        6.579_251_212_010_101,
        8.525_161_361_065_415,
        10.604_602_902_745_25,
        12.801_827_480_081_469,
    ];
    if k < 10.0 {
        return TABLE[k as usize];
    }
    let k1 = k + 1.0;
    (k1 - 0.5) * k1.ln() - k1 + 0.5 * (2.0 * std::f64::consts::PI).ln() + 1.0 / (12.0 * k1)
        - 1.0 / (360.0 * k1 * k1 * k1)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn moments(xs: &[f64]) -> (f64, f64) {
        let n = xs.len() as f64;
        let m = xs.iter().sum::<f64>() / n;
        let v = xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0);
        (m, v)
    }

    #[test]
    fn same_seed_and_stream_repeat_and_streams_differ() {
        let a: Vec<u64> = (0..8).map(|_| Rng::stream(7, 3).next_u64()).collect();
        assert!(a.windows(2).all(|w| w[0] == w[1]));
        let mut r0 = Rng::stream(7, 0);
        let mut r1 = Rng::stream(7, 1);
        let mut r2 = Rng::stream(8, 0);
        let x0 = r0.next_u64();
        assert_ne!(x0, r1.next_u64());
        assert_ne!(x0, r2.next_u64());
    }

    #[test]
    fn normal_has_unit_variance_within_sampling_error() {
        let mut r = Rng::new(1);
        let xs: Vec<f64> = (0..200_000).map(|_| r.normal()).collect();
        let (m, v) = moments(&xs);
        // Standard errors: mean 1/√n = 2.2e-3, variance √(2/n) = 3.2e-3; 5 SE bounds.
        assert!(m.abs() < 0.011, "mean {m}");
        assert!((v - 1.0).abs() < 0.016, "variance {v}");
    }

    #[test]
    fn poisson_mean_equals_variance_for_small_and_large_lambda() {
        for lambda in [3.5, 250.0, 4000.0] {
            let mut r = Rng::new(2);
            let xs: Vec<f64> = (0..100_000).map(|_| r.poisson(lambda)).collect();
            let (m, v) = moments(&xs);
            // 5 standard errors of the mean (√(λ/n)) and of the variance (≈ λ√(2/n)).
            assert!(
                (m - lambda).abs() < 5.0 * (lambda / 1e5).sqrt(),
                "λ={lambda}: mean {m}"
            );
            assert!(
                (v - lambda).abs() < 5.0 * lambda * (2.0f64 / 1e5).sqrt(),
                "λ={lambda}: var {v}"
            );
            assert!(xs.iter().all(|x| *x >= 0.0 && x.fract() == 0.0));
        }
    }
}
