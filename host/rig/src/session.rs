//! A session with the controller: handshake, schedule upload, and the run itself (answering
//! pattern requests, collecting every trigger and fault report).

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use mlsss_shared::message::{
    ControllerState, DoneSummary, ErrorCode, ExposureDone, FrameDropped, FrameLate, FrameRetried,
    Hello, HelloReply, HostHeartbeat, LateReason, Nack, PatternRequest, PatternShown,
    ProjectorTiming, Retrigger, RunOutcome, StatusReport, Triggered,
};
use mlsss_shared::{ControllerMessage, HostMessage, PROTOCOL_VERSION, SCHEMA_HASH};

use super::RigError;
use super::link::{ByteLink, ControllerLink, HostLinkStats};
use super::schedule::RigSchedule;

/// How often the host proves it is alive while waiting.
const HEARTBEAT_EVERY: Duration = Duration::from_millis(200);
/// Wall time without any message from a running controller before the host gives up.
const CONTROLLER_SILENCE_LIMIT: Duration = Duration::from_secs(10);
/// Wall time without progress (a request, trigger, exposure, drop or `Done`) while the
/// controller still talks (heartbeats, statuses) before the host gives up on the run: a slot is
/// well under a second, so this only trips when the run is stuck, never on a slow one.
const RUN_STALL_LIMIT: Duration = Duration::from_secs(60);
/// After `Done`, how long to keep collecting the per-projector timing reports.
const AFTER_DONE_QUIET: Duration = Duration::from_millis(300);
/// After `Done`, the longest the host collects timing reports, however chatty the controller.
const AFTER_DONE_LIMIT: Duration = Duration::from_secs(3);
/// Attempts of the handshake (the controller may still be booting).
const HELLO_ATTEMPTS: u32 = 10;
const HELLO_TIMEOUT: Duration = Duration::from_millis(500);

/// What the host does when it reconnects to a paused run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReconnectAction {
    /// Continue the run where it stopped.
    Resume,
    /// End the run (frames captured so far are kept).
    Abort,
}

/// A simulated disconnect: at the pattern request of `at_frame` the host goes away for
/// `duration` (hears and says nothing), then reconnects and resumes or aborts.
#[derive(Debug, Clone, Copy)]
pub struct Disconnect {
    /// Frame whose request the host leaves unanswered.
    pub at_frame: u16,
    /// Wall time away.
    pub duration: Duration,
    /// What to do after reconnecting.
    pub then: ReconnectAction,
}

/// Host-side behaviour changes for fault-injection runs.
#[derive(Debug, Clone, Default)]
pub struct HostFaults {
    /// Frames whose first pattern request is answered only after the controller reported
    /// the frame late.
    pub late_ack_frames: Vec<u16>,
    /// At most one disconnect.
    pub disconnect: Option<Disconnect>,
}

/// Everything the controller reported during a run.
#[derive(Debug, Clone)]
pub struct RunLog {
    /// The controller's identification.
    pub controller: HelloReply,
    /// The schedule that ran.
    pub schedule: RigSchedule,
    /// Controller status just before `Start`.
    pub status_before: StatusReport,
    /// Controller status after `Done`.
    pub status_after: Option<StatusReport>,
    /// Pattern requests in arrival order.
    pub requests: Vec<PatternRequest>,
    /// The trigger of each frame (the last one if a frame were ever reported twice).
    pub triggers: BTreeMap<u16, Triggered>,
    /// Exposure ends by frame.
    pub exposures: BTreeMap<u16, ExposureDone>,
    /// Late reports in order.
    pub late: Vec<FrameLate>,
    /// Retries in order.
    pub retried: Vec<FrameRetried>,
    /// Dropped frames in order.
    pub dropped: Vec<FrameDropped>,
    /// Refusals (of pattern acks, typically) during the run.
    pub nacks: Vec<Nack>,
    /// Frames triggered twice without a re-trigger asking for it (must stay empty).
    pub duplicate_triggers: Vec<u16>,
    /// Re-triggers the controller accepted (frames whose camera payload was lost), in order.
    pub retriggers: Vec<Retrigger>,
    /// Re-triggers the controller refused, with its reason (those frames stay missing).
    pub retrigger_refusals: Vec<(Retrigger, ErrorCode)>,
    /// The final summary.
    pub done: DoneSummary,
    /// Measured VSYNC timing by projector (the latest report of each).
    pub projector_timing: BTreeMap<u8, ProjectorTiming>,
    /// Statuses the controller reported when the host reconnected.
    pub reconnect_statuses: Vec<StatusReport>,
    /// Host end link counters.
    pub host_link: HostLinkStats,
}

