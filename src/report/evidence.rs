//! What the report shows of the measurement itself: the force-field map of one
//! setpoint (or why a run has none) with per-node uncertainty, and the camera
//! evidence — the reference frame and loaded frames, cropped to the sensor area, with
//! every tracked marker circled in its tracker status colour and its displacement
//! drawn as an arrow.
//!
//! **No force field for unloaded runs.** A displacement sweep (Table I) shifts the
//! whole sensor with nothing touching it: the markers move rigidly, a field no surface
//! load produces, and whatever the solver returns is its answer to that, not a force.
//! The same holds for any setpoint where the F/T sensor measured (almost) nothing:
//! [`force_field`] returns the reason instead of a figure, and the page prints it.
//!
//! **Per-node uncertainty** is the σ(fz) the run recorded when it solved the setpoint:
//! the `sfx_n, sfy_n, sfz_n` columns of `forces/NNNNN.csv`, `σ(f_j) = σ_u · ‖P_j‖` from
//! the solver's `force_sd` (the runner's) for the tracking noise σ_u of the mean over the
//! setpoint's frames (their scatter / √frames, the noise behind the journal's
//! `fsum_sd_*_n`). The report reads it and builds no solver; a forces file without those
//! columns (a run from before runs recorded σ, one frame per setpoint) gets one line
//! saying the run did not record it ([`SD_NOT_RECORDED`]).
//!
//! **Camera evidence.** Statuses and pixel positions are the tracker's own, as the
//! run recorded them in `displacements/NNNNN.csv` (`x_px, y_px, ux_px, uy_px,
//! status`); frames are the files its `frame` column names. Chosen setpoints: the
//! highest load (|F| of the F/T sensor; |shift| for a displacement sweep) and the one
//! nearest half of it. Images are 8-bit RGB PNGs (`image`), cropped to the markers'
//! bounding box plus one marker pitch, enlarged by an integer factor; written to
//! `plots/camera_reference.png` and `plots/camera_NNNNN.png` and embedded.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use base64::Engine;
use plotters::prelude::*;

use super::force_map::{arrow_parts, fmt_force, fmt_short, nice_floor, ForceMapFigure, NodeSd};
use super::markup::escape;
use super::plot::{encode_png, register_fonts, PngBackend, FONT};
use crate::analysis::{RunAnalysis, RunData, Snapshot};
use crate::bench::journal::JournalRow;
use crate::bench::plan::Sweep;

/// F/T force below which a setpoint counts as unloaded, N (≈ 1 gf).
pub const UNLOADED_N: f64 = 0.01;

/// The force field of the snapshot, or why there is none.
#[derive(Debug, Clone)]
pub enum ForceField {
    /// Draw this map.
    Map(Box<ForceMapFigure>),
    /// No map, and why (a sentence for the page).
    Absent(String),
}

/// |F| the F/T sensor measured at a row, N.
fn applied_n(r: &JournalRow) -> f64 {
    r.fx_n.hypot(r.fy_n).hypot(r.fz_n)
}

