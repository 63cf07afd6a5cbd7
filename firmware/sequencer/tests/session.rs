//! The protocol session: identification, schedule validation (typed refusals), garbage on the
//! line, reconnects; the trigger output is an embedded-hal-mock pin whose `done()` fails when
//! an expected edge did not happen (or an unexpected one did).

mod common;

use std::cell::RefCell;
use std::rc::Rc;

use common::*;
use embedded_hal_mock::eh1::digital::{Mock as PinMock, State, Transaction as Pin};
use mlsss_sequencer::NoExposureInput;
use mlsss_shared::message::{
    ControllerMessage, ControllerState, ErrorCode, Hello, HostMessage, RunOutcome, ScheduleEntry,
    ScheduleHeader,
};
use mlsss_shared::{PROTOCOL_VERSION, SCHEMA_HASH};

fn mock_bench(expected: &[Pin]) -> (Bench<PinMock, NoExposureInput>, PinMock) {
    // The controller drives the output low once at construction, before anything else.
    let mut all = vec![Pin::set(State::Low)];
    all.extend_from_slice(expected);
    let pin = PinMock::new(&all);
    let time = Rc::new(RefCell::new(SimTime::default()));
    (Bench::with_pins(time, pin.clone(), None), pin)
}

fn nacks<T: embedded_hal::digital::OutputPin, X: embedded_hal::digital::InputPin>(
    bench: &Bench<T, X>,
) -> Vec<ErrorCode> {
    bench.find(|m| match m {
        ControllerMessage::Nack(n) => Some(n.error),
        _ => None,
    })
}

fn finish<X: embedded_hal::digital::InputPin>(bench: Bench<PinMock, X>, mut pin: PinMock) {
    drop(bench);
    pin.done();
}

#[test]
fn commands_before_hello_are_refused_as_not_identified() {
    let (mut bench, pin) = mock_bench(&[]);
    bench.send(HostMessage::Arm);
    bench.send(HostMessage::StatusQuery);
    bench.run_until(10_000);
    assert_eq!(nacks(&bench), vec![ErrorCode::NotIdentified; 2]);
    finish(bench, pin);
}

#[test]
fn hello_of_another_version_or_schema_is_refused_with_a_typed_error() {
    let (mut bench, pin) = mock_bench(&[]);
    bench.send(HostMessage::Hello(Hello {
        protocol_version: PROTOCOL_VERSION + 1,
        schema_hash: SCHEMA_HASH,
    }));
    bench.send(HostMessage::Hello(Hello {
        protocol_version: PROTOCOL_VERSION,
        schema_hash: SCHEMA_HASH ^ 1,
    }));
    bench.send(HostMessage::Arm);
    bench.run_until(10_000);
    let replies = bench.find(|m| match m {
        ControllerMessage::HelloReply(r) => Some(*r),
        _ => None,
    });
    assert_eq!(replies.len(), 2);
    assert_eq!(replies[0].protocol_version, PROTOCOL_VERSION);
    assert_eq!(replies[0].projectors, 4);
    assert_eq!(
        nacks(&bench),
        vec![
            ErrorCode::ProtocolVersionMismatch,
            ErrorCode::SchemaHashMismatch,
            ErrorCode::NotIdentified
        ]
    );
    finish(bench, pin);
}

/// A change that makes a valid schedule invalid.
type Mutation = Box<dyn Fn(&mut ScheduleHeader, &mut Vec<ScheduleEntry>)>;

