//! Scene simulation: what the tactile sensor's camera would see under a given load,
//! with the ground truth to test the tracker and the solvers against.
//!
//! - [`render`]: the ideal renderer. Marker positions in mm in, a float RGB frame
//!   ([`image::Rgb32FImage`]) out, with each pixel's exact disc coverage; 8- and
//!   16-bit conversions. Pixel centres are at integer coordinates.
//! - [`effects`]: imaging and manufacturing effects (noise, shot noise, 8-bit
//!   quantisation, depth blur, illumination gradient, vignetting, marker size and
//!   placement jitter, whole-image shift, drift), each with its own parameters and
//!   seed, applied only when listed, in the listed order.
//! - [`contact`]: flat punch, Hertz hemisphere and point load tractions, discretised
//!   and pushed through the half-space model; the force-grid ground truth.
//! - [`scene`]: `scene.toml` (schema in its module docs).
//! - [`simulate`]: [`simulate::Simulation`], a sensor + indenter + effects rendering
//!   the frame and truth for any load (the CLI's `sim render` and the future
//!   simulated camera).
//! - [`rng`]: the seeded generator of the random effects.
//! - [`world`] and [`bench`]: the simulated bench (one world behind simulated devices).
//!
//! Typical use:
//!
//! ```no_run
//! use tactbench::sim::{scene::Scene, simulate::Simulation, render::to_rgb16};
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let scene = Scene::from_path("experiments/scenes/fig4_flat_910gf.toml")?;
//! let mut sim = Simulation::from_scene(&scene);
//! let mut frame = sim.blank_frame();
//! sim.render_reference(&mut frame)?;
//! let truth = sim.render_load(&scene.frame_load(1), 1, &mut frame)?;
//! to_rgb16(&frame).save("frame.png")?;
//! println!("{} markers, first ux = {} mm", sim.markers().len(), truth.elastic_u_mm[0]);
//! # Ok(()) }
//! ```

pub mod bench;
pub mod camera;
pub mod contact;
pub mod effects;
pub mod render;
pub mod rng;
pub mod scene;
pub mod simulate;
pub mod world;
