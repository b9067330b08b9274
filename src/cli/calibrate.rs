//! `tactbench calibrate`: camera calibration from the unloaded reference frame
//! (library: [`tactbench::vision::calibrate`]).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use tactbench::sensor::Sensor;
use tactbench::vision::onboard::check_frame_levels;
use tactbench::vision::{calibrate, check_layers, load_frame, CalibrateConfig};

/// Calibrate the camera from an unloaded reference frame: writes camera.toml.
///
/// The detected marker grid of every layer is the calibration target (its geometry is
/// the sensor file's). Fitted by least squares (Levenberg-Marquardt) to the marker
/// centroids: per layer a scale (px/mm) and origin (px, undistorted position of the
/// sensor-frame origin), the principal point, and Brown-Conrady radial distortion k1,
/// k2 (--radial-terms 0..3; 0 = no distortion) about the principal point, normalised by
/// half the image diagonal; with --tangential also p1, p2 (the principal point is then
/// held at the image centre). A marker at (x, y) mm in layer l is then seen at
/// p = D(origin_l + px_per_mm_l * (x, y)).
///
/// What one frame can identify: each layer's scale and origin (what tracking needs;
/// perspective and refraction fold into them), radial distortion k1 (k2, k3 weakly).
/// Weakly: the principal point, seen only through the distortion and coupled to k1 (not
/// at all without distortion). Not identifiable: pinhole distance and focal length
/// separately (only their ratio per layer), refraction apart from the per-layer scale,
/// tangential distortion apart from a principal-point shift (equal to first order), a
/// rotation about the optical axis (not modelled), and the parallax of marker motion
/// along z under load.
///
/// Prints per layer the scale, origin, residual RMS (px) and marker count, and every
/// fitted parameter with its standard deviation (a large SD = not determined by the
/// frame). Use the file with `tactbench track --camera camera.toml`.
///
/// The frame must be a clean frame of the unloaded sensor showing every layer's whole
/// grid; otherwise nothing is written and the reason is given: with distortion terms
/// (--radial-terms 1..3, --tangential) a layer with less than 85 % of its grid
/// markers matched, or spanning less than 85 % of its grid on either axis, is refused
/// (the distortion and principal point cannot be determined from part of the grid:
/// use --radial-terms 0 to fit scale and origin only); a fit whose residuals exceed 3x
/// (RMS) or 8x (any marker) the centroid noise measured on the frame itself, plus
/// 0.05 / 0.1 px, is refused (a loaded sensor, or part of the frame covered by dust or
/// a shadow); a fitted distortion that cannot be inverted over the image is refused.
///
/// Exit status: 0 written; 2 on errors (missing or unreadable files, a layer with fewer
/// than 6 markers matched to its grid, partial coverage, a frame that is not clean and
/// unloaded, a fit that does not converge).
#[derive(clap::Args)]
#[command(allow_negative_numbers = true)]
pub struct Args {
    /// Sensor description (sensor.toml: layer grids are the calibration target).
    #[arg(long, value_name = "S.toml")]
    sensor: PathBuf,
    /// Reference image taken with no load on the sensor.
    #[arg(long, value_name = "REF.png")]
    reference: PathBuf,
    /// Output calibration (camera.toml; format in README).
    #[arg(long, value_name = "camera.toml")]
    out: PathBuf,
    /// Radial distortion coefficients fitted: 0 (none) to 3 (k1, k2, k3).
    #[arg(long, value_name = "N", default_value_t = 2, value_parser = clap::value_parser!(u8).range(0..=3))]
    radial_terms: u8,
    /// Also fit tangential distortion p1, p2 (holds the principal point at the image
    /// centre: the two are not separable from one frame).
    #[arg(long)]
    tangential: bool,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let sensor = Sensor::from_path(&args.sensor)?;
    let image = load_frame(&args.reference, &sensor.camera)?;
    check_layers(
        &image.view(),
        sensor.layers.iter().map(|l| (l.name.as_str(), l.color)),
    )
    .with_context(|| format!("reference image {}", args.reference.display()))?;
    let config = CalibrateConfig {
        radial_terms: args.radial_terms as usize,
        tangential: args.tangential,
        ..CalibrateConfig::default()
    };
    let fit = match calibrate(&image.view(), &sensor, &config) {
        Ok(fit) => fit,
        Err(e) => {
            // A blank or saturated reference is the likelier cause: say so first.
            check_frame_levels(
                &image.view(),
                sensor.camera.roi_px.as_ref(),
                &args.reference,
            )
            .with_context(|| format!("calibrating with sensor {}", args.sensor.display()))?;
            return Err(e).with_context(|| {
                format!(
                    "calibrating from {} with sensor {}",
                    args.reference.display(),
                    args.sensor.display()
                )
            });
        }
    };
    let c = &fit.calibration;
    if let Err(why) = c.distortion.check_invertible(c.width_px, c.height_px) {
        anyhow::bail!(
            "calibrating from {}: the fitted distortion (k1 {:.3e}, k2 {:.3e}, k3 {:.3e}) {why}: the frame does not determine a usable calibration; nothing was written (try --radial-terms 0 or 1)",
            args.reference.display(),
            c.distortion.k1,
            c.distortion.k2,
            c.distortion.k3
        );
    }
    eprintln!(
        "calibrated from {}: {} markers, residual RMS {:.4} px ({} matching rounds, {} iterations in the last fit, {} blobs unmatched)",
        args.reference.display(),
        c.layers.iter().map(|l| l.markers).sum::<usize>(),
        c.rms_px,
        fit.rounds,
        fit.iterations,
        fit.unmatched
    );
    eprintln!(
        "  centroid noise measured on the frame {:.4} px: residual gate RMS <= {:.4} px, any marker <= {:.4} px (passed)",
        fit.noise_px,
        tactbench::vision::calibrate::RMS_GATE_FACTOR * fit.noise_px
            + tactbench::vision::calibrate::RESIDUAL_FLOOR_PX,
        tactbench::vision::calibrate::MAX_GATE_FACTOR * fit.noise_px
            + 2.0 * tactbench::vision::calibrate::RESIDUAL_FLOOR_PX
    );
    for l in &c.layers {
        eprintln!(
            "  layer {}: {:.5} px/mm ({:.6} mm/px), origin ({:.3}, {:.3}) px, RMS {:.4} px over {} markers",
            l.name,
            l.px_per_mm,
            1.0 / l.px_per_mm,
            l.origin_px[0],
            l.origin_px[1],
            l.rms_px,
            l.markers
        );
    }
    let d = &c.distortion;
    eprintln!(
        "  distortion about ({:.3}, {:.3}) px, norm {:.3} px: k1 {:.6e}, k2 {:.6e}, k3 {:.6e}, p1 {:.6e}, p2 {:.6e}",
        d.center_px[0], d.center_px[1], d.norm_px, d.k1, d.k2, d.k3, d.p1, d.p2
    );
    eprintln!("  fitted parameters (value ± SD):");
    for (name, v, sd) in &fit.parameters {
        eprintln!("    {name} = {v:.6e} ± {sd:.2e}");
    }
    let text = c.to_toml_string(
        &args.sensor.display().to_string(),
        &args.reference.display().to_string(),
    );
    std::fs::write(&args.out, text).with_context(|| format!("writing {}", args.out.display()))?;
    eprintln!("-> {}", args.out.display());
    Ok(ExitCode::SUCCESS)
}
