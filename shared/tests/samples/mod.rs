//! One sample of every message in both directions, with every enum variant used at least once.

use mlsss_shared::message::*;
use mlsss_shared::{ControllerMessage as C, HostMessage as H};

fn link() -> LinkStats {
    LinkStats {
        frames_ok: 1000,
        crc_errors: 3,
        malformed: 2,
        oversize: 1,
        sequence_gaps: 4,
        resyncs: 6,
    }
}

fn header(when_exhausted: ExhaustedAction) -> ScheduleHeader {
    ScheduleHeader {
        frame_count: 268,
        period_us: 200_000,
        refresh_period_us: 16_667,
        exposure_periods: 2,
        settle_vsyncs: 2,
        trigger_phase_us: 500,
        trigger_width_us: 100,
        ack_timeout_us: 100_000,
        host_silence_timeout_us: 1_000_000,
        policy: RetryPolicy {
            max_retries: 3,
            when_exhausted,
        },
        // Metered: projector 1 at the longest exposure a slot allows (6 periods, pulse as long
        // as the exposure), projector 2 at 3 periods, the others at the header's.
        projector_exposure: core::array::from_fn(|k| match k {
            1 => ProjectorExposure {
                exposure_periods: 6,
                trigger_width_us: 100_002,
            },
            2 => ProjectorExposure {
                exposure_periods: 3,
                trigger_width_us: 50_001,
            },
            _ => ProjectorExposure::default(),
        }),
    }
}

/// Named host messages.
pub fn host_messages() -> Vec<(&'static str, H)> {
    let entries: Vec<ScheduleEntry> = (0..32u16)
        .map(|i| ScheduleEntry {
            projector: (i / 8) as u8,
            pattern: i * 7,
        })
        .collect();
    vec![
        (
            "hello",
            H::Hello(Hello {
                protocol_version: 1,
                schema_hash: 0xdead_beef,
            }),
        ),
        (
            "schedule_begin_abort",
            H::ScheduleBegin(header(ExhaustedAction::Abort)),
        ),
        (
            "schedule_begin_drop",
            H::ScheduleBegin(header(ExhaustedAction::Drop)),
        ),
        (
            "schedule_chunk_full",
            H::ScheduleChunk(ScheduleChunk {
                first_frame: 256,
                entries: BoundedVec::from_slice(&entries).unwrap(),
            }),
        ),
        (
            "schedule_chunk_empty",
            H::ScheduleChunk(ScheduleChunk {
                first_frame: 0,
                entries: BoundedVec::new(),
            }),
        ),
        (
            "schedule_commit",
            H::ScheduleCommit(ScheduleCommit {
                frame_count: 268,
                checksum: 0x0123_4567,
            }),
        ),
        ("arm", H::Arm),
        ("start", H::Start),
        ("abort", H::Abort),
        ("status_query", H::StatusQuery),
        (
            "pattern_shown",
            H::PatternShown(PatternShown {
                frame: 100,
                attempt: 1,
                pattern: 66,
            }),
        ),
        (
            "host_heartbeat",
            H::Heartbeat(HostHeartbeat {
                host_time_us: 53_600_000,
            }),
        ),
        ("resume", H::Resume),
        (
            "retrigger",
            H::Retrigger(Retrigger {
                frame: 150,
                attempt: 1,
            }),
        ),
    ]
}