/// The force field of the analysis's snapshot, or why the run has none.
pub fn force_field(analysis: &RunAnalysis) -> Option<ForceField> {
    let run = &analysis.run;
    let unit = run.plan.force_unit;
    let snap = analysis.snapshot.as_ref()?;
    let fzmax = |f: &[crate::formats::ForceRecord]| {
        f.iter()
            .map(|r| r.f_n[2].abs())
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max)
    };
    if matches!(run.plan.sweep, Sweep::Displacement { .. }) {
        let got = snap.forces.as_deref().map_or(String::new(), |f| {
            format!(
                " (the solver's output here reaches |fz| = {})",
                fmt_force(fzmax(f), unit)
            )
        });
        return Some(ForceField::Absent(format!(
            "No force field: this is a displacement sweep (paper Table I), which shifts the \
             whole sensor with nothing touching its surface. The markers move rigidly, a \
             displacement field no surface load produces, so what the solver returns for it{got} \
             is not a measured force."
        )));
    }
    let row = run.rows.iter().find(|r| r.index == snap.index)?;
    let applied = applied_n(row);
    let floor = UNLOADED_N.max(3.0 * row.fz_sd_n);
    if applied < floor {
        return Some(ForceField::Absent(format!(
            "No force field: at setpoint {} (the most loaded by the reconstruction) the F/T \
             sensor measured |F| = {}, below {} (max of {} and 3 × its SD): nothing loaded \
             the sensor, so a reconstructed field would show only noise.",
            snap.index,
            fmt_force(applied, unit),
            fmt_force(floor, unit),
            fmt_force(UNLOADED_N, unit)
        )));
    }
    let forces = snap.forces.clone()?;
    let sd = node_sd(run, snap);
    Some(ForceField::Map(Box::new(ForceMapFigure {
        title: format!(
            "force field, setpoint {} (F/T |F| = {})",
            snap.index,
            fmt_force(applied, unit)
        ),
        pitch_mm: run.sensor.force_grid.pitch_mm,
        forces,
        sd: sd.ok(),
        unit,
    })))
}

/// The caption of a force map.
pub fn force_map_caption(fig: &ForceMapFigure, why_no_sd: Option<&str>) -> String {
    let (kf, kl) = fig.key();
    let u = fig.unit.symbol();
    let mut c = format!(
        "Reconstructed force field (paper Fig. 5): each force-grid cell coloured by fz \
         ({u}; red presses into the sensor, blue pulls out; largest |fz| {}); arrows are \
         the tangential force (fx, fy) at the node, {} {u} per mm of arrow (key arrow {} {u} = \
         {} mm), at most {} of the {} mm pitch so neighbouring arrows never cross. y grows \
         upward here (downward in the camera images). Around a contact between nodes the \
         nearest nodes carry tangential forces pointing in towards the load although the \
         applied load is normal: the grid places the load at the nodes, farther out than \
         the real contact pressure, and the least-squares solution corrects the marker \
         displacements this misplacement causes with inward shear; they cancel in the sum \
         (F_sum x, y ≈ 0).",
        fmt_force(fig.fz_max(), fig.unit),
        fmt_short(fig.per_mm()),
        fmt_short(kf),
        fmt_short(kl),
        super::force_map::ARROW_FRACTION,
        fig.pitch_mm
    );
    match (&fig.sd, why_no_sd) {
        (Some(sd), _) => {
            let m = sd.fz_sd_n.iter().copied().fold(0.0, f64::max);
            let _ = write!(
                c,
                " Right: σ(fz) per node (largest {}) for displacement noise {} px ({}), \
                 propagated through the run's solver.",
                fmt_force(m, fig.unit),
                fmt_short(sd.noise_px),
                sd.source
            );
        }
        (None, Some(why)) => {
            let _ = write!(c, " No per-node uncertainty: {why}.");
        }
        (None, None) => {}
    }
    c
}

/// Why [`node_sd`] gave nothing (for the caption).
pub fn why_no_sd(analysis: &RunAnalysis) -> Option<String> {
    let snap = analysis.snapshot.as_ref()?;
    node_sd(&analysis.run, snap).err()
}

/// The one line the σ panel prints for a run whose forces file carries no σ columns.
pub const SD_NOT_RECORDED: &str = "the run did not record it (its forces file has no \
     sfx_n, sfy_n, sfz_n columns: a run from before runs recorded σ, a setpoint of one \
     frame, which gives no tracking-noise estimate, or a solver that could not give σ)";

