//! The verdict of a report: one outcome for the whole run (PASS, MARGINAL, FAIL,
//! INCOMPLETE), the state of the run it judges, and `verdict.json`, the
//! machine-readable record a build gate reads (schema in the README).
//!
//! Rules, in order:
//! 1. A run that did not measure its whole plan (`--limit`, interrupted, aborted,
//!    killed, still in progress) is **INCOMPLETE**, whatever its metrics, unless the
//!    caller grades it anyway (`--allow-partial`; the verdict then says so).
//! 2. Otherwise, with no criteria and no provenance requirement, **NOT JUDGED** (exit
//!    0 like PASS, but never called a pass: nothing was required, nothing was checked).
//! 3. Otherwise the worst outcome over the criteria and the provenance requirements:
//!    any FAIL gives **FAIL**, else a criterion nothing could judge (a fitted parameter
//!    with no fit, held at nominal or not identifiable) gives **NOT JUDGED**, else any
//!    MARGINAL gives **MARGINAL**, else **PASS** ([`Outcome::combine`]): a build never
//!    passes on a criterion that was not judged.
//!
//! Provenance requirements: `require_build_id` (a build id recorded) and
//! `require_real_bench` (the manifest records `simulated: false`; a simulated run
//! FAILs, and so does a manifest from before the flag was recorded: a gate does not
//! pass what it cannot verify).

use serde::Serialize;

use super::acceptance::{Criteria, Outcome, Verdict};
use super::sha256::sha256_hex;
use crate::analysis::{Ci95, Metric, RunAnalysis};
use crate::bench::integrity::{self, RecordCheck};
use crate::bench::journal::{Provenance, RunStatus, Session, WriteFailure, GIT_COMMIT};
use crate::bench::lock::{Holder, LockState};
use crate::bench::provenance;

/// File name of the verdict inside the report's output directory.
pub const VERDICT_FILE: &str = "verdict.json";

/// `verdict.json`'s schema identifier (bumped on incompatible changes).
pub const SCHEMA: &str = "tactbench-verdict/1";

/// Exit code of `report` for PASS, MARGINAL and NOT JUDGED.
pub const EXIT_PASS: u8 = 0;
/// Exit code of `report` for FAIL.
pub const EXIT_FAIL: u8 = 1;
/// Exit code of `report` for INCOMPLETE (a run that did not measure its whole plan).
pub const EXIT_INCOMPLETE: u8 = 5;

/// The exit code of an outcome (errors, exit 2, never get this far).
pub fn exit_code(outcome: Outcome) -> u8 {
    match outcome {
        Outcome::NotJudged | Outcome::Pass | Outcome::Marginal => EXIT_PASS,
        Outcome::Fail => EXIT_FAIL,
        Outcome::Incomplete => EXIT_INCOMPLETE,
    }
}

/// What the report knows about the state of the run it judges.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunState {
    /// The run directory.
    pub dir: String,
    /// `completed`, `interrupted`, `aborted` (as the manifest records), `in_progress`
    /// (a live process holds the run's lock), `killed` (the manifest says running
    /// but no process holds the lock: the writer died without recording an end), or
    /// `running` (a run from before locking: live or killed cannot be told).
    pub status: String,
    /// A live process is writing the run.
    pub in_progress: bool,
    /// The live writer, as it recorded itself (`PID .. on host .., since ..`).
    pub writer: Option<String>,
    /// Setpoints in the plan.
    pub planned_setpoints: usize,
    /// Setpoints the run set out to measure (the plan's, or the first `--limit`).
    pub run_setpoints: usize,
    /// Setpoints in the journal (complete lines).
    pub measured_setpoints: usize,
    /// The run's `--limit`, if any.
    pub limit: Option<usize>,
    /// The signal that interrupted the run, if one did.
    pub stop_signal: Option<String>,
    /// The manifest's end reason (abort reason, safety trip, interruption).
    pub end_reason: Option<String>,
    /// Whether every planned setpoint was measured and no writer is live.
    pub complete: bool,
    /// Why not, in words (`None` when complete).
    pub incomplete_reason: Option<String>,
    /// A torn last journal line that was skipped: `{line, bytes}`.
    pub torn_journal_line: Option<TornLineJson>,
    /// The first write into the run directory that failed (`null`: none recorded).
    pub write_failure: Option<WriteFailure>,
    /// Failed rows (no force), skipped by the analyses: `setpoint N (journal line L):
    /// why` each. `measured_setpoints` counts them.
    pub failed_rows: Vec<String>,
    /// Rows journalled `quality = implausible` (the run-side force plausibility check).
    pub implausible_rows: usize,
    /// The record's digests verified against the files (`recorded: false`: a run from
    /// before they were recorded).
    pub record: RecordCheck,
    /// The sessions that measured the run (reconciled with the journal after a
    /// session that could not record its end).
    pub sessions: Vec<Session>,
}

