//! Placeholder: being written (see issue 2).
use super::*;

/// Placeholder.
pub struct FourierSolver {
    diag: Diagnostics,
}

impl FourierSolver {
    /// Placeholder.
    pub fn precompute(
        _p: &Problem<'_>,
        _c: &SolverConfig,
        _f: Option<&[f64]>,
    ) -> Result<Self, SolveError> {
        Err(SolveError::InvalidOption("not implemented yet".into()))
    }
}

impl FrameSolver for FourierSolver {
    fn n_inputs(&self) -> usize {
        0
    }
    fn n_outputs(&self) -> usize {
        0
    }
    fn apply(&mut self, _u: &[f64], _f: &mut [f64]) -> Result<(), SolveError> {
        Ok(())
    }
    fn diagnostics(&self) -> &Diagnostics {
        &self.diag
    }
}