/// Per-node σ(fz) of the snapshot as the run recorded it (see the module docs), or why
/// there is none. Reads files only: the report never rebuilds the solver.
pub fn node_sd(run: &RunData, snap: &Snapshot) -> Result<NodeSd, String> {
    let path = crate::analysis::forces_path(&run.dir, snap.index);
    let recorded = crate::formats::read_force_sd(&path).map_err(|e| e.to_string())?;
    let Some(sd) = recorded else {
        return Err(SD_NOT_RECORDED.into());
    };
    let forces = snap.forces.as_deref().unwrap_or(&[]);
    if sd.len() != forces.len() {
        return Err(format!(
            "{}: {} σ rows for {} force rows",
            path.display(),
            sd.len(),
            forces.len()
        ));
    }
    let fz_sd_n: Vec<f64> = sd.iter().map(|s| s[2]).collect();
    let (noise_mm, source) = frame_noise_mm(run, snap.index)?;
    if fz_sd_n.iter().all(|v| *v == 0.0) {
        return Err(format!(
            "the run recorded σ(fz) = 0 at every node ({source} is exactly 0: the frames \
             equal the reference, as with an ideal simulated camera)"
        ));
    }
    Ok(NodeSd {
        fz_sd_n,
        noise_px: noise_mm / run.sensor.camera.mm_per_px,
        source,
    })
}

/// The displacement noise σ(fz) was propagated from, for the caption: the runner's
/// estimate, the pooled scatter between the setpoint's frames of the markers tracked in
/// all of them, divided by √frames (the noise of their mean), mm, and that phrase.
fn frame_noise_mm(run: &RunData, index: usize) -> Result<(f64, String), String> {
    let frames = run.displacements(index).map_err(|e| e.to_string())?;
    let nf = frames.len();
    let n = frames.first().map_or(0, |f| f.records.len());
    let mut mean = vec![[0.0f64; 2]; n];
    let mut present = vec![true; n];
    for f in &frames {
        for (i, r) in f.records.iter().enumerate().take(n) {
            match r.u_mm {
                Some(u) => {
                    mean[i][0] += u[0] / nf as f64;
                    mean[i][1] += u[1] / nf as f64;
                }
                None => present[i] = false,
            }
        }
    }
    let (mut ss, mut dof) = (0.0, 0usize);
    for (i, m) in mean.iter().enumerate().filter(|(i, _)| present[*i]) {
        for f in &frames {
            if let Some(v) = f.records.get(i).and_then(|r| r.u_mm) {
                ss += (v[0] - m[0]).powi(2) + (v[1] - m[1]).powi(2);
            }
        }
        dof += 2 * nf.saturating_sub(1);
    }
    if dof == 0 {
        return Err(format!(
            "setpoint {index} has σ recorded but {nf} frame(s) tracked in its displacement file"
        ));
    }
    Ok((
        (ss / dof as f64).sqrt() / (nf as f64).sqrt(),
        format!("scatter between the setpoint's {nf} frames, of their mean"),
    ))
}

/// One camera panel: an annotated PNG and its caption.
#[derive(Debug, Clone)]
pub struct CameraPanel {
    /// File stem in `plots/`.
    pub stem: String,
    /// Caption.
    pub caption: String,
    /// PNG bytes.
    pub png: Vec<u8>,
}

/// A tracker status's colour.
pub fn status_color(status: &str) -> RGBColor {
    match status {
        "ok" => RGBColor(0, 200, 60),
        "lost" => RGBColor(255, 40, 40),
        "merged" => RGBColor(200, 80, 255),
        _ => RGBColor(255, 170, 0),
    }
}

/// One marker of a recorded track file.
#[derive(Debug, Clone)]
struct TrackedMarker {
    /// Reference centroid, px (the node position for a marker missing from the
    /// reference).
    ref_px: [f64; 2],
    /// Measured displacement, px (`None` when lost).
    u_px: Option<[f64; 2]>,
    /// Tracker status.
    status: String,
}