/// A torn journal line in `verdict.json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TornLineJson {
    /// 1-based line number.
    pub line: u64,
    /// Bytes cut off.
    pub bytes: u64,
}

fn status_word(s: RunStatus) -> &'static str {
    match s {
        RunStatus::Running => "running",
        RunStatus::Interrupted => "interrupted",
        RunStatus::Aborted => "aborted",
        RunStatus::Completed => "completed",
    }
}

impl RunState {
    /// The state of the analysed run, given what [`crate::bench::lock::probe`] found.
    pub fn of(analysis: &RunAnalysis, lock: &LockState) -> RunState {
        let run = &analysis.run;
        let m = &run.manifest;
        let planned = m.planned();
        let measured = run.journalled();
        let holder: Option<&Holder> = match lock {
            LockState::Held(h) => Some(h),
            _ => None,
        };
        let in_progress = holder.is_some();
        let status = match (m.status, lock) {
            (_, LockState::Held(_)) => "in_progress",
            (RunStatus::Running, LockState::Free) => "killed",
            (s, _) => status_word(s),
        };
        let of = format!("{measured} of the plan's {planned} setpoints measured");
        let incomplete_reason = if in_progress {
            Some(format!(
                "the run is still in progress ({}): {of} so far",
                holder.map(|h| h.to_string()).unwrap_or_default()
            ))
        } else if measured >= planned {
            None
        } else {
            Some(match (status, &m.incomplete_reason) {
                ("killed", _) => format!(
                    "the run ended without recording why (killed, or the machine stopped): \
                     {of}; continue it with `tactbench run --resume {}`",
                    run.dir.display()
                ),
                (_, Some(r)) => r.clone(),
                ("running", None) => format!(
                    "the manifest says running (a run from before run locks: still going or \
                     killed): {of}"
                ),
                (_, None) => match (m.limit, m.end_reason.as_deref()) {
                    (Some(n), _) => format!("limited by --limit {n}: {of}"),
                    (None, Some(r)) => format!("{status}: {of}: {r}"),
                    (None, None) => format!("{status}: {of}"),
                },
            })
        };
        RunState {
            dir: run.dir.display().to_string(),
            status: status.to_string(),
            in_progress,
            writer: holder.map(|h| h.to_string()),
            planned_setpoints: planned,
            run_setpoints: m.setpoints,
            measured_setpoints: measured,
            limit: m.limit,
            stop_signal: m.stop_signal.clone(),
            end_reason: m.end_reason.clone(),
            complete: incomplete_reason.is_none(),
            incomplete_reason,
            torn_journal_line: run.torn.as_ref().map(|t| TornLineJson {
                line: t.line,
                bytes: t.bytes,
            }),
            write_failure: m.write_failure.clone(),
            failed_rows: run.failed.iter().map(|f| f.describe()).collect(),
            implausible_rows: run.rows.iter().filter(|r| r.implausible()).count(),
            record: integrity::verify(&run.dir, m),
            sessions: m.sessions.clone(),
        }
    }
}