/// The bad schedules of the issue: zero frames, a period too short for settle + exposure, a
/// projector the board does not have. Each is refused with its code and nothing runs.
#[test]
fn bad_schedules_are_refused_with_typed_errors() {
    let cases: Vec<(Mutation, ErrorCode)> = vec![
        (
            Box::new(|h, e| {
                h.frame_count = 0;
                e.clear();
            }),
            ErrorCode::ScheduleEmpty,
        ),
        // settle 2 + exposure 2 periods + phase = 67 168 us > 60 000 us.
        (
            Box::new(|h, _| h.period_us = 60_000),
            ErrorCode::PeriodTooShort,
        ),
        (
            Box::new(|_, e| e[3].projector = 4),
            ErrorCode::UnknownProjector,
        ),
        (
            Box::new(|h, _| h.exposure_periods = 0),
            ErrorCode::InvalidExposure,
        ),
        (
            Box::new(|h, _| h.trigger_width_us = 40_000),
            ErrorCode::InvalidExposure,
        ),
        (
            Box::new(|h, _| h.trigger_phase_us = 17_000),
            ErrorCode::PeriodTooShort,
        ),
    ];
    for (mutate, code) in cases {
        let (mut bench, pin) = mock_bench(&[]);
        let mut header = booth_header(8);
        let mut entries = booth_entries(2);
        mutate(&mut header, &mut entries);
        bench.send(hello());
        bench.upload(header, &entries);
        bench.send(HostMessage::Arm);
        bench.send(HostMessage::Start);
        bench.run_until(1_000_000);
        let n = nacks(&bench);
        assert_eq!(n.first(), Some(&code), "{n:?}");
        assert!(bench.triggers().is_empty());
        assert!(
            !bench
                .received
                .iter()
                .any(|(_, m)| matches!(m, ControllerMessage::PatternRequest(_)))
        );
        finish(bench, pin);
    }
}

/// The smallest accepted period is exactly settle + exposure + phase.
#[test]
fn the_shortest_valid_period_is_accepted() {
    let (mut bench, _) = Bench::booth();
    let mut header = booth_header(4);
    header.period_us = 2 * 16_667 + 2 * 16_667 + 500;
    bench.send(hello());
    bench.upload(header, &booth_entries(1));
    bench.run_until(10_000);
    assert!(nacks(&bench).is_empty());
    header.period_us -= 1;
    bench.upload(header, &booth_entries(1));
    bench.run_until(20_000);
    // The refused begin, then the chunk and commit of no upload.
    assert_eq!(
        nacks(&bench),
        vec![
            ErrorCode::PeriodTooShort,
            ErrorCode::InvalidState,
            ErrorCode::InvalidState
        ]
    );
}

#[test]
fn a_schedule_whose_checksum_does_not_match_is_refused() {
    let (mut bench, pin) = mock_bench(&[]);
    let entries = booth_entries(2);
    bench.send(hello());
    bench.send(HostMessage::ScheduleBegin(booth_header(8)));
    bench.send(HostMessage::ScheduleChunk(
        mlsss_shared::message::ScheduleChunk {
            first_frame: 0,
            entries: mlsss_shared::message::BoundedVec::from_slice(&entries).expect("fits"),
        },
    ));
    bench.send(HostMessage::ScheduleCommit(
        mlsss_shared::message::ScheduleCommit {
            frame_count: 8,
            checksum: mlsss_shared::schedule_checksum(&entries) ^ 1,
        },
    ));
    bench.send(HostMessage::Arm);
    bench.run_until(10_000);
    assert_eq!(
        nacks(&bench),
        vec![ErrorCode::ScheduleMismatch, ErrorCode::InvalidState]
    );
    finish(bench, pin);
}

/// With the host never confirming a pattern, the mock pin sees no edge at all (done() would
/// fail on an unexpected set_high).
#[test]
fn no_trigger_edge_without_a_confirmed_pattern() {
    let (mut bench, pin) = mock_bench(&[]);
    bench.ack_delay = Box::new(|_, _| None);
    bench.start_run(booth_header(2), &booth_entries(1)[..2]);
    bench.run_until(5_000_000);
    assert!(bench.triggers().is_empty());
    finish(bench, pin);
}

