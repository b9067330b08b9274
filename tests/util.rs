//! Helpers shared by the integration tests: running the `tactbench` binary and its
//! served simulators, the simulated Fig. 7 run, writing input files and reading
//! run-directory files, the paper sensor and the TacTip draft options, grey copies of
//! frames, interior force nodes, F/T wrenches and faults, a small seeded random
//! generator.

#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use image::{GrayImage, Luma, RgbImage};
use tactbench::bench::journal::{self, JournalRow};
use tactbench::device::ft_common::{no_faults, FaultConfig, FaultKind};
use tactbench::device::Wrench;
use tactbench::sensor::Sensor;

/// Path of the built `tactbench` binary.
pub fn bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_tactbench"))
}

/// A `tactbench` command (arguments and I/O to be set by the caller).
pub fn command() -> Command {
    Command::new(bin())
}

/// Runs `tactbench` with `args` in `dir`, returning its output.
pub fn run_in(dir: &Path, args: &[&str]) -> Output {
    Command::new(bin())
        .args(args)
        .current_dir(dir)
        .output()
        .expect("spawn tactbench")
}

/// Runs `tactbench` in the crate root.
pub fn run(args: &[&str]) -> Output {
    run_in(Path::new(env!("CARGO_MANIFEST_DIR")), args)
}

/// stderr as text.
pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// stdout as text.
pub fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// A path inside the crate root.
pub fn root(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(rel)
}

/// Writes `text` as `dir/name` and returns the path.
pub fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

/// The rows of `dir/journal.csv` (the panic names the file and the line).
pub fn rows(dir: &Path) -> Vec<JournalRow> {
    journal::read_rows(dir).unwrap()
}

/// The text of the paper's sensor file, `experiments/paper_sensor.toml`.
pub fn paper_sensor_text() -> String {
    std::fs::read_to_string(root("experiments/paper_sensor.toml")).unwrap()
}

/// The `sensor init` options that draft a sensor file from the real TacTip frames
/// (bright pins, the ROI circle, the image scale).
pub const TACTIP_INIT: [&str; 6] = [
    "--color",
    "bright",
    "--roi",
    "circle:304,250,182",
    "--mm-per-px",
    "0.05",
];

/// `round((R + G + B) / 3)` per pixel: the grey level whose widened pixel `(g, g, g)`
/// the brightness score reads as `3g`, nearest to the RGB pixel's `R + G + B`.
pub fn gray8_of(img: &RgbImage) -> GrayImage {
    GrayImage::from_fn(img.width(), img.height(), |x, y| {
        let p = img.get_pixel(x, y).0;
        Luma([((p[0] as u32 + p[1] as u32 + p[2] as u32 + 1) / 3) as u8])
    })
}

/// Force components (`f`: fx, fy, fz per node) of the nodes at least `margin_mm`
/// from every edge of the sensor's force grid.
pub fn interior(sensor: &Sensor, f: &[f64], margin_mm: f64) -> Vec<f64> {
    let g = sensor.force_grid;
    let m = (margin_mm / g.pitch_mm).ceil() as usize;
    let mut out = Vec::new();
    for iy in m..g.ny.saturating_sub(m) {
        for ix in m..g.nx.saturating_sub(m) {
            let k = iy * g.nx + ix;
            out.extend_from_slice(&f[3 * k..3 * k + 3]);
        }
    }
    out
}

/// `../shared/real_frames` beside the clone (the real camera frames, never copied
/// into the repository); `TACTBENCH_REAL_FRAMES` overrides it (a worktree elsewhere),
/// as for the benches (`benches/common/real_frames.rs`).
pub fn real_frames_dir() -> PathBuf {
    std::env::var_os("TACTBENCH_REAL_FRAMES")
        .map_or_else(|| root("../shared/real_frames"), PathBuf::from)
}

/// A small deterministic generator (SplitMix64) so tests need no extra dependency.
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = self.uniform().max(1e-300);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
}

/// The visible text of a report or comparison page without what quotes other units
/// on purpose: embedded images (`src="data:…"`), preformatted blocks (the plan and
/// sensor files, devices, bench, quoted as recorded) and the note saying which unit
/// the machine names keep (`<p class="unit-note">`).
pub fn page_text(html: &str) -> String {
    let cuts = [
        ("src=\"data:", "\""),
        ("<pre>", "</pre>"),
        ("<p class=\"unit-note\">", "</p>"),
    ];
    let mut s = String::with_capacity(html.len());
    let mut rest = html;
    while let Some((at, open, close)) = cuts
        .iter()
        .filter_map(|(o, c)| rest.find(o).map(|at| (at, *o, *c)))
        .min_by_key(|x| x.0)
    {
        s.push_str(&rest[..at]);
        let from = at + open.len();
        rest = match rest[from..].find(close) {
            Some(e) => &rest[from + e + close.len()..],
            None => "",
        };
    }
    s.push_str(rest);
    s
}