/// One criterion in `verdict.json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CriterionJson {
    /// Metric name.
    pub metric: String,
    /// The run's value (`null` when it could not be computed or is not finite).
    pub value: Option<f64>,
    /// Its unit.
    pub unit: String,
    /// Inclusive lower limit.
    pub min: Option<f64>,
    /// Inclusive upper limit.
    pub max: Option<f64>,
    /// Marginal at or below.
    pub marginal_min: Option<f64>,
    /// Marginal at or above.
    pub marginal_max: Option<f64>,
    /// Fitted parameters: `|value - nominal| <= r |nominal|`.
    pub max_relative_to_nominal: Option<f64>,
    /// Fitted parameters: `|value - nominal| <= d` (the parameter's unit).
    pub max_deviation_from_nominal: Option<f64>,
    /// Fitted parameters: the nominal value the fit started from.
    pub nominal: Option<f64>,
    /// The limits the value was judged against, every bound applied (`null`: none on
    /// that side, or nothing judged).
    pub limits: [Option<f64>; 2],
    /// PASS, MARGINAL, FAIL, or NOT JUDGED (a fitted parameter nothing determined).
    pub outcome: Outcome,
    /// Why there is no value, if so.
    pub note: Option<String>,
    /// The metric's 95 % confidence interval (`null` where none is stated).
    pub ci95: Option<CiJson>,
}

/// A 95 % confidence interval in `verdict.json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CiJson {
    /// Lower bound (metric unit).
    pub low: f64,
    /// Upper bound (metric unit).
    pub high: f64,
    /// `t`, `chi2`, `bootstrap`, `normal`.
    pub method: String,
}

impl CiJson {
    fn of(ci: Option<Ci95>) -> Option<CiJson> {
        let ci = ci?;
        (ci.low.is_finite() && ci.high.is_finite()).then(|| CiJson {
            low: ci.low,
            high: ci.high,
            method: ci.method.to_string(),
        })
    }
}

/// One metric of the run in `verdict.json` (as in `summary.csv`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MetricJson {
    /// Metric name.
    pub name: String,
    /// Value (`null` when not finite).
    pub value: Option<f64>,
    /// Unit.
    pub unit: String,
    /// 95 % confidence interval (`null` where none is stated).
    pub ci95: Option<CiJson>,
}

/// A provenance requirement in `verdict.json` (e.g. `require_build_id`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RequirementJson {
    /// What is required (`build_id`).
    pub requirement: String,
    /// What the run recorded (`null`: nothing).
    pub value: Option<String>,
    /// PASS or FAIL.
    pub outcome: Outcome,
}

/// Where the run and its inputs came from, in `verdict.json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ProvenanceJson {
    /// Plan name.
    pub plan_name: String,
    /// Plan file as given to `run`.
    pub plan_path: String,
    /// SHA-256 of the plan text recorded in the manifest.
    pub plan_sha256: String,
    /// Sensor file as resolved by `run`.
    pub sensor_path: String,
    /// SHA-256 of the sensor text recorded in the manifest.
    pub sensor_sha256: String,
    /// Elastomer build id (`null`: none recorded).
    pub build_id: Option<String>,
    /// `tactbench` version that ran the measurement.
    pub software_version: String,
    /// Git commit of the binary that ran (or last resumed) the measurement (`null`
    /// for runs from before it was recorded).
    pub git_commit: Option<String>,
    /// Identities the devices reported.
    pub devices: serde_json::Value,
    /// `real bench`, `simulated bench`, `replayed bench` (or `not recorded …`).
    pub bench_kind: String,
    /// Each device's provenance (`device`, `identity`, `provenance`, `why`) as the
    /// manifest records it (judged from `devices` for runs recorded before it was).
    pub device_provenance: Vec<crate::bench::journal::DeviceProvenance>,
    /// The bench description.
    pub bench: serde_json::Value,
    /// Start, RFC 3339 UTC.
    pub started_at: String,
    /// Resumptions, RFC 3339 UTC.
    pub resumed_at: Vec<String>,
    /// End (`null`: not recorded: in progress or killed).
    pub ended_at: Option<String>,
}

