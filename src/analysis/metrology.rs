//! Force-measurement metrology in the spirit of ISO 376:2011 ("Metallic materials —
//! Calibration of force-proving instruments used for the verification of uniaxial
//! testing machines"): the reconstructed normal force F^sum (journal `fsum_z_n`) is the
//! instrument under test, the F/T sensor's `fz_n` the reference.
//!
//! Every error is expressed in **% of full scale** (%FS), `FS` = the largest applied
//! force of the run (max `fz_n` over the rows used, N; metric
//! `metrology.full_scale_n`). ISO 376 relates b, b', f_c and v to the mean reading at
//! each force step; a tactile sensor's errors near zero load would make such ratios
//! meaningless, so we divide by FS instead, which is *more lenient* than the standard
//! at every force below full scale. Errors are F^sum errors in newtons divided by FS
//! in newtons (no gain correction).
//!
//! Readings are the journal rows of a magnitude sweep. A *trial* is a
//! `(position, trial)` pair (journal `position`, `trial`); a row is *down* when the
//! journal says `direction = down`, else when its target falls within its trial
//! ([`super::calibration::directions`]); *unloaded* when its target is 0. The
//! calibration line `F^sum = slope·F/T + offset` is the least-squares line through the
//! *loading* (not down) rows, as ISO 376 fits its interpolation equation to the
//! increasing series (we use a straight line, the sensor's calibration, not the
//! standard's polynomial of up to third degree); the residual of a row is
//! `r = F^sum − (slope·F/T + offset)`, which removes the small spread of the applied
//! force within a level. *Loaded levels* are the non-zero targets.
//!
//! | metric | ISO 376:2011 | definition here |
//! |---|---|---|
//! | `metrology.repeatability_pct_fs` | b', relative repeatability error (7.5.1; same mounting, no rotation) | pooled SD of r within cells (position × loaded level × direction) over the trials, `s_r = √(ΣΣ(r − r̄_cell)² / Σ(n_cell − 1))`, ×100/FS. 95 % CI: chi-squared with Σ(n_cell − 1) dof |
//! | `metrology.reproducibility_pct_fs` | b, relative reproducibility error (7.5.1; rotated mountings) | the same pooled SD with cells (loaded level × direction) taken over *all positions* and trials: spread across contact positions plus within them; needs ≥ 2 positions. 95 % CI: bootstrap |
//! | `metrology.interpolation_pct_fs` | f_c, relative interpolation error (7.5.2) | max over loaded levels of \|mean r of the level's loading rows\|, ×100/FS; needs ≥ 3 levels (a line through two fits exactly). 95 % CI: bootstrap |
//! | `metrology.zero_pct_fs` | f_0, relative zero error (7.5.3) | per trial that starts and ends unloaded, `d = e_end − e_start` with `e = F^sum − F/T`; the mean of d over the trials, signed, ×100/FS. 95 % CI: Student t over trials |
//! | `metrology.zero_max_pct_fs` | f_0 (each series must meet the limit) | max \|d\| over the trials, ×100/FS (no CI: a maximum) |
//! | `metrology.reversibility_pct_fs` | v, relative reversibility error (7.5.4; hysteresis) | per loaded level measured both ways, `mean r(down) − mean r(up)`; the max of its absolute value over levels, ×100/FS. 95 % CI: bootstrap |
//! | `metrology.class` | classification (clause 8, Table 2) | the worst class over the criteria the run has (see below) |
//!
//! Creep (`c`, ISO 376:2011 7.5.5: the change of the reading between 30 s and 300 s at
//! constant maximum force) is measured by `hold` sweeps, see [`super::hold`].
//!
//! **Bootstrap** (where no closed form exists): percentile intervals (2.5 %, 97.5 %)
//! over [`BOOTSTRAP_RESAMPLES`] resamples drawn with [`crate::sim::rng::Rng`] seeded
//! with [`BOOTSTRAP_SEED`], resampling whole trials with replacement within each
//! position (so every resample keeps the position design); the line is refitted in
//! every resample. No interval is stated when a position has fewer than two trials, or
//! when more than 5 % of the resamples cannot compute the metric. Intervals of a
//! maximum over levels (interpolation, reversibility) describe how stable the worst
//! level is under resampling; they are not bias-corrected.
//!
//! **Class** (ISO 376:2011 Table 2, limits in %): [`ISO376_CLASSES`]
//!
//! | class | b | b' | f_c | f_0 | v | c |
//! |---|---|---|---|---|---|---|
//! | 00 | 0.05 | 0.025 | ±0.025 | ±0.012 | 0.07 | 0.025 |
//! | 0.5 | 0.10 | 0.05 | ±0.05 | ±0.025 | 0.15 | 0.05 |
//! | 1 | 0.20 | 0.10 | ±0.10 | ±0.050 | 0.30 | 0.10 |
//! | 2 | 0.40 | 0.20 | ±0.20 | ±0.10 | 0.50 | 0.20 |
//!
//! ISO's b and b' are ranges of readings (b: three rotated series, b': two series); we
//! compare the *expected range* of our SDs, `d2·s` with `d2 = 1.693` (3 readings) for b
//! and `1.128` (2 readings) for b'. f_0 is compared as `zero_max`, c as the creep rate
//! times 4.5 min (30 s to 300 s). The metric is 0 for class 00, 0.5, 1 or 2 for those
//! classes, and **3 when a criterion is outside class 2 (no class)**. A tactile sensor
//! is not a force-proving instrument: its F^sum is typically a few % of FS off in every
//! criterion, one to two orders of magnitude outside class 2, and the report says so.

