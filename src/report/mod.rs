//! Reports: plots (plotters), the self-contained HTML report and acceptance verdicts.
//!
//! [`plot`] is the shared figure output used by reports and studies: one drawing
//! routine per figure, written to PNG and SVG from the same code.

pub mod plot;
pub mod study_plots;