/// One frame: exactly one high-low pulse on the mock pin (done() fails if it is missing).
#[test]
fn one_confirmed_frame_gives_exactly_one_pulse() {
    let (mut bench, pin) = mock_bench(&[Pin::set(State::High), Pin::set(State::Low)]);
    bench.start_run(booth_header(1), &booth_entries(1)[..1]);
    bench.run_until(5_000_000);
    assert_eq!(bench.triggers().len(), 1);
    finish(bench, pin);
}

/// Garbage and corrupted frames on the line are counted and the run completes.
#[test]
fn garbage_and_corrupted_frames_are_counted_and_the_run_completes() {
    let (mut bench, _) = Bench::booth();
    bench.start_run(booth_header(8), &booth_entries(2));
    bench
        .outgoing_raw
        .insert(300_000, vec![0x13, 0x37, 0xff, 0x00, 0x00, 0x42]);
    // A valid-looking frame with a flipped bit: COBS ok, CRC wrong.
    let mut corrupted = [0u8; 64];
    let len = mlsss_shared::framing::encode_frame(999, &HostMessage::StatusQuery, &mut corrupted)
        .expect("encode");
    corrupted[2] ^= 0x10;
    bench
        .outgoing_raw
        .insert(700_000, corrupted[..len].to_vec());
    bench.run_until(60_000_000);
    assert_eq!(bench.triggers().len(), 8);
    let done = bench.find(|m| match m {
        ControllerMessage::Done(d) => Some(*d),
        _ => None,
    });
    assert_eq!(done[0].outcome, RunOutcome::Completed);
    assert_eq!(done[0].link.crc_errors, 1);
    assert!(done[0].link.malformed >= 1);
}

/// A host that reconnects mid-run (new Hello) is told where the run is, and the run goes on.
#[test]
fn a_reconnecting_host_gets_the_run_status() {
    let (mut bench, _) = Bench::booth();
    bench.start_run(booth_header(8), &booth_entries(2));
    bench.send_at(700_000, hello());
    bench.run_until(60_000_000);
    let status = bench.find(|m| match m {
        ControllerMessage::Status(s) => Some(*s),
        _ => None,
    });
    assert_eq!(status.len(), 1);
    assert_eq!(status[0].state, ControllerState::Running);
    assert_eq!(status[0].schedule_frames, 8);
    assert_eq!(status[0].next_frame, status[0].frames_triggered);
    assert!(status[0].frames_triggered >= 2);
    assert_eq!(bench.triggers().len(), 8);
}

/// Abort mid-run: the frame in flight is reported dropped, Done says aborted, no more pulses.
#[test]
fn abort_mid_run_drops_the_frame_in_flight_and_ends_the_run() {
    let (mut bench, edges) = Bench::booth();
    bench.start_run(booth_header(8), &booth_entries(2));
    // Frames 0-1 on projector 0, 2-3 on projector 1: at 700 ms frame 3 awaits its slot.
    bench.send_at(700_000, HostMessage::Abort);
    bench.run_until(60_000_000);
    let n = bench.triggers().len();
    assert_eq!(n, 3);
    let dropped = bench.find(|m| match m {
        ControllerMessage::FrameDropped(d) => Some(d.frame),
        _ => None,
    });
    // The frame in flight and every frame after it.
    assert_eq!(dropped, (3..8).collect::<Vec<u16>>());
    let done = bench.find(|m| match m {
        ControllerMessage::Done(d) => Some(d.outcome),
        _ => None,
    });
    assert_eq!(done, vec![RunOutcome::AbortedByHost]);
    let last_edge = edges.borrow().last().copied().expect("edges");
    assert!(!last_edge.1, "output left low");
    assert!(last_edge.0 < 700_000);
}

