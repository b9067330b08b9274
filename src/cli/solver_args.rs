//! Solver options shared by `reconstruct` and `model inspect`.

use tactbench::solve::{Lambda, Method, Precision, Rank, SolverConfig};

/// How forces are solved from displacements.
#[derive(clap::Args, Debug, Clone)]
pub struct SolverArgs {
    /// Inverse method: `pinv` (Moore-Penrose pseudo-inverse, the paper's method),
    /// `tikhonov` (regularised, lambda below), `tsvd` (truncated SVD, rank below), or
    /// `fourier` (regular marker and force grids only; fast for dense force grids).
    #[arg(long, default_value = "pinv", value_parser = parse_method)]
    solver: Method,
    /// Regularisation for tikhonov and fourier: `gcv` (generalised cross-validation),
    /// `lcurve` (L-curve corner), a fixed value in mm/N (the units of H's singular
    /// values; filter factor sigma^2 / (sigma^2 + lambda^2)), or `auto`: gcv for
    /// tikhonov, lcurve for fourier (whose zero padding looks like noise-free data to
    /// GCV, which then picks lambda about 10x too small). Default: auto. An error with
    /// pinv and tsvd, which have no lambda.
    #[arg(long, value_parser = parse_lambda)]
    lambda: Option<LambdaArg>,
    /// Rank for tsvd: `auto` (chosen by GCV) or the number of singular values kept.
    /// Default: auto. An error with the other solvers.
    #[arg(long, value_parser = parse_rank)]
    rank: Option<Rank>,
    /// Arithmetic of the per-frame solve of the dense solvers: `f64` (default), or
    /// `f32` (about twice as fast; measured relative difference 1e-5 for pinv, 3e-7
    /// for tikhonov at the paper size). `f32` is an error with fourier (f64 only).
    #[arg(long, value_parser = parse_precision)]
    precision: Option<Precision>,
    /// pinv: singular values below rcond * sigma_max are dropped
    /// [default: max(rows, cols) * machine epsilon].
    #[arg(long)]
    rcond: Option<f64>,
    /// fourier: `on` (default) adds the precomputed coarse-grid correction to the
    /// per-frequency solve (the two-level solve: force sums of dense tikhonov exactly,
    /// field within ~4 %); `off` is the per-frequency solve alone, about twice as fast
    /// at 64x64 but with the periodic model's boundary error (force sums off by 30 % to
    /// over 100 % on bounded grids). An error with the other solvers.
    #[arg(long, value_name = "on|off", value_parser = parse_on_off)]
    coarse_correction: Option<bool>,
    /// fourier: CGLS refinement iterations on the exact operator after the two-level
    /// solve (a cap: the refinement stops earlier at --refine-tolerance). The default, 0,
    /// is the two-level solve alone: the per-frequency solve plus a precomputed
    /// coarse-grid correction, with the force sums of dense tikhonov exactly and the
    /// field within ~4 % of it (1.2 ms per frame at 64x64). Each iteration costs about
    /// three per-frequency solves and brings the field closer to dense tikhonov
    /// (20 iterations: ~0.1 %). An error with the other solvers.
    #[arg(long, value_name = "N")]
    refine_iterations: Option<usize>,
    /// fourier: the refinement stops once its estimated relative distance to dense
    /// tikhonov is below TOL, in [0, 1) [default: 0.02]; 0 runs all --refine-iterations.
    /// Needs --refine-iterations N > 0; an error with the other solvers.
    #[arg(long, value_name = "TOL")]
    refine_tolerance: Option<f64>,
}

