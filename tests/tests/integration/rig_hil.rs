//! Hardware-in-the-loop tests: the host's rig control against the real firmware image under QEMU
//! (`qemu-system-arm -machine mps2-an386 -icount shift=4,sleep=off`), over a pseudo-terminal.
//! The QEMU board's booth time waits for the host's answer to each pattern request (up to 1 s
//! of virtual time, see `firmware/qemu-mps2`), so the trigger logs do not depend on the
//! machine's load; the fault-injection tests stall or disconnect for longer than that.
//!
//! They need `qemu-system-arm` and the image that `scripts/test.sh` builds (firmware/build.sh);
//! without them they FAIL with the command that fixes it. They run one at a time (one QEMU at a
//! time keeps the host's answers prompt on a 2-core machine).

use std::path::PathBuf;
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use mlsss::booth::Booth;
use mlsss::capture::exposure::{ProjectorExposure, max_exposure_periods};
use mlsss::capture::{Capture, FramePlan};
use mlsss::rig::RigError;
use mlsss::rig::acquire::{Acquired, CaptureTarget, acquire, checked_pattern};
use mlsss::rig::backend::{CameraBackend, Exposure, PatternCamera, VirtualProjectors};
use mlsss::rig::link::{ControllerLink, LinkFaults};
use mlsss::rig::qemu::{self, DEFAULT_ICOUNT_SHIFT, QemuGuard};
use mlsss::rig::schedule::RigSchedule;
use mlsss::rig::session::{Disconnect, HostFaults, ReconnectAction, RunHooks, RunLog, Session};
use mlsss::rig::timing::timing_report;
use mlsss_shared::message::{
    ControllerState, ErrorCode, LateReason, PatternRequest, RunOutcome, ScheduleEntry, Triggered,
};
use serialport::SerialPort;

/// One QEMU at a time.
static QEMU_LOCK: Mutex<()> = Mutex::new(());

fn one_at_a_time() -> MutexGuard<'static, ()> {
    QEMU_LOCK.lock().unwrap_or_else(PoisonError::into_inner)
}

/// The firmware image, or a failure that says how to build it.
fn firmware_image() -> PathBuf {
    let image = qemu::default_firmware_image();
    assert!(
        image.is_file(),
        "firmware image {} is missing: run `./scripts/test.sh` or `{}`",
        image.display(),
        qemu::FIRMWARE_BUILD_COMMAND
    );
    image
}

/// Boots the firmware; fails (never skips) when QEMU is missing.
fn boot() -> (QemuGuard, Session<Box<dyn SerialPort>>) {
    let image = firmware_image();
    let (guard, port) = match qemu::spawn(&image, DEFAULT_ICOUNT_SHIFT) {
        Err(RigError::QemuMissing) => panic!(
            "qemu-system-arm is not installed: `apt-get install qemu-system-arm` \
             (scripts/test.sh installs it)"
        ),
        other => other.expect("QEMU starts"),
    };
    let session = Session::open(ControllerLink::new(port)).expect("handshake with the firmware");
    (guard, session)
}

fn scan(quick: bool, frames: usize) -> (Booth, FramePlan, RigSchedule) {
    let booth = Booth::builtin(quick);
    let plan = FramePlan::scan(&booth.patterns, booth.projectors.len());
    let schedule = RigSchedule::from_plan(&plan, &booth.timing, Some(frames)).unwrap();
    (booth, plan, schedule)
}

/// Hooks that only check requests against the schedule and record what was shown.
struct CheckingHooks {
    schedule: RigSchedule,
    shown: Vec<PatternRequest>,
}

impl RunHooks for CheckingHooks {
    fn show(&mut self, request: &PatternRequest) -> Result<(), RigError> {
        checked_pattern(&self.schedule, request)?;
        self.shown.push(*request);
        Ok(())
    }

