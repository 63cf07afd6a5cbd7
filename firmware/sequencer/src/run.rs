//! The run of a schedule: VSYNC-locked frame slots, shown-ack deadlines, settle counting, trigger
//! timing, late/retry/abort policy.
//!
//! Conventions: times in microseconds of the controller clock; VSYNC counts per projector since
//! the run was armed; frame indices from 0 in capture order.
//!
//! Timing rules (each one has a test in `tests/timing_rules.rs`):
//! 1. **Slots are locked to the lit projector's VSYNC.** A slot starts on a VSYNC edge of the
//!    frame's projector: the first edge at or after `expected - period/2`, where `expected` is
//!    the previous slot start plus `slot_vsyncs` (12) measured periods of the previous frame's
//!    projector (at `Start`: start time + one slot period). Within one projector consecutive
//!    triggers are therefore exactly 12 of its refresh periods apart.
//! 2. **Request a whole slot ahead.** The pattern of frame k+1 is requested as soon as frame k's
//!    exposure is done (frame 0: at `Start`).
//! 3. **No trigger without a confirmed pattern.** The host's shown-ack must arrive before the
//!    slot-start edge and within `ack_timeout_us` of the request; otherwise the frame is late.
//! 4. **Settle.** The trigger is aligned to the `settle_vsyncs`-th edge counting the slot-start
//!    edge as the first (the pattern has then been on screen for `settle_vsyncs` refreshes);
//!    counting from the slot start rather than from the ack makes the trigger time independent
//!    of when an in-time ack arrived (deterministic under QEMU's virtual time).
//! 5. **Phase and width.** The trigger edge is at that VSYNC + `trigger_phase_us`, high for
//!    `trigger_width_us`; an edge more than [`FIRE_TOLERANCE_US`] late is not fired (the frame is
//!    late instead of exposed off its VSYNC).
//! 6. **Exposure** lasts `exposure_periods` measured periods of the lit projector (or until the
//!    camera's exposure-active input falls); then `ExposureDone`.
//! 7. **Late frames** (late ack, missing VSYNC, missed trigger, missing exposure) are reported
//!    `FrameLate` and retried in the next slot (`FrameRetried` + a new request) until
//!    `max_retries`, then dropped (`FrameDropped`) or the run aborts, per the policy. Host
//!    silence pauses the run (`FrameLate{HostSilent}`) until `Resume`. Nothing is dropped
//!    silently.
//! 8. **Re-runs.** A host `Retrigger` of a frame already triggered (its camera payload was
//!    lost) queues a re-run: when the frame in flight is done, the re-run takes the next slot
//!    as attempt `lost + 1` (`FrameRetried`, then request, trigger, exposure as any frame), and
//!    the schedule continues after it. A re-trigger after the last frame extends the finished
//!    run by one slot (a full slot ahead, as after `Resume`) and ends it with another `Done`.

use heapless::Deque;
use mlsss_shared::message::{
    ControllerMessage, DropReason, ErrorCode, ExhaustedAction, ExposureDone, FrameDropped,
    FrameLate, FrameRetried, LateReason, PatternRequest, PatternShown, Retrigger, RunOutcome,
    Triggered,
};

use crate::schedule::Schedule;
use crate::vsync::VsyncTracker;

/// Messages the run produced and the controller has not sent yet.
pub type Outbox = Deque<ControllerMessage, OUTBOX_LEN>;

/// Capacity of the [`Outbox`]; the controller empties it on every poll, and one poll produces at
/// most a handful of messages.
pub const OUTBOX_LEN: usize = 32;

/// Re-runs (host `Retrigger`s) that may wait for a slot at once.
pub const RERUN_QUEUE_LEN: usize = 8;

/// Latest a trigger edge may be fired after its planned time and still count as aligned.
pub const FIRE_TOLERANCE_US: u64 = 50;

/// Counters of a run, for the final summary.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RunStats {
    /// Frames triggered.
    pub triggered: u16,
    /// `FrameLate` reports.
    pub late: u16,
    /// `FrameRetried` reports.
    pub retried: u16,
    /// `FrameDropped` reports.
    pub dropped: u16,
    /// Time of the first trigger.
    pub first_trigger_us: Option<u64>,
    /// Time of the last trigger.
    pub last_trigger_us: Option<u64>,
}

