//! What the model-error study writes: `model_error.csv` and the out directory's
//! `README.md` (see [`super`]).

use super::*;

/// Columns of `model_error.csv` (documented in the README): errors relative (0.05 =
/// 5 %), forces N, build times ms, per-frame times µs, λ mm/N.
pub const MODEL_ERROR_COLUMNS: [&str; 38] = [
    "thickness_mm",
    "depths_mm",
    "physics",
    "solver_model",
    "matched",
    "solver",
    "load",
    "effects",
    "data",
    "status",
    "reason",
    "applied_fx_n",
    "applied_fy_n",
    "applied_fz_n",
    "fsum_x_n",
    "fsum_y_n",
    "fsum_z_n",
    "field_error",
    "field_error_x",
    "field_error_y",
    "field_error_z",
    "sum_error",
    "sum_error_x",
    "sum_error_y",
    "sum_error_z",
    "mean_abs_gf",
    "markers_used",
    "markers_total",
    "realisations",
    "t_h_ms",
    "t_precompute_ms",
    "t_build_ms",
    "t_track_us",
    "t_solve_us",
    "t_frame_us",
    "lambda_mm_per_n",
    "rank",
    "condition_number",
];

/// A number for the CSV: `fmt` when finite, empty otherwise.
fn num(v: f64, scale: f64, digits: usize, sci: bool) -> String {
    if !v.is_finite() {
        return String::new();
    }
    if sci {
        format!("{:.digits$e}", v * scale)
    } else {
        format!("{:.digits$}", v * scale)
    }
}

impl ModelErrorResult {
    /// Writes `model_error.csv` ([`MODEL_ERROR_COLUMNS`]); refused rows have empty
    /// numbers and their reason.
    pub fn write_csv(&self, path: &Path) -> Result<(), ModelErrorStudyError> {
        let werr = |e: &dyn std::fmt::Display| ModelErrorStudyError::Write {
            path: path.to_path_buf(),
            message: e.to_string(),
        };
        let mut w = csv::Writer::from_path(path).map_err(|e| werr(&e))?;
        w.write_record(MODEL_ERROR_COLUMNS).map_err(|e| werr(&e))?;
        for r in &self.rows {
            let ok = r.is_ok();
            let e = |v: f64| {
                if ok {
                    num(v, 1.0, 6, true)
                } else {
                    String::new()
                }
            };
            let f = |v: f64| {
                if ok {
                    num(v, 1.0, 6, false)
                } else {
                    String::new()
                }
            };
            let ms = |v: f64| {
                if ok {
                    num(v, 1e3, 3, false)
                } else {
                    String::new()
                }
            };
            let us = |v: f64| {
                if ok {
                    num(v, 1e6, 3, false)
                } else {
                    String::new()
                }
            };
            let depths: Vec<String> = r.depths_mm.iter().map(|d| format!("{d}")).collect();
            let mut rec = vec![
                format!("{}", r.thickness_mm),
                depths.join(";"),
                r.physics.name().to_string(),
                r.solver_model.name().to_string(),
                r.matched().to_string(),
                r.solver.name().to_string(),
                r.load.name().to_string(),
                r.effects.clone(),
                r.data.name().to_string(),
                match &r.status {
                    RowStatus::Ok => "ok".to_string(),
                    RowStatus::Refused(_) => "refused".to_string(),
                },
                match &r.status {
                    RowStatus::Ok => String::new(),
                    RowStatus::Refused(why) => why.clone(),
                },
            ];
            rec.extend(r.applied_n.map(|v| num(v, 1.0, 6, false)));
            rec.extend(r.errors.fsum_n.map(f));
            rec.push(e(r.errors.field));
            rec.extend(r.errors.field_axis.map(e));
            rec.push(e(r.errors.sum));
            rec.extend(r.errors.sum_axis.map(e));
            rec.push(e(r.errors.mean_abs_gf));
            rec.push(if ok {
                r.markers_used.0.to_string()
            } else {
                String::new()
            });
            rec.push(r.markers_used.1.to_string());
            rec.push(if ok {
                r.realisations.to_string()
            } else {
                String::new()
            });
            rec.push(r.t_h_s.map_or(String::new(), ms));
            rec.push(ms(r.t_precompute_s));
            rec.push(ms(r.t_build_s));
            rec.push(r.t_track_s.map_or(String::new(), us));
            rec.push(us(r.t_solve_s));
            rec.push(us(r.t_frame_s));
            rec.push(r.lambda.map_or(String::new(), |l| num(l, 1.0, 6, true)));
            rec.push(r.rank.map_or(String::new(), |k| k.to_string()));
            rec.push(e(r.condition_number));
            w.write_record(&rec).map_err(|e| werr(&e))?;
        }
        w.flush().map_err(|e| werr(&e))
    }