/// Named controller messages.
pub fn controller_messages() -> Vec<(&'static str, C)> {
    let mut out = vec![];
    for (i, board) in [
        Board::QemuMps2An386,
        Board::Stm32f4Nucleo,
        Board::HostSimulation,
    ]
    .into_iter()
    .enumerate()
    {
        let name = ["hello_reply_qemu", "hello_reply_nucleo", "hello_reply_host"][i];
        out.push((
            name,
            C::HelloReply(HelloReply {
                protocol_version: 1,
                schema_hash: 0xdead_beef,
                board,
                firmware_version: [0, 1, 2],
                projectors: 4,
                timer_tick_ns: 1000,
            }),
        ));
    }
    out.push(("ack", C::Ack(Ack { seq: 65535 })));
    let errors = [
        ("nack_protocol_version", ErrorCode::ProtocolVersionMismatch),
        ("nack_schema_hash", ErrorCode::SchemaHashMismatch),
        ("nack_not_identified", ErrorCode::NotIdentified),
        ("nack_invalid_state", ErrorCode::InvalidState),
        ("nack_schedule_empty", ErrorCode::ScheduleEmpty),
        ("nack_schedule_too_long", ErrorCode::ScheduleTooLong),
        ("nack_unknown_projector", ErrorCode::UnknownProjector),
        ("nack_period_too_short", ErrorCode::PeriodTooShort),
        ("nack_invalid_exposure", ErrorCode::InvalidExposure),
        ("nack_chunk_out_of_order", ErrorCode::ChunkOutOfOrder),
        ("nack_schedule_mismatch", ErrorCode::ScheduleMismatch),
        ("nack_unexpected_shown", ErrorCode::UnexpectedPatternShown),
    ];
    for (name, error) in errors {
        out.push((name, C::Nack(Nack { seq: 7, error })));
    }
    out.push((
        "pattern_request",
        C::PatternRequest(PatternRequest {
            frame: 267,
            attempt: 0,
            projector: 3,
            pattern: 66,
        }),
    ));
    out.push((
        "triggered",
        C::Triggered(Triggered {
            frame: 100,
            attempt: 1,
            projector: 1,
            timestamp_us: 20_400_500,
            vsync_count: 1224,
            vsync_timestamp_us: 20_400_000,
            shown_vsync_count: 1222,
        }),
    ));
    out.push((
        "exposure_done",
        C::ExposureDone(ExposureDone {
            frame: 100,
            timestamp_us: 20_433_834,
        }),
    ));
    for (name, reason) in [
        ("late_ack", LateReason::AckLate),
        ("late_vsync", LateReason::VsyncMissing),
        ("late_silent", LateReason::HostSilent),
        ("late_trigger_missed", LateReason::TriggerMissed),
        ("late_exposure_missing", LateReason::ExposureMissing),
    ] {
        out.push((
            name,
            C::FrameLate(FrameLate {
                frame: 100,
                attempt: 0,
                reason,
            }),
        ));
    }
    out.push((
        "retried",
        C::FrameRetried(FrameRetried {
            frame: 100,
            attempt: 1,
        }),
    ));
    for (name, reason) in [
        ("dropped_retries", DropReason::RetriesExhausted),
        ("dropped_aborted", DropReason::RunAborted),
    ] {
        out.push((name, C::FrameDropped(FrameDropped { frame: 5, reason })));
    }
    out.push(("link_stats", C::LinkStats(link())));
    for (name, outcome) in [
        ("done_completed", RunOutcome::Completed),
        ("done_aborted_host", RunOutcome::AbortedByHost),
        ("done_aborted_retries", RunOutcome::AbortedRetriesExhausted),
        ("done_aborted_silent", RunOutcome::AbortedHostSilent),
    ] {
        out.push((
            name,
            C::Done(DoneSummary {
                outcome,
                frames_triggered: 268,
                frames_late: 1,
                frames_retried: 1,
                frames_dropped: 0,
                first_trigger_us: 233_834,
                last_trigger_us: 53_833_834,
                link: link(),
            }),
        ));
    }
    let states = [
        ControllerState::Unidentified,
        ControllerState::Idle,
        ControllerState::Loading,
        ControllerState::Ready,
        ControllerState::Armed,
        ControllerState::Running,
        ControllerState::Paused,
        ControllerState::Finished,
    ];
    let state_names = [
        "status_unidentified",
        "status_idle",
        "status_loading",
        "status_ready",
        "status_armed",
        "status_running",
        "status_paused",
        "status_finished",
    ];
    for (name, state) in state_names.into_iter().zip(states) {
        out.push((
            name,
            C::Status(StatusReport {
                state,
                schedule_frames: 268,
                next_frame: 150,
                frames_triggered: 149,
                timestamp_us: u64::MAX,
                link: link(),
            }),
        ));
    }
    out.push((
        "controller_heartbeat",
        C::Heartbeat(ControllerHeartbeat {
            timestamp_us: 1,
            state: ControllerState::Running,
        }),
    ));
    out.push((
        "projector_timing",
        C::ProjectorTiming(ProjectorTiming {
            projector: 2,
            vsync_count: 3216,
            period_ns: 16_683_350,
        }),
    ));
    // Codes added in protocol version 2 (appended here so the earlier lines keep their seq).
    for (name, error) in [
        (
            "nack_retrigger_not_triggered",
            ErrorCode::RetriggerNotTriggered,
        ),
        ("nack_retrigger_queue_full", ErrorCode::RetriggerQueueFull),
    ] {
        out.push((name, C::Nack(Nack { seq: 7, error })));
    }
    out
}
