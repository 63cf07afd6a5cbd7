//! Every timing rule of `run.rs`, checked on the simulated booth against the exact edge times
//! of the simulated projectors (independent of the controller's own measurements).

mod common;

use common::*;
use mlsss_shared::message::{
    ControllerMessage, ControllerState, DropReason, ExhaustedAction, LateReason, RunOutcome,
};

const END: u64 = 120_000_000;

fn late_reports(
    bench: &Bench<RecordingPin, mlsss_sequencer::NoExposureInput>,
) -> Vec<(u16, u8, LateReason)> {
    bench.find(|m| match m {
        ControllerMessage::FrameLate(l) => Some((l.frame, l.attempt, l.reason)),
        _ => None,
    })
}

fn done(
    bench: &Bench<RecordingPin, mlsss_sequencer::NoExposureInput>,
) -> mlsss_shared::message::DoneSummary {
    let all = bench.find(|m| match m {
        ControllerMessage::Done(d) => Some(*d),
        _ => None,
    });
    assert_eq!(all.len(), 1, "exactly one Done");
    all[0]
}

/// The full 268-frame booth scan: every frame triggered once, on the settle VSYNC of its own
/// projector plus the phase, 12 refresh periods apart within a projector, pulse width exact.
#[test]
fn nominal_scan_triggers_every_frame_on_the_settle_vsync_of_its_projector() {
    let (mut bench, edges) = Bench::booth();
    let header = booth_header(268);
    let entries = booth_entries(67);
    bench.start_run(header, &entries);
    bench.run_until(END);

    let triggers = bench.triggers();
    assert_eq!(triggers.len(), 268);
    assert!(
        late_reports(&bench).is_empty(),
        "{:?}",
        late_reports(&bench)
    );
    let summary = done(&bench);
    assert_eq!(summary.outcome, RunOutcome::Completed);
    assert_eq!(summary.frames_triggered, 268);

    for (i, t) in triggers.iter().enumerate() {
        assert_eq!(usize::from(t.frame), i);
        assert_eq!(t.attempt, 0);
        assert_eq!(t.projector, entries[i].projector);
        let p = usize::from(t.projector);
        // Rule 4: aligned to the settle-th edge counting the slot-start edge as the first.
        assert_eq!(
            t.vsync_count - t.shown_vsync_count,
            u32::from(header.settle_vsyncs)
        );
        // The VSYNC named is a real edge of the lit projector (counts start at 1 after Arm).
        let edge = bench.edge_time_us(p, u64::from(t.vsync_count) - 1);
        assert_eq!(t.vsync_timestamp_us, edge, "frame {i}");
        // Rule 5: phase.
        assert_eq!(
            t.timestamp_us,
            edge + u64::from(header.trigger_phase_us),
            "frame {i}"
        );
    }
    // Rule 1: within one projector, slots are 12 of its own refresh periods.
    for pair in triggers.windows(2) {
        if pair[0].projector == pair[1].projector {
            assert_eq!(pair[1].vsync_count - pair[0].vsync_count, 12);
            let p = usize::from(pair[0].projector);
            let expected_ns = 12 * bench.projectors[p].period_ns;
            let dt_ns = (pair[1].timestamp_us - pair[0].timestamp_us) * 1000;
            assert!(
                dt_ns.abs_diff(expected_ns) <= 1000,
                "{dt_ns} vs {expected_ns}"
            );
        }
    }
    // Rule 5: the output pulses once per trigger, high for exactly the width.
    let edges = edges.borrow();
    let rising: Vec<u64> = edges.iter().filter(|e| e.1).map(|e| e.0).collect();
    assert_eq!(
        rising,
        triggers.iter().map(|t| t.timestamp_us).collect::<Vec<_>>()
    );
    for w in edges.windows(2).filter(|w| w[0].1) {
        assert!(!w[1].1);
        assert_eq!(w[1].0 - w[0].0, u64::from(header.trigger_width_us));
    }
}

/// Rule 6: exposure done after `exposure_periods` periods of the lit projector.
#[test]
fn exposure_done_after_the_exposure_periods_of_the_lit_projector() {
    let (mut bench, _) = Bench::booth();
    let header = booth_header(8);
    bench.start_run(header, &booth_entries(2));
    bench.run_until(END);
    let triggers = bench.triggers();
    let exposures = bench.find(|m| match m {
        ControllerMessage::ExposureDone(e) => Some(*e),
        _ => None,
    });
    assert_eq!(exposures.len(), 8);
    for (t, e) in triggers.iter().zip(&exposures) {
        assert_eq!(t.frame, e.frame);
        let period_ns = bench.projectors[usize::from(t.projector)].period_ns;
        let expected = t.timestamp_us + (2 * period_ns).div_ceil(1000);
        assert!(
            e.timestamp_us.abs_diff(expected) <= 1,
            "{} vs {expected}",
            e.timestamp_us
        );
    }
}