use std::collections::{BTreeMap, BTreeSet};

use super::calibration::{directions, same_level, Direction};
use super::stats::{self, LineFit};
use super::Ci95;
use crate::bench::journal::{self, JournalRow};
use crate::sim::rng::Rng;

/// Seed of every bootstrap of the analyses.
pub const BOOTSTRAP_SEED: u64 = 376;
/// Resamples of every bootstrap.
pub const BOOTSTRAP_RESAMPLES: usize = 1000;
/// `Ci95::method` of the stratified percentile bootstrap.
pub const BOOTSTRAP_METHOD: &str = "bootstrap";

/// Expected range of two normal readings in SDs (`d2(2) = 2/√π`).
pub const D2_TWO: f64 = 1.128;
/// Expected range of three normal readings in SDs (`d2(3)`).
pub const D2_THREE: f64 = 1.693;
/// ISO 376's creep interval, 30 s to 300 s, in minutes.
pub const CREEP_INTERVAL_MIN: f64 = 4.5;

/// One ISO 376 class and its limits (%).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IsoClass {
    /// `00`, `0.5`, `1`, `2`.
    pub name: &'static str,
    /// Value of `metrology.class` for it.
    pub code: f64,
    /// Relative reproducibility error b.
    pub b: f64,
    /// Relative repeatability error b'.
    pub b_prime: f64,
    /// Relative interpolation error f_c (±).
    pub f_c: f64,
    /// Relative zero error f_0 (±).
    pub f_0: f64,
    /// Relative reversibility error v.
    pub v: f64,
    /// Creep c.
    pub c: f64,
}

/// ISO 376:2011 Table 2, best class first.
pub const ISO376_CLASSES: [IsoClass; 4] = [
    IsoClass {
        name: "00",
        code: 0.0,
        b: 0.05,
        b_prime: 0.025,
        f_c: 0.025,
        f_0: 0.012,
        v: 0.07,
        c: 0.025,
    },
    IsoClass {
        name: "0.5",
        code: 0.5,
        b: 0.10,
        b_prime: 0.05,
        f_c: 0.05,
        f_0: 0.025,
        v: 0.15,
        c: 0.05,
    },
    IsoClass {
        name: "1",
        code: 1.0,
        b: 0.20,
        b_prime: 0.10,
        f_c: 0.10,
        f_0: 0.05,
        v: 0.30,
        c: 0.10,
    },
    IsoClass {
        name: "2",
        code: 2.0,
        b: 0.40,
        b_prime: 0.20,
        f_c: 0.20,
        f_0: 0.10,
        v: 0.50,
        c: 0.20,
    },
];

/// `metrology.class` value of "outside class 2".
pub const NO_CLASS: f64 = 3.0;

/// The criteria of [`IsoClass`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Criterion {
    /// b.
    Reproducibility,
    /// b'.
    Repeatability,
    /// f_c.
    Interpolation,
    /// f_0.
    Zero,
    /// v.
    Reversibility,
    /// c.
    Creep,
}

impl Criterion {
    /// ISO symbol.
    pub fn symbol(self) -> &'static str {
        match self {
            Criterion::Reproducibility => "b",
            Criterion::Repeatability => "b′",
            Criterion::Interpolation => "f_c",
            Criterion::Zero => "f_0",
            Criterion::Reversibility => "v",
            Criterion::Creep => "c",
        }
    }

    /// The class limit (%).
    pub fn limit(self, c: &IsoClass) -> f64 {
        match self {
            Criterion::Reproducibility => c.b,
            Criterion::Repeatability => c.b_prime,
            Criterion::Interpolation => c.f_c,
            Criterion::Zero => c.f_0,
            Criterion::Reversibility => c.v,
            Criterion::Creep => c.c,
        }
    }
}

/// One criterion judged against the class table.
#[derive(Debug, Clone, PartialEq)]
pub struct ClassCheck {
    /// Which.
    pub criterion: Criterion,
    /// The ISO-comparable value, % (of FS).
    pub value_pct: f64,
    /// How it was obtained from the metric (e.g. `1.128 × repeatability SD`).
    pub basis: &'static str,
    /// The best class it meets (`None`: outside class 2).
    pub class: Option<&'static IsoClass>,
}

/// The class implied by some criteria.
#[derive(Debug, Clone, PartialEq)]
pub struct ClassResult {
    /// Each criterion the run has.
    pub checks: Vec<ClassCheck>,
    /// `metrology.class`: the worst over the checks (0, 0.5, 1, 2; [`NO_CLASS`]).
    pub code: f64,
}

