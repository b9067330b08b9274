//! `tactbench sim render`: render a scene's camera frames and their ground truth.
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use image::Rgb32FImage;
use tactbench::formats;
use tactbench::sim::render::{to_rgb16, to_rgb8};
use tactbench::sim::scene::Scene;
use tactbench::sim::simulate::{FrameTruth, Simulation};

/// Simulate the tactile sensor's camera.
#[derive(clap::Subcommand)]
pub enum SimCommand {
    Render(RenderArgs),
}

/// Render a scene: the unloaded reference frame, the loaded frames and ground truth.
///
/// Writes into DIR:
///
/// - reference.png: the unloaded frame;
///
/// - frame_000.png, frame_001.png, ...: one per loaded frame (a [sequence] ramps the
///   load over `frames` steps);
///
/// - markers.csv, columns
///   layer,marker,x_mm,y_mm,ux_mm,uy_mm,frame,x_px,y_px,ux_px,uy_px,elastic_ux_mm,elastic_uy_mm:
///   the marker's true reference position (after any placement jitter; x_px,y_px in
///   reference.png), the apparent displacement an ideal tracker measures against
///   reference.png (elastic displacement plus whole-image shift and drift), and the
///   elastic part alone; marker = row-major index in the layer grid, frame = index of
///   frame_NNN.png;
///
/// - forces.csv, columns ix,iy,x_mm,y_mm,fx_n,fy_n,fz_n (+ frame with several frames):
///   the applied traction integrated over each force-grid cell.
///
/// PNG bit depth: 16-bit RGB when the scene has no `quantize8` effect (ideal renders
/// stay exact to 1/65535), 8-bit RGB when it has.
#[derive(clap::Args)]
pub struct RenderArgs {
    /// The scene file (scene.toml; its `sensor` path is relative to it).
    #[arg(long, value_name = "SCENE")]
    scene: PathBuf,
    /// Output directory (created if missing; existing files are overwritten).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

pub fn run(cmd: SimCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        SimCommand::Render(a) => render(a),
    }
}

fn save(frame: &Rgb32FImage, eight_bit: bool, path: &Path) -> anyhow::Result<()> {
    let r = if eight_bit {
        to_rgb8(frame).save(path)
    } else {
        to_rgb16(frame).save(path)
    };
    r.with_context(|| format!("cannot write {}", path.display()))
}

fn render(a: RenderArgs) -> anyhow::Result<ExitCode> {
    let scene = Scene::from_path(&a.scene)?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create output directory {}", a.out.display()))?;
    let mut sim = Simulation::from_scene(&scene);
    let eight_bit = sim.pipeline().quantizes_to_8bit();
    let mm_per_px = scene.sensor.camera.mm_per_px;
    let mut frame = sim.blank_frame();

    let reference = sim.render_reference(&mut frame)?;
    save(&frame, eight_bit, &a.out.join("reference.png"))?;

    let markers_path = a.out.join("markers.csv");
    let file = std::fs::File::create(&markers_path)
        .with_context(|| format!("cannot write {}", markers_path.display()))?;
    let mut w = std::io::BufWriter::new(file);
    writeln!(
        w,
        "{},frame,x_px,y_px,ux_px,uy_px,elastic_ux_mm,elastic_uy_mm",
        formats::DISPLACEMENT_COLUMNS.join(",")
    )?;
    let mut forces = Vec::with_capacity(scene.frames);
    let mut max_u_px = 0.0f64;
    for k in 0..scene.frames {
        let load = scene.frame_load(k + 1);
        let truth = sim
            .render_load(&load, k as u64 + 1, &mut frame)
            .with_context(|| format!("{}: frame {k}", scene.path.display()))?;
        save(&frame, eight_bit, &a.out.join(format!("frame_{k:03}.png")))?;
        max_u_px = max_u_px.max(write_marker_rows(
            &mut w, &sim, &truth, &reference, k, mm_per_px,
        )?);
        if let Some(c) = &truth.contact {
            if let Some(q) = c.clamped_tangential_n {
                eprintln!(
                    "warning: frame {k}: tangential load {q:.4} N exceeds the friction limit μP = {:.4} N; clamped",
                    load.friction * c.normal_force_n
                );
            }
            if k + 1 == scene.frames {
                let t = c.total_force_n();
                println!(
                    "final load: P = {:.4} N, Q = ({:.4}, {:.4}) N, contact radius {:.3} mm{}",
                    t[2],
                    t[0],
                    t[1],
                    c.contact_radius_mm,
                    c.indentation_mm
                        .map(|d| format!(", indentation {d:.4} mm"))
                        .unwrap_or_default()
                );
            }
        }
        forces.push((k.to_string(), truth.forces_n));
    }
    w.flush()
        .with_context(|| format!("cannot write {}", markers_path.display()))?;
    formats::write_forces(&a.out.join("forces.csv"), &scene.sensor.force_grid, &forces)?;
    println!(
        "wrote reference.png and {} frame(s) ({}-bit PNG), markers.csv, forces.csv to {}; largest apparent marker motion {:.2} px",
        scene.frames,
        if eight_bit { 8 } else { 16 },
        a.out.display(),
        max_u_px
    );
    Ok(ExitCode::SUCCESS)
}

/// Writes one frame's marker rows; returns the largest apparent displacement (px).
fn write_marker_rows(
    w: &mut impl Write,
    sim: &Simulation,
    truth: &FrameTruth,
    reference: &FrameTruth,
    k: usize,
    mm_per_px: f64,
) -> anyhow::Result<f64> {
    let sensor = sim.sensor();
    let mut max_u = 0.0f64;
    for (i, (m, &(layer, id))) in sim.markers().iter().zip(sim.marker_ids()).enumerate() {
        let p_px = sensor.camera.mm_to_px(m.position_mm);
        let p_px = [
            p_px[0] + reference.offset_px[0],
            p_px[1] + reference.offset_px[1],
        ];
        let u_px = truth.apparent_u_px(i, mm_per_px, reference.offset_px);
        max_u = max_u.max(u_px[0].hypot(u_px[1]));
        writeln!(
            w,
            "{},{id},{},{},{},{},{k},{},{},{},{},{},{}",
            sensor.layers[layer].name,
            m.position_mm[0],
            m.position_mm[1],
            u_px[0] * mm_per_px,
            u_px[1] * mm_per_px,
            p_px[0],
            p_px[1],
            u_px[0],
            u_px[1],
            truth.elastic_u_mm[2 * i],
            truth.elastic_u_mm[2 * i + 1]
        )?;
    }
    Ok(max_u)
}
