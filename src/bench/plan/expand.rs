//! Expansion of a validated plan into its numbered setpoints, in run order, one at a
//! time (no list is built unless asked for), and the summary `run --dry-run` prints of
//! what the sweep repeats.

use super::sweep::level_count;
use super::{hold_schedule, total_count, ExplicitPoint, Plan, Setpoint, Sweep, SweepDirection};
use crate::bench::journal::Direction;

impl Plan {
    /// Every setpoint in run order, in internal units. Bounded by [`MAX_SETPOINTS`]
    /// (validation refuses larger plans before anything is expanded).
    pub fn setpoints(&self) -> Vec<Setpoint> {
        let mut out = Vec::with_capacity(self.setpoint_count());
        out.extend(self.setpoints_iter());
        out
    }

    /// The number of setpoints, computed from the sweep's parameters (nothing is
    /// expanded).
    pub fn setpoint_count(&self) -> usize {
        // Validation bounded the count by MAX_SETPOINTS, so the conversion is exact.
        total_count(&self.sweep, self.sweep_direction, self.positions_mm.len()) as usize
    }

    /// The contact positions the trials run at, in turn: `(Some(index), position)`
    /// for each of `sweep.positions_mm`, or `(None, approach.position_mm)` without it.
    fn trial_positions(&self) -> Vec<(Option<usize>, [f64; 2])> {
        if self.positions_mm.is_empty() {
            vec![(None, self.approach_position_mm)]
        } else {
            self.positions_mm
                .iter()
                .enumerate()
                .map(|(i, p)| (Some(i), *p))
                .collect()
        }
    }

    /// The top level of a magnitude sweep, N (the largest `from + k·step` ≤ `to`);
    /// `None` for other sweeps. A resumed up-down trial loads to it before its next
    /// unloading level, so every `down` row is measured on unloading from the top.
    pub fn top_level_n(&self) -> Option<f64> {
        match &self.sweep {
            Sweep::Magnitude { from, to, step, .. } => {
                let n = level_count(*from, *to, *step);
                Some(self.force_unit.to_newtons(from + step * (n - 1.0)))
            }
            _ => None,
        }
    }