/// Callbacks of a run: the projector output and the frame sink.
pub trait RunHooks {
    /// Put pattern `pattern` (schedule id) on `projector` now; return when it is on screen.
    fn show(&mut self, request: &PatternRequest) -> Result<(), RigError>;
    /// The camera was triggered for a frame.
    fn triggered(&mut self, trigger: &Triggered) -> Result<(), RigError>;
    /// The exposure of a frame ended.
    fn exposure_done(&mut self, _exposure: &ExposureDone) -> Result<(), RigError> {
        Ok(())
    }
    /// Frames whose camera payload was lost since the last call, to be re-triggered. With
    /// `wait_for_all` (at the end of a run) first waits until the payload of every triggered
    /// frame has been received or found lost.
    fn lost_payloads(&mut self, _wait_for_all: bool) -> Result<Vec<Retrigger>, RigError> {
        Ok(vec![])
    }
}

/// An open session with an identified controller.
pub struct Session<L: ByteLink> {
    link: ControllerLink<L>,
    controller: HelloReply,
}

impl<L: ByteLink> Session<L> {
    /// Identifies the controller; refuses a protocol version or schema mismatch.
    pub fn open(mut link: ControllerLink<L>) -> Result<Self, RigError> {
        let controller = hello(&mut link)?;
        Ok(Self { link, controller })
    }

    /// The controller's identification.
    pub fn controller(&self) -> &HelloReply {
        &self.controller
    }

    /// The link (fault injection, raw access).
    pub fn link_mut(&mut self) -> &mut ControllerLink<L> {
        &mut self.link
    }

    /// Uploads and commits a schedule. A refusal is [`RigError::Refused`] with the typed code.
    pub fn upload(&mut self, schedule: &RigSchedule) -> Result<(), RigError> {
        self.link
            .command(&HostMessage::ScheduleBegin(schedule.header))?;
        for chunk in schedule.chunks() {
            self.link.command(&HostMessage::ScheduleChunk(chunk))?;
        }
        self.link
            .command(&HostMessage::ScheduleCommit(schedule.commit()))
    }

    /// Asks for the controller's status.
    pub fn status(&mut self) -> Result<StatusReport, RigError> {
        self.link.command(&HostMessage::StatusQuery)?;
        let deadline = Instant::now() + Duration::from_secs(2);
        while Instant::now() < deadline {
            if let Some(ControllerMessage::Status(status)) =
                self.link.recv(Duration::from_millis(100))?
            {
                return Ok(status);
            }
        }
        Err(RigError::NoAnswer {
            command: "StatusQuery",
            attempts: 1,
        })
    }

    /// Uploads `schedule`, arms, starts and runs it to the end.
    pub fn run(
        &mut self,
        schedule: &RigSchedule,
        hooks: &mut dyn RunHooks,
        faults: &HostFaults,
    ) -> Result<RunLog, RigError> {
        self.upload(schedule)?;
        self.link.command(&HostMessage::Arm)?;
        let status_before = self.status()?;
        self.link.command(&HostMessage::Start)?;
        let mut run = RunState::new(self.controller, schedule.clone(), status_before);
        if let Err(error) = self.event_loop(&mut run, hooks, faults) {
            // Best effort: do not leave the controller triggering for a host that gave up.
            let _ = self.link.send(&HostMessage::Abort);
            return Err(error);
        }
        run.status_after = self.status().ok();
        run.finish(self.link.stats())
    }

