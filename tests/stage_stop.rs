//! Stopping a `tactbench stage` motion (issue 29, item 2): SIGINT / SIGTERM to a
//! `stage move` on each simulated controller (GRBL, Marlin, Zaber on pseudo-terminals),
//! `stage stop` from a second process while the first holds the port, and the force
//! limit of a bench file watched while jogging into the simulated gel.
//!
//! Each test spawns the real binary, waits for its "under way" line, signals it, and
//! then reads the simulated stage back with a fresh `stage position`: the stage must
//! stand where the stopped process said, and stay there. Latencies are printed
//! (`--nocapture`), never asserted (the machine is shared).

use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::{Child, ChildStderr, Command, Stdio};
use std::time::Duration;

use crate::util::{bin, root, stderr, stdout, ServedStage};

/// The Marlin CLI tests' short banner wait.
const MARLIN_ARGS: &[&str] = &["--marlin-banner-timeout", "0.3"];

/// A `tactbench stage … ARGS` child on `s`'s port with stderr piped.
fn spawn_stage(s: &ServedStage, protocol: &str, extra: &[&str], args: &[&str]) -> Child {
    Command::new(bin())
        .args(["stage", "--port"])
        .arg(&s.link)
        .args(["--protocol", protocol])
        .args(extra)
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn tactbench stage")
}

/// Reads the child's stderr until the "under way" line; returns what was read.
fn wait_under_way(err: &mut BufReader<ChildStderr>) -> String {
    let mut seen = String::new();
    loop {
        let mut line = String::new();
        let n = err.read_line(&mut line).expect("read stderr");
        seen.push_str(&line);
        assert!(n > 0, "the stage command ended before moving: {seen}");
        if line.contains("under way; Ctrl-C stops the stage") {
            return seen;
        }
    }
}

/// Signals the child, waits for it, returns (exit code, stdout, all of stderr).
fn signal_and_wait(
    mut child: Child,
    mut err: BufReader<ChildStderr>,
    signal: libc::c_int,
) -> (Option<i32>, String, String) {
    let pid = child.id() as libc::pid_t;
    // SAFETY: kill(2) on our own child, which has not been waited for.
    assert_eq!(unsafe { libc::kill(pid, signal) }, 0);
    let mut rest = String::new();
    err.read_to_string(&mut rest).expect("stderr");
    let mut out = String::new();
    child
        .stdout
        .take()
        .expect("stdout")
        .read_to_string(&mut out)
        .expect("stdout");
    let status = child.wait().expect("wait");
    (status.code(), out, rest)
}

/// The `at x = … mm  y = … mm  z = … mm` of a stop message.
fn stop_position(msg: &str) -> [f64; 3] {
    let at = msg
        .split("at x = ")
        .nth(1)
        .unwrap_or_else(|| panic!("no stop position in {msg}"));
    let nums: Vec<f64> = at
        .split_whitespace()
        .filter_map(|t| t.parse().ok())
        .take(3)
        .collect();
    assert_eq!(nums.len(), 3, "{msg}");
    [nums[0], nums[1], nums[2]]
}

