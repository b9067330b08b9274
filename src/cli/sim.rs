//! `tactbench sim render` (a scene's camera frames and their ground truth) and
//! `tactbench sim bench` (the whole bench simulated on pseudo-terminals).
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
    Bench(BenchArgs),
}

/// Serve a simulated bench: stage, force sensor and camera around one virtual world.
///
/// The stage simulator (GRBL or Zaber) and the force-sensor simulator (DynPick, FT 300
/// or Bota) speak their real protocols on pseudo-terminals, linked as DIR/stage and
/// DIR/ft (the ATI Net F/T, `--ft netft`, on 127.0.0.1 UDP/TCP ports chosen by the OS,
/// printed as `ft      127.0.0.1 --rdt-port N --cal-port M`); the camera serves frames on DIR/camera.sock (use `--device sim:DIR/camera.sock`
/// with `tactbench camera`). Where the stage is decides the contact: the force sensor
/// reports the matching wrench (N, N·m) and the camera renders the matching markers,
/// with the scene's effects only. The scene's [load] is not used.
///
/// Default geometry (stage machine coordinates, mm): GRBL: sensor origin at
/// x,y = -100,-100, surface at z = -30, pressing towards -z, start at 0,0,0. Zaber: sensor
/// origin at 15,15, surface at z = 30, pressing towards +z, start mid-travel (23.8 mm).
///
/// Runs until Ctrl-C (or SIGTERM), then removes the links.
#[derive(clap::Args)]
#[command(
    after_long_help = "Example:\n  tactbench sim bench --scene experiments/scenes/fig7_hemisphere_ramp.toml --links /tmp/bench &\n  tactbench stage --port /tmp/bench/stage --protocol grbl move -91 -93.25 -30.5\n  tactbench ft --port /tmp/bench/ft --protocol dynpick read\n  tactbench camera grab --device sim:/tmp/bench/camera.sock --out frame.png"
)]
pub struct BenchArgs {
    /// The scene (sensor, indenter, effects).
    #[arg(long, value_name = "SCENE")]
    scene: PathBuf,
    /// Stage protocol to simulate.
    #[arg(long, value_enum, default_value = "grbl")]
    stage: StageArg,
    /// Force-sensor protocol to simulate.
    #[arg(long, value_enum, default_value = "dynpick")]
    ft: FtArg,
    /// Directory for the links `stage`, `ft` and `camera.sock` (created if missing).
    #[arg(long, value_name = "DIR")]
    links: PathBuf,
    /// Stage x,y (mm) that puts the indenter over the sensor-frame origin.
    #[arg(
        long,
        value_name = "X,Y",
        value_delimiter = ',',
        num_args = 2,
        allow_negative_numbers = true
    )]
    sensor_origin_mm: Option<Vec<f64>>,
    /// Stage z (mm) at which the indenter touches the surface.
    #[arg(long, value_name = "Z", allow_negative_numbers = true)]
    surface_z_mm: Option<f64>,
    /// Friction coefficient between indenter and elastomer.
    #[arg(long, default_value_t = 1.0)]
    friction: f64,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum StageArg {
    Grbl,
    Zaber,
    Marlin,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum FtArg {
    Dynpick,
    Ft300,
    /// ATI Net F/T on loopback UDP/TCP (ports chosen by the OS, printed).
    Netft,
    Bota,
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
///   frame_NNN.png. With camera effects (perspective, refraction, lens_distortion)
///   x_px,y_px and ux_px,uy_px are the projected image positions and their change
///   (parallax of u_z included), and ux_mm,uy_mm that change at [camera] mm_per_px;
///   elastic_ux_mm,elastic_uy_mm stay the true in-plane displacement;
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
        SimCommand::Bench(a) => bench(a),
    }
}

fn bench(a: BenchArgs) -> anyhow::Result<ExitCode> {
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    use tactbench::sim::bench::{FtProtocol, StageProtocol, VirtualBench};

    let scene = Scene::from_path(&a.scene)?;
    let stage = match a.stage {
        StageArg::Grbl => StageProtocol::Grbl,
        StageArg::Zaber => StageProtocol::Zaber,
        StageArg::Marlin => StageProtocol::Marlin,
    };
    let ft = match a.ft {
        FtArg::Dynpick => FtProtocol::DynPick,
        FtArg::Ft300 => FtProtocol::Ft300,
        FtArg::Netft => FtProtocol::NetFt,
        FtArg::Bota => FtProtocol::Bota,
    };
    if !(a.friction.is_finite() && a.friction >= 0.0) {
        anyhow::bail!("--friction {} must be a finite number >= 0", a.friction);
    }
    let (mut geometry, _) = stage.default_geometry();
    if let Some(o) = &a.sensor_origin_mm {
        geometry.sensor_origin_in_stage_mm = [o[0], o[1]];
    }
    if let Some(z) = a.surface_z_mm {
        geometry.surface_z_mm = z;
    }
    geometry.friction = a.friction;

    let stop = Arc::new(AtomicBool::new(false));
    let flag = Arc::clone(&stop);
    ctrlc::set_handler(move || flag.store(true, Ordering::SeqCst))
        .context("cannot install the Ctrl-C handler")?;

    let bench = VirtualBench::start(&scene, stage, ft, &a.links, Some(geometry))?;
    let g = bench.world().geometry();
    println!("stage   {}", bench.stage_port().display());
    println!("ft      {}", bench.ft_endpoint());
    println!("camera  {}", bench.camera_socket().display());
    println!(
        "world   sensor origin at stage ({}, {}) mm, surface at z = {} mm, pressing towards {}z, friction {}",
        g.sensor_origin_in_stage_mm[0],
        g.sensor_origin_in_stage_mm[1],
        g.surface_z_mm,
        if g.press_direction < 0.0 { "-" } else { "+" },
        g.friction
    );
    println!("serving until Ctrl-C");
    let _ = std::io::stdout().flush();
    while !stop.load(Ordering::SeqCst) {
        if bench.is_finished() {
            eprintln!("sim bench: a simulator hung up; stopping");
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    drop(bench);
    eprintln!("sim bench: stopped, links removed");
    Ok(ExitCode::SUCCESS)
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
        let (p_px, u_px) = if sim.optics().is_some() {
            // Camera effects: positions through the camera optics.
            let p = sim.apparent_px(i, reference);
            let q = sim.apparent_px(i, truth);
            (p, [q[0] - p[0], q[1] - p[1]])
        } else {
            let p_px = sensor.camera.mm_to_px(m.position_mm);
            (
                [
                    p_px[0] + reference.offset_px[0],
                    p_px[1] + reference.offset_px[1],
                ],
                truth.apparent_u_px(i, mm_per_px, reference.offset_px),
            )
        };
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