/// A trigger edge that has been planned (the settle VSYNC arrived).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TriggerPlan {
    /// Slot-start VSYNC edge time.
    pub slot_start_us: u64,
    /// VSYNC count just before the slot-start edge.
    pub shown_vsync_count: u32,
    /// Count of the VSYNC the trigger is aligned to.
    pub vsync_count: u32,
    /// Time of that VSYNC.
    pub vsync_us: u64,
    /// Planned rising edge: `vsync_us + trigger_phase_us`.
    pub trigger_at_us: u64,
}

/// Where the current frame is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Requested; waiting for the slot-start VSYNC expected around `Run::next_slot_at_us`.
    AwaitSlot,
    /// Slot started with a confirmed pattern; counting the settle VSYNCs.
    Settling {
        /// Slot-start edge time.
        slot_start_us: u64,
        /// Count just before the slot-start edge.
        shown_vsync_count: u32,
        /// Count of the edge to align the trigger to.
        trigger_vsync_count: u32,
    },
    /// The trigger edge is planned.
    Armed(TriggerPlan),
    /// The trigger output is high.
    Pulse {
        /// The plan that fired.
        plan: TriggerPlan,
        /// Time the output goes low.
        low_at_us: u64,
        /// Planned end of the exposure.
        exposure_end_us: u64,
    },
    /// The trigger pulse is over; the camera is exposing.
    Exposing {
        /// The plan that fired.
        plan: TriggerPlan,
        /// Planned end of the exposure.
        exposure_end_us: u64,
        /// The camera's exposure-active input was seen high.
        seen_active: bool,
    },
    /// Stopped by host silence until `Resume`.
    Paused,
    /// The run is over.
    Finished(RunOutcome),
}

/// What the controller should do with a planned trigger edge it waited for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FireDecision {
    /// Set the output high now; low at `low_at_us`.
    Fire {
        /// Time to set the output low.
        low_at_us: u64,
    },
    /// Too late to be aligned: do not fire (the frame was reported late).
    Skip,
}

/// The state of one run of a schedule.
#[derive(Debug, Clone)]
pub struct Run {
    frame: u16,
    attempt: u8,
    retries_used: u8,
    requested_at_us: u64,
    shown_at_us: Option<u64>,
    next_slot_at_us: u64,
    stage: Stage,
    stats: RunStats,
    last_host_us: u64,
    /// Re-runs waiting for a slot: (frame, attempt whose payload was lost).
    reruns: Deque<(u16, u8), RERUN_QUEUE_LEN>,
    /// While a re-run is in flight: the schedule frame to continue with after it.
    resume_at: Option<u16>,
}

impl Run {
    /// Starts a run at `now_us`: requests frame 0; its slot is one slot period away.
    pub fn start(schedule: &Schedule, now_us: u64, out: &mut Outbox) -> Self {
        let mut run = Self {
            frame: 0,
            attempt: 0,
            retries_used: 0,
            requested_at_us: now_us,
            shown_at_us: None,
            next_slot_at_us: now_us + u64::from(schedule.header.period_us),
            stage: Stage::AwaitSlot,
            stats: RunStats::default(),
            last_host_us: now_us,
            reruns: Deque::new(),
            resume_at: None,
        };
        run.request(schedule, now_us, out);
        run
    }

    /// Current stage.
    pub fn stage(&self) -> Stage {
        self.stage
    }

    /// The frame being worked on (the frame count once finished).
    pub fn frame(&self) -> u16 {
        self.frame
    }

    /// The first schedule frame not run yet (after the frame in flight, or where a re-run
    /// returns to).
    pub fn next_unrun(&self) -> u16 {
        self.resume_at.unwrap_or(self.frame.saturating_add(1))
    }

    /// Counters so far.
    pub fn stats(&self) -> RunStats {
        self.stats
    }

    /// True once the run is over.
    pub fn is_finished(&self) -> bool {
        matches!(self.stage, Stage::Finished(_))
    }