    /// The measured row of a combination, if any.
    #[allow(clippy::too_many_arguments)]
    pub fn find(
        &self,
        thickness_mm: f64,
        physics: ModelKind,
        solver_model: ModelKind,
        solver: Method,
        load: LoadKind,
        effects: &str,
    ) -> Option<&ModelErrorRow> {
        self.rows.iter().find(|r| {
            r.thickness_mm == thickness_mm
                && r.physics == physics
                && r.solver_model == solver_model
                && r.solver == solver
                && r.load == load
                && r.effects == effects
                && r.is_ok()
        })
    }

    /// The effect-set label the headline figures use: `none` when it ran, else the
    /// first set.
    pub fn headline_effects(&self) -> String {
        let labels: Vec<String> = self.options.effects.iter().map(EffectSet::label).collect();
        if labels.iter().any(|l| l == "none") {
            "none".into()
        } else {
            labels.first().cloned().unwrap_or_default()
        }
    }

    /// Writes the out directory's `README.md`: what ran (`command`), the definitions,
    /// the headline table (bonded-layer data, half-space against matching solver) and
    /// the refused rows.
    pub fn write_readme(&self, path: &Path, command: &str) -> Result<(), ModelErrorStudyError> {
        let text = self.readme(command);
        std::fs::write(path, text).map_err(|e| ModelErrorStudyError::Write {
            path: path.to_path_buf(),
            message: e.to_string(),
        })
    }

    /// The text of [`Self::write_readme`].
    pub fn readme(&self, command: &str) -> String {
        use std::fmt::Write as _;
        let o = &self.options;
        let mut s = String::new();
        let _ = writeln!(s, "# Model error: half-space against bonded-layer solver\n");
        let _ = writeln!(
            s,
            "Generated by `{command}` ({}; do not edit by hand).\n",
            if cfg!(debug_assertions) {
                "dev profile: crate at opt-level 1, dependencies at 3"
            } else {
                "release"
            }
        );
        let _ = writeln!(
            s,
            "Data made with each physics (`bonded-layer` at the row's thickness, and the \
             `half-space` reference) is solved by a solver inverting the half-space and one \
             inverting the bonded layer of the same thickness (`matched` = the solver's model \
             is the data's). Load: the paper's Fig. 6 load (100 gf z + 50 gf y over force \
             points (4,3)-(7,6)): `normal` its z part, `tangential` its y part, `mixed` both. \
             Effects `none`: forward-model marker displacements, nodal load{}; other effect \
             sets: rendered, tracked and solved (5 mm flat probe on the patch centre, {} \
             loaded frame(s)). Markers: deepest at most {} of the thickness.\n",
            if o.noise_px > 0.0 {
                format!(", {} px noise", o.noise_px)
            } else {
                ", exact".to_string()
            },
            o.realisations,
            o.max_depth_fraction
        );
        let _ = writeln!(
            s,
            "Errors: `field` = ‖f − f*‖ / ‖f*‖ over nodes and axes; `F_sum` = |ΣF − \
             F_applied| / |F_applied|; per-axis columns in `model_error.csv` (see the \
             project README). Times: build = H (cold) + solver precompute, per frame = \
             tracking + solve, medians over {} repetitions on this machine.\n",
            o.reps
        );
        self.readme_tables(&mut s);
        self.readme_notes(&mut s);
        let _ = writeln!(
            s,
            "Files: `model_error.csv` (every row, columns in the project README), \
             `model_error.png` / `.svg` (error against thickness)."
        );
        s
    }