    fn event_loop(
        &mut self,
        run: &mut RunState,
        hooks: &mut dyn RunHooks,
        faults: &HostFaults,
    ) -> Result<(), RigError> {
        let mut last_sent = Instant::now();
        let mut last_heard = Instant::now();
        let mut last_progress = Instant::now();
        let mut withheld: Vec<PatternRequest> = vec![];
        let mut disconnect = faults.disconnect;
        loop {
            for lost in hooks.lost_payloads(false)? {
                self.retrigger(run, lost)?;
                last_sent = Instant::now();
            }
            if last_sent.elapsed() >= HEARTBEAT_EVERY {
                self.heartbeat()?;
                last_sent = Instant::now();
            }
            if last_progress.elapsed() > RUN_STALL_LIMIT {
                return Err(RigError::RunStalled(RUN_STALL_LIMIT));
            }
            let Some(message) = self.link.recv(Duration::from_millis(50))? else {
                if last_heard.elapsed() > CONTROLLER_SILENCE_LIMIT {
                    return Err(RigError::ControllerSilent(CONTROLLER_SILENCE_LIMIT));
                }
                continue;
            };
            last_heard = Instant::now();
            if makes_progress(&message) {
                last_progress = Instant::now();
            }
            match message {
                ControllerMessage::PatternRequest(request) => {
                    run.requests.push(request);
                    if let Some(d) = disconnect.filter(|d| d.at_frame == request.frame) {
                        disconnect = None;
                        if self.away_and_back(run, d)? == ReconnectAction::Abort {
                            continue;
                        }
                    } else if request.attempt == 0
                        && faults.late_ack_frames.contains(&request.frame)
                    {
                        withheld.push(request);
                    } else {
                        self.show_and_ack(hooks, &request)?;
                    }
                    last_sent = Instant::now();
                }
                ControllerMessage::FrameLate(late) => {
                    run.late.push(late);
                    if late.reason == LateReason::HostSilent {
                        // The controller paused because it did not hear from us in time (this
                        // host was busy, not away): we are here, so the run goes on.
                        self.resume_after_host_silence()?;
                        last_sent = Instant::now();
                    } else if let Some(i) = withheld.iter().position(|r| r.frame == late.frame) {
                        // A withheld ack is now late: send it (the controller retries the frame).
                        let request = withheld.swap_remove(i);
                        self.show_and_ack(hooks, &request)?;
                        last_sent = Instant::now();
                    }
                }
                ControllerMessage::Triggered(trigger) => {
                    let asked_again = run
                        .retriggers
                        .iter()
                        .any(|r| r.frame == trigger.frame && r.attempt < trigger.attempt);
                    // The latest trigger of a frame is the one whose payload is kept.
                    if run.triggers.insert(trigger.frame, trigger).is_some() && !asked_again {
                        run.duplicate_triggers.push(trigger.frame);
                    }
                    hooks.triggered(&trigger)?;
                }
                ControllerMessage::ExposureDone(exposure) => {
                    run.exposures.insert(exposure.frame, exposure);
                    hooks.exposure_done(&exposure)?;
                }
                ControllerMessage::FrameRetried(retried) => run.retried.push(retried),
                ControllerMessage::FrameDropped(dropped) => run.dropped.push(dropped),
                ControllerMessage::Nack(nack) => run.nacks.push(nack),
                ControllerMessage::ProjectorTiming(timing) => {
                    run.projector_timing.insert(timing.projector, timing);
                }
                ControllerMessage::Done(done) => {
                    // Payloads still in flight may turn out lost: re-trigger them before the
                    // run ends (the controller extends it and sends another Done).
                    if done.outcome == RunOutcome::Completed {
                        let mut extended = false;
                        for lost in hooks.lost_payloads(true)? {
                            extended |= self.retrigger(run, lost)?;
                        }
                        // A re-trigger sent just before this Done was read extends the run
                        // too: this Done is then not the last one.
                        if extended || run.rerun_outstanding() {
                            last_progress = Instant::now();
                            continue;
                        }
                    }
                    run.done = Some(done);
                    self.collect_after_done(run)?;
                    return Ok(());
                }
                ControllerMessage::HelloReply(_)
                | ControllerMessage::Ack(_)
                | ControllerMessage::LinkStats(_)
                | ControllerMessage::Heartbeat(_)
                | ControllerMessage::Status(_) => {}
            }
        }
    }

    /// Resumes a run the controller paused for host silence. A refusal as `InvalidState` means
    /// it is not paused any more (a retransmitted `Resume` after a lost ack): nothing to do.
    fn resume_after_host_silence(&mut self) -> Result<(), RigError> {
        match self.link.command(&HostMessage::Resume) {
            Err(RigError::Refused {
                error: ErrorCode::InvalidState,
                ..
            }) => Ok(()),
            other => other,
        }
    }

    /// Asks the controller to run a frame again; `false` when it refused (recorded in the log).
    fn retrigger(&mut self, run: &mut RunState, lost: Retrigger) -> Result<bool, RigError> {
        match self.link.command(&HostMessage::Retrigger(lost)) {
            Ok(()) => {
                run.retriggers.push(lost);
                Ok(true)
            }
            Err(RigError::Refused { error, .. }) => {
                run.retrigger_refusals.push((lost, error));
                Ok(false)
            }
            Err(e) => Err(e),
        }
    }