    fn triggered(&mut self, trigger: &Triggered) -> Result<(), RigError> {
        // Never a trigger on a pattern the host did not confirm for that frame.
        assert!(
            self.shown.iter().any(|r| r.frame == trigger.frame),
            "frame {} triggered before its pattern was shown",
            trigger.frame
        );
        Ok(())
    }
}

fn run(schedule: &RigSchedule, faults: &HostFaults, link_faults: LinkFaults) -> RunLog {
    let (_qemu, mut session) = boot();
    session.link_mut().set_faults(link_faults);
    let mut hooks = CheckingHooks {
        schedule: schedule.clone(),
        shown: vec![],
    };
    session
        .run(schedule, &mut hooks, faults)
        .expect("the run completes")
}

/// Captures `schedule` through the virtual projectors and a camera that records the pattern.
fn acquire_with_virtual_devices(
    session: &mut Session<Box<dyn SerialPort>>,
    schedule: &RigSchedule,
    booth: &Booth,
    plan: &FramePlan,
    out: &std::path::Path,
    faults: &HostFaults,
) -> Result<Acquired, RigError> {
    acquire(
        session,
        schedule,
        CaptureTarget {
            booth,
            plan,
            out,
            source: serde_json::json!("hil test"),
        },
        &mut VirtualProjectors::new(),
        Box::new(PatternCamera::new(booth)),
        faults,
        &mut |_| {},
    )
}

/// Trigger log as comparable tuples.
fn trigger_log(log: &RunLog) -> Vec<(u16, u8, u64, u32, u64, u32)> {
    log.triggers
        .values()
        .map(|t| {
            (
                t.frame,
                t.attempt,
                t.timestamp_us,
                t.vsync_count,
                t.vsync_timestamp_us,
                t.shown_vsync_count,
            )
        })
        .collect()
}

/// Every frame triggered once, on the projector the schedule names.
fn assert_complete_and_labelled(log: &RunLog) {
    let n = log.schedule.entries.len();
    assert_eq!(log.triggers.len(), n, "every frame triggered");
    assert!(log.duplicate_triggers.is_empty());
    for (frame, t) in &log.triggers {
        assert_eq!(
            t.projector,
            log.schedule.entries[usize::from(*frame)].projector,
            "frame {frame} lit the wrong projector"
        );
    }
    assert_eq!(log.done.outcome, RunOutcome::Completed);
}

#[test]
fn nominal_268_frames_twice_with_identical_trigger_logs() {
    let _one = one_at_a_time();
    let (_, _, schedule) = scan(false, 268);
    let first = run(&schedule, &HostFaults::default(), LinkFaults::default());
    let second = run(&schedule, &HostFaults::default(), LinkFaults::default());

    for log in [&first, &second] {
        assert_complete_and_labelled(log);
        let report = timing_report(log, 0.0);
        assert_eq!(report.frames_lost, 0);
        assert_eq!(report.frames_late, 0);
        assert_eq!(report.settle_violations, 0);
        let tick_us = f64::from(log.controller.timer_tick_ns) / 1000.0;
        let phase = u64::from(schedule.header.trigger_phase_us);
        let settle = u32::from(schedule.header.settle_vsyncs);
        for t in log.triggers.values() {
            // On its VSYNC: the settle-th VSYNC after the slot start, at the configured phase.
            assert_eq!(
                t.vsync_count - t.shown_vsync_count,
                settle,
                "frame {}",
                t.frame
            );
            let offset = t.timestamp_us.abs_diff(t.vsync_timestamp_us + phase) as f64;
            assert!(
                offset <= tick_us,
                "frame {} fires {offset} us off its VSYNC",
                t.frame
            );
        }
        // Period: consecutive frames of one projector are 12 of its VSYNCs apart, and the
        // trigger-to-trigger time equals the VSYNC-to-VSYNC time within one timer tick.
        let slot_vsyncs = schedule
            .header
            .period_us
            .div_ceil(schedule.header.refresh_period_us);
        let triggers: Vec<_> = log.triggers.values().collect();
        for pair in triggers
            .windows(2)
            .filter(|p| p[0].projector == p[1].projector)
        {
            let (a, b) = (pair[0], pair[1]);
            assert_eq!(
                b.vsync_count - a.vsync_count,
                slot_vsyncs,
                "frames {}-{}",
                a.frame,
                b.frame
            );
            let dt = (b.timestamp_us - a.timestamp_us) as f64;
            let dv = (b.vsync_timestamp_us - a.vsync_timestamp_us) as f64;
            assert!(
                (dt - dv).abs() <= tick_us,
                "frames {}-{}: {dt} vs {dv}",
                a.frame,
                b.frame
            );
        }
        // The projectors are not genlocked: each slot lasts 12 of the lit projector's periods.
        assert!((report.period_us_mean - 200_000.0).abs() < 200.0);
    }
    assert_eq!(
        trigger_log(&first),
        trigger_log(&second),
        "runs are deterministic"
    );
}

