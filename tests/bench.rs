//! `tactbench sim bench` end to end: the real CLI commands against the simulated bench
//! on pseudo-terminals, and the full pipeline stage -> contact -> frame -> track ->
//! reconstruct checked against the force sensor.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use tactbench::device::camera::SocketCamera;
use tactbench::device::Camera;
use tactbench::sensor::paper_sensor;
use tactbench::solve::{self, Problem, SolverConfig};
use tactbench::vision::{self, FrameView, TrackConfig, Tracker};

use crate::util;

/// A running `tactbench sim bench`, stopped with SIGINT (Ctrl-C) when dropped.
struct BenchProcess {
    child: Child,
    links: PathBuf,
    _dir: tempfile::TempDir,
}

impl BenchProcess {
    fn start(extra: &[&str]) -> BenchProcess {
        let dir = tempfile::tempdir().unwrap();
        let links = dir.path().join("links");
        let child = Command::new(util::bin())
            .args([
                "sim",
                "bench",
                "--scene",
                "experiments/scenes/fig7_hemisphere_ramp.toml",
                "--links",
            ])
            .arg(&links)
            .args(extra)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let t = Instant::now();
        while !(links.join("stage").exists()
            && links.join("ft").exists()
            && links.join("camera.sock").exists())
        {
            assert!(
                t.elapsed() < Duration::from_secs(20),
                "sim bench did not come up"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        BenchProcess {
            child,
            links,
            _dir: dir,
        }
    }

    fn path(&self, name: &str) -> String {
        self.links.join(name).display().to_string()
    }

    /// Ctrl-C, then the exit status and whether the links are gone.
    fn interrupt(mut self) -> (bool, bool) {
        let pid = self.child.id().to_string();
        let _ = Command::new("kill").args(["-INT", &pid]).status();
        let t = Instant::now();
        let status = loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                break s;
            }
            assert!(
                t.elapsed() < Duration::from_secs(10),
                "sim bench ignored Ctrl-C"
            );
            std::thread::sleep(Duration::from_millis(20));
        };
        let gone = !self.links.join("stage").exists() && !self.links.join("camera.sock").exists();
        (status.success(), gone)
    }
}

impl Drop for BenchProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn cli(args: &[&str]) -> String {
    let o = util::run(args);
    assert!(o.status.success(), "{args:?}: {}", util::stderr(&o));
    util::stdout(&o)
}

fn ft_fz(bench: &BenchProcess, protocol: &str) -> f64 {
    let out = cli(&[
        "ft",
        "--port",
        &bench.path("ft"),
        "--protocol",
        protocol,
        "read",
        "--json",
    ]);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    v["mean"]["fz_n"].as_f64().unwrap()
}

/// Hertz: P = 4/3 E* √R δ^{3/2}, E* = E/(1−ν²) = 4/3 N/mm² for the paper elastomer.
fn hertz_n(radius_mm: f64, depth_mm: f64) -> f64 {
    4.0 / 3.0 * (4.0 / 3.0) * radius_mm.sqrt() * depth_mm.powf(1.5)
}