impl ClassResult {
    /// Judges `(criterion, value %, basis)` triples; `None` when there are none.
    pub fn judge(values: &[(Criterion, f64, &'static str)]) -> Option<ClassResult> {
        if values.is_empty() {
            return None;
        }
        let checks: Vec<ClassCheck> = values
            .iter()
            .map(|&(criterion, value_pct, basis)| ClassCheck {
                criterion,
                value_pct,
                basis,
                class: ISO376_CLASSES
                    .iter()
                    .find(|c| value_pct.abs() <= criterion.limit(c)),
            })
            .collect();
        let code = checks
            .iter()
            .map(|c| c.class.map_or(NO_CLASS, |k| k.code))
            .fold(0.0, f64::max);
        Some(ClassResult { checks, code })
    }

    /// `00`, `0.5`, `1`, `2` or `none (outside class 2)`.
    pub fn name(&self) -> &'static str {
        ISO376_CLASSES
            .iter()
            .find(|c| c.code == self.code)
            .map_or("none (outside class 2)", |c| c.name)
    }
}

/// One reading of the instrument under test.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reading {
    /// Setpoint index.
    pub index: usize,
    /// Trial number (per position).
    pub trial: usize,
    /// Contact position (index into `sweep.positions_mm`), `None` for one position.
    pub position: Option<usize>,
    /// Target normal force, N.
    pub target_n: f64,
    /// Applied force (F/T `fz_n`), N.
    pub applied_n: f64,
    /// F^sum (`fsum_z_n`), N.
    pub measured_n: f64,
    /// Measured while unloading.
    pub down: bool,
}

impl Reading {
    fn unit(&self) -> (Option<usize>, usize) {
        (self.position, self.trial)
    }

    fn unloaded(&self) -> bool {
        same_level(self.target_n, 0.0)
    }
}

/// Readings of magnitude-sweep rows, with directions from the journal or the run order.
pub fn readings(rows: &[JournalRow]) -> Vec<Reading> {
    let mut by_unit: BTreeMap<(Option<usize>, usize), Vec<&JournalRow>> = BTreeMap::new();
    for r in rows {
        by_unit.entry((r.position, r.trial)).or_default().push(r);
    }
    let mut out = Vec::with_capacity(rows.len());
    for unit in by_unit.values_mut() {
        unit.sort_by_key(|r| r.index);
        let targets: Vec<f64> = unit.iter().map(|r| r.target_normal_n).collect();
        for (r, d) in unit.iter().zip(directions(&targets)) {
            let down = match r.direction {
                Some(journal::Direction::Down) => true,
                Some(journal::Direction::Up) => false,
                None => d == Direction::Unloading,
            };
            out.push(Reading {
                index: r.index,
                trial: r.trial,
                position: r.position,
                target_n: r.target_normal_n,
                applied_n: r.fz_n,
                measured_n: r.fsum_z_n,
                down,
            });
        }
    }
    out.sort_by_key(|r| r.index);
    out
}

/// Up and down branches of one loaded level.
#[derive(Debug, Clone, PartialEq)]
pub struct LevelBranches {
    /// Target, N.
    pub target_n: f64,
    /// Mean applied force of the loading rows, N.
    pub up_applied_n: Option<f64>,
    /// Mean F^sum of the loading rows, N.
    pub up_measured_n: Option<f64>,
    /// Mean residual of the loading rows, N.
    pub up_residual_n: Option<f64>,
    /// Mean applied force of the unloading rows, N.
    pub down_applied_n: Option<f64>,
    /// Mean F^sum of the unloading rows, N.
    pub down_measured_n: Option<f64>,
    /// Mean residual of the unloading rows, N.
    pub down_residual_n: Option<f64>,
}

impl LevelBranches {
    /// `down − up` mean residual, N, when both exist.
    pub fn reversibility_n(&self) -> Option<f64> {
        Some(self.down_residual_n? - self.up_residual_n?)
    }
}

/// The up and down branch means of the readings at level `target_n` (N), residuals
/// by `res`.
fn level_branches(
    readings: &[Reading],
    target_n: f64,
    res: impl Fn(&Reading) -> f64,
) -> LevelBranches {
    let mean = |v: Vec<f64>| stats::mean(&v);
    let pick = |down: bool| -> Vec<&Reading> {
        readings
            .iter()
            .filter(|r| r.down == down && same_level(r.target_n, target_n))
            .collect()
    };
    let (up, dn) = (pick(false), pick(true));
    LevelBranches {
        target_n,
        up_applied_n: mean(up.iter().map(|r| r.applied_n).collect()),
        up_measured_n: mean(up.iter().map(|r| r.measured_n).collect()),
        up_residual_n: mean(up.iter().map(|r| res(r)).collect()),
        down_applied_n: mean(dn.iter().map(|r| r.applied_n).collect()),
        down_measured_n: mean(dn.iter().map(|r| r.measured_n).collect()),
        down_residual_n: mean(dn.iter().map(|r| res(r)).collect()),
    }
}