/// Metered exposure (issue 18): each projector's frames are exposed for its own periods, the
/// longest the host allows included, and the 268-frame plan keeps its timing.
#[test]
fn metered_exposure_up_to_the_longest_allowed_keeps_the_268_frame_timing() {
    let _one = one_at_a_time();
    let (booth, _, schedule) = scan(false, 268);
    let nominal = booth.timing.exposure_periods;
    let longest = max_exposure_periods(&booth.timing);
    // By hand: 12 periods per 200 ms slot at 60 Hz - 2 settle - 4 kept for the host.
    assert_eq!(longest, 6);
    let periods = [nominal, longest, 4, longest];
    let exposure: Vec<ProjectorExposure> = (0..4u8)
        .map(|k| ProjectorExposure {
            projector: k,
            periods: periods[usize::from(k)],
            analog_gain: 1.0,
            scale: f64::from(periods[usize::from(k)]) / f64::from(nominal),
        })
        .collect();
    let schedule = schedule.with_exposure(&exposure).unwrap();
    let log = run(&schedule, &HostFaults::default(), LinkFaults::default());

    assert_complete_and_labelled(&log);
    let report = timing_report(&log, 0.0);
    assert_eq!(
        (report.frames_lost, report.frames_late),
        (0, 0),
        "late: {:?}",
        log.late
    );
    assert_eq!(report.settle_violations, 0);
    assert!((report.period_us_mean - 200_000.0).abs() < 200.0);
    for t in log.triggers.values() {
        // Exposure end - trigger = the projector's periods of its measured refresh period.
        let period_ns = u64::from(log.projector_timing[&t.projector].period_ns);
        let want_us = u64::from(periods[usize::from(t.projector)]) * period_ns / 1000;
        let got_us = log.exposures[&t.frame].timestamp_us - t.timestamp_us;
        assert!(
            got_us.abs_diff(want_us) <= 3,
            "frame {} (projector {}): exposed {got_us} us, want {want_us}",
            t.frame,
            t.projector
        );
    }
}

