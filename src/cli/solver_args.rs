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
    /// GCV, which then picks lambda about 10x too small).
    #[arg(long, default_value = "auto", value_parser = parse_lambda)]
    lambda: LambdaArg,
    /// Rank for tsvd: `auto` (chosen by GCV) or the number of singular values kept.
    #[arg(long, default_value = "auto", value_parser = parse_rank)]
    rank: Rank,
    /// Arithmetic of the per-frame solve: `f64`, or `f32` (about twice as fast,
    /// ~1e-6 relative error).
    #[arg(long, default_value = "f64", value_parser = parse_precision)]
    precision: Precision,
    /// pinv: singular values below rcond * sigma_max are dropped
    /// [default: max(rows, cols) * machine epsilon].
    #[arg(long)]
    rcond: Option<f64>,
}

impl SolverArgs {
    /// The library configuration these flags select.
    pub fn config(&self) -> SolverConfig {
        SolverConfig {
            method: self.solver,
            lambda: match (self.lambda, self.solver) {
                (LambdaArg::Given(l), _) => l,
                (LambdaArg::Auto, Method::Fourier) => Lambda::LCurve,
                (LambdaArg::Auto, _) => Lambda::Gcv,
            },
            rank: self.rank,
            precision: self.precision,
            rcond: self.rcond,
            ..SolverConfig::default()
        }
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