/// The software that wrote the report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReportJson {
    /// `tactbench` version of the report.
    pub software_version: String,
    /// Git commit the report's binary was built from.
    pub git_commit: String,
    /// When the report was written, RFC 3339 UTC.
    pub generated_at: String,
}

/// `verdict.json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct VerdictDoc {
    /// [`SCHEMA`].
    pub schema: String,
    /// NOT JUDGED, PASS, MARGINAL, FAIL or INCOMPLETE.
    pub outcome: Outcome,
    /// The run was measured on the built-in simulated bench (`null`: the manifest
    /// predates the flag, not recorded).
    pub simulated: Option<bool>,
    /// The exit code `report` returns for it.
    pub exit_code: u8,
    /// One line: the outcome and why.
    pub summary: String,
    /// A partial run graded anyway (`--allow-partial`).
    pub graded_partial: bool,
    /// The criteria file (`null` without `--acceptance`).
    pub criteria_file: Option<String>,
    /// Each criterion, in file order.
    pub criteria: Vec<CriterionJson>,
    /// Provenance requirements of the criteria file.
    pub requirements: Vec<RequirementJson>,
    /// Every metric of the run with its interval (empty until [`VerdictDoc::with_metrics`]).
    pub metrics: Vec<MetricJson>,
    /// The run's state and counts.
    pub run: RunState,
    /// Where the run came from.
    pub provenance: ProvenanceJson,
    /// The report's own software.
    pub report: ReportJson,
}