/// `stage position --json` through a fresh process.
fn position(s: &ServedStage) -> [f64; 3] {
    let o = s.stage(&["position", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_str(&stdout(&o)).expect("json");
    ["x_mm", "y_mm", "z_mm"].map(|k| v[k].as_f64().expect(k))
}

fn assert_near(got: [f64; 3], want: [f64; 3], tol: f64, what: &str) {
    for i in 0..3 {
        assert!(
            (got[i] - want[i]).abs() <= tol,
            "{what}: axis {i}: {got:?} vs {want:?}"
        );
    }
}

/// Moves towards a far target on `protocol`'s simulator, signals the mover after it
/// got under way, and checks the exit code, the message and that the stage stays
/// where the message says. `tol`: the protocol's reported resolution.
fn stop_move_by_signal(
    protocol: &str,
    sim_args: &[&str],
    extra: &[&str],
    target: [f64; 3],
    signal: libc::c_int,
    tol: f64,
) {
    let s = ServedStage::start(protocol, sim_args, extra);
    let start = position(&s);
    let t = target.map(|v| v.to_string());
    let args = ["move", &t[0], &t[1], &t[2], "--speed", "2"];
    let mut child = spawn_stage(&s, protocol, extra, &args);
    let mut err = BufReader::new(child.stderr.take().expect("stderr"));
    let seen = wait_under_way(&mut err);
    // Let the controller carry the head a little way first.
    std::thread::sleep(Duration::from_millis(400));
    let (code, out, rest) = signal_and_wait(child, err, signal);
    let msg = format!("{seen}{rest}");
    eprintln!("{protocol}: {}", rest.trim());
    let name = if signal == libc::SIGINT {
        "SIGINT (Ctrl-C)"
    } else {
        "SIGTERM"
    };
    assert_eq!(code, Some(4), "{msg}");
    assert!(msg.contains(&format!("stopped by {name}")), "{msg}");
    assert!(msg.contains("the stage stood still"), "{msg}");
    let stopped = stop_position(&msg);
    // It had moved, and stopped far short of the target.
    let moved: f64 = (0..3).map(|i| (stopped[i] - start[i]).abs()).sum();
    let left: f64 = (0..3).map(|i| (target[i] - stopped[i]).abs()).sum();
    assert!(moved > 0.0 && left > 10.0, "{stopped:?}: {msg}");
    // The position printed on stdout, as a finished move prints it.
    assert!(out.starts_with("x = "), "{out}");
    // A fresh process finds the stage there, and it stays there: nothing buffered
    // moves it on.
    let after = position(&s);
    assert_near(after, stopped, tol, "after the stop");
    std::thread::sleep(Duration::from_millis(1000));
    assert_near(position(&s), after, 1e-9, "one second later");
}

#[test]
fn sigint_stops_a_grbl_move_and_the_stage_stays_where_reported() {
    stop_move_by_signal("grbl", &[], &[], [-60.0, 0.0, 0.0], libc::SIGINT, 1.5e-3);
}

#[test]
fn sigterm_stops_a_grbl_move_and_the_stage_stays_where_reported() {
    stop_move_by_signal("grbl", &[], &[], [-60.0, 0.0, 0.0], libc::SIGTERM, 1.5e-3);
}

#[test]
fn sigint_stops_a_marlin_move_with_m410_and_the_position_is_resynced() {
    stop_move_by_signal(
        "marlin",
        &[],
        MARLIN_ARGS,
        [60.0, 0.0, 100.0],
        libc::SIGINT,
        0.02,
    );
}

#[test]
fn sigterm_stops_a_marlin_move() {
    stop_move_by_signal(
        "marlin",
        &[],
        MARLIN_ARGS,
        [60.0, 0.0, 100.0],
        libc::SIGTERM,
        0.02,
    );
}

/// Zaber: `--zaber-mm-per-step 0.001` (1 µm steps; the simulator's 1 000 000 steps
/// are 1000 mm).
const ZABER_ARGS: &[&str] = &["--zaber-mm-per-step", "0.001"];

fn zaber_homed() -> ServedStage {
    let s = ServedStage::start("zaber", &[], ZABER_ARGS);
    let o = s.stage(&["home"]);
    assert!(o.status.success(), "{}", stderr(&o));
    s
}

#[test]
fn sigint_stops_a_zaber_move() {
    stop_move_zaber(libc::SIGINT);
}

#[test]
fn sigterm_stops_a_zaber_move() {
    stop_move_zaber(libc::SIGTERM);
}

fn stop_move_zaber(signal: libc::c_int) {
    let s = zaber_homed();
    let start = position(&s);
    let mut child = spawn_stage(
        &s,
        "zaber",
        ZABER_ARGS,
        &["move", "60", "0", "0", "--speed", "2"],
    );
    let mut err = BufReader::new(child.stderr.take().expect("stderr"));
    let seen = wait_under_way(&mut err);
    std::thread::sleep(Duration::from_millis(400));
    let (code, _, rest) = signal_and_wait(child, err, signal);
    let msg = format!("{seen}{rest}");
    eprintln!("zaber: {}", rest.trim());
    assert_eq!(code, Some(4), "{msg}");
    assert!(msg.contains("stopped by SIG"), "{msg}");
    let stopped = stop_position(&msg);
    assert!(
        stopped[0] > start[0] && stopped[0] < 50.0,
        "{stopped:?}: {msg}"
    );
    let after = position(&s);
    assert_near(after, stopped, 1e-3, "after the stop");
    std::thread::sleep(Duration::from_millis(1000));
    assert_near(position(&s), after, 1e-9, "one second later");
}

#[test]
fn stage_stop_from_a_second_process_signals_the_mover_that_holds_the_port() {
    let s = ServedStage::start("grbl", &[], &[]);
    let mut child = spawn_stage(&s, "grbl", &[], &["move", "-60", "0", "0", "--speed", "2"]);
    let pid = child.id();
    let mut err = BufReader::new(child.stderr.take().expect("stderr"));
    let seen = wait_under_way(&mut err);
    std::thread::sleep(Duration::from_millis(300));
    // Today's main: `cannot open serial port … busy`, and the move carries on.
    let o = s.stage(&["stop"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let e = stderr(&o);
    assert!(
        e.contains(&format!("PID {pid}")) && e.contains("'tactbench stage move'"),
        "{e}"
    );
    assert!(e.contains("sent it SIGINT"), "{e}");
    assert_eq!(stdout(&o), "stopped; state: idle\n");
    let mut rest = String::new();
    err.read_to_string(&mut rest).unwrap();
    let status = child.wait().unwrap();
    let msg = format!("{seen}{rest}");
    assert_eq!(status.code(), Some(4), "{msg}");
    assert!(msg.contains("stopped by SIGINT (Ctrl-C)"), "{msg}");
    let stopped = stop_position(&msg);
    assert!(stopped[0] < 0.0 && stopped[0] > -50.0, "{msg}");
    let after = position(&s);
    assert_near(after, stopped, 1.5e-3, "after the stop");
    std::thread::sleep(Duration::from_millis(1000));
    assert_near(position(&s), after, 1e-9, "one second later");
}

#[test]
fn a_second_mover_is_refused_naming_the_process_that_holds_the_port() {
    let s = ServedStage::start("grbl", &[], &[]);
    let mut child = spawn_stage(&s, "grbl", &[], &["move", "-60", "0", "0", "--speed", "2"]);
    let pid = child.id();
    let mut err = BufReader::new(child.stderr.take().expect("stderr"));
    wait_under_way(&mut err);
    let o = s.stage(&["move", "-1", "0", "0"]);
    assert_eq!(o.status.code(), Some(2));
    let e = stderr(&o);
    assert!(
        e.contains("is in use by another tactbench process")
            && e.contains(&format!("PID {pid}"))
            && e.contains("Ctrl-C in its terminal"),
        "{e}"
    );
    let (code, _, _) = signal_and_wait(child, err, libc::SIGINT);
    assert_eq!(code, Some(4));
}

/// A simulated bench whose GRBL stage starts 2 mm above the gel, over the sensor's
/// centre (fig. 7 hemisphere scene), with a 1 N normal force limit.
fn force_bench(dir: &Path, limit_n: f64) -> std::path::PathBuf {
    let scene = root("experiments/scenes/fig7_hemisphere_ramp.toml");
    let bench = dir.join("bench.toml");
    std::fs::write(
        &bench,
        format!(
            "[sim]\nscene = {:?}\nstage = \"grbl\"\nforce_sensor = \"dynpick\"\n\n\
             [geometry]\nsensor_origin_in_stage_mm = [-9.0, -6.75]\nsurface_z_mm = -2.0\n\
             press_direction = -1\n\n[safety]\nmax_force_n = [5.0, 5.0, {limit_n}]\n",
            scene.display().to_string()
        ),
    )
    .unwrap();
    bench
}

#[test]
fn stage_jog_with_a_bench_stops_at_its_force_limit_before_crushing_the_gel() {
    let dir = tempfile::tempdir().unwrap();
    let bench = force_bench(dir.path(), 1.0);
    // 5 mm down from 2 mm above the surface: 3 mm into the gel if nothing stopped it.
    let o = Command::new(bin())
        .args(["stage", "--bench"])
        .arg(&bench)
        .args(["jog", "0", "0", "-5", "--speed", "1"])
        .output()
        .unwrap();
    let e = stderr(&o);
    eprintln!("{e}");
    assert_eq!(o.status.code(), Some(3), "{e}");
    assert!(
        e.contains("stopped at the force limit of")
            && e.contains("measured fz = ")
            && e.contains("exceeds the safety limit 1.0000 N"),
        "{e}"
    );
    let z = stop_position(&e)[2];
    // In contact (below the surface at -2 mm), far short of the -5 mm target.
    assert!(z < -2.0 && z > -4.0, "z = {z}: {e}");
}

#[test]
fn stage_move_with_a_bench_without_a_force_limit_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let bench = force_bench(dir.path(), 1.0);
    let text = std::fs::read_to_string(&bench).unwrap();
    let cut = text.split("[safety]").next().unwrap().to_string();
    std::fs::write(&bench, cut).unwrap();
    let o = Command::new(bin())
        .args(["stage", "--bench"])
        .arg(&bench)
        .args(["jog", "0", "0", "-1"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(
        stderr(&o).contains("has no [safety] max_force_n"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn sigint_during_grbl_homing_resets_names_the_alarm_and_the_next_home_works() {
    let s = ServedStage::start("grbl", &["--homing"], &[]);
    let mut child = spawn_stage(&s, "grbl", &[], &["home"]);
    let mut err = BufReader::new(child.stderr.take().expect("stderr"));
    let seen = wait_under_way(&mut err);
    std::thread::sleep(Duration::from_millis(200));
    let (code, _, rest) = signal_and_wait(child, err, libc::SIGINT);
    let msg = format!("{seen}{rest}");
    eprintln!("grbl home: {}", rest.trim());
    assert_eq!(code, Some(4), "{msg}");
    assert!(
        msg.contains("homing stopped by SIGINT (Ctrl-C): sent GRBL soft reset 0x18")
            && msg.contains("ALARM:6")
            && msg.contains("run `home` again"),
        "{msg}"
    );
    let o = s.stage(&["home", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(stdout(&o), "{\"x_mm\":-1.0,\"y_mm\":-1.0,\"z_mm\":-1.0}\n");
}