    /// Any valid message from the host (liveness).
    pub fn on_host_message(&mut self, now_us: u64) {
        self.last_host_us = self.last_host_us.max(now_us);
    }

    /// The host's shown-ack; `Err` is the code to nack it with.
    pub fn on_shown(
        &mut self,
        schedule: &Schedule,
        shown: &PatternShown,
        now_us: u64,
    ) -> Result<(), ErrorCode> {
        let pattern = schedule
            .entries
            .get(usize::from(self.frame))
            .map(|e| e.pattern);
        let running = !matches!(self.stage, Stage::Finished(_));
        if !running
            || shown.frame != self.frame
            || shown.attempt > self.attempt
            || Some(shown.pattern) != pattern
        {
            return Err(ErrorCode::UnexpectedPatternShown);
        }
        // The first confirmation counts (a duplicate must not move the ack time later).
        if self.shown_at_us.is_none() {
            self.shown_at_us = Some(now_us);
        }
        Ok(())
    }

    /// A VSYNC edge of `projector` at `t_us` (already counted in `vsync`).
    pub fn on_vsync(
        &mut self,
        schedule: &Schedule,
        projector: u8,
        t_us: u64,
        vsync: &[VsyncTracker],
        out: &mut Outbox,
    ) {
        let Some(lit) = self.lit_projector(schedule) else {
            return;
        };
        if projector != lit {
            return;
        }
        let Some(tracker) = vsync.get(usize::from(lit)) else {
            return;
        };
        let count = tracker.count();
        let h = &schedule.header;
        match self.stage {
            Stage::AwaitSlot => {
                let half_period = tracker.span_us(1) / 2;
                if t_us + half_period < self.next_slot_at_us {
                    return; // an edge inside the previous slot
                }
                let deadline = self.requested_at_us + u64::from(h.ack_timeout_us);
                let confirmed = self
                    .shown_at_us
                    .is_some_and(|shown| shown < t_us && shown <= deadline);
                if !confirmed {
                    self.late(schedule, LateReason::AckLate, t_us, t_us, vsync, out);
                    return;
                }
                let shown_vsync_count = count.wrapping_sub(1);
                let trigger_vsync_count =
                    shown_vsync_count.wrapping_add(u32::from(h.settle_vsyncs.max(1)));
                self.stage = Stage::Settling {
                    slot_start_us: t_us,
                    shown_vsync_count,
                    trigger_vsync_count,
                };
                self.settle_edge(schedule, t_us, count);
            }
            Stage::Settling { .. } => self.settle_edge(schedule, t_us, count),
            _ => {}
        }
    }

    /// Plans the trigger when `count` is the settle edge.
    fn settle_edge(&mut self, schedule: &Schedule, t_us: u64, count: u32) {
        if let Stage::Settling {
            slot_start_us,
            shown_vsync_count,
            trigger_vsync_count,
        } = self.stage
            && count == trigger_vsync_count
        {
            self.stage = Stage::Armed(TriggerPlan {
                slot_start_us,
                shown_vsync_count,
                vsync_count: count,
                vsync_us: t_us,
                trigger_at_us: t_us + u64::from(schedule.header.trigger_phase_us),
            });
        }
    }

    /// The planned trigger edge, when the controller should start waiting for it: no earlier
    /// than `spin_us` before it.
    pub fn trigger_due(&self, now_us: u64, spin_us: u64) -> Option<TriggerPlan> {
        match self.stage {
            Stage::Armed(plan) if now_us + spin_us >= plan.trigger_at_us => Some(plan),
            _ => None,
        }
    }

