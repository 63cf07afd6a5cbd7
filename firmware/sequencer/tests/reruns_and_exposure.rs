//! Rule 8 (re-runs of frames whose camera payload the host lost) and per-projector exposure,
//! checked on the simulated booth against the simulated projectors' exact edge times and the
//! recorded trigger output.

mod common;

use common::*;
use mlsss_shared::message::{
    ControllerMessage, ErrorCode, HostMessage, ProjectorExposure, Retrigger, RunOutcome,
    ScheduleHeader,
};

const END: u64 = 120_000_000;

type BoothBench = Bench<RecordingPin, mlsss_sequencer::NoExposureInput>;

fn dones(bench: &BoothBench) -> Vec<mlsss_shared::message::DoneSummary> {
    bench.find(|m| match m {
        ControllerMessage::Done(d) => Some(*d),
        _ => None,
    })
}

fn nacks(bench: &BoothBench) -> Vec<ErrorCode> {
    bench.find(|m| match m {
        ControllerMessage::Nack(n) => Some(n.error),
        _ => None,
    })
}

fn late_count(bench: &BoothBench) -> usize {
    bench
        .find(|m| matches!(m, ControllerMessage::FrameLate(_)).then_some(()))
        .len()
}

/// The booth header with projector 1 at the longest exposure the host allows (12 periods per
/// slot - 2 settle - 4 for the host = 6 periods, pulse as long as the exposure), projector 2 at
/// 3 periods and projector 3 at 4 periods with a 1 ms pulse; projector 0 keeps the nominal
/// 2 periods and 100 us.
fn metered_header(frame_count: u16) -> ScheduleHeader {
    let mut header = booth_header(frame_count);
    header.projector_exposure[1] = ProjectorExposure {
        exposure_periods: 6,
        trigger_width_us: 6 * 16_667,
    };
    header.projector_exposure[2] = ProjectorExposure {
        exposure_periods: 3,
        trigger_width_us: 50_001,
    };
    header.projector_exposure[3] = ProjectorExposure {
        exposure_periods: 4,
        trigger_width_us: 1_000,
    };
    header
}

/// (periods, width) the test expects for projector `p` of [`metered_header`] (by hand).
const METERED: [(u64, u64); 4] = [(2, 100), (6, 100_002), (3, 50_001), (4, 1_000)];

#[test]
fn each_projector_is_exposed_for_its_own_periods_with_its_own_pulse_width() {
    let (mut bench, edges) = Bench::booth();
    bench.start_run(metered_header(268), &booth_entries(67));
    bench.run_until(END);

    let triggers = bench.triggers();
    assert_eq!(triggers.len(), 268, "every frame of the 268-frame plan");
    assert_eq!(late_count(&bench), 0, "the longest exposure keeps the slot");
    assert_eq!(dones(&bench)[0].outcome, RunOutcome::Completed);
    let exposures = bench.find(|m| match m {
        ControllerMessage::ExposureDone(e) => Some(*e),
        _ => None,
    });
    let edges = edges.borrow();
    for (t, e) in triggers.iter().zip(&exposures) {
        let p = usize::from(t.projector);
        let (periods, width) = METERED[p];
        // The pulse that rose at the trigger falls `width` later.
        let rise = edges
            .iter()
            .position(|&(at, high)| high && at == t.timestamp_us)
            .unwrap_or_else(|| panic!("no rising edge for frame {}", t.frame));
        assert_eq!(
            edges[rise + 1],
            (t.timestamp_us + width, false),
            "frame {}",
            t.frame
        );
        // Exposure: `periods` refresh periods of the lit projector (its true period).
        let want_us = periods * bench.projectors[p].period_ns / 1000;
        let got_us = e.timestamp_us - t.timestamp_us;
        assert!(
            got_us.abs_diff(want_us) <= 1,
            "frame {}: exposed {got_us} us, want {want_us}",
            t.frame
        );
    }
}