    /// The headline tables of the README: per effect set and solver, half-space against matching solver on bonded-layer data.
    fn readme_tables(&self, s: &mut String) {
        use std::fmt::Write as _;
        let o = &self.options;
        let sets: Vec<String> = o.effects.iter().map(EffectSet::label).collect();
        for (eff, config) in sets
            .iter()
            .flat_map(|e| o.solvers.iter().map(move |c| (e.clone(), c)))
        {
            let m = config.method;
            let _ = writeln!(
                s,
                "## Bonded-layer data, effects `{eff}`, solver `{}`\n",
                m.name()
            );
            let _ = writeln!(
                s,
                "| thickness, mm | depths, mm | load | field error, half-space solver | field error, matching | F_sum error, half-space | F_sum error, matching | build, half-space / matching, ms | per frame, half-space / matching, µs |"
            );
            let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|");
            for &h in &o.thicknesses_mm {
                for &load in &o.loads {
                    let hs = self.find(
                        h,
                        ModelKind::BondedLayer,
                        ModelKind::HalfSpace,
                        m,
                        load,
                        &eff,
                    );
                    let bl = self.find(
                        h,
                        ModelKind::BondedLayer,
                        ModelKind::BondedLayer,
                        m,
                        load,
                        &eff,
                    );
                    if hs.is_none() && bl.is_none() {
                        continue;
                    }
                    let depths = hs
                        .or(bl)
                        .map(|r| {
                            r.depths_mm
                                .iter()
                                .map(|d| format!("{d}"))
                                .collect::<Vec<_>>()
                                .join(" / ")
                        })
                        .unwrap_or_default();
                    let pct = |r: Option<&ModelErrorRow>, f: fn(&ModelErrorRow) -> f64| {
                        r.map_or("refused".to_string(), |r| format!("{:.2} %", 100.0 * f(r)))
                    };
                    let t = |r: Option<&ModelErrorRow>, f: fn(&ModelErrorRow) -> f64, sc: f64| {
                        r.map_or("—".to_string(), |r| format!("{:.1}", f(r) * sc))
                    };
                    let _ = writeln!(
                        s,
                        "| {h} | {depths} | {} | {} | {} | {} | {} | {} / {} | {} / {} |",
                        load.name(),
                        pct(hs, |r| r.errors.field),
                        pct(bl, |r| r.errors.field),
                        pct(hs, |r| r.errors.sum),
                        pct(bl, |r| r.errors.sum),
                        t(hs, |r| r.t_build_s, 1e3),
                        t(bl, |r| r.t_build_s, 1e3),
                        t(hs, |r| r.t_frame_s, 1e6),
                        t(bl, |r| r.t_frame_s, 1e6),
                    );
                }
            }
            let _ = writeln!(s);
        }
    }

    /// The README's notes: rendered rows whose upper layer is shallower than the force grid resolves, and the refused rows by reason.
    fn readme_notes(&self, s: &mut String) {
        use std::fmt::Write as _;
        let o = &self.options;
        let shallow: Vec<f64> = o
            .thicknesses_mm
            .iter()
            .copied()
            .filter(|&h| {
                self.rows.iter().any(|r| {
                    r.thickness_mm == h
                        && r.data == DataPath::Pipeline
                        && r.depths_mm.iter().fold(f64::INFINITY, |a, b| a.min(*b))
                            < 0.75 * self.force_pitch_mm
                })
            })
            .collect();
        if !shallow.is_empty() {
            let _ = writeln!(
                s,
                "Note on the rendered rows at {} mm: the upper marker layer lies at less than \
                 3/4 of the force-grid pitch ({} mm), so its markers see the contact's traction \
                 in more detail than point forces on the grid nodes can represent; the errors \
                 of both \
                 solvers on those rows are dominated by that discretisation, not by the elastic \
                 model (the forward rows, load on the nodes, show the model error alone). A thin \
                 gel needs a force grid about as fine as its marker depth.\n",
                shallow
                    .iter()
                    .map(|h| h.to_string())
                    .collect::<Vec<_>>()
                    .join(", "),
                self.force_pitch_mm
            );
        }
        let refused: Vec<&ModelErrorRow> = self.rows.iter().filter(|r| !r.is_ok()).collect();
        if !refused.is_empty() {
            let _ = writeln!(s, "## Refused rows ({})\n", refused.len());
            let mut reasons: Vec<(String, usize)> = Vec::new();
            for r in refused {
                let RowStatus::Refused(why) = &r.status else {
                    continue;
                };
                let key = format!(
                    "{} solver, {} load, effects {}: {}",
                    r.solver.name(),
                    r.load.name(),
                    r.effects,
                    why.split("; ").next().unwrap_or_default()
                );
                match reasons.iter_mut().find(|(k, _)| *k == key) {
                    Some((_, n)) => *n += 1,
                    None => reasons.push((key, 1)),
                }
            }
            for (k, n) in reasons {
                let _ = writeln!(s, "- {n} × {k}");
            }
            let _ = writeln!(s);
        }
    }
}