/// Every command gets its Ack before anything it causes (Start: Ack, then the first request).
#[test]
fn commands_are_acked_by_sequence_number_before_their_effects() {
    let (mut bench, _) = Bench::booth();
    bench.start_run(booth_header(4), &booth_entries(1));
    bench.run_until(100_000);
    let acks = bench.find(|m| match m {
        ControllerMessage::Ack(a) => Some(a.seq),
        _ => None,
    });
    // Hello (seq 0) is answered by HelloReply; Begin, 1 chunk, Commit, Arm, Start: seq 1..=5.
    assert_eq!(acks[..5], [1, 2, 3, 4, 5]);
    let start_ack = bench
        .received
        .iter()
        .position(|(_, m)| matches!(m, ControllerMessage::Ack(a) if a.seq == 5));
    let first_request = bench
        .received
        .iter()
        .position(|(_, m)| matches!(m, ControllerMessage::PatternRequest(_)));
    assert!(start_ack < first_request);
}

/// An aborted long scan reports every frame: triggered, or dropped before `Done` (streamed over
/// several polls, more than the outbox holds at once).
#[test]
fn an_aborted_scan_reports_every_frame_triggered_or_dropped() {
    let (mut bench, _) = Bench::booth();
    bench.start_run(booth_header(268), &booth_entries(67));
    bench.send_at(1_100_000, HostMessage::Abort);
    bench.run_until(60_000_000);
    let mut frames: Vec<u16> = bench.triggers().iter().map(|t| t.frame).collect();
    let triggered = frames.len();
    frames.extend(bench.find(|m| match m {
        ControllerMessage::FrameDropped(d) => Some(d.frame),
        _ => None,
    }));
    assert_eq!(frames, (0..268).collect::<Vec<u16>>());
    let done_at = bench
        .received
        .iter()
        .position(|(_, m)| matches!(m, ControllerMessage::Done(_)))
        .expect("Done");
    let last_drop = bench
        .received
        .iter()
        .rposition(|(_, m)| matches!(m, ControllerMessage::FrameDropped(_)))
        .expect("drops");
    assert!(last_drop < done_at, "every drop is reported before Done");
    let done = bench.find(|m| match m {
        ControllerMessage::Done(d) => Some(*d),
        _ => None,
    });
    assert_eq!(usize::from(done[0].frames_triggered), triggered);
    assert_eq!(usize::from(done[0].frames_dropped), 268 - triggered);
}

/// Regression (seen under a CPU hog): the host resends a command whose Ack it did not see in
/// time (with a new sequence number). A resent last chunk or commit is acked again and changes
/// nothing; a chunk that skips or overlaps differently is still refused.
#[test]
fn a_resent_schedule_chunk_or_commit_is_acked_again() {
    use mlsss_shared::message::{BoundedVec, ScheduleChunk, ScheduleCommit};
    use mlsss_shared::schedule_checksum;

    let (mut bench, pin) = mock_bench(&[]);
    let entries = booth_entries(10); // 40 frames: chunks of 32 and 8
    let chunk = |first: usize, len: usize| {
        HostMessage::ScheduleChunk(ScheduleChunk {
            first_frame: first as u16,
            entries: BoundedVec::from_slice(&entries[first..first + len]).expect("fits"),
        })
    };
    let commit = HostMessage::ScheduleCommit(ScheduleCommit {
        frame_count: 40,
        checksum: schedule_checksum(&entries),
    });
    bench.send(hello());
    bench.send(HostMessage::ScheduleBegin(booth_header(40)));
    bench.send(chunk(0, 32));
    bench.send(chunk(0, 32)); // resent
    bench.send(chunk(16, 16)); // the tail of the last chunk only: a repeat too
    bench.send(chunk(0, 16)); // not where the upload stands
    bench.send(chunk(32, 8));
    bench.send(commit.clone());
    bench.send(commit); // resent
    bench.send(HostMessage::StatusQuery);
    bench.run_until(10_000);

    assert_eq!(nacks(&bench), vec![ErrorCode::ChunkOutOfOrder]);
    let status = bench.find(|m| match m {
        ControllerMessage::Status(s) => Some(*s),
        _ => None,
    });
    assert_eq!(status[0].schedule_frames, 40);
    assert_eq!(status[0].state, ControllerState::Ready);
    finish(bench, pin);
}
