//! Analysis of measurements and simulations: the paper's evaluation figures and the
//! accuracy-against-time study.
//!
//! - [`accuracy_time`]: force error against time per frame over solver, force-grid,
//!   tracking and averaging choices, on a simulated scene; Pareto front and budgets.
//! - [`layer_separation`]: force error against the distance between the two marker
//!   layers (paper Fig. 6), from the forward model, per solver.

pub mod accuracy_time;
pub mod layer_separation;