/// Every place `text` shows a force in newtons: the unit symbol `N` standing alone as
/// a word (`7.3 N`, `fz (N)`, `[N]`, `N per mm`), with 30 characters of context each.
pub fn newton_units(text: &str) -> Vec<String> {
    let b = text.as_bytes();
    let mut out = Vec::new();
    for (i, &c) in b.iter().enumerate() {
        if c != b'N' {
            continue;
        }
        let before = if i > 0 { b[i - 1] } else { b' ' };
        let after = b.get(i + 1).copied().unwrap_or(b' ');
        let opens = matches!(before, b' ' | b'(' | b'[' | b'\n');
        let closes = matches!(
            after,
            b' ' | b')' | b']' | b',' | b';' | b'<' | b'\n' | b'/' | b'.'
        );
        if opens && closes {
            // Context by characters (the pages are UTF-8: µ, ±, −).
            let head: String = text[..i].chars().rev().take(30).collect();
            let tail: String = text[i..].chars().take(30).collect();
            out.push(
                format!("{}{tail}", head.chars().rev().collect::<String>()).replace('\n', " "),
            );
        }
    }
    out
}

/// The text elements of a plotters SVG: `(x, y, text)`.
pub fn svg_texts(svg: &str) -> Vec<(f64, f64, String)> {
    let attr = |tag: &str, name: &str| -> Option<f64> {
        let at = tag.find(&format!(" {name}=\""))? + name.len() + 3;
        tag[at..].split('"').next()?.parse().ok()
    };
    svg.split("<text")
        .skip(1)
        .filter_map(|t| {
            let (tag, rest) = t.split_once('>')?;
            let text = rest.split("</text>").next()?.trim().to_string();
            Some((attr(tag, "x")?, attr(tag, "y")?, text))
        })
        .collect()
}

/// The y of the topmost axis tick label (a text that is a number) of an SVG figure:
/// the plotting area begins about there.
pub fn svg_top_tick_y(svg: &str) -> f64 {
    svg_texts(svg)
        .into_iter()
        .filter(|(_, _, t)| t.parse::<f64>().is_ok())
        .map(|(_, y, _)| y)
        .fold(f64::INFINITY, f64::min)
}

/// The paper's Fig. 7 plan cut to 0 ... `to_gf` gf (its 50 gf steps) with `trials`
/// trials, its sensor path made absolute, written to `dir/name`.
pub fn fig7_plan_cut(dir: &Path, name: &str, to_gf: f64, trials: u32) -> PathBuf {
    let sensor = root("experiments/paper_sensor.toml");
    let (to, trials) = (format!("to = {to_gf:.1}"), format!("trials = {trials}"));
    let text = std::fs::read_to_string(root("experiments/fig7_magnitude.toml"))
        .expect("experiments/fig7_magnitude.toml")
        .replace(
            "sensor = \"paper_sensor.toml\"",
            &format!("sensor = {:?}", sensor.display().to_string()),
        )
        .replace("to = 750.0", &to)
        .replace("trials = 10", &trials);
    assert!(
        text.contains(&to) && text.contains(&trials),
        "the Fig. 7 plan no longer has the lines this cut replaces"
    );
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

/// The Fig. 7 plan cut to 0, 50, 100, 150 gf with two trials (8 setpoints): the
/// short simulated run the run, archive and compare tests measure.
pub fn eight_setpoint_fig7_plan(dir: &Path, name: &str) -> PathBuf {
    fig7_plan_cut(dir, name, 150.0, 2)
}

/// A path as a `&str` argument (the temporary directories tests use are UTF-8).
pub fn arg(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// `tactbench run` of the paper's Fig. 7 plan on the simulated Fig. 7 ramp scene, from
/// the crate root: the start of most simulated-run invocations; the caller adds `--out`,
/// `--limit` and the rest.
pub const FIG7_SIM_RUN: [&str; 4] = [
    "run",
    "experiments/fig7_magnitude.toml",
    "--sim",
    "experiments/scenes/fig7_hemisphere_ramp.toml",
];

/// Runs [`FIG7_SIM_RUN`] with `extra` arguments.
pub fn run_fig7_sim(extra: &[&str]) -> Output {
    let mut args = FIG7_SIM_RUN.to_vec();
    args.extend_from_slice(extra);
    run(&args)
}

/// The number of rows (header excluded) of `dir/journal.csv`.
pub fn journal_rows(dir: &Path) -> usize {
    std::fs::read_to_string(dir.join("journal.csv"))
        .expect("journal.csv")
        .lines()
        .count()
        - 1
}

/// A JSON file, parsed (the panic names the file).
pub fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap())
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// A `tactbench` child process, killed on drop (so a failing test leaks nothing).
pub struct Served(pub Child);

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `tactbench sim-serve-stage --protocol PROTOCOL` on a pseudo-terminal linked in a
/// temporary directory; stops when dropped (its stdin closed).
pub struct ServedStage {
    child: Child,
    /// The pseudo-terminal's link.
    pub link: PathBuf,
    protocol: String,
    stage_args: Vec<String>,
    _dir: tempfile::TempDir,
}

impl ServedStage {
    /// Serves `protocol` with the simulator arguments `extra`; `stage_args` are added to
    /// every [`ServedStage::stage`] command (driver options).
    pub fn start(protocol: &str, extra: &[&str], stage_args: &[&str]) -> ServedStage {
        let dir = tempfile::tempdir().expect("tempdir");
        let link = dir.path().join("stage");
        let mut child = Command::new(bin())
            .args(["sim-serve-stage", "--protocol", protocol, "--link"])
            .arg(&link)
            .args(extra)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .expect("spawn sim-serve-stage");
        // The helper prints one line once the pty is served.
        let mut line = String::new();
        let out = child.stdout.take().expect("stdout");
        BufReader::new(out).read_line(&mut line).expect("read");
        assert!(line.starts_with("serving on /dev/pts/"), "{line}");
        let deadline = Instant::now() + Duration::from_secs(5);
        while !link.exists() && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(10));
        }
        ServedStage {
            child,
            link,
            protocol: protocol.to_string(),
            stage_args: stage_args.iter().map(|s| s.to_string()).collect(),
            _dir: dir,
        }
    }

    /// `tactbench stage --port LINK --protocol PROTOCOL [stage_args] ARGS`.
    pub fn stage(&self, args: &[&str]) -> Output {
        Command::new(bin())
            .args(["stage", "--port"])
            .arg(&self.link)
            .args(["--protocol", &self.protocol])
            .args(&self.stage_args)
            .args(args)
            .output()
            .expect("run tactbench stage")
    }
}