#[test]
fn timing_test_command_prints_the_report_for_268_frames() {
    let _one = one_at_a_time();
    firmware_image();
    let out = mlsss_tests::mlsss()
        .args([
            "rig",
            "timing-test",
            "--emulated",
            "--frames",
            "268",
            "--json",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    for key in [
        "frames_requested",
        "frames_triggered",
        "frames_lost",
        "frames_late",
        "period_us_mean",
        "period_us_max_abs_error",
        "vsync_alignment_us_max",
        "settle_violations",
        "crc_errors",
        "virtual_duration_s",
        "wall_duration_s",
    ] {
        assert!(json.get(key).is_some(), "missing key {key} in {json}");
    }
    assert_eq!(json["frames_requested"], 268);
    assert_eq!(json["frames_triggered"], 268);
    assert_eq!(json["frames_lost"], 0);
    assert_eq!(json["settle_violations"], 0);
    // 268 slots of 200 ms.
    let virtual_s = json["virtual_duration_s"].as_f64().unwrap();
    assert!((53.6..55.0).contains(&virtual_s), "{virtual_s}");
}

#[test]
fn garbage_and_corrupted_frames_are_counted_and_the_run_completes() {
    let _one = one_at_a_time();
    let (_, _, schedule) = scan(false, 40);
    // Deterministic garbage: bytes of every value (delimiters included), ending in a delimiter.
    let garbage: Vec<u8> = (0..64u32).map(|i| (i * 97 + 13) as u8).chain([0]).collect();
    let faults = LinkFaults {
        garbage_every: Some(5),
        garbage,
        corrupt_frames: vec![12, 25, 26],
    };
    let log = run(&schedule, &HostFaults::default(), faults);
    assert_complete_and_labelled(&log);
    let link = log.done.link;
    assert_eq!(log.host_link.frames_corrupted, 3);
    // Each corrupted frame and each garbage burst was rejected, none accepted.
    let garbage_sent = log.host_link.frames_sent / 5;
    assert!(
        link.resyncs >= 3 + garbage_sent.saturating_sub(1),
        "controller resyncs {} for 3 corrupted frames and ~{garbage_sent} garbage bursts",
        link.resyncs
    );
    assert!(link.crc_errors >= 1, "{link:?}");
    assert_eq!(timing_report(&log, 0.0).frames_lost, 0);
}

#[test]
fn late_ack_of_frame_100_is_reported_retried_and_captured_correctly() {
    let _one = one_at_a_time();
    let (booth, plan, schedule) = scan(true, 104);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("capture");
    let (_qemu, mut session) = boot();
    let faults = HostFaults {
        late_ack_frames: vec![100],
        disconnect: None,
    };
    let acquired =
        acquire_with_virtual_devices(&mut session, &schedule, &booth, &plan, &out, &faults)
            .expect("capture written");
    let log = &acquired.log;
    assert!(acquired.complete);
    assert_complete_and_labelled(log);
    assert!(
        log.late
            .iter()
            .any(|l| l.frame == 100 && l.reason == LateReason::AckLate),
        "frame 100 reported late: {:?}",
        log.late
    );
    assert!(log.retried.iter().any(|r| r.frame == 100));
    assert!(log.triggers[&100].attempt >= 1);
    assert_eq!(log.late.iter().filter(|l| l.frame != 100).count(), 0);

    // The capture: complete, frame 100 marked late, and its image is the pattern of frame 100.
    let capture = Capture::open(&out).unwrap();
    assert_eq!(capture.manifest.plan.frames.len(), 104);
    assert_eq!(capture.manifest.trigger_log.len(), 104);
    let record = &capture.manifest.trigger_log[100];
    assert!(record.late && record.retries >= 1 && record.frame_index == 100);
    let expected = PatternCamera::new(&booth)
        .capture(&Exposure::nominal(
            100,
            Some((
                plan.frames[100].projector.unwrap(),
                plan.frames[100].pattern,
            )),
        ))
        .unwrap();
    let image = capture.read_frame(100).unwrap();
    let max_diff = image
        .pixels()
        .zip(expected.pixels())
        .map(|(a, b)| (a.0[0] - b.0[0]).abs())
        .fold(0.0f32, f32::max);
    assert!(
        max_diff < 1e-3,
        "frame 100 shows another pattern ({max_diff})"
    );
}

/// A schedule with a short host-silence timeout and enough retries that the silence, not the
/// retry limit, decides what happens. The tests' stalls and disconnects last 8 s of real time:
/// the QEMU board holds booth time for up to 1 s of virtual time while it waits for an answer
/// (up to ~4 s of real time on a loaded machine), then the 0.5 s silence timeout must pass.
fn silence_schedule(quick: bool, frames: usize) -> (Booth, FramePlan, RigSchedule) {
    let (booth, plan, mut schedule) = scan(quick, frames);
    schedule.header.host_silence_timeout_us = 500_000;
    schedule.header.policy.max_retries = 20;
    (booth, plan, schedule)
}

#[test]
fn disconnect_mid_run_pauses_and_the_host_resumes() {
    let _one = one_at_a_time();
    let (_, _, schedule) = silence_schedule(false, 24);
    let faults = HostFaults {
        late_ack_frames: vec![],
        disconnect: Some(Disconnect {
            at_frame: 12,
            duration: Duration::from_secs(8),
            then: ReconnectAction::Resume,
        }),
    };
    let log = run(&schedule, &faults, LinkFaults::default());
    assert_eq!(log.reconnect_statuses.len(), 1);
    let status = log.reconnect_statuses[0];
    assert_eq!(status.state, ControllerState::Paused, "{status:?}");
    assert_eq!(status.next_frame, 12);
    assert_eq!(status.frames_triggered, 12);
    assert_complete_and_labelled(&log);
    // Nothing fired while the host was away.
    assert!(log.triggers[&12].timestamp_us > status.timestamp_us);
    assert!(log.triggers[&11].timestamp_us < status.timestamp_us);
}

/// Hooks that stall once, without heartbeat or ack, when `frame` is first shown.
struct StallingHooks {
    checking: CheckingHooks,
    frame: u16,
    stall: Duration,
    stalled: bool,
}

impl RunHooks for StallingHooks {
    fn show(&mut self, request: &PatternRequest) -> Result<(), RigError> {
        if request.frame == self.frame && !self.stalled {
            self.stalled = true;
            std::thread::sleep(self.stall);
        }
        self.checking.show(request)
    }

    fn triggered(&mut self, trigger: &Triggered) -> Result<(), RigError> {
        self.checking.triggered(trigger)
    }
}

/// Regression: on a loaded machine the host was slow to answer, the controller paused for host
/// silence, and the host, which never meant to leave, ignored the pause and waited forever.
#[test]
fn a_host_too_slow_to_answer_resumes_the_paused_run() {
    let _one = one_at_a_time();
    let (_, _, schedule) = silence_schedule(true, 8);
    let (_qemu, mut session) = boot();
    let mut hooks = StallingHooks {
        checking: CheckingHooks {
            schedule: schedule.clone(),
            shown: vec![],
        },
        frame: 2,
        stall: Duration::from_secs(8),
        stalled: false,
    };
    let log = session
        .run(&schedule, &mut hooks, &HostFaults::default())
        .expect("the run completes");
    assert!(
        log.late
            .iter()
            .any(|late| late.frame == 2 && late.reason == LateReason::HostSilent),
        "the controller paused for the stall: {:?}",
        log.late
    );
    assert_eq!(log.done.outcome, RunOutcome::Completed);
    assert_complete_and_labelled(&log);
}

#[test]
fn disconnect_then_abort_keeps_every_frame_already_captured() {
    let _one = one_at_a_time();
    let (booth, plan, schedule) = silence_schedule(true, 20);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("capture");
    let (_qemu, mut session) = boot();
    let faults = HostFaults {
        late_ack_frames: vec![],
        disconnect: Some(Disconnect {
            at_frame: 8,
            duration: Duration::from_secs(8),
            then: ReconnectAction::Abort,
        }),
    };
    let acquired =
        acquire_with_virtual_devices(&mut session, &schedule, &booth, &plan, &out, &faults)
            .expect("capture of the frames before the abort written");
    assert!(!acquired.complete);
    assert_eq!(acquired.log.done.outcome, RunOutcome::AbortedByHost);
    assert_eq!(acquired.frames_written, 8);
    let report = timing_report(&acquired.log, 0.0);
    assert_eq!(
        report.frames_lost, 0,
        "every untriggered frame reported dropped"
    );
    let capture = Capture::open(&out).unwrap();
    assert_eq!(capture.manifest.trigger_log.len(), 8);
    for i in 0..8 {
        capture.read_frame(i).expect("captured frame kept");
    }
}

#[test]
fn bad_schedules_are_refused_with_typed_errors() {
    let _one = one_at_a_time();
    let (_, _, good) = scan(false, 10);
    let (_qemu, mut session) = boot();

    let mut empty = good.clone();
    empty.entries.clear();
    empty.header.frame_count = 0;

    let mut short_period = good.clone();
    // 2 settle + 2 exposure refresh periods do not fit 50 ms.
    short_period.header.period_us = 50_000;

    let mut unknown_projector = good.clone();
    unknown_projector.entries[3] = ScheduleEntry {
        projector: 9,
        pattern: 0,
    };

    for (schedule, expected) in [
        (&empty, ErrorCode::ScheduleEmpty),
        (&short_period, ErrorCode::PeriodTooShort),
        (&unknown_projector, ErrorCode::UnknownProjector),
    ] {
        match session.upload(schedule) {
            Err(RigError::Refused { error, .. }) => assert_eq!(error, expected),
            other => panic!("expected a refusal {expected:?}, got {other:?}"),
        }
    }
    // After the refusals a good schedule is accepted and armed.
    session
        .upload(&good)
        .expect("a good schedule after refusals");
    let status = session.status().unwrap();
    assert_eq!(status.schedule_frames, 10);
    assert_eq!(status.state, ControllerState::Ready);
}

/// `rig run` meters before the scan. A grey screen of reflectance 0.2 seen at the nominal
/// exposure needs 4x the signal to bring its 99th percentile to 0.8 of full scale
/// (`MeteringTarget::default`): 6 refresh periods (3x, the longest the slot allows) and analog
/// gain 4/3. The capture records that exposure and its frames read back in nominal units, as
/// the pattern on a 0.2 screen; with `--fixed-exposure` the same frames come at the nominal
/// exposure.
#[test]
fn rig_run_meters_a_dim_subject_and_its_frames_read_back_in_nominal_units() {
    let _one = one_at_a_time();
    firmware_image();
    let dir = tempfile::tempdir().expect("temp dir");
    let booth = Booth::builtin(true);
    let grey_screen = PatternCamera::new(&booth).with_reflectance(0.2);
    for fixed in [false, true] {
        let out = dir.path().join(format!("capture-fixed-{fixed}"));
        let mut cmd = mlsss_tests::mlsss();
        cmd.args(["rig", "run", "--emulated", "--quick", "--frames", "6"])
            .args(["--camera", "virtual:0.2", "--json", "--out"])
            .arg(&out);
        if fixed {
            cmd.arg("--fixed-exposure");
        }
        let json = mlsss_tests::run_json(&mut cmd);
        assert_eq!(json["complete"], true, "{json}");
        let capture = Capture::open(&out).expect("capture folder");
        let exposure = &capture.manifest.exposure;
        if fixed {
            assert!(exposure.is_empty(), "{exposure:?}");
        } else {
            // The first 6 frames of the plan are all projector 0's: only it is metered.
            assert_eq!(exposure.len(), 1, "{exposure:?}");
            let e = exposure[0];
            assert_eq!((e.projector, e.periods), (0, 6), "{e:?}");
            assert!((e.analog_gain - 4.0 / 3.0).abs() < 1e-3, "{e:?}");
            assert!((e.scale - 4.0).abs() < 3e-3, "{e:?}");
            assert_eq!(json["exposure"][0]["periods"], 6);
        }
        for spec in &capture.manifest.plan.frames {
            let lit = spec.projector.map(|p| (p, spec.pattern));
            let expected = grey_screen
                .clone()
                .capture(&Exposure::nominal(spec.index, lit))
                .expect("pattern image");
            let got = capture.read_frame(spec.index).expect("frame");
            let worst = got
                .iter()
                .zip(expected.iter())
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            // One 16-bit code of the stored frame, divided by the exposure's scale.
            assert!(
                worst < 2.0 / 65535.0,
                "frame {}: off by {worst}",
                spec.index
            );
        }
        let name = format!(".capture-fixed-{fixed}.metering");
        assert!(
            !dir.path().join(name).exists(),
            "metering frames left behind"
        );
    }
}