    /// The controller waited for the planned edge and the clock now reads `at_us`: fire when
    /// still aligned, else report the frame late.
    pub fn fire(
        &mut self,
        schedule: &Schedule,
        at_us: u64,
        vsync: &[VsyncTracker],
        out: &mut Outbox,
    ) -> FireDecision {
        let Stage::Armed(plan) = self.stage else {
            return FireDecision::Skip;
        };
        if at_us > plan.trigger_at_us + FIRE_TOLERANCE_US {
            self.late(
                schedule,
                LateReason::TriggerMissed,
                plan.slot_start_us,
                at_us,
                vsync,
                out,
            );
            return FireDecision::Skip;
        }
        let h = &schedule.header;
        let lit = self.lit_projector(schedule).unwrap_or(0);
        // The lit projector's own (metered) exposure and pulse width.
        let (periods, width_us) = schedule.exposure_of(lit);
        let exposure_us = vsync
            .get(usize::from(lit))
            .map_or(u64::from(periods) * u64::from(h.refresh_period_us), |v| {
                v.span_us(u32::from(periods))
            });
        let low_at_us = at_us + u64::from(width_us);
        self.stage = Stage::Pulse {
            plan,
            low_at_us,
            exposure_end_us: at_us + exposure_us,
        };
        self.stats.triggered += 1;
        self.stats.first_trigger_us.get_or_insert(at_us);
        self.stats.last_trigger_us = Some(at_us);
        push(
            out,
            ControllerMessage::Triggered(Triggered {
                frame: self.frame,
                attempt: self.attempt,
                projector: lit,
                timestamp_us: at_us,
                vsync_count: plan.vsync_count,
                vsync_timestamp_us: plan.vsync_us,
                shown_vsync_count: plan.shown_vsync_count,
            }),
        );
        FireDecision::Fire { low_at_us }
    }

    /// When the trigger output must go low (while it is high).
    pub fn pulse_low_at(&self) -> Option<u64> {
        match self.stage {
            Stage::Pulse { low_at_us, .. } => Some(low_at_us),
            _ => None,
        }
    }

    /// The controller set the trigger output low.
    pub fn pulse_ended(&mut self) {
        if let Stage::Pulse {
            plan,
            exposure_end_us,
            ..
        } = self.stage
        {
            self.stage = Stage::Exposing {
                plan,
                exposure_end_us,
                seen_active: false,
            };
        }
    }

    /// Time-driven rules: exposure end, missing VSYNC, host silence. `exposure_active` is the
    /// camera's exposure-active input when the board has one.
    pub fn tick(
        &mut self,
        schedule: &Schedule,
        now_us: u64,
        exposure_active: Option<bool>,
        vsync: &[VsyncTracker],
        out: &mut Outbox,
    ) {
        let h = schedule.header;
        let tracker = self
            .lit_projector(schedule)
            .and_then(|p| vsync.get(usize::from(p)));
        let period_us = tracker.map_or(u64::from(h.refresh_period_us), |v| v.span_us(1));
        match self.stage {
            Stage::AwaitSlot | Stage::Settling { .. }
                if now_us > self.last_host_us + u64::from(h.host_silence_timeout_us) =>
            {
                self.report_late(LateReason::HostSilent, out);
                self.stage = Stage::Paused;
            }
            Stage::AwaitSlot if now_us > self.next_slot_at_us + period_us => {
                // No edge of the lit projector where the slot should have started.
                let slot_start = self.next_slot_at_us;
                self.late(
                    schedule,
                    LateReason::VsyncMissing,
                    slot_start,
                    now_us,
                    vsync,
                    out,
                );
            }
            Stage::Settling { slot_start_us, .. } => {
                let last = tracker
                    .and_then(VsyncTracker::last_us)
                    .unwrap_or(slot_start_us);
                if now_us > last + period_us + period_us / 2 {
                    let reason = LateReason::VsyncMissing;
                    self.late(schedule, reason, slot_start_us, now_us, vsync, out);
                }
            }
            Stage::Exposing {
                plan,
                exposure_end_us,
                seen_active,
            } => self.exposure_tick(
                schedule,
                now_us,
                exposure_active,
                (plan, exposure_end_us, seen_active),
                period_us,
                vsync,
                out,
            ),
            _ => {}
        }
    }