/// The statistics of one set of readings (the data, or one bootstrap resample), N.
#[derive(Debug, Clone, PartialEq)]
struct Core {
    fit: LineFit,
    repeatability: Option<(f64, usize)>,
    reproducibility: Option<f64>,
    interpolation: Option<f64>,
    zero_diffs: Vec<f64>,
    reversibility: Option<f64>,
    levels: Vec<LevelBranches>,
}

/// Pooled SD of groups of values (`None` when no group has two).
fn pooled(groups: impl Iterator<Item = Vec<f64>>) -> Option<(f64, usize)> {
    let (mut ss, mut dof) = (0.0, 0usize);
    for g in groups {
        if g.len() >= 2 {
            let m = g.iter().sum::<f64>() / g.len() as f64;
            ss += g.iter().map(|v| (v - m).powi(2)).sum::<f64>();
            dof += g.len() - 1;
        }
    }
    (dof > 0).then(|| ((ss / dof as f64).sqrt(), dof))
}

fn core(readings: &[Reading]) -> Option<Core> {
    let loading: Vec<&Reading> = readings.iter().filter(|r| !r.down).collect();
    let x: Vec<f64> = loading.iter().map(|r| r.applied_n).collect();
    let y: Vec<f64> = loading.iter().map(|r| r.measured_n).collect();
    let fit = stats::fit_line(&x, &y)?;
    let res = |r: &Reading| r.measured_n - fit.at(r.applied_n);
    let mut targets: Vec<f64> = readings
        .iter()
        .filter(|r| !r.unloaded())
        .map(|r| r.target_n)
        .collect();
    targets.sort_by(f64::total_cmp);
    targets.dedup_by(|a, b| same_level(*a, *b));
    let level_of = |t: f64| targets.iter().position(|&l| same_level(l, t));

    // Cells: (position, level, down) and (level, down).
    let mut cells: BTreeMap<(Option<usize>, usize, bool), Vec<f64>> = BTreeMap::new();
    let mut across: BTreeMap<(usize, bool), Vec<f64>> = BTreeMap::new();
    for r in readings.iter().filter(|r| !r.unloaded()) {
        if let Some(l) = level_of(r.target_n) {
            cells
                .entry((r.position, l, r.down))
                .or_default()
                .push(res(r));
            across.entry((l, r.down)).or_default().push(res(r));
        }
    }
    let repeatability = pooled(cells.into_values());
    let positions: BTreeSet<Option<usize>> = readings.iter().map(|r| r.position).collect();
    let reproducibility = if positions.len() >= 2 {
        pooled(across.values().cloned()).map(|p| p.0)
    } else {
        None
    };

    let levels: Vec<LevelBranches> = targets
        .iter()
        .map(|&t| level_branches(readings, t, res))
        .collect();
    // A line through two levels (0 and one load) fits them exactly.
    let all_levels = targets.len() + usize::from(readings.iter().any(|r| r.unloaded()));
    let interpolation = if all_levels >= 3 {
        levels
            .iter()
            .filter_map(|l| l.up_residual_n)
            .map(f64::abs)
            .reduce(f64::max)
    } else {
        None
    };
    let reversibility = levels
        .iter()
        .filter_map(LevelBranches::reversibility_n)
        .map(f64::abs)
        .reduce(f64::max);

    let mut units: BTreeMap<(Option<usize>, usize), Vec<&Reading>> = BTreeMap::new();
    for r in readings {
        units.entry(r.unit()).or_default().push(r);
    }
    let zero_diffs = units
        .values()
        .filter_map(|u| {
            let (first, last) = (u.first()?, u.last()?);
            (u.len() >= 2 && first.unloaded() && last.unloaded()).then_some(
                (last.measured_n - last.applied_n) - (first.measured_n - first.applied_n),
            )
        })
        .collect();
    Some(Core {
        fit,
        repeatability,
        reproducibility,
        interpolation,
        zero_diffs,
        reversibility,
        levels,
    })
}

/// A metric value in %FS with its interval.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    /// Value, % of full scale.
    pub pct_fs: f64,
    /// 95 % interval, % of full scale.
    pub ci95: Option<Ci95>,
}

