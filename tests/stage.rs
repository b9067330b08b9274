//! Stage drivers (GRBL, Zaber) against their simulators over real pseudo-terminals,
//! fault outcomes, transcript replays, and the `tactbench stage` CLI end to end.

use std::time::Duration;

use tactbench::device::fault::{FaultConfig, FaultKind, FaultTarget};
use tactbench::device::grbl::sim::{GrblSim, GrblSimConfig};
use tactbench::device::grbl::{open_serial, Grbl, GrblConfig};
use tactbench::device::pty::PtyServer;
use tactbench::device::{ErrorKind, Stage, StageState};

type Port = Box<dyn serialport::SerialPort>;

/// Position tolerance: GRBL reports 3 decimals.
const POS_TOL_MM: f64 = 1.5e-3;

fn grbl_on_pty(cfg: GrblSimConfig, driver: GrblConfig) -> (PtyServer<GrblSim>, Grbl<Port>) {
    let server = PtyServer::spawn(GrblSim::new(cfg), None).expect("pty");
    let port = open_serial(&server.path().to_string_lossy(), 115_200).expect("open pty");
    let grbl = Grbl::connect(port, driver).expect("connect");
    (server, grbl)
}

fn assert_pos(got: [f64; 3], want: [f64; 3]) {
    for i in 0..3 {
        assert!(
            (got[i] - want[i]).abs() <= POS_TOL_MM,
            "axis {i}: got {got:?}, want {want:?}"
        );
    }
}

fn fast_driver() -> GrblConfig {
    GrblConfig {
        reply_timeout: Duration::from_millis(400),
        status_timeout: Duration::from_millis(200),
        ..Default::default()
    }
}

#[test]
fn grbl_homes_moves_and_reports_position_over_a_pty() {
    let mut cfg = GrblSimConfig::homing_bench();
    cfg.start_mpos_mm = [-1.5, -1.5, -1.5];
    let (server, mut g) = grbl_on_pty(cfg, GrblConfig::default());
    assert_eq!(
        g.state().unwrap(),
        StageState::Alarm,
        "power-up with homing enabled"
    );
    // Limits derived from $130..$132 in GRBL's negative space.
    assert_eq!(
        g.limits().axes_mm,
        [[-100.0, 0.0], [-100.0, 0.0], [-50.0, 0.0]]
    );
    g.home().unwrap();
    assert_pos(g.position().unwrap(), [-1.0; 3]);
    g.move_to([-2.0, -3.0, -1.5], Some(20.0)).unwrap();
    g.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(g.position().unwrap(), [-2.0, -3.0, -1.5]);
    g.move_by([0.5, 0.25, -0.125], None).unwrap();
    g.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(g.position().unwrap(), [-1.5, -2.75, -1.625]);
    assert_eq!(g.state().unwrap(), StageState::Idle);
    let sim = server.stop().expect("sim back");
    assert_pos(sim.mpos_mm(), [-1.5, -2.75, -1.625]);
}

#[test]
fn grbl_refuses_out_of_travel_moves_before_sending() {
    let mut cfg = GrblSimConfig::homing_bench();
    cfg.start_in_alarm = false;
    let (server, mut g) = grbl_on_pty(cfg, GrblConfig::default());
    let e = g.move_to([-10.0, -10.0, 1.0], None).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Limit);
    assert!(
        e.message.contains("z = 1 mm exceeds travel limit 0 mm"),
        "{e}"
    );
    let sim = server.stop().unwrap();
    assert!(!sim.in_alarm(), "nothing was sent, so no soft-limit alarm");
}

#[test]
fn grbl_home_with_homing_disabled_is_a_clear_rejection() {
    let (_server, mut g) = grbl_on_pty(GrblSimConfig::default(), GrblConfig::default());
    let e = g.home().unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Rejected);
    assert!(
        e.message
            .starts_with("homing is disabled on the controller ($22=0)"),
        "{e}"
    );
    assert!(e.hint.as_deref().unwrap_or("").contains("$22=1"));
}

#[test]
fn grbl_moves_in_alarm_are_rejected_with_an_unlock_hint_and_unlock_clears() {
    let mut cfg = GrblSimConfig::homing_bench();
    cfg.start_mpos_mm = [-5.0; 3];
    let (_server, mut g) = grbl_on_pty(cfg, GrblConfig::default());
    // The state is asked first: refused as an alarm, nothing sent.
    let e = g.move_to([-6.0, -5.0, -5.0], Some(10.0)).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Limit);
    assert!(e.message.contains("alarm state"), "{e}");
    assert!(e.hint.as_deref().unwrap_or("").contains("unlock"));
    let r = g.unlock_report().unwrap();
    assert_eq!(
        r.actions[0],
        "`$X`: cleared the alarm (raised before this connection; code not seen)"
    );
    g.move_to([-6.0, -5.0, -5.0], Some(10.0)).unwrap();
    g.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(g.position().unwrap(), [-6.0, -5.0, -5.0]);
}

#[test]
fn grbl_stop_holds_then_resets_without_alarm_and_position_is_kept() {
    let (server, mut g) = grbl_on_pty(GrblSimConfig::default(), GrblConfig::default());
    g.move_to([-20.0, 0.0, 0.0], Some(2.0)).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(g.state().unwrap(), StageState::Moving);
    g.stop().unwrap();
    assert_eq!(
        g.state().unwrap(),
        StageState::Idle,
        "hold complete + reset: no alarm 3"
    );
    let x = g.position().unwrap()[0];
    std::thread::sleep(Duration::from_millis(200));
    assert_pos(g.position().unwrap(), [x, 0.0, 0.0]);
    assert!(
        x < -0.3 && x > -19.5,
        "stopped part way to -20 mm: x = {x} mm"
    );
    assert!(!server.stop().unwrap().in_alarm());
}

#[test]
fn grbl_connect_recovers_a_controller_left_in_a_critical_alarm() {
    let mut cfg = GrblSimConfig::homing_bench();
    cfg.start_in_alarm = false;
    cfg.start_mpos_mm = [-5.0; 3];
    let server = PtyServer::spawn(GrblSim::new(cfg), None).expect("pty");
    let path = server.path().to_string_lossy().into_owned();
    {
        // A driver with wrong (too wide) limits lets GRBL's soft limit trip.
        let wide = GrblConfig {
            limits: Some(tactbench::device::TravelLimits {
                axes_mm: [[-500.0, 500.0]; 3],
            }),
            ..fast_driver()
        };
        // The driver intersects the configured box with GRBL's own, so another
        // program sends the out-of-travel move.
        let _ = wide;
        use std::io::Write;
        let mut p = open_serial(&path, 115_200).unwrap();
        p.write_all(b"G53 G0 X-5 Y-5 Z10\n").unwrap();
        std::thread::sleep(Duration::from_millis(300));
    }
    // A new session finds GRBL locked ("Reset to continue"), answering nothing, not
    // even `?`: a plain connect (as `status`) says why and changes nothing; the
    // resetting connect (as `unlock`) resets, and `$X` clears.
    let Err(e) = Grbl::connect(open_serial(&path, 115_200).unwrap(), fast_driver()) else {
        panic!("a locked controller answered");
    };
    assert_eq!(e.kind(), ErrorKind::Timeout);
    assert!(e.message.contains("critical alarm"), "{e}");
    assert!(e.hint.as_deref().unwrap_or("").contains("unlock"), "{e}");
    let mut g =
        Grbl::connect_resetting(open_serial(&path, 115_200).unwrap(), fast_driver()).unwrap();
    assert!(g.reset_at_connect());
    assert_eq!(g.state().unwrap(), StageState::Alarm);
    g.unlock().unwrap();
    assert_eq!(g.state().unwrap(), StageState::Idle);
    assert_pos(g.position().unwrap(), [-5.0; 3]);
}

#[test]
fn grbl_jog_and_probe() {
    let cfg = GrblSimConfig {
        probe_contact_z_mm: Some(-3.0),
        ..Default::default()
    };
    let (_server, mut g) = grbl_on_pty(cfg, GrblConfig::default());
    g.jog([-1.0, 0.0, 0.0], 5.0).unwrap();
    g.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(g.position().unwrap(), [-1.0, 0.0, 0.0]);
    let contact = g.probe_z(-5.0, 5.0, Duration::from_secs(5)).unwrap();
    assert_pos(contact, [-1.0, 0.0, -3.0]);
}

// ---- GRBL faults: each has a defined outcome ----

fn grbl_with_fault(
    kind: FaultKind,
    target: FaultTarget,
    skip: u32,
    late_by_ms: u64,
) -> (PtyServer<GrblSim>, Grbl<Port>) {
    let mut fault = FaultConfig::once(kind, target, skip);
    fault.late_by = Duration::from_millis(late_by_ms);
    let cfg = GrblSimConfig {
        faults: Some(fault),
        ..Default::default()
    };
    grbl_on_pty(cfg, fast_driver())
}

/// Queries at connect: `?` (1+), `$G`, `$I`, `$$` — skip enough to hit a later query.
const AFTER_CONNECT: u32 = 4;