/// Rule 2: the next pattern is requested as soon as the exposure is done, a whole slot ahead
/// (more than 100 ms before the slot it is for).
#[test]
fn next_pattern_is_requested_when_the_exposure_ends() {
    let (mut bench, _) = Bench::booth();
    bench.start_run(booth_header(8), &booth_entries(2));
    bench.run_until(END);
    let exposures: Vec<(u64, u16)> = bench
        .received
        .iter()
        .filter_map(|(t, m)| match m {
            ControllerMessage::ExposureDone(e) => Some((*t, e.frame)),
            _ => None,
        })
        .collect();
    let requests: Vec<(u64, u16)> = bench
        .received
        .iter()
        .filter_map(|(t, m)| match m {
            ControllerMessage::PatternRequest(r) => Some((*t, r.frame)),
            _ => None,
        })
        .collect();
    let triggers = bench.triggers();
    for &(t_req, frame) in requests.iter().skip(1) {
        let (t_exp, _) = exposures[usize::from(frame) - 1];
        assert_eq!(
            t_req, t_exp,
            "frame {frame} requested at its predecessor's exposure end"
        );
        let trig = triggers[usize::from(frame)];
        assert!(trig.vsync_timestamp_us > t_req + 100_000, "frame {frame}");
    }
}

/// Rule 3 + determinism: an early and a late (but in time) ack give identical triggers,
/// because settle is counted from the slot start, not from the ack.
#[test]
fn trigger_times_do_not_depend_on_when_an_in_time_ack_arrived() {
    let run = |delay: u64| {
        let (mut bench, _) = Bench::booth();
        bench.ack_delay = Box::new(move |_, _| Some(delay));
        bench.start_run(booth_header(12), &booth_entries(3));
        bench.run_until(END);
        bench.triggers()
    };
    let early = run(300);
    let late = run(120_000);
    assert_eq!(early.len(), 12);
    assert_eq!(early, late);
}

/// Rule 3: an ack after the slot start -> late, retried in the next slot (12 edges later),
/// triggered with attempt 1; the scan still completes.
#[test]
fn late_ack_is_reported_and_the_frame_retried_in_the_next_slot() {
    let (mut bench, _) = Bench::booth();
    bench.ack_delay = Box::new(|frame, attempt| {
        Some(if frame == 5 && attempt == 0 {
            180_000
        } else {
            2_000
        })
    });
    bench.start_run(booth_header(12), &booth_entries(3));
    bench.run_until(END);
    assert_eq!(late_reports(&bench), vec![(5, 0, LateReason::AckLate)]);
    let retried = bench.find(|m| match m {
        ControllerMessage::FrameRetried(r) => Some((r.frame, r.attempt)),
        _ => None,
    });
    assert_eq!(retried, vec![(5, 1)]);
    let triggers = bench.triggers();
    assert_eq!(triggers.len(), 12);
    assert_eq!(triggers[5].attempt, 1);
    assert_eq!(triggers[5].vsync_count - triggers[4].vsync_count, 24);
    let summary = done(&bench);
    assert_eq!((summary.frames_late, summary.frames_retried), (1, 1));
    assert_eq!(summary.outcome, RunOutcome::Completed);
}

/// Rule 3: an ack before the slot start but after `ack_timeout_us` is late too.
#[test]
fn ack_after_the_ack_timeout_is_late_even_before_the_slot_start() {
    let (mut bench, _) = Bench::booth();
    let mut header = booth_header(4);
    header.ack_timeout_us = 50_000;
    bench.ack_delay = Box::new(|frame, attempt| {
        Some(if frame == 2 && attempt == 0 {
            60_000
        } else {
            2_000
        })
    });
    bench.start_run(header, &booth_entries(1));
    bench.run_until(END);
    assert_eq!(late_reports(&bench), vec![(2, 0, LateReason::AckLate)]);
    assert_eq!(bench.triggers().len(), 4);
}