impl SolverArgs {
    /// The library configuration these flags select. A flag that does not apply to the
    /// chosen solver (`--lambda` with pinv or tsvd, `--rank` with anything but tsvd,
    /// `--precision f32` with fourier) is an error naming both, not silently ignored.
    pub fn config(&self) -> Result<SolverConfig, String> {
        let m = self.solver;
        if self.lambda.is_some() && matches!(m, Method::Pinv | Method::Tsvd) {
            return Err(format!(
                "--lambda does not apply to the {m} solver, which has no regularisation parameter lambda (tikhonov and fourier use it{})",
                if m == Method::Tsvd { "; tsvd is tuned with --rank" } else { "" }
            ));
        }
        if self.rank.is_some() && m != Method::Tsvd {
            return Err(format!(
                "--rank does not apply to the {m} solver: only tsvd truncates at a rank{}",
                match m {
                    Method::Pinv => "; pinv drops singular values below --rcond * sigma_max",
                    Method::Tikhonov | Method::Fourier =>
                        "; tikhonov and fourier are tuned with --lambda",
                    Method::Tsvd => "",
                }
            ));
        }
        if self.precision == Some(Precision::F32) && m == Method::Fourier {
            return Err(
                "--precision f32 does not apply to the fourier solver: its per-frame solve runs in f64 only (f32 is for pinv, tikhonov and tsvd)"
                    .into(),
            );
        }
        if self.refine_tolerance.is_some() && m != Method::Fourier {
            return Err(format!(
                "--refine-tolerance does not apply to the {m} solver: only fourier refines its per-frequency solve"
            ));
        }
        if self.coarse_correction.is_some() && m != Method::Fourier {
            return Err(format!(
                "--coarse-correction does not apply to the {m} solver: only fourier has a per-frequency solve to correct"
            ));
        }
        if self.refine_iterations.is_some() && m != Method::Fourier {
            return Err(format!(
                "--refine-iterations does not apply to the {m} solver: only fourier refines its per-frequency solve"
            ));
        }
        if let (Some(t), None | Some(0)) = (self.refine_tolerance, self.refine_iterations) {
            return Err(format!(
                "--refine-tolerance {t} has no effect without refinement: add --refine-iterations N (N > 0; the default, 0, is the two-level solve without refinement)"
            ));
        }
        Ok(SolverConfig {
            method: m,
            lambda: match (self.lambda.unwrap_or(LambdaArg::Auto), m) {
                (LambdaArg::Given(l), _) => l,
                (LambdaArg::Auto, Method::Fourier) => Lambda::LCurve,
                (LambdaArg::Auto, _) => Lambda::Gcv,
            },
            rank: self.rank.unwrap_or_default(),
            precision: self.precision.unwrap_or_default(),
            rcond: self.rcond,
            fourier_coarse: self.coarse_correction.unwrap_or(true),
            fourier_refine_iterations: self
                .refine_iterations
                .unwrap_or(tactbench::solve::fourier::DEFAULT_REFINE_ITERATIONS),
            fourier_refine_tolerance: self
                .refine_tolerance
                .unwrap_or(tactbench::solve::fourier::DEFAULT_REFINE_TOLERANCE),
            ..SolverConfig::default()
        })
    }
}

fn parse_on_off(s: &str) -> Result<bool, String> {
    match s {
        "on" => Ok(true),
        "off" => Ok(false),
        other => Err(format!("expected on or off, got {other:?}")),
    }
}

fn parse_method(s: &str) -> Result<Method, String> {
    s.parse()
}

/// `--lambda`: `auto` lets the method decide (see the flag's help).
#[derive(Debug, Clone, Copy)]
enum LambdaArg {
    Auto,
    Given(Lambda),
}

fn parse_lambda(s: &str) -> Result<LambdaArg, String> {
    if s == "auto" {
        Ok(LambdaArg::Auto)
    } else {
        s.parse().map(LambdaArg::Given)
    }
}

fn parse_rank(s: &str) -> Result<Rank, String> {
    s.parse()
}

fn parse_precision(s: &str) -> Result<Precision, String> {
    match s {
        "f64" => Ok(Precision::F64),
        "f32" => Ok(Precision::F32),
        _ => Err(format!("unknown precision `{s}`: expected f64 or f32")),
    }
}
