//! Timing statistics of a run, computed by the host from the controller's reports (the
//! `mlsss rig timing-test` JSON).
//!
//! Conventions: controller clock in microseconds; "period" is trigger-to-trigger of consecutive
//! frames; projectors are not genlocked, so slots lock to the lit projector's VSYNC and a slot
//! lasts `period_us / refresh_period_us` refresh periods of *that* projector.

use serde::Serialize;

use super::session::RunLog;

/// The timing report of one run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TimingReport {
    /// Frames in the schedule.
    pub frames_requested: u32,
    /// Frames with a trigger.
    pub frames_triggered: u32,
    /// Frames neither triggered nor reported dropped (must be 0: nothing lost silently).
    pub frames_lost: u32,
    /// Frames reported late at least once.
    pub frames_late: u32,
    /// Frames reported dropped.
    pub frames_dropped: u32,
    /// Retries reported.
    pub frames_retried: u32,
    /// Mean trigger-to-trigger interval of consecutive frames lit by the same projector.
    pub period_us_mean: f64,
    /// Max |trigger-to-trigger - nominal period (200 000)| over consecutive frames of the same
    /// projector (includes the projectors' refresh-rate offsets: 200 us at 59.94 Hz).
    pub period_us_max_abs_error: f64,
    /// Max |trigger-to-trigger - VSYNCs elapsed x that projector's measured refresh period|:
    /// the sequencer's own error, within a timer tick when correct.
    pub period_us_max_abs_error_vs_refresh: f64,
    /// Max |trigger - its VSYNC - configured phase|.
    pub vsync_alignment_us_max: f64,
    /// Triggers fired fewer than `settle_vsyncs` VSYNCs after the pattern was confirmed, or
    /// whose VSYNC is not `settle_vsyncs` after the slot start.
    pub settle_violations: u32,
    /// CRC errors on both ends of the link (controller receive + host receive).
    pub crc_errors: u32,
    /// Controller clock from just before `Start` to just after `Done`, seconds.
    pub virtual_duration_s: f64,
    /// Wall-clock duration of the whole test (including QEMU boot), seconds.
    pub wall_duration_s: f64,
    /// The controller's timer resolution, microseconds.
    pub timer_tick_us: f64,
    /// Measured refresh rate per projector, Hz.
    pub refresh_hz: Vec<f64>,
}