#[test]
fn grbl_fault_late_status_reply_is_retried_and_recovers() {
    let (server, mut g) = grbl_with_fault(
        FaultKind::LateReply,
        FaultTarget::Queries,
        AFTER_CONNECT,
        300,
    );
    assert_pos(g.position().unwrap(), [0.0; 3]);
    assert_eq!(server.stop().unwrap().faults_injected(), 1);
}

#[test]
fn grbl_fault_late_move_reply_times_out_is_not_resent_and_the_stream_resyncs() {
    let (server, mut g) = grbl_with_fault(FaultKind::LateReply, FaultTarget::Commands, 0, 1000);
    let e = g.move_to([-1.0, 0.0, 0.0], Some(10.0)).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Timeout);
    assert!(e.message.contains("not re-sent"), "{e}");
    // The late `ok` is discarded by the resync before the next line.
    g.move_to([-2.0, 0.0, 0.0], Some(10.0)).unwrap();
    g.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(g.position().unwrap(), [-2.0, 0.0, 0.0]);
    let sim = server.stop().unwrap();
    assert_eq!(sim.motions_accepted(), 2, "each move sent exactly once");
}

#[test]
fn grbl_fault_dropped_byte_in_a_move_reply_is_a_protocol_error_without_resend() {
    let (server, mut g) = grbl_with_fault(FaultKind::DroppedByte, FaultTarget::Commands, 0, 0);
    let e = g.move_to([-1.0, 0.0, 0.0], Some(10.0)).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Protocol);
    assert!(e.message.contains("not re-sent"), "{e}");
    g.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(g.position().unwrap(), [-1.0, 0.0, 0.0]);
    assert_eq!(server.stop().unwrap().motions_accepted(), 1);
}

#[test]
fn grbl_fault_garbled_status_report_is_retried_and_recovers() {
    let (server, mut g) =
        grbl_with_fault(FaultKind::Garbled, FaultTarget::Queries, AFTER_CONNECT, 0);
    assert_pos(g.position().unwrap(), [0.0; 3]);
    assert_eq!(server.stop().unwrap().faults_injected(), 1);
}

#[test]
fn grbl_fault_garbled_status_report_during_a_wait_is_requeried_not_fatal() {
    // Queries after connect: `?` before the move, `?` at the start of wait_idle,
    // then the `?` polls while `G4 P0` waits: garble the second poll.
    let (server, mut g) = grbl_with_fault(
        FaultKind::Garbled,
        FaultTarget::Queries,
        AFTER_CONNECT + 3,
        0,
    );
    g.move_to([-1.0, 0.0, 0.0], Some(2.0)).unwrap();
    g.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(g.position().unwrap(), [-1.0, 0.0, 0.0]);
    let sim = server.stop().unwrap();
    assert_eq!(sim.faults_injected(), 1);
    assert_eq!(sim.motions_accepted(), 1);
}

#[test]
fn grbl_fault_unsolicited_messages_are_ignored() {
    let mut fault = FaultConfig::once(FaultKind::Unsolicited, FaultTarget::Any, 0);
    fault.max_faults = 1000;
    let cfg = GrblSimConfig {
        faults: Some(fault),
        ..Default::default()
    };
    let (server, mut g) = grbl_on_pty(cfg, fast_driver());
    g.move_to([-1.0, -1.0, 0.0], Some(20.0)).unwrap();
    g.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(g.position().unwrap(), [-1.0, -1.0, 0.0]);
    assert_eq!(g.last_message(), Some("Simulated unsolicited message"));
    assert!(server.stop().unwrap().faults_injected() >= 4);
}

#[test]
fn grbl_fault_reset_during_a_status_query_recovers_by_asking_again() {
    let (server, mut g) = grbl_with_fault(
        FaultKind::DeviceReset,
        FaultTarget::Queries,
        AFTER_CONNECT,
        0,
    );
    let before = g.resets_seen();
    assert_pos(g.position().unwrap(), [0.0; 3]);
    assert_eq!(g.resets_seen(), before + 1);
    assert_eq!(server.stop().unwrap().faults_injected(), 1);
}

#[test]
fn grbl_fault_reset_after_a_move_is_an_alarm_3_then_unlock_recovers() {
    let (_server, mut g) = grbl_with_fault(FaultKind::DeviceReset, FaultTarget::Commands, 0, 0);
    let e = g.move_to([-1.0, 0.0, 0.0], Some(10.0)).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Limit);
    assert!(e.message.contains("ALARM:3"), "{e}");
    assert_eq!(g.state().unwrap(), StageState::Alarm);
    g.unlock().unwrap();
    assert_eq!(g.state().unwrap(), StageState::Idle);
}

#[test]
fn grbl_fault_hard_limit_trip_fails_wait_idle_with_limit_and_unlock_resets() {
    let (_server, mut g) = grbl_with_fault(FaultKind::LimitTrip, FaultTarget::Commands, 0, 0);
    g.move_to([-5.0, 0.0, 0.0], Some(10.0)).unwrap();
    let e = g.wait_idle(Duration::from_secs(5)).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Limit, "{e}");
    assert!(
        e.message.contains("ALARM:1") && e.message.contains("hard limit"),
        "{e}"
    );
    // Further moves fail fast until unlock (which needs a reset first).
    assert_eq!(
        g.move_to([-1.0, 0.0, 0.0], None).unwrap_err().kind(),
        ErrorKind::Limit
    );
    g.unlock().unwrap();
    assert_eq!(g.state().unwrap(), StageState::Idle);
    g.move_to([-1.0, 0.0, 0.0], Some(10.0)).unwrap();
    g.wait_idle(Duration::from_secs(5)).unwrap();
}

#[test]
fn grbl_fault_disconnect_is_reported_as_disconnected() {
    let (server, mut g) =
        grbl_with_fault(FaultKind::Disconnect, FaultTarget::Any, AFTER_CONNECT, 0);
    let e = g.position().unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
    assert!(server.is_finished() || server.stop().is_some());
}

// ---- Zaber ----

use tactbench::device::zaber::codec::Warning;
use tactbench::device::zaber::sim::{ZaberSim, ZaberSimConfig};
use tactbench::device::zaber::{self, Zaber, ZaberConfig};

/// 1 µm per microstep keeps numbers readable; travel 0..50 mm.
const ZABER_MM_PER_STEP: f64 = 1e-3;
const ZABER_TRAVEL_STEPS: i64 = 50_000;

fn zaber_sim_config() -> ZaberSimConfig {
    let mut cfg = ZaberSimConfig::three_single_axis(ZABER_TRAVEL_STEPS);
    for axes in cfg.devices.values_mut() {
        // 20 mm/s = 20_000 steps/s.
        axes[0].maxspeed = (20_000.0 * zaber::VELOCITY_UNITS_PER_STEP_S) as i64;
    }
    cfg
}

fn zaber_driver_config() -> ZaberConfig {
    let mut c = ZaberConfig::single_axis_devices([1, 2, 3], ZABER_MM_PER_STEP);
    c.reply_timeout = Duration::from_millis(300);
    c
}

fn zaber_on_pty(cfg: ZaberSimConfig, driver: ZaberConfig) -> (PtyServer<ZaberSim>, Zaber<Port>) {
    let server = PtyServer::spawn(ZaberSim::new(cfg), None).expect("pty");
    let port = zaber::open_serial(&server.path().to_string_lossy(), 115_200).expect("open pty");
    let z = Zaber::connect(port, driver).expect("connect");
    (server, z)
}

#[test]
fn zaber_homes_moves_and_reports_position_over_a_pty() {
    let (server, mut z) = zaber_on_pty(zaber_sim_config(), zaber_driver_config());
    assert_eq!(
        z.limits().axes_mm,
        [[0.0, 50.0]; 3],
        "from limit.min/limit.max x resolution"
    );
    assert_eq!(z.warnings(), [Warning::NOT_HOMED; 3]);
    assert_eq!(z.state().unwrap(), StageState::Alarm, "not homed");
    let e = z.move_to([1.0, 1.0, 1.0], None).unwrap_err();
    assert!(e.message.contains("no reference position (WR)"), "{e}");
    z.home().unwrap();
    assert_eq!(z.state().unwrap(), StageState::Idle);
    assert_pos(z.position().unwrap(), [0.0; 3]);
    z.move_to([10.0, 5.5, 0.25], Some(40.0)).unwrap();
    z.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(z.position().unwrap(), [10.0, 5.5, 0.25]);
    z.move_by([-1.0, 0.5, 0.0], None).unwrap();
    z.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(z.position().unwrap(), [9.0, 6.0, 0.25]);
    let sim = server.stop().unwrap();
    assert_eq!(sim.axis(1, 1).unwrap().pos, 9000.0);
}

#[test]
fn zaber_without_checksums_or_ids_still_works() {
    let mut d = zaber_driver_config();
    d.checksums = false;
    d.message_ids = false;
    let (_server, mut z) = zaber_on_pty(zaber_sim_config(), d);
    z.home().unwrap();
    z.move_to([1.0, 2.0, 3.0], None).unwrap();
    z.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(z.position().unwrap(), [1.0, 2.0, 3.0]);
}