impl Drop for ServedStage {
    fn drop(&mut self) {
        drop(self.child.stdin.take());
        let _ = self.child.wait();
    }
}

// ---- force/torque sensors (ft.rs, ft_net_bota.rs) ------------------------------------

/// The load the F/T tests apply: distinct values per channel, within every simulated
/// sensor's range.
pub const FT_LOAD: Wrench = Wrench {
    force_n: [1.5, -2.25, 12.34],
    torque_nm: [0.125, -0.05, 0.3],
};

/// [`FT_LOAD`] as `sim-serve-ft --wrench` takes it.
pub const FT_LOAD_ARG: &str = "1.5,-2.25,12.34,0.125,-0.05,0.3";

/// A wrench's six channels: fx, fy, fz (N), mx, my, mz (N·m).
pub fn wrench_channels(w: &Wrench) -> [f64; 6] {
    [
        w.force_n[0],
        w.force_n[1],
        w.force_n[2],
        w.torque_nm[0],
        w.torque_nm[1],
        w.torque_nm[2],
    ]
}

/// Asserts `got` equals `want` within half a quantum per channel (`quantum`: N for
/// forces, N·m for torques), plus floating-point slack.
pub fn assert_wrench_near(got: &Wrench, want: &Wrench, quantum: [f64; 6]) {
    let (g, w) = (wrench_channels(got), wrench_channels(want));
    for i in 0..6 {
        assert!(
            (g[i] - w[i]).abs() <= 0.5 * quantum[i] + 1e-9,
            "channel {i}: got {} want {} (quantum {})",
            g[i],
            w[i],
            quantum[i]
        );
    }
}

/// Faults of `kinds` (drawn uniformly) on each reply or record with probability `p`,
/// seeded, unlimited in number, from the first on, on any target.
pub fn ft_faults(seed: u64, kinds: &[FaultKind], p: f64) -> FaultConfig {
    FaultConfig {
        seed,
        kinds: kinds.to_vec(),
        probability: p,
        skip: 0,
        max_faults: u32::MAX,
        ..no_faults()
    }
}

/// Starts `tactbench sim-serve-ft --protocol PROTOCOL` serving [`FT_LOAD`] for 60 s
/// with `extra` arguments, and returns it with its first ("serving") line.
pub fn serve_ft<S: AsRef<std::ffi::OsStr>>(protocol: &str, extra: &[S]) -> (Served, String) {
    let mut child = Command::new(bin())
        .args([
            "sim-serve-ft",
            "--protocol",
            protocol,
            "--wrench",
            FT_LOAD_ARG,
            "--duration-s",
            "60",
        ])
        .args(extra)
        .stdout(Stdio::piped())
        .spawn()
        .expect("spawn tactbench");
    let stdout = child.stdout.take().expect("stdout");
    let served = Served(child);
    let mut line = String::new();
    BufReader::new(stdout)
        .read_line(&mut line)
        .expect("serving line");
    (served, line)
}

/// A wrench from the JSON `tactbench ft … --json` prints (`fx_n` … `mz_nm`).
pub fn json_wrench(v: &serde_json::Value) -> Wrench {
    let f = |k: &str| {
        v[k].as_f64()
            .unwrap_or_else(|| panic!("missing {k} in {v}"))
    };
    Wrench {
        force_n: [f("fx_n"), f("fy_n"), f("fz_n")],
        torque_nm: [f("mx_nm"), f("my_nm"), f("mz_nm")],
    }
}