/// Computes the report of `log`; `wall_duration_s` is measured by the caller.
pub fn timing_report(log: &RunLog, wall_duration_s: f64) -> TimingReport {
    let header = &log.schedule.header;
    let frames_requested = log.schedule.entries.len() as u32;
    let dropped: std::collections::BTreeSet<u16> = log.dropped.iter().map(|d| d.frame).collect();
    let frames_lost = (0..frames_requested as u16)
        .filter(|f| !log.triggers.contains_key(f) && !dropped.contains(f))
        .count() as u32;
    let late: std::collections::BTreeSet<u16> = log.late.iter().map(|l| l.frame).collect();

    let refresh_us = |projector: u8| {
        log.projector_timing
            .get(&projector)
            .map(|t| f64::from(t.period_ns) / 1000.0)
    };
    let nominal = f64::from(header.period_us);
    let mut intervals = vec![];
    let mut max_err = 0.0f64;
    let mut max_err_refresh = 0.0f64;
    let triggers: Vec<_> = log.triggers.values().collect();
    for pair in triggers.windows(2) {
        let (a, b) = (pair[0], pair[1]);
        if b.frame != a.frame + 1 || a.projector != b.projector {
            continue;
        }
        let dt = b.timestamp_us as f64 - a.timestamp_us as f64;
        intervals.push(dt);
        max_err = max_err.max((dt - nominal).abs());
        if let Some(period) = refresh_us(a.projector) {
            let vsyncs = f64::from(b.vsync_count.wrapping_sub(a.vsync_count));
            max_err_refresh = max_err_refresh.max((dt - vsyncs * period).abs());
        }
    }
    let period_us_mean = if intervals.is_empty() {
        0.0
    } else {
        intervals.iter().sum::<f64>() / intervals.len() as f64
    };

    let phase = f64::from(header.trigger_phase_us);
    let vsync_alignment_us_max = log
        .triggers
        .values()
        .map(|t| (t.timestamp_us as f64 - t.vsync_timestamp_us as f64 - phase).abs())
        .fold(0.0, f64::max);
    let settle_violations = log
        .triggers
        .values()
        .filter(|t| {
            t.vsync_count.wrapping_sub(t.shown_vsync_count) < u32::from(header.settle_vsyncs)
        })
        .count() as u32;

    let virtual_duration_s = log
        .status_after
        .map(|after| {
            (after
                .timestamp_us
                .saturating_sub(log.status_before.timestamp_us)) as f64
                / 1e6
        })
        .unwrap_or(0.0);
    let refresh_hz = log
        .projector_timing
        .values()
        .map(|t| 1e9 / f64::from(t.period_ns.max(1)))
        .collect();

    TimingReport {
        frames_requested,
        frames_triggered: log.triggers.len() as u32,
        frames_lost,
        frames_late: late.len() as u32,
        frames_dropped: dropped.len() as u32,
        frames_retried: log.retried.len() as u32,
        period_us_mean,
        period_us_max_abs_error: max_err,
        period_us_max_abs_error_vs_refresh: max_err_refresh,
        vsync_alignment_us_max,
        settle_violations,
        crc_errors: log.done.link.crc_errors + log.host_link.decoder.crc_errors,
        virtual_duration_s,
        wall_duration_s,
        timer_tick_us: f64::from(log.controller.timer_tick_ns) / 1000.0,
        refresh_hz,
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use mlsss_shared::message::*;

    use super::*;
    use crate::link::HostLinkStats;
    use crate::schedule::RigSchedule;
    use mlsss_core::booth::Booth;
    use mlsss_core::capture::FramePlan;

    fn trigger(frame: u16, t: u64, vsync: u32, vsync_t: u64, shown: u32) -> Triggered {
        Triggered {
            frame,
            attempt: 0,
            projector: 0,
            timestamp_us: t,
            vsync_count: vsync,
            vsync_timestamp_us: vsync_t,
            shown_vsync_count: shown,
        }
    }

    /// Five frames on projector 0: 0-2 triggered, 3 dropped, 4 never reported.
    fn log() -> RunLog {
        let booth = Booth::builtin(false);
        let plan = FramePlan::scan(&booth.patterns, booth.projectors.len());
        let schedule = RigSchedule::from_plan(&plan, &booth.timing, Some(5)).unwrap();
        let mut triggers = BTreeMap::new();
        // Phase 500 us. Frame 1 fires 3 us off its VSYNC; frame 2 has settle 1 < 2.
        triggers.insert(0, trigger(0, 1_000, 2, 500, 0));
        triggers.insert(1, trigger(1, 201_003, 14, 200_500, 12));
        triggers.insert(2, trigger(2, 401_500, 26, 401_000, 25));
        let status = |timestamp_us| StatusReport {
            state: ControllerState::Running,
            schedule_frames: 5,
            next_frame: 0,
            frames_triggered: 0,
            timestamp_us,
            link: LinkStats::default(),
        };
        let mut projector_timing = BTreeMap::new();
        projector_timing.insert(
            0,
            ProjectorTiming {
                projector: 0,
                vsync_count: 30,
                period_ns: 16_666_667,
            },
        );
        RunLog {
            controller: HelloReply {
                protocol_version: 1,
                schema_hash: 0,
                board: Board::HostSimulation,
                firmware_version: [0, 0, 0],
                projectors: 4,
                timer_tick_ns: 1000,
            },
            schedule,
            status_before: status(0),
            status_after: Some(status(1_250_000)),
            requests: vec![],
            triggers,
            exposures: BTreeMap::new(),
            late: vec![FrameLate {
                frame: 3,
                attempt: 0,
                reason: LateReason::AckLate,
            }],
            retried: vec![],
            dropped: vec![FrameDropped {
                frame: 3,
                reason: DropReason::RetriesExhausted,
            }],
            nacks: vec![],
            duplicate_triggers: vec![],
            retriggers: vec![],
            retrigger_refusals: vec![],
            done: DoneSummary {
                outcome: RunOutcome::Completed,
                frames_triggered: 3,
                frames_late: 1,
                frames_retried: 0,
                frames_dropped: 1,
                first_trigger_us: 1_000,
                last_trigger_us: 401_500,
                link: LinkStats {
                    crc_errors: 2,
                    ..LinkStats::default()
                },
            },
            projector_timing,
            reconnect_statuses: vec![],
            host_link: HostLinkStats::default(),
        }
    }

    #[test]
    fn report_of_a_hand_built_run() {
        let r = timing_report(&log(), 3.5);
        assert_eq!(r.frames_requested, 5);
        assert_eq!(r.frames_triggered, 3);
        assert_eq!(r.frames_dropped, 1);
        assert_eq!(r.frames_lost, 1, "frame 4: neither triggered nor reported");
        assert_eq!(r.frames_late, 1);
        // Intervals 200 003 and 200 497 us.
        assert!((r.period_us_mean - 200_250.0).abs() < 1e-9);
        assert!((r.period_us_max_abs_error - 497.0).abs() < 1e-9);
        // 12 VSYNCs of 16 666.667 us = 200 000.004 us.
        assert!((r.period_us_max_abs_error_vs_refresh - 496.996).abs() < 1e-3);
        assert!((r.vsync_alignment_us_max - 3.0).abs() < 1e-9);
        assert_eq!(r.settle_violations, 1);
        assert_eq!(r.crc_errors, 2);
        assert!((r.virtual_duration_s - 1.25).abs() < 1e-12);
        assert_eq!(r.wall_duration_s, 3.5);
        assert_eq!(r.timer_tick_us, 1.0);
    }
}
