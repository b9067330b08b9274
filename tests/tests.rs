//! Integration tests (one harness; one module per area).

mod fourier;
