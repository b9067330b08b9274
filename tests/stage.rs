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
    let e = g.move_to([-6.0, -5.0, -5.0], Some(10.0)).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Rejected);
    assert!(e.message.starts_with("error:9"), "{e}");
    assert!(e.hint.as_deref().unwrap_or("").contains("unlock"));
    g.unlock().unwrap();
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
        let mut g = Grbl::connect(open_serial(&path, 115_200).unwrap(), wide).unwrap();
        let e = g.move_to([-5.0, -5.0, 10.0], None).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Limit);
        assert!(e.message.contains("ALARM:2"), "{e}");
    }
    // A new session finds GRBL locked ("Reset to continue"): connect still works.
    let mut g = Grbl::connect(open_serial(&path, 115_200).unwrap(), fast_driver()).unwrap();
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

/// Queries at connect: `?` (1+), `$G`, `$$` — skip enough to hit a later query.
const AFTER_CONNECT: u32 = 3;

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
    use std::io::BufRead;
    use std::path::{Path, PathBuf};
    use std::process::{Child, Command, Output, Stdio};
    use std::time::{Duration, Instant};

    const BIN: &str = env!("CARGO_BIN_EXE_tactbench");

    /// A `tactbench sim-serve-stage` child; stops when dropped (stdin closed).
    struct Served {
        child: Child,
        link: PathBuf,
        _dir: tempfile::TempDir,
    }

    impl Served {
        fn start(protocol: &str, extra: &[&str]) -> Served {
            let dir = tempfile::tempdir().expect("tempdir");
            let link = dir.path().join("stage");
            let mut child = Command::new(BIN)
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
            std::io::BufReader::new(out)
                .read_line(&mut line)
                .expect("read");
            assert!(line.starts_with("serving on /dev/pts/"), "{line}");
            let deadline = Instant::now() + Duration::from_secs(5);
            while !link.exists() && Instant::now() < deadline {
                std::thread::sleep(Duration::from_millis(10));
            }
            Served {
                child,
                link,
                _dir: dir,
            }
        }

        fn stage(&self, protocol: &str, args: &[&str]) -> Output {
            Command::new(BIN)
                .args(["stage", "--port"])
                .arg(&self.link)
                .args(["--protocol", protocol])
                .args(args)
                .output()
                .expect("run tactbench stage")
        }
    }

    impl Drop for Served {
        fn drop(&mut self) {
            drop(self.child.stdin.take());
            let _ = self.child.wait();
        }
    }

    fn stdout(o: &Output) -> String {
        String::from_utf8_lossy(&o.stdout).into_owned()
    }

    fn stderr(o: &Output) -> String {
        String::from_utf8_lossy(&o.stderr).into_owned()
    }

    #[test]
    fn cli_grbl_status_home_move_jog_and_exact_position_json() {
        let s = Served::start("grbl", &["--homing"]);
        let o = s.stage("grbl", &["status"]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(stdout(&o).starts_with("state: alarm\n"), "{}", stdout(&o));
        // Moves in alarm: clear message, non-zero exit.
        let o = s.stage("grbl", &["move", "-10", "-5", "-1"]);
        assert!(!o.status.success());
        assert!(
            stderr(&o).contains("error:9") && stderr(&o).contains("unlock"),
            "{}",
            stderr(&o)
        );
        let o = s.stage("grbl", &["home", "--json"]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert_eq!(stdout(&o), "{\"x_mm\":-1.0,\"y_mm\":-1.0,\"z_mm\":-1.0}\n");
        let o = s.stage("grbl", &["move", "-10", "-5", "-1.25", "--speed", "50"]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert_eq!(
            stdout(&o),
            "x = -10.0000 mm  y = -5.0000 mm  z = -1.2500 mm\n"
        );
        let o = s.stage("grbl", &["jog", "1", "-1", "0.25", "--speed", "20"]);
        assert!(o.status.success(), "{}", stderr(&o));
        let o = s.stage("grbl", &["position", "--json"]);
        assert_eq!(stdout(&o), "{\"x_mm\":-9.0,\"y_mm\":-6.0,\"z_mm\":-1.0}\n");
        // Outside the soft-limit box: refused before sending.
        let o = s.stage("grbl", &["move", "-1000", "0", "0"]);
        assert_eq!(o.status.code(), Some(2));
        assert!(
            stderr(&o).contains("requested x = -1000 mm is below travel limit -100 mm"),
            "{}",
            stderr(&o)
        );
    }

    #[test]
    fn cli_grbl_home_with_homing_disabled_explains() {
        let s = Served::start("grbl", &[]);
        let o = s.stage("grbl", &["home"]);
        assert!(!o.status.success());
        assert!(
            stderr(&o).contains("homing is disabled on the controller ($22=0)"),
            "{}",
            stderr(&o)
        );
    }

    #[test]
    fn cli_zaber_home_move_and_position_json() {
        let s = Served::start("zaber", &[]);
        let res = ["--zaber-mm-per-step", "0.001"];
        let o = s.stage("zaber", &[&["status"][..], &res].concat());
        assert!(
            stdout(&o).contains("zaber warnings x WR y WR z WR"),
            "{}",
            stdout(&o)
        );
        let o = s.stage("zaber", &[&["home"][..], &res].concat());
        assert!(o.status.success(), "{}", stderr(&o));
        let o = s.stage("zaber", &[&["move", "1.5", "2", "3"][..], &res].concat());
        assert!(o.status.success(), "{}", stderr(&o));
        let o = s.stage("zaber", &[&["position", "--json"][..], &res].concat());
        assert_eq!(stdout(&o), "{\"x_mm\":1.5,\"y_mm\":2.0,\"z_mm\":3.0}\n");
        let o = s.stage(
            "zaber",
            &[&["status", "--zaber-devices", "7,8,9"][..], &res].concat(),
        );
        assert!(!o.status.success());
        assert!(
            stderr(&o).contains("no answer from device 7 axis 1"),
            "{}",
            stderr(&o)
        );
    }

    #[test]
    fn cli_missing_port_and_bad_options_are_clear_errors() {
        let o = Command::new(BIN)
            .args(["stage", "--protocol", "grbl", "status"])
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(2));
        assert!(stderr(&o).contains("missing --port"), "{}", stderr(&o));
        let missing = Path::new("/nonexistent/tty");
        let o = Command::new(BIN)
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
        let o = Command::new(BIN)
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
        let o = Command::new(BIN).arg("ports").output().unwrap();
        assert!(o.status.success());
        let out = stdout(&o);
        assert!(
            out.starts_with("no serial ports found") || out.lines().all(|l| l.starts_with("/dev/")),
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
        assert_eq!(g.version(), Some("1.1h"));
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