/// Rule 3: no ack at all -> never a trigger; late every slot until the retries are used up,
/// then the run aborts (policy Abort).
#[test]
fn without_an_ack_nothing_is_triggered_and_the_run_aborts_per_policy() {
    let (mut bench, edges) = Bench::booth();
    bench.ack_delay = Box::new(|_, _| None);
    bench.start_run(booth_header(4), &booth_entries(1));
    bench.run_until(END);
    assert!(bench.triggers().is_empty());
    assert_eq!(edges.borrow().iter().filter(|e| e.1).count(), 0);
    let late = late_reports(&bench);
    assert_eq!(late.len(), 4, "first try + 3 retries: {late:?}");
    assert!(late.iter().all(|l| l.0 == 0 && l.2 == LateReason::AckLate));
    let dropped = bench.find(|m| match m {
        ControllerMessage::FrameDropped(d) => Some((d.frame, d.reason)),
        _ => None,
    });
    // Frame 0 used up its retries; 1-3 were never reached: all reported.
    assert_eq!(
        dropped,
        vec![
            (0, DropReason::RetriesExhausted),
            (1, DropReason::RunAborted),
            (2, DropReason::RunAborted),
            (3, DropReason::RunAborted)
        ]
    );
    assert_eq!(done(&bench).frames_dropped, 4);
    assert_eq!(done(&bench).outcome, RunOutcome::AbortedRetriesExhausted);
}

/// Rule 7, policy Drop: the exhausted frame is reported dropped and the scan goes on.
#[test]
fn policy_drop_reports_the_frame_and_continues() {
    let (mut bench, _) = Bench::booth();
    let mut header = booth_header(4);
    header.policy.max_retries = 1;
    header.policy.when_exhausted = ExhaustedAction::Drop;
    bench.ack_delay = Box::new(|frame, _| (frame != 1).then_some(2_000));
    bench.start_run(header, &booth_entries(1));
    bench.run_until(END);
    let frames: Vec<u16> = bench.triggers().iter().map(|t| t.frame).collect();
    assert_eq!(frames, vec![0, 2, 3]);
    let summary = done(&bench);
    assert_eq!(summary.outcome, RunOutcome::Completed);
    assert_eq!(
        (
            summary.frames_late,
            summary.frames_retried,
            summary.frames_dropped
        ),
        (2, 1, 1)
    );
}

/// Rule 7: a projector that stops sending VSYNC while settling -> VsyncMissing, retried once
/// it is back, triggered on a real edge.
#[test]
fn missing_vsync_during_settle_is_reported_and_retried() {
    let (mut bench, _) = Bench::booth();
    // Projector 0's first frame slot starts around 200 ms: remove its edges 205..300 ms.
    bench.projectors[0].missing.push((205_000, 300_000));
    bench.start_run(booth_header(4), &booth_entries(1));
    bench.run_until(END);
    let late = late_reports(&bench);
    assert_eq!(late, vec![(0, 0, LateReason::VsyncMissing)]);
    let triggers = bench.triggers();
    assert_eq!(triggers.len(), 4);
    assert_eq!(triggers[0].attempt, 1);
    assert!(triggers[0].vsync_timestamp_us >= 300_000);
    assert_eq!(triggers[0].vsync_count - triggers[0].shown_vsync_count, 2);
}

/// Rule 7: a projector without any VSYNC at its slot start -> VsyncMissing each slot.
#[test]
fn dead_projector_is_reported_missing_and_never_triggered() {
    let (mut bench, edges) = Bench::booth();
    bench.projectors[1].missing.push((0, u64::MAX));
    let mut header = booth_header(4);
    header.policy.max_retries = 2;
    bench.start_run(header, &booth_entries(1));
    bench.run_until(END);
    let late = late_reports(&bench);
    assert_eq!(late.len(), 3, "{late:?}");
    assert!(
        late.iter()
            .all(|l| l.0 == 1 && l.2 == LateReason::VsyncMissing)
    );
    assert_eq!(bench.triggers().len(), 1);
    assert_eq!(edges.borrow().iter().filter(|e| e.1).count(), 1);
    assert_eq!(done(&bench).outcome, RunOutcome::AbortedRetriesExhausted);
}