#[test]
fn zaber_stop_leaves_ni_and_is_not_an_error() {
    let (_server, mut z) = zaber_on_pty(zaber_sim_config(), zaber_driver_config());
    z.home().unwrap();
    z.move_to([40.0, 0.0, 0.0], Some(10.0)).unwrap();
    std::thread::sleep(Duration::from_millis(200));
    assert_eq!(z.state().unwrap(), StageState::Moving);
    z.stop().unwrap();
    z.wait_idle(Duration::from_secs(1)).unwrap();
    assert_eq!(z.warnings()[0], Warning::INTERRUPTED);
    let x = z.position().unwrap()[0];
    assert!(x > 0.5 && x < 39.5, "stopped part way to 40 mm: {x} mm");
    z.unlock().unwrap();
    assert_eq!(z.warnings()[0], Warning::NONE);
}

#[test]
fn zaber_rejections_carry_the_reason_and_out_of_travel_is_refused_locally() {
    let mut d = zaber_driver_config();
    // Driver limits wider than the device's: the device must reject.
    d.limits = Some(tactbench::device::TravelLimits {
        axes_mm: [[-100.0, 100.0]; 3],
    });
    let (_server, mut z) = zaber_on_pty(zaber_sim_config(), d);
    z.home().unwrap();
    let e = z.move_to([60.0, 0.0, 0.0], None).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Rejected);
    assert!(e.message.ends_with("rejected the command: BADDATA"), "{e}");
    let (_server2, mut z2) = zaber_on_pty(zaber_sim_config(), zaber_driver_config());
    let e = z2.move_by([0.0, 0.0, 30.0], None).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Limit);
    assert!(
        e.message.contains("z = 55 mm exceeds travel limit 50 mm"),
        "{e}"
    );
}

// ---- Zaber faults ----

/// Queries at connect: 3 status + 3 × (limit.min, limit.max).
const ZABER_CONNECT_QUERIES: u32 = 9;

fn zaber_with_fault(
    kind: FaultKind,
    target: FaultTarget,
    skip: u32,
    late_by_ms: u64,
) -> (PtyServer<ZaberSim>, Zaber<Port>) {
    let mut cfg = zaber_sim_config();
    let mut fault = FaultConfig::once(kind, target, skip);
    fault.late_by = Duration::from_millis(late_by_ms);
    cfg.faults = Some(fault);
    zaber_on_pty(cfg, zaber_driver_config())
}

#[test]
fn zaber_fault_late_query_reply_is_retried_and_the_stale_reply_discarded_by_id() {
    let (server, mut z) = zaber_with_fault(
        FaultKind::LateReply,
        FaultTarget::Queries,
        ZABER_CONNECT_QUERIES,
        400,
    );
    assert_pos(z.position().unwrap(), [25.0; 3]);
    assert_pos(z.position().unwrap(), [25.0; 3]);
    assert_eq!(server.stop().unwrap().faults_injected(), 1);
}

#[test]
fn zaber_fault_late_move_reply_times_out_without_resend() {
    let (server, mut z) = zaber_with_fault(FaultKind::LateReply, FaultTarget::Commands, 3, 600);
    z.home().unwrap();
    let e = z.move_to([1.0, 1.0, 1.0], None).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Timeout);
    assert!(e.message.contains("not re-sent"), "{e}");
    // The late reply is recognised by its id and skipped.
    z.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(z.position().unwrap(), [1.0, 0.0, 0.0]);
    assert_eq!(
        server.stop().unwrap().moves_accepted(),
        4,
        "3 homes + 1 move, none repeated"
    );
}

#[test]
fn zaber_fault_dropped_byte_in_a_move_reply_is_a_protocol_error_without_resend() {
    let (server, mut z) = zaber_with_fault(FaultKind::DroppedByte, FaultTarget::Commands, 3, 0);
    z.home().unwrap();
    let e = z.move_to([2.0, 2.0, 2.0], None).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Protocol, "{e}");
    assert!(e.message.contains("not re-sent"), "{e}");
    z.wait_idle(Duration::from_secs(5)).unwrap();
    assert_eq!(server.stop().unwrap().moves_accepted(), 4);
}

#[test]
fn zaber_fault_bad_checksum_on_a_query_is_retried_and_recovers() {
    let (server, mut z) = zaber_with_fault(
        FaultKind::Garbled,
        FaultTarget::Queries,
        ZABER_CONNECT_QUERIES,
        0,
    );
    assert_pos(z.position().unwrap(), [25.0; 3]);
    assert_eq!(server.stop().unwrap().faults_injected(), 1);
}

#[test]
fn zaber_fault_unsolicited_alerts_and_info_are_ignored() {
    let mut cfg = zaber_sim_config();
    let mut fault = FaultConfig::once(FaultKind::Unsolicited, FaultTarget::Any, 0);
    fault.max_faults = 1000;
    cfg.faults = Some(fault);
    let (server, mut z) = zaber_on_pty(cfg, zaber_driver_config());
    z.home().unwrap();
    z.move_to([3.0, 2.0, 1.0], None).unwrap();
    z.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(z.position().unwrap(), [3.0, 2.0, 1.0]);
    assert!(server.stop().unwrap().faults_injected() > 10);
}

#[test]
fn zaber_fault_device_reset_surfaces_lost_reference_and_refuses_absolute_moves() {
    // The reset swallows the reply to the first move after homing (3 homes).
    let (_server, mut z) = zaber_with_fault(FaultKind::DeviceReset, FaultTarget::Commands, 3, 0);
    z.home().unwrap();
    let e = z.move_to([1.0, 1.0, 1.0], None).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Timeout, "{e}");
    assert_eq!(
        z.state().unwrap(),
        StageState::Alarm,
        "reset device reports WR"
    );
    assert_eq!(z.warnings()[0], Warning::NOT_HOMED);
    let e = z.move_to([1.0, 1.0, 1.0], None).unwrap_err();
    assert!(
        e.message
            .contains("x axis (device 1 axis 1) has no reference position"),
        "{e}"
    );
    z.home().unwrap();
    z.move_to([1.0, 1.0, 1.0], None).unwrap();
    z.wait_idle(Duration::from_secs(5)).unwrap();
    assert_pos(z.position().unwrap(), [1.0, 1.0, 1.0]);
}

#[test]
fn zaber_fault_limit_trip_fails_wait_idle_with_limit_and_unlock_clears() {
    let (_server, mut z) = zaber_with_fault(FaultKind::LimitTrip, FaultTarget::Commands, 3, 0);
    z.home().unwrap();
    z.move_to([5.0, 5.0, 5.0], None).unwrap();
    let e = z.wait_idle(Duration::from_secs(5)).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Limit, "{e}");
    assert!(e.message.contains("WL (unexpected limit trigger)"), "{e}");
    z.unlock().unwrap();
    assert_eq!(z.warnings()[0], Warning::NONE);
    z.wait_idle(Duration::from_secs(5)).unwrap();
    assert_eq!(z.state().unwrap(), StageState::Idle);
}

#[test]
fn zaber_fault_disconnect_is_reported_as_disconnected() {
    let (_server, mut z) = zaber_with_fault(
        FaultKind::Disconnect,
        FaultTarget::Any,
        ZABER_CONNECT_QUERIES,
        0,
    );
    assert_eq!(z.position().unwrap_err().kind(), ErrorKind::Disconnected);
}

// ---- `tactbench stage` end to end against a simulator on a pty ----

mod cli {
    use std::path::Path;
    use std::time::Duration;

    use crate::util::{command, stderr, stdout, ServedStage};