    fn show_and_ack(
        &mut self,
        hooks: &mut dyn RunHooks,
        request: &PatternRequest,
    ) -> Result<(), RigError> {
        hooks.show(request)?;
        self.link.send(&HostMessage::PatternShown(PatternShown {
            frame: request.frame,
            attempt: request.attempt,
            pattern: request.pattern,
        }))?;
        Ok(())
    }

    fn heartbeat(&mut self) -> Result<(), RigError> {
        let host_time_us = u64::try_from(
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap_or_default()
                .as_micros(),
        )
        .unwrap_or(u64::MAX);
        self.link
            .send(&HostMessage::Heartbeat(HostHeartbeat { host_time_us }))?;
        Ok(())
    }

    /// The host goes away, comes back, identifies again, reads the state and resumes or aborts.
    fn away_and_back(
        &mut self,
        run: &mut RunState,
        disconnect: Disconnect,
    ) -> Result<ReconnectAction, RigError> {
        self.link.go_silent(disconnect.duration)?;
        self.link.resync();
        self.controller = hello(&mut self.link)?;
        let status = self.status()?;
        run.reconnect_statuses.push(status);
        match (disconnect.then, status.state) {
            (ReconnectAction::Resume, ControllerState::Paused) => {
                self.link.command(&HostMessage::Resume)?;
            }
            (ReconnectAction::Resume, _) => {}
            (ReconnectAction::Abort, _) => self.link.command(&HostMessage::Abort)?,
        }
        Ok(disconnect.then)
    }

    fn collect_after_done(&mut self, run: &mut RunState) -> Result<(), RigError> {
        collect_timings(&mut self.link, &mut run.projector_timing)
    }
}

/// Collects the per-projector timing reports that follow `Done`, until none has come for
/// [`AFTER_DONE_QUIET`] and never past [`AFTER_DONE_LIMIT`]. Only a timing report extends the
/// wait: the controller's heartbeats go on after `Done`, and under QEMU's warped idle clock they
/// came more often than the quiet interval, so waiting for silence never ended (a clean-clone
/// test run hung 10 minutes in `disconnect_then_abort_keeps_every_frame_already_captured`).
fn collect_timings<L: ByteLink>(
    link: &mut ControllerLink<L>,
    timings: &mut BTreeMap<u8, ProjectorTiming>,
) -> Result<(), RigError> {
    let limit = Instant::now() + AFTER_DONE_LIMIT;
    let mut quiet_until = Instant::now() + AFTER_DONE_QUIET;
    loop {
        let until = quiet_until.min(limit);
        let now = Instant::now();
        if now >= until {
            return Ok(());
        }
        match link.recv(until - now)? {
            Some(ControllerMessage::ProjectorTiming(timing)) => {
                timings.insert(timing.projector, timing);
                quiet_until = Instant::now() + AFTER_DONE_QUIET;
            }
            Some(_) => {}
            None => return Ok(()),
        }
    }
}

/// Whether a message shows the run moving (heartbeats and statuses alone do not).
fn makes_progress(message: &ControllerMessage) -> bool {
    matches!(
        message,
        ControllerMessage::PatternRequest(_)
            | ControllerMessage::Triggered(_)
            | ControllerMessage::ExposureDone(_)
            | ControllerMessage::FrameDropped(_)
            | ControllerMessage::FrameRetried(_)
            | ControllerMessage::Done(_)
    )
}

/// Handshake: Hello until a HelloReply comes; version and schema must match.
fn hello<L: ByteLink>(link: &mut ControllerLink<L>) -> Result<HelloReply, RigError> {
    let ours = Hello {
        protocol_version: PROTOCOL_VERSION,
        schema_hash: SCHEMA_HASH,
    };
    for _ in 0..HELLO_ATTEMPTS {
        link.send(&HostMessage::Hello(ours))?;
        let deadline = Instant::now() + HELLO_TIMEOUT;
        while Instant::now() < deadline {
            let remaining = deadline.saturating_duration_since(Instant::now());
            if let Some(ControllerMessage::HelloReply(reply)) = link.recv(remaining)? {
                return check_identity(reply);
            }
        }
    }
    Err(RigError::NoAnswer {
        command: "Hello",
        attempts: HELLO_ATTEMPTS,
    })
}