    #[allow(clippy::too_many_arguments)] // the pieces of the Exposing stage, unpacked once
    fn exposure_tick(
        &mut self,
        schedule: &Schedule,
        now_us: u64,
        exposure_active: Option<bool>,
        (plan, exposure_end_us, seen_active): (TriggerPlan, u64, bool),
        period_us: u64,
        vsync: &[VsyncTracker],
        out: &mut Outbox,
    ) {
        let done_at = match exposure_active {
            // No camera feedback: the exposure is as long as planned.
            None => (now_us >= exposure_end_us).then_some(exposure_end_us),
            Some(true) => {
                self.stage = Stage::Exposing {
                    plan,
                    exposure_end_us,
                    seen_active: true,
                };
                // A camera that keeps exposing far too long still ends the frame.
                (now_us >= exposure_end_us + 2 * period_us).then_some(now_us)
            }
            Some(false) if seen_active => Some(now_us),
            Some(false) => {
                if now_us >= exposure_end_us + period_us {
                    self.late(
                        schedule,
                        LateReason::ExposureMissing,
                        plan.slot_start_us,
                        now_us,
                        vsync,
                        out,
                    );
                }
                None
            }
        };
        if let Some(t) = done_at {
            push(
                out,
                ControllerMessage::ExposureDone(ExposureDone {
                    frame: self.frame,
                    timestamp_us: t,
                }),
            );
            self.next_frame(schedule, plan.slot_start_us, t, vsync, out);
        }
    }

    /// True while the run only waits for VSYNC edges or the planned end of an exposure (no
    /// host answer outstanding, no trigger edge within `guard_us`): a board may then sleep until
    /// its next VSYNC interrupt. `exposure_feedback`: the camera's exposure-active input is read
    /// (it has no interrupt, so it must be sampled).
    pub fn waits_for_edges_only(
        &self,
        now_us: u64,
        exposure_feedback: bool,
        guard_us: u64,
    ) -> bool {
        match self.stage {
            Stage::Settling { .. } => true,
            Stage::AwaitSlot => self.shown_at_us.is_some(),
            Stage::Exposing {
                exposure_end_us, ..
            } => !exposure_feedback && exposure_end_us > now_us + guard_us,
            _ => false,
        }
    }

    /// The (frame, attempt) whose pattern request the host has not confirmed yet, while the
    /// run waits for that confirmation before the slot starts. A board whose time is virtual
    /// may hold its clock meanwhile (the QEMU board does), so the host's real-time latency does
    /// not become booth time.
    pub fn awaited_ack(&self) -> Option<(u16, u8)> {
        (self.stage == Stage::AwaitSlot && self.shown_at_us.is_none())
            .then_some((self.frame, self.attempt))
    }

    /// Whether a `Retrigger` can be accepted (rule 8): the frame ran already (it was triggered
    /// or dropped) in a run that has not been aborted, and a re-run can be queued.
    pub fn check_retrigger(&self, schedule: &Schedule, rt: &Retrigger) -> Result<(), ErrorCode> {
        let current_fired = matches!(self.stage, Stage::Pulse { .. } | Stage::Exposing { .. });
        let ran = rt.frame < self.resume_at.unwrap_or(self.frame)
            || (rt.frame == self.frame && current_fired);
        if !ran || rt.frame >= schedule.frame_count() {
            return Err(ErrorCode::RetriggerNotTriggered);
        }
        match self.stage {
            Stage::Finished(RunOutcome::Completed) => Ok(()),
            Stage::Finished(_) => Err(ErrorCode::InvalidState),
            _ if self.reruns.is_full() && !self.is_queued(rt.frame) => {
                Err(ErrorCode::RetriggerQueueFull)
            }
            _ => Ok(()),
        }
    }

    /// Queues the re-run of a frame that passed [`Self::check_retrigger`]; a completed run is
    /// extended by it at once. A frame already queued or being re-run is not queued twice.
    pub fn retrigger(
        &mut self,
        schedule: &Schedule,
        rt: &Retrigger,
        now_us: u64,
        out: &mut Outbox,
    ) {
        let rerunning = self.resume_at.is_some() && self.frame == rt.frame;
        if self.is_queued(rt.frame) || rerunning {
            return;
        }
        if self.stage == Stage::Finished(RunOutcome::Completed) {
            self.resume_at = Some(self.frame);
            self.next_slot_at_us = now_us + u64::from(schedule.header.period_us);
            self.start_rerun(schedule, (rt.frame, rt.attempt), now_us, out);
            return;
        }
        // Cannot fail: check_retrigger refused a full queue.
        let _ = self.reruns.push_back((rt.frame, rt.attempt));
    }