    #[test]
    fn cli_grbl_status_home_move_jog_and_exact_position_json() {
        let s = ServedStage::start("grbl", &["--homing"], &[]);
        let o = s.stage(&["status"]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(stdout(&o).starts_with("state: alarm\n"), "{}", stdout(&o));
        // Moves in alarm: clear message, non-zero exit.
        let o = s.stage(&["move", "-10", "-5", "-1"]);
        assert!(!o.status.success());
        assert!(
            stderr(&o).contains("alarm state") && stderr(&o).contains("unlock"),
            "{}",
            stderr(&o)
        );
        let o = s.stage(&["home", "--json"]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert_eq!(stdout(&o), "{\"x_mm\":-1.0,\"y_mm\":-1.0,\"z_mm\":-1.0}\n");
        let o = s.stage(&["move", "-10", "-5", "-1.25", "--speed", "50"]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert_eq!(
            stdout(&o),
            "x = -10.0000 mm  y = -5.0000 mm  z = -1.2500 mm\n"
        );
        let o = s.stage(&["jog", "1", "-1", "0.25", "--speed", "20"]);
        assert!(o.status.success(), "{}", stderr(&o));
        let o = s.stage(&["position", "--json"]);
        assert_eq!(stdout(&o), "{\"x_mm\":-9.0,\"y_mm\":-6.0,\"z_mm\":-1.0}\n");
        // Outside the soft-limit box: refused before sending.
        let o = s.stage(&["move", "-1000", "0", "0"]);
        assert_eq!(o.status.code(), Some(2));
        assert!(
            stderr(&o).contains("requested x = -1000 mm is below travel limit -100 mm"),
            "{}",
            stderr(&o)
        );
    }

    /// Writes raw bytes to the served controller, as another program would.
    fn send_raw(link: &Path, bytes: &[u8]) {
        use std::io::Write;
        let mut p = tactbench::device::grbl::open_serial(&link.to_string_lossy(), 115_200)
            .expect("open the served pty");
        p.write_all(bytes).unwrap();
        std::thread::sleep(Duration::from_millis(300));
    }

    #[test]
    fn cli_grbl_status_in_hold_resume_stop_and_unlock_after_a_critical_alarm() {
        let s = ServedStage::start("grbl", &["--homing"], &[]);
        let o = s.stage(&["unlock"]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(
            stdout(&o).starts_with("`$X`: cleared the alarm"),
            "{}",
            stdout(&o)
        );
        // Another program starts a slow move and presses feed hold.
        send_raw(&s.link, b"G53 G1 X-60 F60\n");
        send_raw(&s.link, b"!");
        let o = s.stage(&["status"]);
        assert!(o.status.success(), "{}", stderr(&o));
        let out = stdout(&o);
        assert!(out.starts_with("state: held\n"), "{out}");
        assert!(out.contains("; state Hold:0"), "{out}");
        assert!(out.contains("hint: motion is paused"), "{out}");
        let o = s.stage(&["move", "-1", "-1", "-1"]);
        assert_eq!(o.status.code(), Some(2));
        assert!(
            stderr(&o).contains("failed (held)") && stderr(&o).contains("resume"),
            "{}",
            stderr(&o)
        );
        let o = s.stage(&["resume"]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert_eq!(stdout(&o), "resumed (`~`); state: Run\n");
        let o = s.stage(&["stop"]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert_eq!(stdout(&o), "stopped; state: idle\n");
        // A soft-limit violation by another program: ALARM:2, then silence.
        send_raw(&s.link, b"G53 G0 X5\n");
        let o = s.stage(&["status"]);
        assert_eq!(o.status.code(), Some(2));
        let err = stderr(&o);
        assert!(err.contains("Likely cause: a critical alarm"), "{err}");
        assert!(err.contains("unlock"), "{err}");
        let o = s.stage(&["unlock"]);
        assert!(o.status.success(), "{}", stderr(&o));
        let out = stdout(&o);
        assert!(out.starts_with("soft reset (0x18)"), "{out}");
        assert!(out.contains("`$X`: cleared the alarm"), "{out}");
        assert!(out.ends_with("unlocked; state: idle\n"), "{out}");
        let o = s.stage(&["status"]);
        assert!(stdout(&o).starts_with("state: idle\n"), "{}", stdout(&o));
        assert!(
            stdout(&o).contains("grbl 1.1h.20190830; state Idle"),
            "{}",
            stdout(&o)
        );
    }

    #[test]
    fn cli_grbl_home_with_homing_disabled_explains() {
        let s = ServedStage::start("grbl", &[], &[]);
        let o = s.stage(&["home"]);
        assert!(!o.status.success());
        assert!(
            stderr(&o).contains("homing is disabled on the controller ($22=0)"),
            "{}",
            stderr(&o)
        );
    }

    #[test]
    fn cli_zaber_home_move_and_position_json() {
        let s = ServedStage::start("zaber", &[], &[]);
        let res = ["--zaber-mm-per-step", "0.001"];
        let o = s.stage(&[&["status"][..], &res].concat());
        assert!(
            stdout(&o).contains("zaber warnings x WR y WR z WR"),
            "{}",
            stdout(&o)
        );
        let o = s.stage(&[&["home"][..], &res].concat());
        assert!(o.status.success(), "{}", stderr(&o));
        let o = s.stage(&[&["move", "1.5", "2", "3"][..], &res].concat());
        assert!(o.status.success(), "{}", stderr(&o));
        let o = s.stage(&[&["position", "--json"][..], &res].concat());
        assert_eq!(stdout(&o), "{\"x_mm\":1.5,\"y_mm\":2.0,\"z_mm\":3.0}\n");
        let o = s.stage(&[&["status", "--zaber-devices", "7,8,9"][..], &res].concat());
        assert!(!o.status.success());
        assert!(
            stderr(&o).contains("no answer from device 7 axis 1"),
            "{}",
            stderr(&o)
        );
    }

    #[test]
    fn cli_missing_port_and_bad_options_are_clear_errors() {
        let o = command()
            .args(["stage", "--protocol", "grbl", "status"])
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(2));
        assert!(stderr(&o).contains("missing --port"), "{}", stderr(&o));
        let missing = Path::new("/nonexistent/tty");
        let o = command()
            .args(["stage", "--protocol", "zaber", "--port"])
            .arg(missing)
            .args(["--zaber-mm-per-step", "0,1", "position"])
            .output()
            .unwrap();
        assert!(
            stderr(&o).contains("--zaber-mm-per-step takes 1 or 3 values"),
            "{}",
            stderr(&o)
        );
        let o = command()
            .args(["stage", "--port"])
            .arg(missing)
            .args(["--protocol", "grbl", "status"])
            .output()
            .unwrap();
        assert!(
            stderr(&o).contains("cannot open serial port /nonexistent/tty"),
            "{}",
            stderr(&o)
        );
    }

    #[test]
    fn cli_ports_lists_or_says_none() {
        let o = command().arg("ports").output().unwrap();
        assert!(o.status.success());
        let out = stdout(&o);
        assert!(
            out.starts_with("no serial ports found")
                || out.lines().all(|l| l.starts_with("/dev/")
                    || l.starts_with("network force sensors are not listed")),
            "{out}"
        );
    }
}

// ---- transcript replays (protocols/transcripts/) ----

mod replay {
    use super::*;
    use tactbench::device::replay::{Replay, Transcript};

    fn load(name: &str) -> Replay {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("protocols/transcripts")
            .join(name);
        let text = std::fs::read_to_string(&path).expect("transcript");
        Replay::new(Transcript::parse(&text).expect("parse transcript"))
    }

    #[test]
    fn replay_grbl_connect_home_move() {
        let mut g =
            Grbl::connect(load("grbl_connect_home_move.txt"), GrblConfig::default()).unwrap();
        assert_eq!(g.version(), Some("1.1h.20190830"), "from `$I`");
        assert_eq!(
            g.limits().axes_mm,
            [[-100.0, 0.0], [-100.0, 0.0], [-50.0, 0.0]]
        );
        g.home().unwrap();
        assert_eq!(g.position().unwrap(), [-1.0; 3]);
        g.move_to([-10.0, -5.0, -1.25], Some(10.0)).unwrap();
        g.wait_idle(Duration::from_secs(1)).unwrap();
        assert_eq!(g.position().unwrap(), [-10.0, -5.0, -1.25]);
        g.into_inner().finish().unwrap();
    }

    #[test]
    fn replay_grbl_wpos_homing_disabled_hard_limit() {
        let mut g = Grbl::connect(
            load("grbl_wpos_homing_disabled_hard_limit.txt"),
            GrblConfig::default(),
        )
        .unwrap();
        let e = g.home().unwrap_err();
        assert!(
            e.message
                .starts_with("homing is disabled on the controller ($22=0)"),
            "{e}"
        );
        // MPos = WPos + WCO = (1, 2, 3) + (-10, -10, -2).
        assert_eq!(g.position().unwrap(), [-9.0, -8.0, 1.0]);
        g.move_to([-20.0, -10.0, -1.0], None).unwrap();
        let e = g.wait_idle(Duration::from_secs(1)).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Limit);
        assert!(e.message.contains("ALARM:1"), "{e}");
        g.unlock().unwrap();
        assert_eq!(g.position().unwrap(), [-12.0, -10.0, -1.0]);
        g.into_inner().finish().unwrap();
    }

    // Recorded from the real GRBL 1.1h firmware (see `real_firmware`), replayed
    // through the same scenario code.

    #[test]
    fn replay_grbl_real_connect_in_feed_hold_status_resume_stop() {
        grbl_states::held(load("grbl_real_hold.txt"))
            .finish()
            .unwrap();
    }

    #[test]
    fn replay_grbl_real_feed_hold_during_a_move_fails_the_wait_with_held() {
        grbl_states::hold_during_wait(load("grbl_real_hold_during_wait.txt"))
            .finish()
            .unwrap();
    }

    #[test]
    fn replay_grbl_real_connect_while_running() {
        grbl_states::running(load("grbl_real_run.txt"))
            .finish()
            .unwrap();
    }

    #[test]
    fn replay_grbl_real_soft_limit_critical_alarm_status_then_unlock() {
        grbl_states::critical_alarm(load("grbl_real_soft_limit_alarm.txt"))
            .finish()
            .unwrap();
    }

    #[test]
    fn replay_grbl_real_soft_limits_off_accepts_positive_moves() {
        grbl_states::soft_limits_off(load("grbl_real_soft_limits_off.txt"))
            .finish()
            .unwrap();
    }

    #[test]
    fn replay_grbl_real_wpos_reports_with_a_g54_offset() {
        grbl_states::work_offset(load("grbl_real_wpos_g54.txt"))
            .finish()
            .unwrap();
    }

    #[test]
    fn replay_grbl_real_alarm_after_failed_homing() {
        grbl_states::alarm(load("grbl_real_alarm.txt"))
            .finish()
            .unwrap();
    }

    #[test]
    fn replay_grbl_real_sleep_then_unlock() {
        grbl_states::sleeping(load("grbl_real_sleep.txt"))
            .finish()
            .unwrap();
    }

    #[test]
    fn replay_grbl_real_check_mode_then_unlock() {
        grbl_states::check_mode(load("grbl_real_check.txt"))
            .finish()
            .unwrap();
    }

    #[test]
    fn replay_zaber_connect_home_move() {
        let cfg = ZaberConfig::single_axis_devices([1, 2, 3], 0.001);
        let mut z = Zaber::connect(load("zaber_connect_home_move.txt"), cfg).unwrap();
        assert_eq!(z.limits().axes_mm, [[0.0, 50.0]; 3]);
        z.home().unwrap();
        z.move_to([1.5, 2.0, 3.0], None).unwrap();
        z.wait_idle(Duration::from_secs(1)).unwrap();
        assert_pos(z.position().unwrap(), [1.5, 2.0, 3.0]);
        z.into_inner().finish().unwrap();
    }

    #[test]
    fn replay_detects_a_driver_that_deviates_from_the_transcript() {
        let cfg = ZaberConfig::single_axis_devices([1, 2, 3], 0.001);
        let mut z = Zaber::connect(load("zaber_connect_home_move.txt"), cfg).unwrap();
        // Skipping `home` makes the next write differ from the transcript.
        let e = z.move_to([1.5, 2.0, 3.0], None).unwrap_err();
        assert!(e.message.contains("has no reference position"), "{e}");
        let r = z.into_inner();
        assert!(r.finish().unwrap_err().contains("host bytes never written"));
    }
}

// ---- GRBL in every state: scenarios run against the real firmware (recorded) and
// replayed from the recordings in CI ----
//
// Each scenario is one driver session. `real_firmware::*` (ignored) runs it against
// GRBL 1.1h built for the PC (grbl-sim) on a pty, after putting the firmware in the
// state named by the scenario with raw bytes, and records the session; with
// `TACTBENCH_GRBL_RECORD_DIR=protocols/transcripts` it (re)writes the transcript.
// `replay::*` runs the same scenario code against the recorded transcript. Build and
// run: see `tests/grbl_real_firmware.sh`.

mod grbl_states {
    use super::*;
    use std::io::{Read, Write};
    use tactbench::device::grbl::codec::MachineState;

    /// Longest wait for a move: the PC build runs several times slower than real
    /// time on a loaded host.
    const WAIT: Duration = Duration::from_secs(300);

    /// Connect in feed hold (Hold:0): the state is reported without changing it;
    /// moves and waits fail at once with `Held` and the resume/abort hint; `resume`
    /// continues the move; `stop` aborts it (hold + reset, position kept).
    pub fn held<P: Read + Write>(port: P) -> P {
        let mut g = Grbl::connect(port, GrblConfig::default()).expect("connect in hold");
        assert_eq!(g.last_state(), Some(MachineState::Hold(0)));
        assert_eq!(g.state().unwrap(), StageState::Held);
        let x0 = g.position().unwrap()[0];
        assert!(x0 < 0.0 && x0 > -20.0, "stopped part way: {x0}");
        let e = g.move_to([-1.0, 0.0, 0.0], None).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Held, "{e}");
        assert!(e.hint.as_deref().unwrap_or("").contains("`~`"), "{e}");
        let e = g.wait_idle(Duration::from_secs(5)).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Held, "{e}");
        let after = g.resume().unwrap();
        assert_eq!(after, MachineState::Run);
        g.stop().unwrap();
        assert_eq!(g.state().unwrap(), StageState::Idle, "no alarm after stop");
        let x1 = g.position().unwrap()[0];
        assert!(x1 <= x0 && x1 > -20.0, "kept where it stopped: {x1}");
        g.into_inner()
    }

    /// A feed hold pressed during a move: `wait_idle` returns at once with `Held`.
    pub fn hold_during_wait<P: Read + Write>(port: P) -> P {
        let mut g = Grbl::connect(port, GrblConfig::default()).expect("connect");
        assert_eq!(g.state().unwrap(), StageState::Idle);
        g.move_to([-5.0, 0.0, 0.0], Some(1.0)).unwrap();
        let e = g.wait_idle(WAIT).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Held, "{e}");
        assert!(e.message.contains("feed hold"), "{e}");
        g.stop().unwrap();
        assert_eq!(g.state().unwrap(), StageState::Idle);
        g.into_inner()
    }

    /// Connect while a move runs (`Run`: `$$` would answer error:8): reported as
    /// moving; the wait ends when it is done; the settings are read afterwards.
    pub fn running<P: Read + Write>(port: P) -> P {
        let mut g = Grbl::connect(port, GrblConfig::default()).expect("connect while running");
        assert_eq!(g.state().unwrap(), StageState::Moving);
        assert!(g.settings().is_empty(), "no `$$` while running");
        g.wait_idle(WAIT).unwrap();
        assert_pos(g.position().unwrap(), [-1.0, 0.0, 0.0]);
        g.move_to([-0.5, 0.0, 0.0], None).unwrap();
        g.wait_idle(WAIT).unwrap();
        assert_eq!(g.settings().get(&130).map(String::as_str), Some("200.000"));
        assert_pos(g.position().unwrap(), [-0.5, 0.0, 0.0]);
        g.into_inner()
    }

    /// Soft limits on ($20=1, $22=1) and a soft-limit alarm (ALARM:2, critical):
    /// `status`'s connect fails naming the critical alarm and `unlock`; `unlock`'s
    /// connect resets, `$X` clears; the envelope is then GRBL's `[-$13x, 0]`.
    pub fn critical_alarm<P: Read + Write>(mut port: P) -> P {
        let Err(e) = Grbl::connect(&mut port, GrblConfig::default()) else {
            panic!("connect succeeded in a critical alarm");
        };
        assert_eq!(e.kind(), ErrorKind::Timeout);
        assert!(e.message.contains("critical alarm"), "{e}");
        assert!(!e.message.contains("baud"), "{e}");
        assert!(e.hint.as_deref().unwrap_or("").contains("unlock"), "{e}");
        let mut g = Grbl::connect_resetting(&mut port, GrblConfig::default()).unwrap();
        assert!(g.reset_at_connect());
        let r = g.unlock_report().unwrap();
        assert!(r.actions[0].starts_with("soft reset (0x18)"), "{r:?}");
        assert!(r.actions.iter().any(|a| a.starts_with("`$X`")), "{r:?}");
        assert_eq!(g.state().unwrap(), StageState::Idle);
        assert_eq!(g.limits().axes_mm, [[-200.0, 0.0]; 3]);
        let e = g.move_to([5.0, 0.0, 0.0], None).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Limit);
        assert!(e.message.contains("exceeds travel limit 0 mm"), "{e}");
        g.move_to([-1.0, 0.0, 0.0], None).unwrap();
        g.wait_idle(WAIT).unwrap();
        assert_pos(g.position().unwrap(), [-1.0, 0.0, 0.0]);
        drop(g);
        port
    }