fn check_identity(reply: HelloReply) -> Result<HelloReply, RigError> {
    if reply.protocol_version != PROTOCOL_VERSION {
        return Err(RigError::ProtocolMismatch {
            host: PROTOCOL_VERSION,
            controller: reply.protocol_version,
        });
    }
    if reply.schema_hash != SCHEMA_HASH {
        return Err(RigError::SchemaMismatch {
            host: SCHEMA_HASH,
            controller: reply.schema_hash,
        });
    }
    Ok(reply)
}

/// A run in progress.
struct RunState {
    controller: HelloReply,
    schedule: RigSchedule,
    status_before: StatusReport,
    status_after: Option<StatusReport>,
    requests: Vec<PatternRequest>,
    triggers: BTreeMap<u16, Triggered>,
    exposures: BTreeMap<u16, ExposureDone>,
    late: Vec<FrameLate>,
    retried: Vec<FrameRetried>,
    dropped: Vec<FrameDropped>,
    nacks: Vec<Nack>,
    duplicate_triggers: Vec<u16>,
    retriggers: Vec<Retrigger>,
    retrigger_refusals: Vec<(Retrigger, ErrorCode)>,
    done: Option<DoneSummary>,
    projector_timing: BTreeMap<u8, ProjectorTiming>,
    reconnect_statuses: Vec<StatusReport>,
}

impl RunState {
    fn new(controller: HelloReply, schedule: RigSchedule, status_before: StatusReport) -> Self {
        Self {
            controller,
            schedule,
            status_before,
            status_after: None,
            requests: vec![],
            triggers: BTreeMap::new(),
            exposures: BTreeMap::new(),
            late: vec![],
            retried: vec![],
            dropped: vec![],
            nacks: vec![],
            duplicate_triggers: vec![],
            retriggers: vec![],
            retrigger_refusals: vec![],
            done: None,
            projector_timing: BTreeMap::new(),
            reconnect_statuses: vec![],
        }
    }

    /// Whether an accepted re-trigger has neither been triggered again nor dropped yet.
    fn rerun_outstanding(&self) -> bool {
        self.retriggers.iter().any(|r| {
            let rerun = self
                .triggers
                .get(&r.frame)
                .is_some_and(|t| t.attempt > r.attempt);
            let dropped = self.dropped.iter().any(|d| d.frame == r.frame);
            !rerun && !dropped
        })
    }