    fn is_queued(&self, frame: u16) -> bool {
        self.reruns.iter().any(|&(f, _)| f == frame)
    }

    /// Requests `frame` again as the attempt after `lost_attempt`.
    fn start_rerun(
        &mut self,
        schedule: &Schedule,
        (frame, lost_attempt): (u16, u8),
        now_us: u64,
        out: &mut Outbox,
    ) {
        self.frame = frame;
        self.attempt = lost_attempt.saturating_add(1);
        self.retries_used = 0;
        self.stats.retried += 1;
        push(
            out,
            ControllerMessage::FrameRetried(FrameRetried {
                frame,
                attempt: self.attempt,
            }),
        );
        self.request(schedule, now_us, out);
    }

    /// `Resume` after a pause: the same frame is requested again with a full slot ahead.
    pub fn resume(&mut self, schedule: &Schedule, now_us: u64, out: &mut Outbox) -> bool {
        if self.stage != Stage::Paused {
            return false;
        }
        self.last_host_us = now_us;
        self.attempt = self.attempt.saturating_add(1);
        self.stats.retried += 1;
        push(
            out,
            ControllerMessage::FrameRetried(FrameRetried {
                frame: self.frame,
                attempt: self.attempt,
            }),
        );
        self.next_slot_at_us = now_us + u64::from(schedule.header.period_us);
        self.request(schedule, now_us, out);
        true
    }

    /// `Abort` from the host: the run ends; a frame requested but not triggered is dropped (one
    /// already triggered keeps its `Triggered` report).
    pub fn abort(&mut self, out: &mut Outbox) {
        match self.stage {
            Stage::Finished(_) => return,
            Stage::Pulse { .. } | Stage::Exposing { .. } => {}
            _ => self.drop_frame(DropReason::RunAborted, out),
        }
        // Queued re-runs will not happen: each is reported.
        while let Some((frame, _)) = self.reruns.pop_front() {
            self.stats.dropped += 1;
            push(
                out,
                ControllerMessage::FrameDropped(FrameDropped {
                    frame,
                    reason: DropReason::RunAborted,
                }),
            );
        }
        self.stage = Stage::Finished(RunOutcome::AbortedByHost);
    }

    /// The earliest time at which [`Self::tick`] or the trigger has something to do.
    pub fn next_deadline(
        &self,
        schedule: &Schedule,
        vsync: &[VsyncTracker],
        spin_us: u64,
    ) -> Option<u64> {
        let h = &schedule.header;
        let silence = self.last_host_us + u64::from(h.host_silence_timeout_us) + 1;
        let tracker = self
            .lit_projector(schedule)
            .and_then(|p| vsync.get(usize::from(p)));
        let period = tracker.map_or(u64::from(h.refresh_period_us), |v| v.span_us(1));
        match self.stage {
            Stage::AwaitSlot => Some(silence.min(self.next_slot_at_us + period + 1)),
            Stage::Settling { slot_start_us, .. } => {
                let last = tracker
                    .and_then(VsyncTracker::last_us)
                    .unwrap_or(slot_start_us);
                Some(silence.min(last + period + period / 2 + 1))
            }
            Stage::Armed(plan) => Some(plan.trigger_at_us.saturating_sub(spin_us)),
            Stage::Pulse { low_at_us, .. } => Some(low_at_us.saturating_sub(spin_us)),
            Stage::Exposing {
                exposure_end_us, ..
            } => Some(exposure_end_us),
            Stage::Paused | Stage::Finished(_) => None,
        }
    }

    fn lit_projector(&self, schedule: &Schedule) -> Option<u8> {
        schedule
            .entries
            .get(usize::from(self.frame))
            .map(|e| e.projector)
    }

    fn request(&mut self, schedule: &Schedule, now_us: u64, out: &mut Outbox) {
        let Some(entry) = schedule.entries.get(usize::from(self.frame)) else {
            return;
        };
        self.requested_at_us = now_us;
        self.shown_at_us = None;
        self.stage = Stage::AwaitSlot;
        push(
            out,
            ControllerMessage::PatternRequest(PatternRequest {
                frame: self.frame,
                attempt: self.attempt,
                projector: entry.projector,
                pattern: entry.pattern,
            }),
        );
    }