    /// Homing and soft limits off (GRBL's defaults): positive coordinates are
    /// accepted as GRBL accepts them; the version comes from `$I`.
    pub fn soft_limits_off<P: Read + Write>(port: P) -> P {
        let mut g = Grbl::connect(port, GrblConfig::default()).expect("connect");
        assert_eq!(g.version(), Some("1.1h.20190830"));
        assert!(g.soft_limit_box().is_none());
        assert_eq!(g.limits().axes_mm, [[f64::NEG_INFINITY, f64::INFINITY]; 3]);
        g.move_to([5.0, 0.0, 0.0], None).unwrap();
        g.wait_idle(WAIT).unwrap();
        assert_pos(g.position().unwrap(), [5.0, 0.0, 0.0]);
        g.into_inner()
    }

    /// `$10=0` (WPos reports) with a G54 offset, connecting when the report carries
    /// no `WCO:`: the driver asks `$#` and reports machine positions.
    pub fn work_offset<P: Read + Write>(port: P) -> P {
        let mut g = Grbl::connect(port, GrblConfig::default()).expect("connect");
        assert_eq!(g.wco_mm(), Some([-2.0, -3.0, -1.0]));
        assert_pos(g.position().unwrap(), [-5.0, 0.0, 0.0]);
        g.move_to([-6.0, -1.0, 0.0], None).unwrap();
        g.wait_idle(WAIT).unwrap();
        assert_pos(g.position().unwrap(), [-6.0, -1.0, 0.0]);
        g.into_inner()
    }