/// The first frame's markers of `displacements/NNNNN.csv` and that frame's path.
fn read_tracks(run: &RunData, index: usize) -> Result<(PathBuf, Vec<TrackedMarker>), String> {
    let path = crate::analysis::displacements_path(&run.dir, index);
    let mut rd = csv::Reader::from_path(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let headers = rd
        .headers()
        .map_err(|e| format!("{}: {e}", path.display()))?
        .clone();
    let col = |name: &str| headers.iter().position(|h| h == name);
    let (Some(cf), Some(cx), Some(cy), Some(cux), Some(cuy), Some(cs), Some(cxm), Some(cym)) = (
        col("frame"),
        col("x_px"),
        col("y_px"),
        col("ux_px"),
        col("uy_px"),
        col("status"),
        col("x_mm"),
        col("y_mm"),
    ) else {
        return Err(format!(
            "{} has no tracker columns (frame, x_px, y_px, ux_px, uy_px, status)",
            path.display()
        ));
    };
    let cam = &run.sensor.camera;
    let num = |s: &str| s.trim().parse::<f64>().ok().filter(|v| v.is_finite());
    let mut frame: Option<String> = None;
    let mut out = Vec::new();
    for rec in rd.records() {
        let rec = rec.map_err(|e| format!("{}: {e}", path.display()))?;
        let f = rec.get(cf).unwrap_or("").to_string();
        match &frame {
            None => frame = Some(f),
            Some(first) if *first != f => break,
            _ => {}
        }
        let ref_px = match (
            num(rec.get(cx).unwrap_or("")),
            num(rec.get(cy).unwrap_or("")),
        ) {
            (Some(x), Some(y)) => [x, y],
            _ => {
                let (Some(xm), Some(ym)) = (
                    num(rec.get(cxm).unwrap_or("")),
                    num(rec.get(cym).unwrap_or("")),
                ) else {
                    continue;
                };
                [
                    xm / cam.mm_per_px + cam.origin_px[0],
                    ym / cam.mm_per_px + cam.origin_px[1],
                ]
            }
        };
        let u_px = match (
            num(rec.get(cux).unwrap_or("")),
            num(rec.get(cuy).unwrap_or("")),
        ) {
            (Some(a), Some(b)) => Some([a, b]),
            _ => None,
        };
        out.push(TrackedMarker {
            ref_px,
            u_px,
            status: rec.get(cs).unwrap_or("").trim().to_string(),
        });
    }
    let frame = frame.ok_or_else(|| format!("{}: no rows", path.display()))?;
    Ok((run.dir.join(frame), out))
}

/// The setpoints the camera evidence shows: the highest load and the one nearest
/// half of it (by F/T |F|; by |shift| on a displacement sweep).
pub fn chosen_setpoints(run: &RunData) -> Vec<usize> {
    let load = |r: &JournalRow| match run.plan.sweep {
        Sweep::Displacement { .. } => {
            let s = run.setpoints[r.index].shift_mm;
            s[0].hypot(s[1])
        }
        _ => applied_n(r),
    };
    let Some(top) = run
        .rows
        .iter()
        .filter(|r| load(r).is_finite())
        .max_by(|a, b| load(a).total_cmp(&load(b)))
    else {
        return Vec::new();
    };
    let half = 0.5 * load(top);
    let mid = run
        .rows
        .iter()
        .filter(|r| r.index != top.index && load(r).is_finite())
        .min_by(|a, b| (load(a) - half).abs().total_cmp(&(load(b) - half).abs()));
    let mut out = vec![top.index];
    if let Some(m) = mid {
        if load(m) > 0.0 {
            out.push(m.index);
        }
    }
    out
}

/// Smallest marker pitch and diameter of the sensor's layers, mm.
fn marker_geometry(run: &RunData) -> (f64, f64) {
    let mut pitch = f64::INFINITY;
    let mut diam = f64::INFINITY;
    for l in &run.sensor.layers {
        if let Some(m) = l.markers {
            pitch = pitch.min(m.grid.pitch_mm);
            diam = diam.min(m.diameter_mm);
        }
    }
    (
        if pitch.is_finite() { pitch } else { 1.5 },
        if diam.is_finite() { diam } else { 0.6 },
    )
}

/// Draws one annotated camera image. `arrows` = the displacement scale (×), `None`
/// for the reference frame.
fn annotate(
    image_path: &Path,
    markers: &[TrackedMarker],
    run: &RunData,
    arrow_scale: Option<f64>,
    title: &str,
) -> Result<(Vec<u8>, [u32; 4], u32), String> {
    let img = image::open(image_path)
        .map_err(|e| format!("{}: {e}", image_path.display()))?
        .to_rgb8();
    let (iw, ih) = img.dimensions();
    let mm_per_px = run.sensor.camera.mm_per_px;
    let (pitch_mm, diam_mm) = marker_geometry(run);
    let pitch_px = pitch_mm / mm_per_px;
    // Crop: the markers' reference box plus one pitch, inside the image.
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for m in markers {
        x0 = x0.min(m.ref_px[0]);
        y0 = y0.min(m.ref_px[1]);
        x1 = x1.max(m.ref_px[0]);
        y1 = y1.max(m.ref_px[1]);
    }
    if x0 > x1 {
        (x0, y0, x1, y1) = (0.0, 0.0, iw as f64, ih as f64);
    }
    let cx0 = (x0 - pitch_px).floor().clamp(0.0, iw as f64 - 1.0) as u32;
    let cy0 = (y0 - pitch_px).floor().clamp(0.0, ih as f64 - 1.0) as u32;
    let cx1 = (x1 + pitch_px).ceil().clamp(cx0 as f64 + 1.0, iw as f64) as u32;
    let cy1 = (y1 + pitch_px).ceil().clamp(cy0 as f64 + 1.0, ih as f64) as u32;
    let (cw, ch) = (cx1 - cx0, cy1 - cy0);
    let zoom = (900 / cw).clamp(1, 4);
    let band = 58u32; // title and legend band, px
    let (w, h) = (cw * zoom, ch * zoom + band);
    let mut rgb = vec![255u8; (w * h * 3) as usize];
    // The band is grey so the light status colours read on it.
    rgb[..(w * band * 3) as usize].fill(70);
    for y in 0..ch * zoom {
        for x in 0..cw * zoom {
            let p = img.get_pixel(cx0 + x / zoom, cy0 + y / zoom).0;
            let o = (((y + band) * w + x) * 3) as usize;
            rgb[o..o + 3].copy_from_slice(&p);
        }
    }
    register_fonts();
    let to = |p: [f64; 2]| -> (i32, i32) {
        (
            ((p[0] - cx0 as f64 + 0.5) * zoom as f64).round() as i32,
            ((p[1] - cy0 as f64 + 0.5) * zoom as f64).round() as i32 + band as i32,
        )
    };
    let radius = ((0.5 * diam_mm / mm_per_px + 2.0) * zoom as f64).round() as i32;
    {
        let root = PngBackend::new(&mut rgb, (w, h)).into_drawing_area();
        let e = |e: DrawingAreaErrorKind<_>| e.to_string();
        root.draw(&Text::new(
            title.to_string(),
            (8, 6),
            (FONT, 17).into_font().color(&WHITE),
        ))
        .map_err(e)?;
        let mut counts: HashMap<&str, usize> = HashMap::new();
        for m in markers {
            let status = m.status.as_str();
            *counts.entry(status).or_default() += 1;
            let c = status_color(status);
            let at = match (m.u_px, arrow_scale) {
                (Some(u), Some(_)) => [m.ref_px[0] + u[0], m.ref_px[1] + u[1]],
                _ => m.ref_px,
            };
            let p = to(at);
            if status == "lost" {
                let r = radius.max(3);
                for (a, b) in [((-r, -r), (r, r)), ((-r, r), (r, -r))] {
                    root.draw(&PathElement::new(
                        vec![(p.0 + a.0, p.1 + a.1), (p.0 + b.0, p.1 + b.1)],
                        c.stroke_width(2),
                    ))
                    .map_err(e)?;
                }
            } else {
                root.draw(&Circle::new(p, radius, c.stroke_width(2)))
                    .map_err(e)?;
            }
            if let (Some(u), Some(k)) = (m.u_px, arrow_scale) {
                let a = to(m.ref_px);
                let b = to([m.ref_px[0] + k * u[0], m.ref_px[1] + k * u[1]]);
                let len = ((b.0 - a.0) as f64).hypot((b.1 - a.1) as f64);
                if let Some((shaft, head)) = arrow_parts(
                    (a.0 as f64, a.1 as f64),
                    (b.0 as f64, b.1 as f64),
                    (0.35 * len).min(4.0 * zoom as f64),
                ) {
                    let ip = |q: (f64, f64)| (q.0.round() as i32, q.1.round() as i32);
                    let yellow = RGBColor(255, 235, 0);
                    root.draw(&PathElement::new(
                        vec![ip(shaft[0]), ip(shaft[1])],
                        yellow.stroke_width(2),
                    ))
                    .map_err(e)?;
                    root.draw(&Polygon::new(
                        head.iter().map(|q| ip(*q)).collect::<Vec<_>>(),
                        yellow.filled(),
                    ))
                    .map_err(e)?;
                }
            }
        }
        // Legend with counts, in the band above the image.
        for (i, st) in ["ok", "lost", "merged", "outlier"].iter().enumerate() {
            let x = 14 + 150 * i as i32;
            let y = 42;
            root.draw(&Circle::new((x, y), 6, status_color(st).stroke_width(3)))
                .map_err(e)?;
            root.draw(&Text::new(
                format!("{st} {}", counts.get(st).copied().unwrap_or(0)),
                (x + 12, y - 8),
                (FONT, 15).into_font().color(&WHITE),
            ))
            .map_err(e)?;
        }
        root.present().map_err(e)?;
    }
    let png = encode_png(&rgb, w, h)?;
    Ok((png, [cx0, cy0, cw, ch], zoom))
}

/// The camera panels of a run, or why there are none.
pub fn camera_evidence(analysis: &RunAnalysis) -> Result<Vec<CameraPanel>, String> {
    let run = &analysis.run;
    let chosen = chosen_setpoints(run);
    if chosen.is_empty() {
        return Err("the journal has no rows".into());
    }
    let mut panels = Vec::new();
    let mm_per_px = run.sensor.camera.mm_per_px;
    let (pitch_mm, _) = marker_geometry(run);
    let mut reference_done = false;
    for &index in &chosen {
        let tracks = crate::analysis::displacements_path(&run.dir, index);
        if !tracks.is_file() {
            return Err(format!(
                "{} (tracked displacements of setpoint {index}) is not in the run directory",
                tracks.display()
            ));
        }
        let (frame, markers) = read_tracks(run, index)?;
        if !frame.is_file() {
            return Err(format!(
                "{} (frame of setpoint {index}) is not in the run directory",
                frame.display()
            ));
        }
        if !reference_done {
            // The reference these tracks were measured against.
            let reference = run.dir.join("frames").join("reference.png");
            if reference.is_file() {
                let ref_markers: Vec<TrackedMarker> = markers
                    .iter()
                    .map(|m| TrackedMarker {
                        ref_px: m.ref_px,
                        u_px: None,
                        status: if m.status == "lost" && m.u_px.is_none() {
                            // Missing from the reference itself when its centroid is
                            // absent; the track file cannot tell otherwise.
                            "lost".into()
                        } else {
                            "ok".into()
                        },
                    })
                    .collect();
                let (png, crop, zoom) = annotate(
                    &reference,
                    &ref_markers,
                    run,
                    None,
                    "reference frame (unloaded)",
                )?;
                panels.push(CameraPanel {
                    stem: "camera_reference".into(),
                    caption: format!(
                        "Reference frame frames/reference.png, cropped to x {}–{} px, y {}–{} px, \
                         shown ×{zoom}: every marker at its reference centroid (green: found; red \
                         cross: a marker whose node has no centroid in the track file).",
                        crop[0],
                        crop[0] + crop[2],
                        crop[1],
                        crop[1] + crop[3]
                    ),
                    png,
                });
            }
            reference_done = true;
        }
        let umax = markers
            .iter()
            .filter_map(|m| m.u_px)
            .fold(0.0f64, |a, u| a.max(u[0].hypot(u[1])));
        let scale = if umax > 0.0 {
            nice_floor((0.8 * pitch_mm / mm_per_px / umax).max(1.0))
        } else {
            1.0
        };
        let row = run.rows.iter().find(|r| r.index == index);
        let what = match (&run.plan.sweep, row) {
            (Sweep::Displacement { .. }, _) => {
                let s = run.setpoints[index].shift_mm;
                format!("shift ({:.3}, {:.3}) mm", s[0], s[1])
            }
            (_, Some(r)) => format!("F/T |F| = {}", fmt_force(applied_n(r), run.plan.force_unit)),
            _ => String::new(),
        };
        let rel = frame
            .strip_prefix(&run.dir)
            .unwrap_or(&frame)
            .display()
            .to_string();
        let (png, crop, zoom) = annotate(
            &frame,
            &markers,
            run,
            Some(scale),
            &format!("setpoint {index}: {what}; arrows ×{scale}"),
        )?;
        panels.push(CameraPanel {
            stem: format!("camera_{index:05}"),
            caption: format!(
                "Setpoint {index} ({what}): frame {rel}, cropped to x {}–{} px, y {}–{} px, shown \
                 ×{zoom}. Circles at the tracked marker positions coloured by the tracker's \
                 status as recorded in displacements/{index:05}.csv (green ok, red ✕ lost at \
                 its reference position, purple merged, orange outlier; counts in the legend); \
                 yellow arrows from each marker's reference position along its displacement, \
                 drawn ×{scale} (largest displacement {:.2} px).",
                crop[0],
                crop[0] + crop[2],
                crop[1],
                crop[1] + crop[3],
                umax
            ),
            png,
        });
    }
    Ok(panels)
}

/// Writes the panels into `plots/` and renders the page sections: the force-field
/// note (when the run has no force field) and the camera evidence.
pub fn write_sections(
    plots: &Path,
    force_note: Option<&str>,
    camera: &Result<Vec<CameraPanel>, String>,
) -> Result<(String, Vec<PathBuf>), (PathBuf, std::io::Error)> {
    let mut o = String::new();
    let mut files = Vec::new();
    if let Some(n) = force_note {
        let _ = writeln!(
            o,
            "<h2>Force field</h2>\n<p class=\"no-force-field\">{}</p>",
            escape(n)
        );
    }
    o.push_str("<h2 id=\"camera-evidence\">Camera evidence</h2>\n");
    match camera {
        Err(why) => {
            let _ = writeln!(
                o,
                "<p class=\"no-camera-evidence\">No camera evidence: {}.</p>",
                escape(why)
            );
        }
        Ok(panels) => {
            std::fs::create_dir_all(plots).map_err(|e| (plots.to_path_buf(), e))?;
            let b64 = base64::engine::general_purpose::STANDARD;
            for p in panels {
                let path = plots.join(format!("{}.png", p.stem));
                std::fs::write(&path, &p.png).map_err(|e| (path.clone(), e))?;
                files.push(path);
                let _ = writeln!(
                    o,
                    "<figure id=\"{}\" class=\"camera\"><img alt=\"{}\" src=\"data:image/png;base64,{}\">\
                     <figcaption>{}</figcaption></figure>",
                    escape(&p.stem),
                    escape(&p.caption),
                    b64.encode(&p.png),
                    escape(&p.caption)
                );
            }
        }
    }
    Ok((o, files))
}