    fn finish(self, host_link: HostLinkStats) -> Result<RunLog, RigError> {
        let done = self.done.ok_or(RigError::NoDone)?;
        Ok(RunLog {
            controller: self.controller,
            schedule: self.schedule,
            status_before: self.status_before,
            status_after: self.status_after,
            requests: self.requests,
            triggers: self.triggers,
            exposures: self.exposures,
            late: self.late,
            retried: self.retried,
            dropped: self.dropped,
            nacks: self.nacks,
            duplicate_triggers: self.duplicate_triggers,
            retriggers: self.retriggers,
            retrigger_refusals: self.retrigger_refusals,
            done,
            projector_timing: self.projector_timing,
            reconnect_statuses: self.reconnect_statuses,
            host_link,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mlsss_shared::framing::{ControllerEncoder, HostDecoder, MAX_WIRE_FRAME_LEN};
    use mlsss_shared::message::{Board, ControllerHeartbeat, ControllerState};
    use std::io;

    /// A controller that answers every Hello with `reply` and ignores everything else.
    struct ScriptedController {
        reply: HelloReply,
        decoder: HostDecoder,
        encoder: ControllerEncoder,
        outbox: Vec<u8>,
        hellos_seen: usize,
    }

    impl ScriptedController {
        fn new(reply: HelloReply) -> Self {
            Self {
                reply,
                decoder: HostDecoder::new(),
                encoder: ControllerEncoder::new(),
                outbox: Vec::new(),
                hellos_seen: 0,
            }
        }
    }

    impl ByteLink for ScriptedController {
        fn send_bytes(&mut self, bytes: &[u8]) -> io::Result<()> {
            let hellos = self
                .decoder
                .feed(bytes)
                .flatten()
                .filter(|received| matches!(received.message, HostMessage::Hello(_)))
                .count();
            for _ in 0..hellos {
                self.hellos_seen += 1;
                let mut frame = [0u8; MAX_WIRE_FRAME_LEN];
                let (_, bytes) = self
                    .encoder
                    .encode(&ControllerMessage::HelloReply(self.reply), &mut frame)
                    .map_err(|e| io::Error::other(format!("{e:?}")))?;
                self.outbox.extend_from_slice(bytes);
            }
            Ok(())
        }

        fn recv_bytes(&mut self, buf: &mut [u8], _timeout: Duration) -> io::Result<usize> {
            let n = self.outbox.len().min(buf.len());
            buf[..n].copy_from_slice(&self.outbox[..n]);
            self.outbox.drain(..n);
            Ok(n)
        }
    }

    fn reply_from_this_build() -> HelloReply {
        HelloReply {
            protocol_version: PROTOCOL_VERSION,
            schema_hash: SCHEMA_HASH,
            board: Board::QemuMps2An386,
            firmware_version: [0, 1, 0],
            projectors: 4,
            timer_tick_ns: 1000,
        }
    }

    fn open_against(reply: HelloReply) -> Result<HelloReply, RigError> {
        let link = ControllerLink::new(ScriptedController::new(reply));
        Session::open(link).map(|session| *session.controller())
    }

    /// A controller that sends a heartbeat on every read, forever (QEMU's warped clock).
    struct ChattyController {
        encoder: ControllerEncoder,
        timings_left: u8,
    }

    impl ByteLink for ChattyController {
        fn send_bytes(&mut self, _bytes: &[u8]) -> io::Result<()> {
            Ok(())
        }

        fn recv_bytes(&mut self, buf: &mut [u8], _timeout: Duration) -> io::Result<usize> {
            let message = if self.timings_left > 0 {
                self.timings_left -= 1;
                ControllerMessage::ProjectorTiming(ProjectorTiming {
                    projector: self.timings_left,
                    vsync_count: 10,
                    period_ns: 16_666_667,
                })
            } else {
                ControllerMessage::Heartbeat(ControllerHeartbeat {
                    timestamp_us: 0,
                    state: ControllerState::Idle,
                })
            };
            let mut frame = [0u8; MAX_WIRE_FRAME_LEN];
            let (_, bytes) = self
                .encoder
                .encode(&message, &mut frame)
                .map_err(|e| io::Error::other(format!("{e:?}")))?;
            buf[..bytes.len()].copy_from_slice(bytes);
            Ok(bytes.len())
        }
    }

    #[test]
    fn collecting_timings_after_done_ends_though_heartbeats_never_stop() {
        let mut link = ControllerLink::new(ChattyController {
            encoder: ControllerEncoder::new(),
            timings_left: 4,
        });
        let mut timings = BTreeMap::new();
        let start = Instant::now();
        collect_timings(&mut link, &mut timings).unwrap();
        // The quiet interval after the last timing report, not the limit: heartbeats do not
        // extend the wait (before the fix this loop never returned).
        assert!(start.elapsed() < AFTER_DONE_LIMIT, "{:?}", start.elapsed());
        assert_eq!(timings.len(), 4);
    }

    #[test]
    fn a_controller_built_from_the_same_source_is_accepted() {
        let reply = reply_from_this_build();
        let accepted = open_against(reply).expect("same version and schema");
        assert_eq!(accepted, reply);
    }

    #[test]
    fn a_controller_speaking_another_protocol_version_is_refused() {
        let reply = HelloReply {
            protocol_version: PROTOCOL_VERSION.wrapping_add(1),
            ..reply_from_this_build()
        };
        match open_against(reply) {
            Err(RigError::ProtocolMismatch { host, controller }) => {
                assert_eq!(host, PROTOCOL_VERSION);
                assert_eq!(controller, PROTOCOL_VERSION.wrapping_add(1));
            }
            other => panic!("expected ProtocolMismatch, got {other:?}"),
        }
    }

    #[test]
    fn a_controller_with_other_message_definitions_is_refused() {
        // Same version number, different schema: someone changed a message without bumping it.
        let reply = HelloReply {
            schema_hash: SCHEMA_HASH ^ 0x0100_0000,
            ..reply_from_this_build()
        };
        match open_against(reply) {
            Err(RigError::SchemaMismatch { host, controller }) => {
                assert_eq!(host, SCHEMA_HASH);
                assert_eq!(controller, SCHEMA_HASH ^ 0x0100_0000);
            }
            other => panic!("expected SchemaMismatch, got {other:?}"),
        }
    }
}