    /// An alarm left by a failed homing cycle (grbl-sim has no switches: ALARM:8)
    /// with homing enabled: moves refused with `Limit` and the unlock hint; `unlock`
    /// is `$X` alone (not critical).
    pub fn alarm<P: Read + Write>(port: P) -> P {
        let mut g = Grbl::connect(port, GrblConfig::default()).expect("connect in alarm");
        assert_eq!(g.state().unwrap(), StageState::Alarm);
        let e = g.move_to([-1.0, 0.0, 0.0], None).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Limit);
        assert!(e.hint.as_deref().unwrap_or("").contains("unlock"), "{e}");
        let r = g.unlock_report().unwrap();
        assert!(r.actions[0].starts_with("`$X`"), "{r:?}");
        assert_eq!(g.state().unwrap(), StageState::Idle);
        g.into_inner()
    }

    /// Sleep (`$SLP`): `?` is answered, lines are not; `unlock` resets (GRBL
    /// re-initialises sleep as alarm) and unlocks.
    pub fn sleeping<P: Read + Write>(port: P) -> P {
        let mut g = Grbl::connect(port, GrblConfig::default()).expect("connect asleep");
        assert_eq!(g.last_state(), Some(MachineState::Sleep));
        assert_eq!(g.state().unwrap(), StageState::Alarm);
        let r = g.unlock_report().unwrap();
        assert!(r.actions[0].contains("sleep"), "{r:?}");
        assert_eq!(g.state().unwrap(), StageState::Idle);
        g.into_inner()
    }

    /// Check mode (`$C`): connect reads everything (`$#` is refused there, so the
    /// offset comes from a report); moves are refused; `unlock` leaves check mode.
    pub fn check_mode<P: Read + Write>(port: P) -> P {
        let mut g = Grbl::connect(port, GrblConfig::default()).expect("connect in check mode");
        assert_eq!(g.last_state(), Some(MachineState::Check));
        let e = g.move_to([-1.0, 0.0, 0.0], None).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Rejected);
        assert!(e.message.contains("check mode"), "{e}");
        let r = g.unlock_report().unwrap();
        assert!(r.actions[0].starts_with("`$C`"), "{r:?}");
        assert_eq!(g.state().unwrap(), StageState::Idle);
        g.into_inner()
    }
}

/// Records a session in the transcript format of `protocols/` (`> ` host bytes,
/// `< ` device bytes, escaped), as the driver saw it: each write, each read.
struct Recorder<P> {
    inner: P,
    steps: Vec<(bool, Vec<u8>)>,
}

impl<P> Recorder<P> {
    fn new(inner: P) -> Self {
        Recorder {
            inner,
            steps: Vec::new(),
        }
    }

    fn push(&mut self, host: bool, bytes: &[u8]) {
        match self.steps.last_mut() {
            Some((h, b)) if *h == host => b.extend_from_slice(bytes),
            _ => self.steps.push((host, bytes.to_vec())),
        }
    }

    /// The transcript text: host steps on one line each, device steps one line per
    /// received line.
    fn transcript(&self, header: &str) -> String {
        let mut out = String::new();
        for l in header.lines() {
            out.push_str(&format!("# {l}\n"));
        }
        for (host, bytes) in &self.steps {
            let prefix = if *host { "> " } else { "< " };
            let chunks: Vec<&[u8]> = if *host {
                vec![bytes.as_slice()]
            } else {
                bytes.split_inclusive(|b| *b == b'\n').collect()
            };
            for c in chunks {
                out.push_str(prefix);
                // Spaces are written as such, except at the end of a line (the
                // transcript parser trims trailing whitespace).
                let trailing = c.len() - c.iter().rev().take_while(|b| **b == b' ').count();
                for (i, &b) in c.iter().enumerate() {
                    match b {
                        b'\r' => out.push_str("\\r"),
                        b'\n' => out.push_str("\\n"),
                        b'\\' => out.push_str("\\\\"),
                        b' ' if i < trailing => out.push(' '),
                        0x21..=0x7e => out.push(b as char),
                        _ => out.push_str(&format!("\\x{b:02X}")),
                    }
                }
                out.push('\n');
            }
        }
        out
    }
}

impl<P> Drop for Recorder<P> {
    /// A failed real-firmware scenario leaves its session in the temp dir to look at.
    fn drop(&mut self) {
        if std::thread::panicking() {
            let path = std::env::temp_dir().join("tactbench-grbl-failed-session.txt");
            let _ = std::fs::write(&path, self.transcript("session of a failed scenario"));
            eprintln!("session written to {}", path.display());
        }
    }
}

impl<P: std::io::Read> std::io::Read for Recorder<P> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.push(false, &buf[..n]);
        Ok(n)
    }
}

impl<P: std::io::Write> std::io::Write for Recorder<P> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.push(true, &buf[..n]);
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

#[test]
fn recorder_escapes_so_that_the_transcript_parses_back_to_the_same_bytes() {
    use tactbench::device::replay::{Dir, Transcript};
    let mut r = Recorder::new(());
    r.push(true, b"?");
    r.push(
        false,
        b"<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n\r\nGrbl 1.1h ['$' for help]\r\n",
    );
    r.push(true, b"\x18 \\");
    r.push(false, b"ok \xFE ok  ");
    let t = Transcript::parse(&r.transcript("header\nline 2")).unwrap();
    assert_eq!(
        t.steps,
        vec![
            (Dir::Host, b"?".to_vec()),
            (
                Dir::Device,
                b"<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n\r\nGrbl 1.1h ['$' for help]\r\n"
                    .to_vec()
            ),
            (Dir::Host, b"\x18 \\".to_vec()),
            (Dir::Device, b"ok \xFE ok  ".to_vec()),
        ]
    );
}

/// The real GRBL 1.1h firmware (grbl-sim built for the PC, served on a pty by
/// socat). Ignored: needs `TACTBENCH_GRBL_SIM` = path of `grbl_sim.exe` (and
/// `socat`); see `tests/grbl_real_firmware.sh`.
mod real_firmware {
    use super::*;
    use std::io::{Read, Write};
    use std::path::PathBuf;
    use std::process::{Child, Command};
    use std::time::Instant;

    struct Firmware {
        child: Child,
        dir: PathBuf,
        tty: PathBuf,
    }

    impl Firmware {
        /// A fresh instance (its own EEPROM file: GRBL's default settings).
        fn start(name: &str) -> Firmware {
            let exe = std::env::var("TACTBENCH_GRBL_SIM").expect(
                "set TACTBENCH_GRBL_SIM to the grbl_sim.exe built from gnea/grbl + grbl-sim",
            );
            let dir =
                std::env::temp_dir().join(format!("tactbench-grbl-{name}-{}", std::process::id()));
            let _ = std::fs::remove_dir_all(&dir);
            std::fs::create_dir_all(&dir).unwrap();
            let tty = dir.join("tty");
            let child = Command::new("socat")
                .current_dir(&dir)
                .arg(format!("PTY,raw,echo=0,link={}", tty.display()))
                .arg(format!(
                    "EXEC:'{exe} -n -s /dev/null -b /dev/null',pty,raw,echo=0"
                ))
                .spawn()
                .expect("socat (apt-get install socat)");
            let t0 = Instant::now();
            while !tty.exists() {
                assert!(t0.elapsed() < Duration::from_secs(10), "no pty from socat");
                std::thread::sleep(Duration::from_millis(50));
            }
            let fw = Firmware { child, dir, tty };
            // A fresh EEPROM: GRBL restores its defaults (error:7, the settings) and
            // prints its banner; take all that before anything is sent.
            fw.raw("", "['$' for help]");
            fw
        }

        fn path(&self) -> String {
            self.tty.to_string_lossy().into_owned()
        }

        /// Sends raw bytes (setup, not recorded) and collects replies until `until`
        /// appears in them (or 30 s pass: the firmware runs slowly on a busy host).
        fn raw(&self, bytes: &str, until: &str) -> String {
            let mut p = open_serial(&self.path(), 115_200).unwrap();
            p.write_all(bytes.as_bytes()).unwrap();
            let mut got = String::new();
            let t0 = Instant::now();
            let mut buf = [0u8; 512];
            while !got.contains(until) {
                assert!(
                    t0.elapsed() < Duration::from_secs(30),
                    "waiting for {until:?}: {got:?}"
                );
                match p.read(&mut buf) {
                    Ok(n) => got.push_str(&String::from_utf8_lossy(&buf[..n])),
                    Err(_) => {
                        // Ask for a report now and then while waiting for a state.
                        if until.starts_with('<') || until.starts_with('|') {
                            p.write_all(b"?").unwrap();
                            std::thread::sleep(Duration::from_millis(100));
                        }
                    }
                }
            }
            got
        }