impl VerdictDoc {
    /// Judges a run: criteria verdicts (already evaluated), provenance requirements,
    /// completeness; `allow_partial` grades a partial run anyway.
    pub fn judge(
        analysis: &RunAnalysis,
        criteria: Option<&Criteria>,
        verdicts: &[Verdict],
        run: RunState,
        allow_partial: bool,
    ) -> VerdictDoc {
        let m = &analysis.run.manifest;
        let mut requirements = Vec::new();
        if criteria.is_some_and(|c| c.require_build_id) {
            let value = m.build_id.clone().filter(|b| !b.trim().is_empty());
            requirements.push(RequirementJson {
                requirement: "build_id".into(),
                outcome: if value.is_some() {
                    Outcome::Pass
                } else {
                    Outcome::Fail
                },
                value,
            });
        }
        let (bench_kind, not_real) = bench_provenance(m);
        if criteria.is_some_and(|c| c.require_real_bench) {
            let outcome = if bench_kind == "real bench" {
                Outcome::Pass
            } else {
                Outcome::Fail
            };
            requirements.push(RequirementJson {
                requirement: "real_bench".into(),
                value: Some(if not_real.is_empty() {
                    bench_kind.clone()
                } else {
                    format!("{bench_kind}: {}", not_real.join("; "))
                }),
                outcome,
            });
        }
        // A run judged against criteria is at most MARGINAL with rows it could not
        // use, and FAILs when its record no longer matches what the run wrote.
        if criteria.is_some() {
            if !run.failed_rows.is_empty() {
                requirements.push(RequirementJson {
                    requirement: "no_failed_rows".into(),
                    value: Some(format!(
                        "{} failed row(s) skipped: {}",
                        run.failed_rows.len(),
                        run.failed_rows.join("; ")
                    )),
                    outcome: Outcome::Marginal,
                });
            }
            if run.implausible_rows > 0 {
                requirements.push(RequirementJson {
                    requirement: "no_implausible_rows".into(),
                    value: Some(format!(
                        "{} row(s) with quality = implausible",
                        run.implausible_rows
                    )),
                    outcome: Outcome::Marginal,
                });
            }
            if run.record.modified() {
                requirements.push(RequirementJson {
                    requirement: "record_intact".into(),
                    value: Some(run.record.lines().join("; ")),
                    outcome: Outcome::Fail,
                });
            }
        }
        // Nothing required, nothing checked, or a criterion nothing judged: NOT
        // JUDGED, never PASS.
        let graded = Outcome::combine(
            verdicts
                .iter()
                .map(|v| v.outcome)
                .chain(requirements.iter().map(|r| r.outcome)),
        );
        let partial = !run.complete;
        let outcome = if partial && !allow_partial {
            Outcome::Incomplete
        } else {
            graded
        };
        let counts = format!(
            "{} of {} planned setpoints",
            run.measured_setpoints, run.planned_setpoints
        );
        let failed = verdicts
            .iter()
            .filter(|v| v.outcome == Outcome::Fail)
            .count()
            + requirements
                .iter()
                .filter(|r| r.outcome == Outcome::Fail)
                .count();
        let marginal = verdicts
            .iter()
            .filter(|v| v.outcome == Outcome::Marginal)
            .count()
            + requirements
                .iter()
                .filter(|r| r.outcome == Outcome::Marginal)
                .count();
        let judged = verdicts.len() + requirements.len();
        let unjudged: Vec<String> = verdicts
            .iter()
            .filter(|v| v.outcome == Outcome::NotJudged)
            .map(|v| {
                format!(
                    "{} ({})",
                    v.criterion.metric,
                    v.note.as_deref().unwrap_or("no value")
                )
            })
            .collect();
        let detail = match outcome {
            Outcome::Incomplete => format!(
                "{}; not graded (grade a partial run with --allow-partial)",
                run.incomplete_reason.clone().unwrap_or_default()
            ),
            Outcome::NotJudged if !unjudged.is_empty() => format!(
                "{} of {judged} criteria not judged: {}",
                unjudged.len(),
                unjudged.join("; ")
            ),
            Outcome::NotJudged => "no acceptance criteria given; nothing was judged".to_string(),
            Outcome::Fail if !unjudged.is_empty() => format!(
                "{failed} of {judged} criteria failed, {} not judged",
                unjudged.len()
            ),
            Outcome::Fail => format!("{failed} of {judged} criteria failed"),
            Outcome::Marginal => format!("{marginal} of {judged} criteria marginal"),
            Outcome::Pass => format!("{judged} criteria"),
        };
        // The built-in simulated bench says so as before; any other bench that is not
        // real names the device that made it so.
        let builtin = m.bench.get("sim").is_some();
        let mut detail = match bench_kind.as_str() {
            "replayed bench" => format!("{detail}; REPLAYED bench ({})", not_real.join("; ")),
            "simulated bench" if builtin || not_real.is_empty() => {
                format!("{detail}; SIMULATED bench")
            }
            "simulated bench" => format!("{detail}; SIMULATED bench ({})", not_real.join("; ")),
            _ => detail,
        };
        if !run.failed_rows.is_empty() {
            detail.push_str(&format!(
                "; {} failed row(s) skipped (no force)",
                run.failed_rows.len()
            ));
        }
        if run.implausible_rows > 0 {
            detail.push_str(&format!(
                "; {} row(s) with implausible forces",
                run.implausible_rows
            ));
        }
        if run.record.modified() {
            detail.push_str("; RECORD MODIFIED AFTER THE RUN");
        }
        let mut summary = format!("{outcome}: {detail}");
        if partial && allow_partial {
            summary.push_str(&format!(
                "; PARTIAL RUN graded with --allow-partial ({counts}: {})",
                run.incomplete_reason.clone().unwrap_or_default()
            ));
        }
        let criteria_json = verdicts
            .iter()
            .map(|v| CriterionJson {
                metric: v.criterion.metric.clone(),
                value: v.value.is_finite().then_some(v.value),
                unit: v.unit.to_string(),
                min: v.criterion.min,
                max: v.criterion.max,
                marginal_min: v.criterion.marginal_min,
                marginal_max: v.criterion.marginal_max,
                max_relative_to_nominal: v.criterion.max_relative_to_nominal,
                max_deviation_from_nominal: v.criterion.max_deviation_from_nominal,
                nominal: v.nominal,
                limits: if v.outcome == Outcome::NotJudged {
                    [None, None]
                } else {
                    let (lo, hi) = v.limits();
                    [lo, hi]
                },
                outcome: v.outcome,
                note: v.note.clone().or_else(|| {
                    (!v.value.is_finite()).then(|| format!("value {} is not finite", v.value))
                }),
                ci95: v.ci95.map(|[low, high]| CiJson {
                    low,
                    high,
                    method: "fit".into(),
                }),
            })
            .collect();
        VerdictDoc {
            schema: SCHEMA.into(),
            outcome,
            simulated: m.simulated,
            exit_code: exit_code(outcome),
            summary,
            graded_partial: partial && allow_partial,
            criteria_file: criteria.map(|c| c.path.display().to_string()),
            criteria: criteria_json,
            requirements,
            metrics: Vec::new(),
            run,
            provenance: ProvenanceJson {
                plan_name: m.plan_name.clone(),
                plan_path: m.plan_path.clone(),
                plan_sha256: sha256_hex(m.plan_toml.as_bytes()),
                sensor_path: m.sensor_path.clone(),
                sensor_sha256: sha256_hex(m.sensor_toml.as_bytes()),
                build_id: m.build_id.clone(),
                software_version: m.software_version.clone(),
                git_commit: m.software_commit.clone(),
                devices: m.devices.clone(),
                bench_kind: bench_kind.clone(),
                device_provenance: if m.device_provenance.is_empty() && m.devices.is_object() {
                    provenance::judge(&m.devices, m.simulated == Some(true))
                } else {
                    m.device_provenance.clone()
                },
                bench: m.bench.clone(),
                started_at: m.started_at.clone(),
                resumed_at: m.resumed_at.clone(),
                ended_at: m.ended_at.clone(),
            },
            report: ReportJson {
                software_version: env!("CARGO_PKG_VERSION").into(),
                git_commit: GIT_COMMIT.into(),
                generated_at: crate::bench::runner::rfc3339_now(),
            },
        }
    }
}