    fn report_late(&mut self, reason: LateReason, out: &mut Outbox) {
        log!(
            warn,
            "frame {} attempt {} late: {}",
            self.frame,
            self.attempt,
            defmt::Debug2Format(&reason)
        );
        self.stats.late += 1;
        push(
            out,
            ControllerMessage::FrameLate(FrameLate {
                frame: self.frame,
                attempt: self.attempt,
                reason,
            }),
        );
    }

    /// The current attempt missed the slot that started (or should have started) at
    /// `slot_start_us`: report, then retry in the next slot, drop, or abort per the policy.
    fn late(
        &mut self,
        schedule: &Schedule,
        reason: LateReason,
        slot_start_us: u64,
        now_us: u64,
        vsync: &[VsyncTracker],
        out: &mut Outbox,
    ) {
        self.report_late(reason, out);
        let policy = schedule.header.policy;
        if self.retries_used >= policy.max_retries {
            self.drop_frame(DropReason::RetriesExhausted, out);
            match policy.when_exhausted {
                ExhaustedAction::Abort => {
                    self.stage = Stage::Finished(RunOutcome::AbortedRetriesExhausted);
                }
                ExhaustedAction::Drop => {
                    self.next_frame(schedule, slot_start_us, now_us, vsync, out);
                }
            }
            return;
        }
        self.retries_used += 1;
        self.attempt = self.attempt.saturating_add(1);
        self.stats.retried += 1;
        push(
            out,
            ControllerMessage::FrameRetried(FrameRetried {
                frame: self.frame,
                attempt: self.attempt,
            }),
        );
        self.next_slot_at_us = slot_start_us + self.slot_len_us(schedule, vsync);
        let keep_shown = self.shown_at_us;
        self.request(schedule, now_us, out);
        // A confirmation that arrived after the slot start (a late ack) confirms the same
        // pattern for the retry.
        self.shown_at_us = keep_shown.filter(|&shown| shown >= slot_start_us);
    }

    fn drop_frame(&mut self, reason: DropReason, out: &mut Outbox) {
        log!(
            warn,
            "frame {} dropped: {}",
            self.frame,
            defmt::Debug2Format(&reason)
        );
        self.stats.dropped += 1;
        push(
            out,
            ControllerMessage::FrameDropped(FrameDropped {
                frame: self.frame,
                reason,
            }),
        );
    }

    /// Frame done (exposed or dropped): request the next one for the next slot.
    fn next_frame(
        &mut self,
        schedule: &Schedule,
        slot_start_us: u64,
        now_us: u64,
        vsync: &[VsyncTracker],
        out: &mut Outbox,
    ) {
        let slot_len = self.slot_len_us(schedule, vsync);
        let next = self.next_unrun();
        if let Some(rerun) = self.reruns.pop_front() {
            // Rule 8: a queued re-run takes the next slot; the schedule continues after it.
            self.resume_at = Some(next);
            self.next_slot_at_us = slot_start_us + slot_len;
            self.start_rerun(schedule, rerun, now_us, out);
            return;
        }
        self.resume_at = None;
        self.frame = next;
        self.attempt = 0;
        self.retries_used = 0;
        if self.frame >= schedule.frame_count() {
            self.stage = Stage::Finished(RunOutcome::Completed);
            return;
        }
        self.next_slot_at_us = slot_start_us + slot_len;
        self.request(schedule, now_us, out);
    }

    /// Slot length on the current frame's projector: `slot_vsyncs` measured periods.
    fn slot_len_us(&self, schedule: &Schedule, vsync: &[VsyncTracker]) -> u64 {
        let slots = schedule.slot_vsyncs();
        self.lit_projector(schedule)
            .and_then(|p| vsync.get(usize::from(p)))
            .map_or(u64::from(schedule.header.period_us), |v| v.span_us(slots))
    }
}

/// Queues a message. The controller empties the outbox on every poll and one poll queues at
/// most a handful, so it never fills up; a full outbox would be a bug, caught in debug builds.
fn push(out: &mut Outbox, message: ControllerMessage) {
    debug_assert!(!out.is_full(), "outbox full");
    let _ = out.push_back(message);
}