        /// Runs `scenario` on a recorded port; writes the transcript when
        /// `TACTBENCH_GRBL_RECORD_DIR` is set.
        fn record(&self, file: &str, header: &str, scenario: fn(Recorder<Port>) -> Recorder<Port>) {
            let port = open_serial(&self.path(), 115_200).unwrap();
            let rec = scenario(Recorder::new(port));
            if let Ok(dir) = std::env::var("TACTBENCH_GRBL_RECORD_DIR") {
                let path = PathBuf::from(dir).join(file);
                std::fs::write(&path, rec.transcript(header)).unwrap();
                eprintln!("wrote {}", path.display());
            }
        }
    }

    impl Drop for Firmware {
        fn drop(&mut self) {
            let _ = self.child.kill();
            let _ = self.child.wait();
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }

    const RECORDED: &str =
        "Recorded from the real GRBL 1.1h firmware (gnea/grbl 1.1h.20190830 built\n\
        for the PC with grbl/grbl-sim, served on a pty by socat) by\n\
        tests/stage.rs real_firmware::";

    #[test]
    #[ignore = "needs the real GRBL firmware: TACTBENCH_GRBL_SIM (tests/grbl_real_firmware.sh)"]
    fn real_grbl_connect_in_feed_hold_status_resume_stop() {
        let fw = Firmware::start("hold");
        fw.raw("G53 G1 X-20 F60\n", "ok");
        fw.raw("", "<Run");
        fw.raw("!", "<Hold:0");
        fw.record(
            "grbl_real_hold.txt",
            &format!("{RECORDED}real_grbl_connect_in_feed_hold_status_resume_stop.\nSetup: `G53 G1 X-20 F60`, then `!` (feed hold) until Hold:0.\nScenario: tests/stage.rs grbl_states::held."),
            grbl_states::held,
        );
    }

    #[test]
    #[ignore = "needs the real GRBL firmware: TACTBENCH_GRBL_SIM (tests/grbl_real_firmware.sh)"]
    fn real_grbl_feed_hold_during_a_move_fails_the_wait_with_held() {
        let fw = Firmware::start("holdwait");
        let path = fw.path();
        // The operator presses feed hold while the driver waits for the move.
        let presser = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(2500));
            let mut f = std::fs::OpenOptions::new().write(true).open(path).unwrap();
            f.write_all(b"!").unwrap();
        });
        fw.record(
            "grbl_real_hold_during_wait.txt",
            &format!("{RECORDED}real_grbl_feed_hold_during_a_move_fails_the_wait_with_held.\nSetup: none; `!` written to the pty by another thread 2.5 s into the session.\nScenario: tests/stage.rs grbl_states::hold_during_wait."),
            grbl_states::hold_during_wait,
        );
        presser.join().unwrap();
    }

    #[test]
    #[ignore = "needs the real GRBL firmware: TACTBENCH_GRBL_SIM (tests/grbl_real_firmware.sh)"]
    fn real_grbl_connect_while_running() {
        let fw = Firmware::start("run");
        fw.raw("G53 G1 X-1 F60\n", "ok");
        fw.raw("", "<Run");
        fw.record(
            "grbl_real_run.txt",
            &format!("{RECORDED}real_grbl_connect_while_running.\nSetup: `G53 G1 X-1 F60` until Run.\nScenario: tests/stage.rs grbl_states::running."),
            grbl_states::running,
        );
    }

    #[test]
    #[ignore = "needs the real GRBL firmware: TACTBENCH_GRBL_SIM (tests/grbl_real_firmware.sh)"]
    fn real_grbl_soft_limit_critical_alarm_status_then_unlock() {
        let fw = Firmware::start("critical");
        fw.raw("$22=1\n$20=1\n", "ok\r\nok");
        fw.raw("G0 X5\n", "Reset to continue");
        fw.record(
            "grbl_real_soft_limit_alarm.txt",
            &format!("{RECORDED}real_grbl_soft_limit_critical_alarm_status_then_unlock.\nSetup: `$22=1`, `$20=1`, `G0 X5` -> ALARM:2 (critical).\nScenario: tests/stage.rs grbl_states::critical_alarm (a `status` connect, then an `unlock` one)."),
            grbl_states::critical_alarm,
        );
    }

    #[test]
    #[ignore = "needs the real GRBL firmware: TACTBENCH_GRBL_SIM (tests/grbl_real_firmware.sh)"]
    fn real_grbl_soft_limits_off_accepts_positive_moves() {
        let fw = Firmware::start("positive");
        fw.record(
            "grbl_real_soft_limits_off.txt",
            &format!("{RECORDED}real_grbl_soft_limits_off_accepts_positive_moves.\nSetup: none (GRBL defaults: $20=0, $22=0).\nScenario: tests/stage.rs grbl_states::soft_limits_off."),
            grbl_states::soft_limits_off,
        );
    }

    #[test]
    #[ignore = "needs the real GRBL firmware: TACTBENCH_GRBL_SIM (tests/grbl_real_firmware.sh)"]
    fn real_grbl_wpos_reports_with_a_g54_offset() {
        let fw = Firmware::start("wco");
        fw.raw("G10 L2 P1 X-2 Y-3 Z-1\nG53 G0 X-5\n", "ok\r\nok");
        fw.raw("", "<Idle");
        fw.raw("$10=0\n", "ok");
        // Use up the report that carries WCO: the driver's first report has none.
        fw.raw("", "|WCO:");
        fw.raw("?", "|Ov:");
        fw.record(
            "grbl_real_wpos_g54.txt",
            &format!("{RECORDED}real_grbl_wpos_reports_with_a_g54_offset.\nSetup: `G10 L2 P1 X-2 Y-3 Z-1`, `G53 G0 X-5`, `$10=0`, two `?`.\nScenario: tests/stage.rs grbl_states::work_offset."),
            grbl_states::work_offset,
        );
    }

    #[test]
    #[ignore = "needs the real GRBL firmware: TACTBENCH_GRBL_SIM (tests/grbl_real_firmware.sh)"]
    fn real_grbl_alarm_after_failed_homing() {
        let fw = Firmware::start("alarm");
        fw.raw("$22=1\n", "ok");
        fw.raw("$H\n", "ALARM:8");
        fw.raw("", "<Alarm");
        fw.record(
            "grbl_real_alarm.txt",
            &format!("{RECORDED}real_grbl_alarm_after_failed_homing.\nSetup: `$22=1`, `$H` -> ALARM:8 (grbl-sim has no limit switches).\nScenario: tests/stage.rs grbl_states::alarm."),
            grbl_states::alarm,
        );
    }

    #[test]
    #[ignore = "needs the real GRBL firmware: TACTBENCH_GRBL_SIM (tests/grbl_real_firmware.sh)"]
    fn real_grbl_sleep_then_unlock() {
        let fw = Firmware::start("sleep");
        fw.raw("$SLP\n", "Sleeping");
        fw.record(
            "grbl_real_sleep.txt",
            &format!("{RECORDED}real_grbl_sleep_then_unlock.\nSetup: `$SLP`.\nScenario: tests/stage.rs grbl_states::sleeping."),
            grbl_states::sleeping,
        );
    }

    #[test]
    #[ignore = "needs the real GRBL firmware: TACTBENCH_GRBL_SIM (tests/grbl_real_firmware.sh)"]
    fn real_grbl_check_mode_then_unlock() {
        let fw = Firmware::start("check");
        fw.raw("$C\n", "Enabled");
        fw.record(
            "grbl_real_check.txt",
            &format!("{RECORDED}real_grbl_check_mode_then_unlock.\nSetup: `$C`.\nScenario: tests/stage.rs grbl_states::check_mode."),
            grbl_states::check_mode,
        );
    }
}

#[test]
fn bench_file_travel_box_reaches_the_grbl_driver_and_is_validated() {
    use tactbench::bench::config::BenchConfig;
    let dir = tempfile::tempdir().unwrap();
    let bench = |stage_extra: &str| {
        let p = dir.path().join("bench.toml");
        std::fs::write(
            &p,
            format!(
                "[stage]\nprotocol = \"grbl\"\nport = \"/dev/null\"\n{stage_extra}\n\
                 [force_sensor]\nprotocol = \"dynpick\"\nport = \"/dev/null\"\n\
                 [camera]\ndevice = \"dir:frames\"\n\
                 [geometry]\nsensor_origin_in_stage_mm = [-100.0, -100.0]\nsurface_z_mm = -30.0\n\
                 press_direction = -1\n"
            ),
        )
        .unwrap();
        BenchConfig::from_path(&p)
    };
    let c =
        bench("travel_min_mm = [-200.0, -200.0, -50.0]\ntravel_max_mm = [10.0, 0.0, 5.0]").unwrap();
    let tactbench::bench::config::BenchDevices::Hardware { stage, .. } = c.devices else {
        panic!("a hardware bench");
    };
    assert_eq!(
        stage.travel.unwrap().axes_mm,
        [[-200.0, 10.0], [-200.0, 0.0], [-50.0, 5.0]]
    );
    let e = bench("travel_min_mm = [0.0, 0.0, 0.0]")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("give both stage.travel_min_mm and stage.travel_max_mm"),
        "{e}"
    );
    let e = bench("travel_min_mm = [0.0, 0.0, 0.0]\ntravel_max_mm = [1.0, -1.0, 1.0]")
        .unwrap_err()
        .to_string();
    assert!(e.contains("stage.travel_max_mm[1]"), "{e}");
}