#[test]
fn stage_ft_and_camera_clis_drive_the_simulated_bench_and_agree() {
    let bench = BenchProcess::start(&[]);
    let stage = bench.path("stage");
    let out = cli(&[
        "stage",
        "--port",
        &stage,
        "--protocol",
        "grbl",
        "position",
        "--json",
    ]);
    assert_eq!(out.trim(), r#"{"x_mm":0.0,"y_mm":0.0,"z_mm":0.0}"#);
    assert_eq!(ft_fz(&bench, "dynpick"), 0.0, "no contact, no force");

    // Over the sensor centre (9, 6.75) mm, then straight down 0.5 mm into the surface
    // (GRBL: surface at z = -30 mm, +z up).
    cli(&[
        "stage",
        "--port",
        &stage,
        "--protocol",
        "grbl",
        "move",
        "-91",
        "-93.25",
        "-29",
    ]);
    cli(&[
        "stage",
        "--port",
        &stage,
        "--protocol",
        "grbl",
        "move",
        "-91",
        "-93.25",
        "-30.5",
    ]);
    let fz = ft_fz(&bench, "dynpick");
    let expected = hertz_n(2.5, 0.5);
    assert!(
        (fz - expected).abs() < 0.02 * expected,
        "fz {fz} N vs Hertz {expected} N"
    );
    let out = cli(&[
        "stage",
        "--port",
        &stage,
        "--protocol",
        "grbl",
        "position",
        "--json",
    ]);
    let p: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert!((p["z_mm"].as_f64().unwrap() + 30.5).abs() < 1e-3);

    let png = bench.links.parent().unwrap().join("frame.png");
    cli(&[
        "camera",
        "grab",
        "--device",
        &format!("sim:{}", bench.path("camera.sock")),
        "--out",
        png.to_str().unwrap(),
    ]);
    let img = image::open(&png).unwrap();
    assert_eq!((img.width(), img.height()), (430, 340));

    let (ok, gone) = bench.interrupt();
    assert!(
        ok && gone,
        "Ctrl-C must stop the bench cleanly and remove its links"
    );
}

#[test]
fn frames_from_the_bench_reconstruct_the_force_the_sensor_measures() {
    let bench = BenchProcess::start(&["--stage", "zaber", "--ft", "ft300"]);
    let sensor = paper_sensor();
    let mut cam = SocketCamera::connect(Path::new(&bench.path("camera.sock"))).unwrap();
    let reference = cam.grab_reference().unwrap();
    let rview = FrameView::rgb8(&reference.image);
    let reference = vision::detect(&rview, &sensor, &vision::DetectConfig::default()).unwrap();
    assert_eq!(reference.markers.len(), 260);
    let mut tracker = Tracker::new(reference, TrackConfig::default());

    // Zaber (+z presses, surface at 30 mm, sensor origin at stage 15, 15): press the
    // 5 mm hemisphere 0.6 mm deep over the sensor centre.
    let stage = bench.path("stage");
    cli(&["stage", "--port", &stage, "--protocol", "zaber", "home"]);
    cli(&[
        "stage",
        "--port",
        &stage,
        "--protocol",
        "zaber",
        "move",
        "24",
        "21.75",
        "29",
    ]);
    cli(&[
        "stage",
        "--port",
        &stage,
        "--protocol",
        "zaber",
        "move",
        "24",
        "21.75",
        "30.6",
    ]);
    let fz = ft_fz(&bench, "ft300");
    let expected = hertz_n(2.5, 0.6);
    // The FT 300 reports 0.01 N steps.
    assert!(
        (fz - expected).abs() < 0.02 * expected + 0.01,
        "fz {fz} N vs Hertz {expected} N"
    );

    let frame = cam.grab().unwrap();
    let tracks = tracker
        .track(&FrameView::rgb8(&frame.image))
        .unwrap()
        .to_vec();
    let records = tracker.displacement_records(&tracks, &sensor.camera);
    let frame = tactbench::formats::DisplacementFrame {
        frame: String::new(),
        records,
    };
    let sites = frame.sites(&sensor);
    let u = frame.u_mm();
    assert!(sites.len() >= 250, "tracked {} of 260 markers", sites.len());
    let problem = Problem::new(&sensor, &sites);
    let mut solver = solve::precompute(&problem, &SolverConfig::default(), Some(&u)).unwrap();
    let mut f = vec![0.0; solver.n_outputs()];
    solver.apply(&u, &mut f).unwrap();
    let fsum_z: f64 = f.iter().skip(2).step_by(3).sum();
    eprintln!(
        "bench: F/T fz = {fz:.4} N, Hertz {expected:.4} N, reconstructed F_sum z = {fsum_z:.4} N"
    );
    // 8-bit frames, the paper's pinv: the summed force (paper F^sum) matches the
    // force sensor within 10 %.
    assert!(
        (fsum_z - fz).abs() < 0.10 * fz,
        "F_sum z {fsum_z} N vs F/T {fz} N"
    );
}