/// Rule 5: an edge the controller could only fire more than the tolerance late is not fired.
#[test]
fn a_trigger_that_cannot_be_fired_on_time_is_not_fired() {
    let (mut bench, edges) = Bench::booth();
    bench.time.borrow_mut().wait_overshoot_us = mlsss_sequencer::run::FIRE_TOLERANCE_US + 1;
    let mut header = booth_header(1);
    header.policy.max_retries = 1;
    bench.start_run(header, &booth_entries(1)[..1]);
    bench.run_until(END);
    assert!(bench.triggers().is_empty());
    assert_eq!(edges.borrow().iter().filter(|e| e.1).count(), 0);
    let late = late_reports(&bench);
    assert_eq!(
        late,
        vec![
            (0, 0, LateReason::TriggerMissed),
            (0, 1, LateReason::TriggerMissed)
        ]
    );
}

/// ... and one within the tolerance is fired and reported at the real time.
#[test]
fn a_trigger_fired_within_the_tolerance_reports_its_real_time() {
    let (mut bench, _) = Bench::booth();
    bench.time.borrow_mut().wait_overshoot_us = 7;
    bench.start_run(booth_header(1), &booth_entries(1)[..1]);
    bench.run_until(END);
    let t = bench.triggers();
    assert_eq!(t.len(), 1);
    assert_eq!(t[0].timestamp_us, t[0].vsync_timestamp_us + 500 + 7);
}

/// Host silence pauses the run without triggering; Resume continues and the scan completes.
#[test]
fn host_silence_pauses_the_run_and_resume_continues_it() {
    let (mut bench, _) = Bench::booth();
    bench.host_silent = Some((500_000, 2_500_000));
    bench.resume_when_paused = true;
    let mut header = booth_header(8);
    header.host_silence_timeout_us = 250_000;
    bench.start_run(header, &booth_entries(2));
    bench.run_until(END);
    let late = late_reports(&bench);
    let silent: Vec<_> = late
        .iter()
        .filter(|l| l.2 == LateReason::HostSilent)
        .collect();
    assert_eq!(silent.len(), 1, "{late:?}");
    assert!(
        late.iter()
            .all(|l| matches!(l.2, LateReason::HostSilent | LateReason::AckLate))
    );
    let paused_at = bench
        .received
        .iter()
        .find(|(_, m)| matches!(m, ControllerMessage::FrameLate(l) if l.reason == LateReason::HostSilent))
        .map(|(t, _)| *t)
        .expect("late report");
    // The last host message came in the 100 ms before the silence began.
    assert!(
        (650_000..=750_001).contains(&paused_at),
        "paused at {paused_at}"
    );
    // Nothing is triggered between the pause and the resume.
    let triggers = bench.triggers();
    assert!(
        triggers
            .iter()
            .all(|t| t.timestamp_us < paused_at || t.timestamp_us > 2_500_000)
    );
    assert_eq!(triggers.len(), 8);
    let frames: Vec<u16> = triggers.iter().map(|t| t.frame).collect();
    assert_eq!(frames, (0..8).collect::<Vec<_>>());
    let statuses = bench.find(|m| match m {
        ControllerMessage::Status(s) => Some(s.state),
        _ => None,
    });
    assert!(statuses.contains(&ControllerState::Paused));
    assert_eq!(done(&bench).outcome, RunOutcome::Completed);
}

/// The controller's measured periods match the generators (ProjectorTiming at Done).
#[test]
fn measured_vsync_periods_match_the_projectors() {
    let (mut bench, _) = Bench::booth();
    bench.start_run(booth_header(8), &booth_entries(2));
    bench.run_until(END);
    let timing = bench.find(|m| match m {
        ControllerMessage::ProjectorTiming(t) => Some(*t),
        _ => None,
    });
    assert_eq!(timing.len(), 4);
    for t in timing {
        let truth = bench.projectors[usize::from(t.projector)].period_ns;
        assert!(
            u64::from(t.period_ns).abs_diff(truth) < 200,
            "{} vs {truth}",
            t.period_ns
        );
    }
}

/// Nothing is written to the serial port within IO_GUARD_US before a trigger edge or during
/// the pulse (a blocking UART must not delay the edge).
#[test]
fn no_serial_output_close_to_a_trigger_edge() {
    let (mut bench, _) = Bench::booth();
    bench.start_run(booth_header(8), &booth_entries(2));
    bench.run_until(END);
    let writes = bench.line.borrow().write_times_us.clone();
    for t in bench.triggers() {
        let from = t.timestamp_us - mlsss_sequencer::controller::IO_GUARD_US;
        let to = t.timestamp_us + 100;
        assert!(
            !writes.iter().any(|&w| from < w && w < to),
            "write near trigger {}",
            t.timestamp_us
        );
    }
}