/// The ISO 376-style analysis of a magnitude sweep.
#[derive(Debug, Clone, PartialEq)]
pub struct MetrologyAnalysis {
    /// Full scale: the largest applied force, N.
    pub full_scale_n: f64,
    /// The calibration line through the loading rows.
    pub fit: LineFit,
    /// Every reading, in setpoint order.
    pub readings: Vec<Reading>,
    /// Loaded levels with their branches.
    pub levels: Vec<LevelBranches>,
    /// The unloaded level (target 0) with its branches, when the run recorded one: the
    /// trials' starts (loading) and returns (unloading). Not a loaded level, so neither
    /// in `levels` nor in the interpolation and reversibility errors (ISO 376 judges the
    /// return to zero as f_0); the hysteresis loop starts and ends on it.
    pub unloaded_level: Option<LevelBranches>,
    /// Distinct positions.
    pub positions: usize,
    /// Trials (position, trial pairs).
    pub trials: usize,
    /// b' (SD based).
    pub repeatability: Option<Estimate>,
    /// Degrees of freedom of the repeatability SD.
    pub repeatability_dof: usize,
    /// b (SD based).
    pub reproducibility: Option<Estimate>,
    /// f_c.
    pub interpolation: Option<Estimate>,
    /// f_0, mean signed return to zero.
    pub zero: Option<Estimate>,
    /// f_0, worst trial.
    pub zero_max_pct_fs: Option<f64>,
    /// v.
    pub reversibility: Option<Estimate>,
    /// Implied class.
    pub class: Option<ClassResult>,
    /// Metrics that could not be computed: (metric name, why).
    pub absent: Vec<(&'static str, String)>,
}

/// Percentile interval of `values` (`None` when fewer than 95 % of `total` resamples
/// gave a value).
fn percentile_ci(mut values: Vec<f64>, total: usize, scale: f64) -> Option<Ci95> {
    if values.len() * 100 < total * 95 {
        return None;
    }
    let lo = stats::quantile(&mut values, 0.025)?;
    let hi = stats::quantile(&mut values, 0.975)?;
    Some(Ci95 {
        low: lo * scale,
        high: hi * scale,
        method: BOOTSTRAP_METHOD,
    })
}

/// Analyses the rows of a magnitude sweep (`None` when no line can be fitted through
/// the loading rows or the full scale is not positive).
pub fn analyze(rows: &[JournalRow]) -> Option<MetrologyAnalysis> {
    analyze_readings(readings(rows))
}

/// As [`analyze`], from readings.
///
/// Steps: full scale (the largest applied force) and the statistics of the readings
/// ([`core`]); the trials per position; the seeded bootstrap over trials within
/// positions ([`bootstrap`]); each estimate in % of full scale with its interval,
/// or why it is absent ([`Estimates::new`]); the class they imply
/// ([`class_checks`], [`ClassResult::judge`]); the unloaded level.
pub fn analyze_readings(readings: Vec<Reading>) -> Option<MetrologyAnalysis> {
    let fs = readings
        .iter()
        .map(|r| r.applied_n)
        .fold(f64::NEG_INFINITY, f64::max);
    if !(fs.is_finite() && fs > 0.0) {
        return None;
    }
    let c = core(&readings)?;
    let pct = 100.0 / fs;
    let mut units: BTreeMap<Option<usize>, BTreeSet<usize>> = BTreeMap::new();
    for r in &readings {
        units.entry(r.position).or_default().insert(r.trial);
    }
    let positions = units.len();
    let trials: usize = units.values().map(BTreeSet::len).sum();
    let boot = bootstrap(&readings, &units);
    let e = Estimates::new(&c, pct, boot, positions);
    let checks = class_checks(&e);
    // Outside `core`: no bootstrap statistic needs it.
    let unloaded_level = readings
        .iter()
        .any(Reading::unloaded)
        .then(|| level_branches(&readings, 0.0, |r| r.measured_n - c.fit.at(r.applied_n)));
    Some(MetrologyAnalysis {
        full_scale_n: fs,
        fit: c.fit,
        readings,
        levels: c.levels,
        unloaded_level,
        positions,
        trials,
        repeatability: e.repeatability,
        repeatability_dof: c.repeatability.map_or(0, |p| p.1),
        reproducibility: e.reproducibility,
        interpolation: e.interpolation,
        zero: e.zero,
        zero_max_pct_fs: e.zero_max_pct_fs,
        reversibility: e.reversibility,
        class: ClassResult::judge(&checks),
        absent: e.absent,
    })
}

/// The bootstrap resamples' reproducibility, interpolation and reversibility (N),
/// one value per resample that gave one.
#[derive(Default)]
struct BootSamples {
    reproducibility: Vec<f64>,
    interpolation: Vec<f64>,
    reversibility: Vec<f64>,
}

/// Bootstrap over trials within positions (`units`: the trials per position):
/// [`BOOTSTRAP_RESAMPLES`] resamples from [`BOOTSTRAP_SEED`], each drawing as many
/// trials per position as it has, with replacement, each draw a distinct trial of the
/// resample. `None` when a position has fewer than two trials.
fn bootstrap(
    readings: &[Reading],
    units: &BTreeMap<Option<usize>, BTreeSet<usize>>,
) -> Option<BootSamples> {
    if !units.values().all(|t| t.len() >= 2) {
        return None;
    }
    let mut out = BootSamples::default();
    let by_unit: BTreeMap<(Option<usize>, usize), Vec<Reading>> =
        readings.iter().fold(BTreeMap::new(), |mut m, r| {
            m.entry(r.unit()).or_insert_with(Vec::new).push(*r);
            m
        });
    let strata: Vec<Vec<&Vec<Reading>>> = units
        .keys()
        .map(|p| {
            by_unit
                .iter()
                .filter(|(k, _)| k.0 == *p)
                .map(|(_, v)| v)
                .collect()
        })
        .collect();
    let mut rng = Rng::new(BOOTSTRAP_SEED);
    let mut sample = Vec::with_capacity(readings.len());
    for _ in 0..BOOTSTRAP_RESAMPLES {
        sample.clear();
        let mut new_trial = 0usize;
        for stratum in &strata {
            for _ in 0..stratum.len() {
                let k = ((rng.uniform() * stratum.len() as f64) as usize).min(stratum.len() - 1);
                // Each draw is a distinct trial of the resample.
                sample.extend(stratum[k].iter().map(|r| Reading {
                    trial: new_trial,
                    ..*r
                }));
                new_trial += 1;
            }
        }
        if let Some(b) = core(&sample) {
            out.reproducibility.extend(b.reproducibility);
            out.interpolation.extend(b.interpolation);
            out.reversibility.extend(b.reversibility);
        }
    }
    Some(out)
}

/// The estimates in % of full scale with their 95 % intervals, and the metrics that
/// could not be computed with why.
struct Estimates {
    repeatability: Option<Estimate>,
    reproducibility: Option<Estimate>,
    interpolation: Option<Estimate>,
    zero: Option<Estimate>,
    zero_max_pct_fs: Option<f64>,
    reversibility: Option<Estimate>,
    absent: Vec<(&'static str, String)>,
}

impl Estimates {
    /// From the statistics `c` (N), `pct` = 100 / full scale: the repeatability SD
    /// with its chi-squared interval, reproducibility, interpolation and
    /// reversibility with bootstrap percentile intervals (none without a
    /// bootstrap), the mean return to zero with its t interval and the worst trial's.
    fn new(c: &Core, pct: f64, boot: Option<BootSamples>, positions: usize) -> Estimates {
        let can_boot = boot.is_some();
        let b = boot.unwrap_or_default();
        let boot = |v: Vec<f64>| {
            if can_boot {
                percentile_ci(v, BOOTSTRAP_RESAMPLES, pct)
            } else {
                None
            }
        };
        let mut absent: Vec<(&'static str, String)> = Vec::new();
        let repeatability = c.repeatability.map(|(s, dof)| Estimate {
            pct_fs: s * pct,
            ci95: stats::sd_ci95(s, dof).map(|(lo, hi)| Ci95 {
                low: lo * pct,
                high: hi * pct,
                method: "chi2",
            }),
        });
        if repeatability.is_none() {
            absent.push((
                "metrology.repeatability_pct_fs",
                "no loaded level was measured twice at the same position and direction".into(),
            ));
        }
        let reproducibility = c.reproducibility.map(|s| Estimate {
            pct_fs: s * pct,
            ci95: boot(b.reproducibility),
        });
        if reproducibility.is_none() {
            absent.push((
                "metrology.reproducibility_pct_fs",
                format!("needs trials at two or more contact positions (sweep.positions_mm); the run has {positions}"),
            ));
        }
        let interpolation = c.interpolation.map(|v| Estimate {
            pct_fs: v * pct,
            ci95: boot(b.interpolation),
        });
        if interpolation.is_none() {
            absent.push((
                "metrology.interpolation_pct_fs",
                "needs three or more force levels (a line through two fits them exactly)".into(),
            ));
        }
        let zero = if c.zero_diffs.is_empty() {
            absent.push((
                "metrology.zero_pct_fs",
                "no trial starts and ends with an unloaded reading (target 0)".into(),
            ));
            None
        } else {
            let m = stats::mean(&c.zero_diffs).unwrap_or(f64::NAN);
            Some(Estimate {
                pct_fs: m * pct,
                ci95: stats::mean_ci95(&c.zero_diffs).map(|(lo, hi)| Ci95 {
                    low: lo * pct,
                    high: hi * pct,
                    method: "t",
                }),
            })
        };
        let zero_max_pct_fs = c
            .zero_diffs
            .iter()
            .map(|d| d.abs())
            .reduce(f64::max)
            .map(|v| v * pct);
        let reversibility = c.reversibility.map(|v| Estimate {
            pct_fs: v * pct,
            ci95: boot(b.reversibility),
        });
        if reversibility.is_none() {
            absent.push((
                "metrology.reversibility_pct_fs",
                "no loaded level was measured both loading and unloading (sweep.direction = \"up-down\")".into(),
            ));
        }
        Estimates {
            repeatability,
            reproducibility,
            interpolation,
            zero,
            zero_max_pct_fs,
            reversibility,
            absent,
        }
    }
}

/// The values the class is judged on (ISO 376 Table 2's criteria as this analysis
/// measures them): ranges expected of three and two series from the reproducibility
/// and repeatability SDs, interpolation, the worst trial's zero, reversibility.
fn class_checks(e: &Estimates) -> Vec<(Criterion, f64, &'static str)> {
    let mut checks = Vec::new();
    if let Some(e) = e.reproducibility {
        checks.push((
            Criterion::Reproducibility,
            D2_THREE * e.pct_fs,
            "1.693 × reproducibility SD (expected range of 3 series)",
        ));
    }
    if let Some(e) = e.repeatability {
        checks.push((
            Criterion::Repeatability,
            D2_TWO * e.pct_fs,
            "1.128 × repeatability SD (expected range of 2 series)",
        ));
    }
    if let Some(e) = e.interpolation {
        checks.push((Criterion::Interpolation, e.pct_fs, "interpolation error"));
    }
    if let Some(z) = e.zero_max_pct_fs {
        checks.push((Criterion::Zero, z, "worst trial's zero error"));
    }
    if let Some(e) = e.reversibility {
        checks.push((Criterion::Reversibility, e.pct_fs, "reversibility error"));
    }
    checks
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// An up-down trial 0, 100, 200, 300, 200, 100, 0 (N) at `position`; F^sum =
    /// 0.9·F + 0.5 + `noise(level, down)`, plus `w` on the down branch of loaded levels.
    pub(crate) fn up_down(
        position: Option<usize>,
        trial: usize,
        first_index: usize,
        w: f64,
        noise: impl Fn(f64, bool) -> f64,
    ) -> Vec<Reading> {
        let t = [0.0, 100.0, 200.0, 300.0, 200.0, 100.0, 0.0];
        t.iter()
            .enumerate()
            .map(|(k, &f)| {
                let down = k > 3;
                let loaded = f > 0.0;
                Reading {
                    index: first_index + k,
                    trial,
                    position,
                    target_n: f,
                    applied_n: f,
                    measured_n: 0.9 * f
                        + 0.5
                        + noise(f, down)
                        + if down && loaded { w } else { 0.0 },
                    down,
                }
            })
            .collect()
    }

    #[test]
    fn hysteresis_loop_of_known_width_gives_the_reversibility() {
        // 4 trials, down branch 3 N above the up branch at 100 and 200 N; the fit runs
        // through the loading rows only, so the up branch has zero residual.
        let mut r = Vec::new();
        for t in 0..4 {
            r.extend(up_down(None, t, 7 * t, 3.0, |_, _| 0.0));
        }
        let m = analyze_readings(r).unwrap();
        assert_eq!(m.full_scale_n, 300.0);
        assert!((m.fit.slope - 0.9).abs() < 1e-12);
        let v = m.reversibility.unwrap();
        assert!(
            (v.pct_fs - 100.0 * 3.0 / 300.0).abs() < 1e-9,
            "{}",
            v.pct_fs
        );
        assert!(m.interpolation.unwrap().pct_fs < 1e-9);
        let l100 = m.levels.iter().find(|l| l.target_n == 100.0).unwrap();
        assert!((l100.reversibility_n().unwrap() - 3.0).abs() < 1e-9);
        // The top level is only loaded.
        assert_eq!(m.levels.last().unwrap().reversibility_n(), None);
        // Zero returns exactly; v = 1 %FS is outside class 2 (0.5).
        assert!(m.zero.unwrap().pct_fs.abs() < 1e-9);
        let class = m.class.unwrap();
        assert_eq!(class.code, NO_CLASS);
        assert_eq!(class.name(), "none (outside class 2)");
    }

    #[test]
    fn repeatability_of_known_sd_and_reproducibility_across_positions() {
        // Two positions, 4 trials each; trial errors ±e alternate (mean zero per cell),
        // so each cell's SD is e·√(4/3); position 1 reads 1 N higher when loaded.
        let e = 0.6;
        let mut r = Vec::new();
        let mut i = 0;
        for p in 0..2 {
            for t in 0..4 {
                let s = if t % 2 == 0 { e } else { -e };
                let shift = p as f64;
                r.extend(up_down(Some(p), t, i, 0.0, |f, _| {
                    if f > 0.0 {
                        s + shift
                    } else {
                        0.0
                    }
                }));
                i += 7;
            }
        }
        let m = analyze_readings(r).unwrap();
        assert_eq!((m.positions, m.trials), (2, 8));
        let sd = e * (4.0f64 / 3.0).sqrt();
        let rep = m.repeatability.unwrap();
        assert!(
            (rep.pct_fs - 100.0 * sd / 300.0).abs() < 1e-9,
            "{}",
            rep.pct_fs
        );
        let ci = rep.ci95.unwrap();
        assert_eq!(ci.method, "chi2");
        assert!(ci.low < rep.pct_fs && rep.pct_fs < ci.high);
        // Across positions: 8 values per cell, ±e around ±0.5 (the two positions'
        // means about their common mean): SS = 8e² + 8·0.25, dof 7.
        let across = ((8.0 * e * e + 8.0 * 0.25) / 7.0).sqrt();
        let b = m.reproducibility.unwrap();
        assert!(
            (b.pct_fs - 100.0 * across / 300.0).abs() < 1e-9,
            "{}",
            b.pct_fs
        );
        let ci = b.ci95.unwrap();
        assert_eq!(ci.method, "bootstrap");
        assert!(ci.low <= b.pct_fs + 1e-12 && ci.high >= ci.low);
    }

    #[test]
    fn zero_error_is_the_mean_return_of_the_unloaded_reading() {
        // Each trial ends 0.3 N (trial 0) / 0.5 N (trial 1) above where it started.
        let mut r = Vec::new();
        for (t, z) in [0.3, 0.5].into_iter().enumerate() {
            r.extend(up_down(None, t, 7 * t, 0.0, move |f, down| {
                if f == 0.0 && down {
                    z
                } else {
                    0.0
                }
            }));
        }
        let m = analyze_readings(r).unwrap();
        let z = m.zero.unwrap();
        assert!((z.pct_fs - 100.0 * 0.4 / 300.0).abs() < 1e-9);
        assert!((m.zero_max_pct_fs.unwrap() - 100.0 * 0.5 / 300.0).abs() < 1e-9);
        assert_eq!(z.ci95.unwrap().method, "t");
    }

    #[test]
    fn a_single_up_sweep_lists_what_it_cannot_compute() {
        let r: Vec<Reading> = up_down(None, 0, 0, 0.0, |_, _| 0.0)
            .into_iter()
            .take(4)
            .collect();
        let m = analyze_readings(r).unwrap();
        let names: Vec<&str> = m.absent.iter().map(|a| a.0).collect();
        assert!(names.contains(&"metrology.repeatability_pct_fs"));
        assert!(names.contains(&"metrology.reversibility_pct_fs"));
        assert!(names.contains(&"metrology.zero_pct_fs"));
        assert!(names.contains(&"metrology.reproducibility_pct_fs"));
        assert!(
            m.interpolation.unwrap().ci95.is_none(),
            "one trial: no bootstrap"
        );
    }

    #[test]
    fn class_table_picks_the_best_class_each_criterion_meets() {
        let c = ClassResult::judge(&[
            (Criterion::Repeatability, 0.04, "x"),
            (Criterion::Interpolation, -0.15, "x"),
        ])
        .unwrap();
        assert_eq!(c.checks[0].class.unwrap().name, "0.5");
        assert_eq!(c.checks[1].class.unwrap().name, "2");
        assert_eq!(c.code, 2.0);
        assert_eq!(c.name(), "2");
        assert_eq!(ClassResult::judge(&[]), None);
    }

    #[test]
    fn ci95_cover_the_truth_in_93_to_97_percent_of_1000_seeded_runs() {
        use super::super::calibration::{calibrate, Sample};
        use super::super::hold::pooled_slope;
        // Each of 1000 synthetic runs (seeded): a magnitude sweep of 6 levels × 3 trials,
        // F^sum = 0.9·F + 0.1 + N(0, 0.05²); two holds of 10 samples with creep
        // 0.002 N/s + N(0, 0.01²); 4 zero returns N(0.03, 0.02²).
        let mut rng = Rng::new(2026);
        let mut hits = [0usize; 6];
        let runs = 1000;
        for _ in 0..runs {
            let mut v = Vec::new();
            for k in 0..6 {
                for _ in 0..3 {
                    let x = k as f64;
                    v.push(Sample {
                        target: x,
                        applied: x,
                        measured: 0.9 * x + 0.1 + 0.05 * rng.normal(),
                        direction: Direction::Loading,
                    });
                }
            }
            let c = calibrate(&v).unwrap();
            let covers = |ci: Option<(f64, f64)>, truth: f64| {
                let (lo, hi) = ci.unwrap();
                usize::from(lo <= truth && truth <= hi)
            };
            hits[0] += covers(c.fit.slope_ci95(), 0.9);
            hits[1] += covers(c.fit.offset_ci95(), 0.1);
            hits[2] += covers(stats::sd_ci95(c.pooled_sd, c.pooled_dof), 0.05);
            hits[3] += covers(c.resolution_ci95(), 2.0 * 0.05 / 0.9);
            let pts: Vec<(usize, f64, f64)> = (0..20)
                .map(|i| {
                    let (h, t) = (i / 10, 6.0 * (i % 10) as f64);
                    (h, t, 0.3 * h as f64 + 0.002 * t + 0.01 * rng.normal())
                })
                .collect();
            hits[4] += covers(pooled_slope(&pts).unwrap().0.ci95, 0.002);
            let z: Vec<f64> = (0..4).map(|_| 0.03 + 0.02 * rng.normal()).collect();
            hits[5] += covers(stats::mean_ci95(&z), 0.03);
        }
        let names = [
            "slope",
            "offset",
            "pooled SD",
            "resolution",
            "creep",
            "zero",
        ];
        for (name, h) in names.iter().zip(hits) {
            eprintln!("{name}: {h} of {runs} intervals cover the truth");
            assert!(
                (930..=970).contains(&h),
                "{name}: {h} of {runs} 95 % intervals cover the truth"
            );
        }
    }
}