/// Runs that start from a stage left held, alarmed, or with a work offset and WPos
/// reports (the GRBL simulator of the simulated bench put in that state by raw
/// bytes before the driver connects): the run recovers as documented or refuses
/// clearly.
mod runs_from_a_stage_left_in_a_state {
    use super::*;
    use std::io::{Read, Write};
    use std::path::Path;
    use std::sync::atomic::AtomicBool;
    use std::sync::Arc;
    use std::time::Instant;
    use tactbench::bench::config::BenchConfig;
    use tactbench::bench::connect::{self, SimOptions};
    use tactbench::bench::journal::{self, RunStatus};
    use tactbench::bench::plan::Plan;
    use tactbench::bench::runner::{self, Devices, RunOptions, RunSummary};
    use tactbench::sensor::Sensor;

    /// Sends `bytes` to the raw stage port and reads until `until` appears.
    fn raw(port: &mut Port, bytes: &[u8], until: &str) -> String {
        port.write_all(bytes).unwrap();
        let mut got = String::new();
        let mut buf = [0u8; 256];
        let t0 = Instant::now();
        while !got.contains(until) {
            assert!(
                t0.elapsed() < Duration::from_secs(20),
                "waiting for {until:?}: {got:?}"
            );
            if let Ok(n) = port.read(&mut buf) {
                got.push_str(&String::from_utf8_lossy(&buf[..n]));
            } else if until.starts_with('<') {
                port.write_all(b"?").unwrap();
                std::thread::sleep(Duration::from_millis(50));
            }
        }
        got
    }

    /// Connects the simulated bench, puts its GRBL in a state with `setup` (raw
    /// bytes on the stage's pty, with the bench's own driver disconnected), connects
    /// a fresh driver and runs 2 setpoints of the fig. 7 plan.
    fn run_from(
        out: &Path,
        setup: impl FnOnce(&mut Port),
    ) -> (RunSummary, Grbl<Port>, connect::Connected) {
        let plan = Plan::from_path(crate::util::root("experiments/fig7_magnitude.toml")).unwrap();
        let scene = crate::util::root("experiments/scenes/fig7_hemisphere_ramp.toml");
        let bench = BenchConfig::sim(&scene);
        let sim = SimOptions {
            links: out.with_extension("links"),
            start_over_mm: Some(plan.approach_position_mm),
            stage_faults: None,
            ft_faults: None,
        };
        let mut c = connect::connect(&bench, &sim).unwrap();
        let stage_port = c.sim.as_ref().unwrap().stage_port().display().to_string();
        // Free the port: the bench's driver goes, the state is set, a new one comes.
        c.stage = Box::new(Parked);
        let mut p = open_serial(&stage_port, 115_200).unwrap();
        setup(&mut p);
        drop(p);
        let mut g = Grbl::connect(
            open_serial(&stage_port, 115_200).unwrap(),
            GrblConfig::default(),
        )
        .expect("connect in any state");
        let sensor_toml = std::fs::read_to_string(&plan.sensor_path).unwrap();
        let sensor = Sensor::from_toml_str(&sensor_toml, &plan.sensor_path).unwrap();
        let options = RunOptions {
            dir: out.to_path_buf(),
            resume: false,
            build_id: Some("test-build".into()),
            plan_toml: std::fs::read_to_string(&plan.path).unwrap_or_default(),
            sensor_toml,
            camera: None,
            bench: c.description.clone(),
            devices: c.identities.clone(),
            home: c.home,
            tare: c.tare,
            simulated: c.sim.is_some(),
            write_fault: None,
            limit: Some(2),
            stop: Arc::new(AtomicBool::new(false)),
            stop_signal: Default::default(),
        };
        let summary = {
            let mut devices = Devices {
                stage: &mut g,
                ft: c.ft.as_mut(),
                camera: c.camera.as_mut(),
            };
            runner::run(
                &plan,
                &sensor,
                &c.geometry,
                &mut devices,
                &options,
                &mut |_| {},
            )
            .unwrap()
        };
        (summary, g, c)
    }

    /// Holds the place of the bench's own stage driver while the test drives the pty.
    struct Parked;

    impl Stage for Parked {
        fn home(&mut self) -> tactbench::device::DeviceResult<()> {
            Ok(())
        }
        fn move_to(&mut self, _: [f64; 3], _: Option<f64>) -> tactbench::device::DeviceResult<()> {
            Ok(())
        }
        fn move_by(&mut self, _: [f64; 3], _: Option<f64>) -> tactbench::device::DeviceResult<()> {
            Ok(())
        }
        fn position(&mut self) -> tactbench::device::DeviceResult<[f64; 3]> {
            Ok([0.0; 3])
        }
        fn state(&mut self) -> tactbench::device::DeviceResult<StageState> {
            Ok(StageState::Idle)
        }
        fn wait_idle(&mut self, _: Duration) -> tactbench::device::DeviceResult<()> {
            Ok(())
        }
        fn stop(&mut self) -> tactbench::device::DeviceResult<()> {
            Ok(())
        }
        fn unlock(&mut self) -> tactbench::device::DeviceResult<()> {
            Ok(())
        }
        fn limits(&self) -> tactbench::device::TravelLimits {
            tactbench::device::TravelLimits {
                axes_mm: [[0.0; 2]; 3],
            }
        }
        fn status_interval(&self) -> Duration {
            Duration::from_millis(200)
        }
    }

    fn stage_columns(dir: &Path) -> Vec<[f64; 3]> {
        journal::read_rows(dir)
            .unwrap()
            .iter()
            .map(|r| [r.stage_x_mm, r.stage_y_mm, r.stage_z_mm])
            .collect()
    }

    #[test]
    fn run_from_a_stage_with_a_work_offset_and_wpos_reports_uses_machine_positions() {
        let tmp = tempfile::tempdir().unwrap();
        let plain = tmp.path().join("plain");
        let (s, _, _) = run_from(&plain, |_| {});
        assert_eq!(s.status, RunStatus::Completed, "{:?}", s.reason);
        let offset = tmp.path().join("offset");
        let (s, mut g, _bench) = run_from(&offset, |p| {
            raw(p, b"G10 L2 P1 X-2 Y-3 Z-1\n$10=0\n", "ok\r\nok\r\n");
        });
        assert_eq!(s.status, RunStatus::Completed, "{:?}", s.reason);
        assert_eq!(g.wco_mm(), Some([-2.0, -3.0, -1.0]));
        let (a, b) = (stage_columns(&plain), stage_columns(&offset));
        assert_eq!(a.len(), 2);
        assert_eq!(b.len(), 2);
        for (ra, rb) in a.iter().zip(&b) {
            for i in 0..3 {
                assert!(
                    (ra[i] - rb[i]).abs() < 0.05,
                    "machine positions differ: {ra:?} vs {rb:?}"
                );
            }
        }
        let s = g.status().unwrap();
        assert!(s.wpos_mm.is_some(), "the controller still reports WPos");
    }

    #[test]
    fn run_from_an_alarmed_stage_refuses_clearly_and_unlock_recovers() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("alarm");
        // A reset during a move: ALARM:3 (not critical: `$X` clears it).
        let (s, mut g, _bench) = run_from(&out, |p| {
            raw(p, b"G91 G1 Z2 F30\n", "ok");
            raw(p, b"", "<Run");
            raw(p, b"\x18", "to unlock]");
        });
        assert_eq!(s.status, RunStatus::Aborted);
        let reason = s.reason.unwrap_or_default();
        assert!(reason.contains("alarm state"), "{reason}");
        assert!(reason.contains("unlock"), "{reason}");
        assert!(stage_columns(&out).is_empty());
        // What the hint says works: `$X`, and the stage moves again.
        let r = g.unlock_report().unwrap();
        assert!(r.actions[0].starts_with("`$X`"), "{r:?}");
        assert_eq!(g.state().unwrap(), StageState::Idle);
    }

    #[test]
    fn run_from_a_held_stage_refuses_clearly_and_discards_the_held_move() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("held");
        let (s, mut g, _bench) = run_from(&out, |p| {
            raw(p, b"G91 G1 Z2 F30\n", "ok");
            raw(p, b"", "<Run");
            raw(p, b"!", "<Hold:0");
        });
        assert_eq!(s.status, RunStatus::Aborted);
        let reason = s.reason.unwrap_or_default();
        assert!(reason.contains("feed hold"), "{reason}");
        assert!(reason.contains("resume"), "{reason}");
        assert!(stage_columns(&out).is_empty());
        // The runner's abort path stops the stage (feed hold + reset): the move that
        // was held is discarded, not resumed behind the user's back.
        assert_eq!(g.state().unwrap(), StageState::Idle);
        let here = g.position().unwrap();
        std::thread::sleep(Duration::from_millis(200));
        assert_pos(g.position().unwrap(), here);
    }
}