/// The bench's provenance in words (`real bench`, `simulated bench`, `replayed bench`,
/// `not recorded …`) and the devices that made it not real (`camera: why` each).
/// Judged from the manifest's `device_provenance` when recorded, else its
/// `simulated` flag; a manifest naming a `dir:` camera or a simulator's firmware in
/// `devices` is judged from those even without `device_provenance` (runs recorded
/// before it was).
pub fn bench_provenance(m: &crate::bench::journal::Manifest) -> (String, Vec<String>) {
    let devices = if m.device_provenance.is_empty() && m.devices.is_object() {
        provenance::judge(&m.devices, m.simulated == Some(true))
    } else {
        m.device_provenance.clone()
    };
    let (worst, why) = provenance::overall(&devices);
    let word = if worst == Provenance::Replayed {
        "replayed bench"
    } else if worst == Provenance::Simulated || m.simulated == Some(true) {
        "simulated bench"
    } else if m.simulated == Some(false) {
        "real bench"
    } else {
        "not recorded (manifest from before the simulated flag)"
    };
    let why = if why.is_empty() && m.simulated == Some(true) {
        vec!["the built-in simulated bench".to_string()]
    } else {
        why
    };
    (word.to_string(), why)
}

impl VerdictDoc {
    /// Adds the run's metrics (`metrics[]`) and each criterion's confidence interval.
    pub fn with_metrics(mut self, metrics: &[Metric]) -> VerdictDoc {
        for c in &mut self.criteria {
            if let Some(ci) = metrics
                .iter()
                .find(|m| m.name == c.metric)
                .and_then(|m| CiJson::of(m.ci95))
            {
                c.ci95 = Some(ci);
            } else if !c.metric.starts_with(super::acceptance::FIT_PREFIX) {
                c.ci95 = None;
            }
        }
        self.metrics = metrics
            .iter()
            .map(|m| MetricJson {
                name: m.name.clone(),
                value: m.value.is_finite().then_some(m.value),
                unit: m.unit.to_string(),
                ci95: CiJson::of(m.ci95),
            })
            .collect();
        self
    }
}