    /// Every setpoint in run order, generated one at a time (no list is built): the
    /// sweep kind's setpoints ([`Self::magnitude_raw`], [`Self::angle_raw`],
    /// [`Self::hold_raw`], [`Self::spatial_raw`], [`Self::displacement_raw`],
    /// [`Self::explicit_raw`]), numbered in turn.
    pub fn setpoints_iter(&self) -> impl Iterator<Item = Setpoint> + '_ {
        let raw: RawIter<'_> = match &self.sweep {
            Sweep::Magnitude {
                from,
                to,
                step,
                trials,
            } => self.magnitude_raw(*from, *to, *step, *trials),
            Sweep::Angle {
                force,
                from_deg,
                to_deg,
                step_deg,
                direction_deg,
                trials,
            } => self.angle_raw(
                *force,
                [*from_deg, *to_deg, *step_deg],
                *direction_deg,
                *trials,
            ),
            Sweep::Hold {
                force,
                duration_s,
                sample_interval_s,
                trials,
            } => self.hold_raw(*force, *duration_s, *sample_interval_s, *trials),
            Sweep::Spatial {
                force,
                start_mm,
                end_mm,
                subdivisions,
            } => self.spatial_raw(*force, *start_mm, *end_mm, *subdivisions),
            Sweep::Displacement { shift_mm, trials } => self.displacement_raw(*shift_mm, *trials),
            Sweep::Setpoints(points) => self.explicit_raw(points),
        };
        raw.enumerate().map(|(index, r)| Setpoint {
            index,
            trial: r.trial,
            position_mm: r.position_mm,
            normal_n: r.normal_n,
            tangential_n: r.tangential_n,
            shift_mm: r.shift_mm,
            swept_value: r.swept_value,
            direction: r.direction,
            position: r.position,
            hold_t_s: r.hold_t_s,
        })
    }

    /// Fig. 7: per contact position, `trials` trials of the levels `from + k·step` ≤
    /// `to` (plan unit), each trial up (and back down, see [`magnitude_trial`]).
    fn magnitude_raw(&self, from: f64, to: f64, step: f64, trials: usize) -> RawIter<'_> {
        let u = self.force_unit;
        let updown = self.sweep_direction == SweepDirection::UpDown;
        let n = level_count(from, to, step) as usize;
        Box::new(
            self.trial_positions()
                .into_iter()
                .enumerate()
                .flat_map(move |(pi, (pidx, p))| {
                    (0..trials).flat_map(move |t| {
                        magnitude_trial(from, step, n, updown).map(move |(v, d)| Raw {
                            trial: pi * trials + t,
                            position_mm: p,
                            normal_n: u.to_newtons(v),
                            swept_value: v,
                            direction: d,
                            position: pidx,
                            ..Raw::default()
                        })
                    })
                }),
        )
    }

    /// Fig. 8: per contact position, `trials` trials of the force `force` tilted from
    /// the normal by `from + k·step` ≤ `to` deg (`[from, to, step]`) towards
    /// `direction_deg`.
    fn angle_raw(
        &self,
        force: f64,
        [from, to_deg, step]: [f64; 3],
        direction_deg: f64,
        trials: usize,
    ) -> RawIter<'_> {
        let f = self.force_unit.to_newtons(force);
        let n = level_count(from, to_deg, step) as usize;
        let (dcos, dsin) = cos_sin_deg(direction_deg);
        Box::new(
            self.trial_positions()
                .into_iter()
                .enumerate()
                .flat_map(move |(pi, (pidx, p))| {
                    (0..trials).flat_map(move |t| {
                        (0..n).map(move |i| {
                            let a = from + step * i as f64;
                            let (c, s) = cos_sin_deg(a);
                            let tan = f * s;
                            Raw {
                                trial: pi * trials + t,
                                position_mm: p,
                                normal_n: f * c,
                                tangential_n: [tan * dcos, tan * dsin],
                                swept_value: a,
                                position: pidx,
                                ..Raw::default()
                            }
                        })
                    })
                }),
        )
    }

    /// Creep: an unloaded reading, then per trial the hold's samples
    /// ([`hold_schedule`]) and an unloaded reading after it.
    fn hold_raw(&self, force: f64, d: f64, dt: f64, trials: usize) -> RawIter<'_> {
        let pos = self.approach_position_mm;
        let f = self.force_unit.to_newtons(force);
        let unloaded = move |trial: usize| Raw {
            trial,
            position_mm: pos,
            ..Raw::default()
        };
        Box::new(
            std::iter::once(unloaded(0)).chain((0..trials).flat_map(move |k| {
                hold_schedule(d, dt)
                    .map(move |t| Raw {
                        trial: k,
                        position_mm: pos,
                        normal_n: f,
                        swept_value: force,
                        hold_t_s: Some(t),
                        ..Raw::default()
                    })
                    .chain(std::iter::once(unloaded(k)))
            })),
        )
    }

    /// Fig. 9: the force at `k + 1` evenly spaced points from `a` to `b` (mm), swept
    /// value the distance along the line.
    fn spatial_raw(&self, force: f64, a: [f64; 2], b: [f64; 2], k: usize) -> RawIter<'_> {
        let f = self.force_unit.to_newtons(force);
        let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
        Box::new((0..=k).map(move |i| {
            let s = i as f64 / k as f64;
            Raw {
                position_mm: [a[0] + s * (b[0] - a[0]), a[1] + s * (b[1] - a[1])],
                normal_n: f,
                swept_value: s * len,
                ..Raw::default()
            }
        }))
    }

    /// Table I: `trials` shifts by `shift` (mm) at the approach position.
    fn displacement_raw(&self, shift: [f64; 2], trials: usize) -> RawIter<'_> {
        let pos = self.approach_position_mm;
        Box::new((0..trials).map(move |t| Raw {
            trial: t,
            position_mm: pos,
            shift_mm: shift,
            swept_value: shift[0].hypot(shift[1]),
            ..Raw::default()
        }))
    }

    /// An explicit list: each point as given, forces converted to N.
    fn explicit_raw<'a>(&'a self, points: &'a [ExplicitPoint]) -> RawIter<'a> {
        let u = self.force_unit;
        Box::new(points.iter().map(move |p| Raw {
            position_mm: p.position_mm,
            normal_n: u.to_newtons(p.normal),
            tangential_n: [u.to_newtons(p.tangential[0]), u.to_newtons(p.tangential[1])],
            swept_value: p.normal,
            ..Raw::default()
        }))
    }

    /// What the sweep repeats and how, for `run --dry-run` (empty for a plain sweep):
    /// the direction of an up-down sweep, the contact positions, a hold's schedule.
    pub fn sweep_summary(&self) -> Vec<String> {
        let fu = self.force_unit.symbol();
        let mut out = Vec::new();
        if let Sweep::Magnitude { from, to, .. } = &self.sweep {
            if self.sweep_direction == SweepDirection::UpDown {
                out.push(format!(
                    "sweep.direction = \"up-down\": each trial runs from {from} up to {to} {fu} (top level once) and back down to {from} {fu}{}; rows direction = up | down",
                    if *from > 0.0 {
                        format!(", with an unloaded reading (0 {fu}, contact released) first (up) and last (down)")
                    } else {
                        String::new()
                    }
                ));
            }
        }
        if !self.positions_mm.is_empty() {
            let trials = match &self.sweep {
                Sweep::Magnitude { trials, .. } | Sweep::Angle { trials, .. } => *trials,
                _ => 0,
            };
            let list: Vec<String> = self
                .positions_mm
                .iter()
                .enumerate()
                .map(|(i, p)| {
                    format!(
                        "{i}: [{}, {}] mm (trials {}..{})",
                        p[0],
                        p[1],
                        i * trials,
                        (i + 1) * trials - 1
                    )
                })
                .collect();
            out.push(format!(
                "sweep.positions_mm: {trials} trial(s) at each of {} positions in turn, trials numbered across positions; {}",
                self.positions_mm.len(),
                list.join(", ")
            ));
        }
        if let Sweep::Hold {
            force,
            duration_s,
            sample_interval_s,
            trials,
        } = &self.sweep
        {
            let times: Vec<f64> = hold_schedule(*duration_s, *sample_interval_s).collect();
            let shown = if times.len() <= 12 {
                times
                    .iter()
                    .map(|t| format!("{t}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            } else {
                format!(
                    "{}, ... ({} samples), {}",
                    times[..5]
                        .iter()
                        .map(|t| format!("{t}"))
                        .collect::<Vec<_>>()
                        .join(", "),
                    times.len(),
                    times[times.len() - 1]
                )
            };
            out.push(format!(
                "hold: {force} {fu} for {duration_s} s, {trials} hold(s); samples at {shown} s after the force is reached (force controlled once, then the stage holds its position); unloaded readings before the first hold and after each (rows with target 0 and hold_t_s empty)"
            ));
        }
        out
    }
}

/// A setpoint before it is numbered (internal units, as in [`Setpoint`]).
#[derive(Clone, Copy, Default)]
struct Raw {
    trial: usize,
    position_mm: [f64; 2],
    normal_n: f64,
    tangential_n: [f64; 2],
    shift_mm: [f64; 2],
    swept_value: f64,
    direction: Option<Direction>,
    position: Option<usize>,
    hold_t_s: Option<f64>,
}

/// A sweep's setpoints before they are numbered.
type RawIter<'a> = Box<dyn Iterator<Item = Raw> + 'a>;

/// One trial of a magnitude sweep with `n` levels `from + i·step`: (level value in the
/// plan's unit, direction). Up only; or, `updown`, up through the top level once and
/// back down, with unloaded readings at both ends even when `from` > 0.
fn magnitude_trial(
    from: f64,
    step: f64,
    n: usize,
    updown: bool,
) -> Box<dyn Iterator<Item = (f64, Option<Direction>)>> {
    // (level value, direction) of one trial.
    let level = move |i: usize, d: Option<Direction>| (from + step * i as f64, d);
    if !updown {
        return Box::new((0..n).map(move |i| level(i, None)));
    }
    // Unloaded readings at both ends even when `from` > 0.
    let extra = from > 0.0;
    let up = Some(Direction::Up);
    let down = Some(Direction::Down);
    Box::new(
        extra
            .then_some((0.0, up))
            .into_iter()
            .chain((0..n).map(move |i| level(i, up)))
            .chain((0..n.saturating_sub(1)).rev().map(move |i| level(i, down)))
            .chain(extra.then_some((0.0, down))),
    )
}

/// cos and sin of an angle in degrees, exact at multiples of 90° (so a tangential
/// load along +y has no 6e-17 x component).
fn cos_sin_deg(deg: f64) -> (f64, f64) {
    let quarter = deg / 90.0;
    if quarter.fract() == 0.0 && quarter.abs() < 1e15 {
        match (quarter as i64).rem_euclid(4) {
            0 => (1.0, 0.0),
            1 => (0.0, 1.0),
            2 => (-1.0, 0.0),
            _ => (0.0, -1.0),
        }
    } else {
        let r = deg.to_radians();
        (r.cos(), r.sin())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench::plan::fixtures::*;
    use crate::units::gf_to_n;
    use std::path::Path;

    #[test]
    fn magnitude_sweep_expands_to_the_papers_sixteen_levels_times_ten_trials() {
        let p = parse(FIG7).unwrap();
        let s = p.setpoints();
        assert_eq!(s.len(), 16 * 10);
        assert_eq!(s[15].normal_n, gf_to_n(750.0));
        assert_eq!(s[16].trial, 1);
        assert_eq!(s[16].normal_n, 0.0);
        assert_eq!(s[159].index, 159);
        assert_eq!(p.sensor_path, Path::new("experiments/paper_sensor.toml"));
        assert_eq!(p.force_tolerance_n, gf_to_n(5.0));
    }

    #[test]
    fn angle_sweep_splits_the_force_into_normal_and_tangential_parts() {
        let t = FIG7.replace(
            "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
            "kind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 45.0\nangle_step_deg = 5.0\ndirection_deg = 90.0\ntrials = 1",
        );
        let s = parse(&t).unwrap().setpoints();
        assert_eq!(s.len(), 10);
        let last = s[9];
        let f = gf_to_n(400.0);
        assert!((last.normal_n - f * 45f64.to_radians().cos()).abs() < 1e-12);
        assert!(last.tangential_n[0].abs() < 1e-12);
        assert!((last.tangential_n[1] - f * 45f64.to_radians().sin()).abs() < 1e-12);
        assert_eq!(last.swept_value, 45.0);
    }

    #[test]
    fn spatial_sweep_steps_between_two_points() {
        let t = FIG7.replace(
            "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
            "kind = \"spatial\"\nforce = 200.0\nstart_mm = [8.9, 6.75]\nend_mm = [11.1, 6.75]\nsubdivisions = 6",
        );
        let s = parse(&t).unwrap().setpoints();
        assert_eq!(s.len(), 7);
        assert!((s[6].position_mm[0] - 11.1).abs() < 1e-12);
        assert!((s[1].swept_value - 2.2 / 6.0).abs() < 1e-12);
    }

    #[test]
    fn a_tangential_load_along_y_has_an_exact_zero_x_part() {
        let t = FIG7.replace(
            "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
            "kind = \"angle\"\nforce = 200.0\nangle_from_deg = 0.0\nangle_to_deg = 30.0\nangle_step_deg = 30.0\ndirection_deg = 90.0\ntrials = 1",
        );
        let s = parse(&t).unwrap().setpoints();
        assert_eq!(s[1].tangential_n[0], 0.0);
        assert_eq!(s[0].tangential_n, [0.0, 0.0]);
        assert_eq!(cos_sin_deg(-90.0), (0.0, -1.0));
        assert_eq!(cos_sin_deg(180.0), (-1.0, 0.0));
    }

    #[test]
    fn the_setpoint_count_matches_the_expansion_for_every_kind() {
        let kinds = [
            FIG7.to_string(),
            FIG7.replace(
                "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
                "kind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 45.0\nangle_step_deg = 5.0\ntrials = 3",
            ),
            FIG7.replace(
                "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
                "kind = \"displacement\"\nshift_mm = [0.1, 0.0]\ntrials = 4",
            ),
            FIG7.replace(
                "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
                "kind = \"magnitude\"\nfrom = 0.1\nto = 0.7\nstep = 0.1\ntrials = 2",
            ),
        ];
        for (t, n) in kinds.iter().zip([160, 30, 4, 14]) {
            let p = parse(t).unwrap();
            assert_eq!(p.setpoint_count(), n);
            assert_eq!(p.setpoints().len(), n);
            assert_eq!(p.frame_count(), n);
        }
    }

    #[test]
    fn an_up_down_sweep_runs_each_trial_up_and_back_down_with_the_top_once() {
        let p = parse(&with_sweep(
            "kind = \"magnitude\"\nfrom = 0.0\nto = 300.0\nstep = 100.0\ntrials = 2\ndirection = \"up-down\"",
        ))
        .unwrap();
        assert_eq!(p.sweep_direction, SweepDirection::UpDown);
        let s = p.setpoints();
        let got: Vec<(usize, f64, Option<Direction>)> = s
            .iter()
            .map(|s| (s.trial, s.swept_value, s.direction))
            .collect();
        let (u, d) = (Some(Direction::Up), Some(Direction::Down));
        let one = |t| {
            vec![
                (t, 0.0, u),
                (t, 100.0, u),
                (t, 200.0, u),
                (t, 300.0, u),
                (t, 200.0, d),
                (t, 100.0, d),
                (t, 0.0, d),
            ]
        };
        assert_eq!(got, [one(0), one(1)].concat());
        assert!(s
            .iter()
            .all(|s| s.position.is_none() && s.hold_t_s.is_none()));
        assert_eq!(s[6].normal_n, 0.0, "the trial ends unloaded");
        assert_eq!(p.top_level_n(), Some(gf_to_n(300.0)));
        // From > 0: an unloaded reading is added at both ends of each trial.
        let p = parse(&with_sweep(
            "kind = \"magnitude\"\nfrom = 100.0\nto = 250.0\nstep = 100.0\ntrials = 1\ndirection = \"up-down\"",
        ))
        .unwrap();
        let got: Vec<(f64, Option<Direction>)> = p
            .setpoints()
            .iter()
            .map(|s| (s.swept_value, s.direction))
            .collect();
        assert_eq!(
            got,
            [(0.0, u), (100.0, u), (200.0, u), (100.0, d), (0.0, d)]
        );
        assert_eq!(
            p.top_level_n(),
            Some(gf_to_n(200.0)),
            "the top level, not `to`"
        );
        // The default ("up") is today's sweep: no direction in the rows.
        let p = parse(FIG7).unwrap();
        assert_eq!(p.sweep_direction, SweepDirection::Up);
        assert!(p.setpoints().iter().all(|s| s.direction.is_none()));
        let p = parse(&FIG7.replace("trials = 10", "trials = 10\ndirection = \"up\"")).unwrap();
        assert_eq!(p.setpoint_count(), 160);
        assert!(p.defaults.iter().all(|(k, _)| k != "sweep.direction"));
    }

    #[test]
    fn trials_repeat_at_each_listed_position_in_turn_numbered_across_positions() {
        let p = parse(&with_sweep(
            "kind = \"magnitude\"\nfrom = 0.0\nto = 100.0\nstep = 100.0\ntrials = 2\ndirection = \"up-down\"\npositions_mm = [[9.0, 6.75], [7.0, 5.0]]",
        ))
        .unwrap();
        let s = p.setpoints();
        assert_eq!(s.len(), 2 * 2 * 3);
        let got: Vec<(usize, Option<usize>, [f64; 2])> = s
            .iter()
            .map(|s| (s.trial, s.position, s.position_mm))
            .collect();
        let mut want = Vec::new();
        for (pi, pos) in [[9.0, 6.75], [7.0, 5.0]].iter().enumerate() {
            for t in 0..2 {
                want.extend([(pi * 2 + t, Some(pi), *pos); 3]);
            }
        }
        assert_eq!(got, want);
        // Angle sweeps repeat the same way; without the key, position is empty.
        let p = parse(&with_sweep(
            "kind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 10.0\nangle_step_deg = 10.0\ntrials = 1\npositions_mm = [[9.0, 6.75], [10.0, 6.75], [11.0, 6.75]]",
        ))
        .unwrap();
        let s = p.setpoints();
        assert_eq!(s.len(), 6);
        assert_eq!(s[5].position, Some(2));
        assert_eq!(s[5].trial, 2);
        assert_eq!(s[5].position_mm, [11.0, 6.75]);
        assert!(parse(FIG7)
            .unwrap()
            .setpoints()
            .iter()
            .all(|s| s.position.is_none()));
    }

    #[test]
    fn the_setpoint_count_matches_the_expansion_for_the_repeating_kinds() {
        for sweep in [
            "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 3\ndirection = \"up-down\"",
            "kind = \"magnitude\"\nfrom = 50.0\nto = 700.0\nstep = 50.0\ntrials = 3\ndirection = \"up-down\"\npositions_mm = [[9.0, 6.75], [8.0, 6.0]]",
            "kind = \"magnitude\"\nfrom = 100.0\nto = 100.0\nstep = 50.0\ntrials = 2\ndirection = \"up-down\"",
            "kind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 45.0\nangle_step_deg = 5.0\ntrials = 2\npositions_mm = [[9.0, 6.75], [8.0, 6.0], [10.0, 7.0]]",
            "kind = \"hold\"\nforce = 300.0\nduration_s = 10.0\nsample_interval_s = 0.3\ntrials = 3",
        ] {
            let p = parse(&with_sweep(sweep)).unwrap();
            assert_eq!(p.setpoint_count(), p.setpoints().len(), "{sweep}");
            assert_eq!(p.setpoints_iter().count(), p.setpoint_count(), "{sweep}");
            assert!(p.setpoints().iter().enumerate().all(|(i, s)| s.index == i));
        }
    }
}
