//! Placeholder: matrix-vector kernels (issue 2).