#[test]
fn an_exposure_the_slot_cannot_hold_or_a_pulse_longer_than_it_is_refused() {
    // 2 settle + 11 exposure periods > 12 periods of a 200 ms slot.
    let mut too_long = booth_header(8);
    too_long.projector_exposure[2] = ProjectorExposure {
        exposure_periods: 11,
        trigger_width_us: 100,
    };
    let mut wide_pulse = booth_header(8);
    wide_pulse.projector_exposure[0] = ProjectorExposure {
        exposure_periods: 2,
        trigger_width_us: 2 * 16_667 + 1,
    };
    for (header, code) in [
        (too_long, ErrorCode::PeriodTooShort),
        (wide_pulse, ErrorCode::InvalidExposure),
    ] {
        let (mut bench, _) = Bench::booth();
        bench.send(hello());
        bench.send(HostMessage::ScheduleBegin(header));
        bench.run_until(1_000);
        assert_eq!(nacks(&bench), [code]);
    }
}

fn retrigger(frame: u16, attempt: u8) -> HostMessage {
    HostMessage::Retrigger(Retrigger { frame, attempt })
}

#[test]
fn a_retriggered_frame_is_run_again_in_the_next_slot_and_the_schedule_continues() {
    let (mut bench, _) = Bench::booth();
    bench.start_run(booth_header(16), &booth_entries(4));
    // Frames 0-4 have been triggered by 1.25 s (frame k fires ~(k + 1) slots after Start).
    bench.send_at(1_250_000, retrigger(3, 0));
    bench.run_until(END);

    assert!(nacks(&bench).is_empty(), "{:?}", nacks(&bench));
    let triggers = bench.triggers();
    let order: Vec<(u16, u8)> = triggers.iter().map(|t| (t.frame, t.attempt)).collect();
    // Frame 5 was in flight; the re-run of frame 3 takes the slot after it.
    let mut want: Vec<(u16, u8)> = (0..=5).map(|f| (f, 0)).collect();
    want.push((3, 1));
    want.extend((6..16).map(|f| (f, 0)));
    assert_eq!(order, want);
    let rerun = triggers[6];
    assert_eq!(rerun.projector, triggers[3].projector);
    assert_eq!(
        rerun.vsync_count - rerun.shown_vsync_count,
        2,
        "settled like any frame"
    );
    let retried = bench.find(|m| match m {
        ControllerMessage::FrameRetried(r) => Some((r.frame, r.attempt)),
        _ => None,
    });
    assert_eq!(retried, [(3, 1)]);
    assert_eq!(late_count(&bench), 0);
    let done = dones(&bench);
    assert_eq!(done.len(), 1);
    assert_eq!(done[0].outcome, RunOutcome::Completed);
    assert_eq!((done[0].frames_triggered, done[0].frames_retried), (17, 1));
}

#[test]
fn a_retrigger_after_the_last_frame_extends_the_run_and_ends_it_with_another_done() {
    let (mut bench, _) = Bench::booth();
    bench.start_run(booth_header(8), &booth_entries(2));
    bench.run_until(END);
    assert_eq!(dones(&bench).len(), 1);
    let first_part = std::mem::take(&mut bench.received);
    let now = bench.now();
    bench.send_at(now, retrigger(7, 0));
    bench.run_until(END);

    let triggers = bench.triggers();
    assert_eq!(
        triggers
            .iter()
            .map(|t| (t.frame, t.attempt))
            .collect::<Vec<_>>(),
        [(7, 1)]
    );
    let done = dones(&bench);
    assert_eq!(done.len(), 1, "the extension ends with its own Done");
    assert_eq!(done[0].outcome, RunOutcome::Completed);
    assert_eq!(done[0].frames_triggered, 9);
    assert!(first_part.len() > 8);
}

#[test]
fn a_retrigger_of_a_frame_not_triggered_yet_is_refused() {
    let (mut bench, _) = Bench::booth();
    bench.send(hello());
    bench.send(retrigger(0, 0)); // no run yet
    bench.start_run(booth_header(8), &booth_entries(2));
    bench.send_at(300_000, retrigger(6, 0)); // frame 0 or 1 in flight
    bench.run_until(END);
    assert_eq!(
        nacks(&bench),
        [
            ErrorCode::RetriggerNotTriggered,
            ErrorCode::RetriggerNotTriggered
        ]
    );
    assert_eq!(bench.triggers().len(), 8);
}
