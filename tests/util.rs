//! Helpers shared by the integration tests: running the `tactbench` binary, temporary
//! directories, a small seeded random generator.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Path of the built `tactbench` binary.
pub fn bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_tactbench"))
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

/// The paper's Fig. 7 plan cut to 0, 50, 100, 150 gf with two trials (8 setpoints),
/// its sensor path made absolute, written to `dir/name`: the short simulated run the
/// run, archive and compare tests measure.
pub fn eight_setpoint_fig7_plan(dir: &Path, name: &str) -> PathBuf {
    let sensor = root("experiments/paper_sensor.toml");
    let text = std::fs::read_to_string(root("experiments/fig7_magnitude.toml"))
        .expect("experiments/fig7_magnitude.toml")
        .replace(
            "sensor = \"paper_sensor.toml\"",
            &format!("sensor = {:?}", sensor.display().to_string()),
        )
        .replace("to = 750.0", "to = 150.0")
        .replace("trials = 10", "trials = 2");
    assert!(
        text.contains("to = 150.0") && text.contains("trials = 2"),
        "the Fig. 7 plan no longer has the lines this cut replaces"
    );
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}