/// A bench whose camera reports exposure-active in the given intervals.
fn bench_with_camera(high: Vec<(u64, u64)>) -> Bench<RecordingPin, CameraActive> {
    let time = std::rc::Rc::new(std::cell::RefCell::new(SimTime::default()));
    let pin = RecordingPin {
        edges: Default::default(),
        time: time.clone(),
    };
    let camera = CameraActive {
        time: time.clone(),
        high: std::rc::Rc::new(std::cell::RefCell::new(high)),
    };
    Bench::with_pins(time, pin, Some(camera))
}

/// Rule 6 with camera feedback: ExposureDone at the falling edge of exposure-active.
#[test]
fn exposure_done_follows_the_cameras_exposure_active_output() {
    // First run without feedback to learn the trigger time, then a camera that exposes from
    // the trigger for 25 ms (shorter than the planned 33 ms).
    let (mut plain, _) = Bench::booth();
    plain.start_run(booth_header(1), &booth_entries(1)[..1]);
    plain.run_until(END);
    let t0 = plain.triggers()[0].timestamp_us;
    let mut bench = bench_with_camera(vec![(t0 + 50, t0 + 25_000)]);
    bench.start_run(booth_header(1), &booth_entries(1)[..1]);
    bench.run_until(END);
    assert_eq!(bench.triggers()[0].timestamp_us, t0);
    let exposures = bench.find(|m| match m {
        ControllerMessage::ExposureDone(e) => Some(e.timestamp_us),
        _ => None,
    });
    assert_eq!(exposures.len(), 1);
    let sample = mlsss_sequencer::controller::EXPOSURE_SAMPLE_US;
    assert!(
        (t0 + 25_000..=t0 + 25_000 + sample).contains(&exposures[0]),
        "{exposures:?}"
    );
}

/// A camera that never exposes after the trigger: ExposureMissing, retried, never done.
#[test]
fn a_camera_that_never_exposes_makes_the_frame_late() {
    let mut bench = bench_with_camera(Vec::new());
    let mut header = booth_header(1);
    header.policy.max_retries = 1;
    bench.start_run(header, &booth_entries(1)[..1]);
    bench.run_until(END);
    let late = bench.find(|m| match m {
        ControllerMessage::FrameLate(l) => Some((l.attempt, l.reason)),
        _ => None,
    });
    assert_eq!(
        late,
        vec![
            (0, LateReason::ExposureMissing),
            (1, LateReason::ExposureMissing)
        ]
    );
    assert!(
        bench
            .find(|m| matches!(m, ControllerMessage::ExposureDone(_)).then_some(()))
            .is_empty()
    );
}

/// The board may sleep (QEMU: skip virtual time) only while the run waits for VSYNC edges or
/// a far exposure end: never while a host answer is outstanding, never near a trigger edge.
#[test]
fn sleep_is_allowed_only_while_waiting_for_edges() {
    let (mut bench, _) = Bench::booth();
    bench.ack_delay = Box::new(|_, _| Some(20_000));
    bench.start_run(booth_header(8), &booth_entries(2));
    bench.run_until(END);
    let sleeps: Vec<u64> = bench
        .sleep_log
        .iter()
        .filter(|s| s.1)
        .map(|s| s.0)
        .collect();
    assert!(!sleeps.is_empty(), "the run has idle phases");
    let requests = bench.find(|m| match m {
        ControllerMessage::PatternRequest(r) => Some(r.frame),
        _ => None,
    });
    let request_times: Vec<u64> = bench
        .received
        .iter()
        .filter(|(_, m)| matches!(m, ControllerMessage::PatternRequest(_)))
        .map(|(t, _)| *t)
        .collect();
    assert_eq!(requests.len(), 8);
    for &t_req in &request_times {
        // The simulated host answers 20 ms after the request.
        assert!(
            !sleeps.iter().any(|&t| t_req <= t && t < t_req + 20_000),
            "slept at request {t_req}"
        );
    }
    for t in bench.triggers() {
        let (from, to) = (t.vsync_timestamp_us, t.timestamp_us + 100);
        let near: Vec<u64> = sleeps
            .iter()
            .copied()
            .filter(|&s| from <= s && s < to)
            .collect();
        assert!(
            near.is_empty(),
            "slept near trigger {} (vsync {from}): {near:?}",
            t.timestamp_us
        );
    }
}
