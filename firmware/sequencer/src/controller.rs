//! The controller: the wire protocol session around a [`Run`], on embedded-hal / embedded-io
//! peripherals.
//!
//! The board owns the interrupts: it timestamps each projector's VSYNC edge (timer input
//! capture, an EXTI interrupt, or on QEMU the timer that generates it) and hands the edges to
//! [`Controller::on_vsync`] from its main loop, then calls [`Controller::poll`] as often as it
//! can (and at the latest at the alarm the controller set on the clock).
//!
//! Session (see `mlsss_shared`): `Hello` -> `HelloReply` (other commands are refused with
//! `NotIdentified` before it); schedule upload; `Arm`; `Start`; during the run the controller
//! requests patterns and reports triggers. Every command except `Hello` and `Heartbeat` is
//! answered by exactly one `Ack` or `Nack` with the command's sequence number, before any
//! message the command causes.

use embedded_hal::digital::{Error as _, ErrorKind, InputPin, OutputPin};
use embedded_io::{Read, ReadReady, Write};
use mlsss_shared::framing::{
    ControllerEncoder, EncodeError, FrameError, HostDecoder, MAX_WIRE_FRAME_LEN, Received,
};
use mlsss_shared::message::{
    Ack, Board, ControllerHeartbeat, ControllerMessage, ControllerState, DoneSummary, DropReason,
    ErrorCode, FrameDropped, Hello, HelloReply, HostMessage, LinkStats, Nack, ProjectorTiming,
    RunOutcome, ScheduleCommit, StatusReport,
};
use mlsss_shared::{PROTOCOL_VERSION, SCHEMA_HASH};

use crate::clock::MonotonicClock;
use crate::run::{FireDecision, Outbox, Run, Stage};
use crate::schedule::{Schedule, ScheduleLoader};
use crate::vsync::VsyncTracker;

/// How long before a trigger edge the controller stops everything else and waits for it.
pub const TRIGGER_SPIN_US: u64 = 200;

/// No serial output this close to a trigger edge (a frame at 921 600 baud takes ~0.5 ms to
/// send through a blocking UART; it must not delay the edge).
pub const IO_GUARD_US: u64 = 2_000;

/// Sampling interval of the exposure-active input while the camera exposes (the resolution of
/// `ExposureDone` with camera feedback).
pub const EXPOSURE_SAMPLE_US: u64 = 50;

/// A board does not sleep when a planned exposure end is closer than this (it may only wake at
/// the next VSYNC edge of any projector).
pub const SLEEP_GUARD_US: u64 = 2_000;

/// Interval of the controller's `Heartbeat` while a host is identified.
pub const HEARTBEAT_US: u64 = 1_000_000;

/// Refresh period assumed for VSYNC measurement before a schedule says otherwise (60 Hz).
const DEFAULT_REFRESH_US: u32 = 16_667;

/// Room kept in the outbox for `Done` and the projector timings.
const DONE_MESSAGES: usize = 1 + 8;

/// Bytes read from the serial port per poll (keeps each poll short).
const READ_CHUNK: usize = 64;

/// What the board tells the host about itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BoardInfo {
    /// Which board.
    pub board: Board,
    /// Firmware version (major, minor, patch).
    pub firmware_version: [u8; 3],
    /// Resolution of the controller clock, nanoseconds.
    pub timer_tick_ns: u32,
}

/// A peripheral failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum Error<SE: core::fmt::Debug> {
    /// The serial port failed to read or write.
    #[error("serial port: {0:?}")]
    Serial(SE),
    /// The trigger output or the exposure input failed.
    #[error("pin: {0:?}")]
    Pin(ErrorKind),
    /// A message did not fit a frame (a bug in the message definitions).
    #[error("encode: {0}")]
    Encode(EncodeError),
}

/// The booth controller, generic over its serial port `S`, trigger output `T`, exposure-active
/// input `X` (use [`NoExposureInput`] when the camera has none), clock `C`, and `N` projectors.
pub struct Controller<S, T, X, C, const N: usize> {
    serial: S,
    trigger: T,
    exposure: Option<X>,
    clock: C,
    info: BoardInfo,
    decoder: HostDecoder,
    encoder: ControllerEncoder,
    identified: bool,
    loader: ScheduleLoader,
    schedule: Option<Schedule>,
    armed: bool,
    run: Option<Run>,
    done_sent: bool,
    /// Next frame to report dropped after an aborted run.
    drop_cursor: Option<u16>,
    trigger_high: bool,
    status_after_silence: bool,
    vsync: [VsyncTracker; N],
    out: Outbox,
    next_heartbeat_us: u64,
}

impl<S, T, X, C, const N: usize> Controller<S, T, X, C, N>
where
    S: Read + ReadReady + Write,
    T: OutputPin,
    X: InputPin,
    C: MonotonicClock,
{
    /// A controller with the trigger output low, waiting for `Hello`.
    pub fn new(
        serial: S,
        mut trigger: T,
        exposure: Option<X>,
        clock: C,
        info: BoardInfo,
    ) -> Result<Self, Error<S::Error>> {
        trigger.set_low().map_err(|e| Error::Pin(e.kind()))?;
        Ok(Self {
            serial,
            trigger,
            exposure,
            clock,
            info,
            decoder: HostDecoder::new(),
            encoder: ControllerEncoder::new(),
            identified: false,
            loader: ScheduleLoader::new(),
            schedule: None,
            armed: false,
            run: None,
            done_sent: false,
            drop_cursor: None,
            trigger_high: false,
            status_after_silence: false,
            vsync: [VsyncTracker::new(DEFAULT_REFRESH_US); N],
            out: Outbox::new(),
            next_heartbeat_us: 0,
        })
    }

    /// A VSYNC edge of `projector` at `timestamp_us` (edges of unknown projectors are ignored).
    pub fn on_vsync(&mut self, projector: u8, timestamp_us: u64) {
        let Some(tracker) = self.vsync.get_mut(usize::from(projector)) else {
            return;
        };
        tracker.on_edge(timestamp_us);
        if let (Some(run), Some(schedule)) = (self.run.as_mut(), self.schedule.as_ref()) {
            run.on_vsync(
                schedule,
                projector,
                timestamp_us,
                &self.vsync,
                &mut self.out,
            );
        }
    }

    /// Does everything that is due: trigger edges first, then time-driven rules, host
    /// messages, and sending. Returns the next time the controller must be polled (also set as
    /// the clock's alarm).
    pub fn poll(&mut self) -> Result<Option<u64>, Error<S::Error>> {
        let now = self.clock.now_us();
        self.trigger_edges(now)?;
        let now = self.clock.now_us();
        let active = match self.exposure.as_mut() {
            Some(pin) => Some(pin.is_high().map_err(|e| Error::Pin(e.kind()))?),
            None => None,
        };
        if let (Some(run), Some(schedule)) = (self.run.as_mut(), self.schedule.as_ref()) {
            run.tick(schedule, now, active, &self.vsync, &mut self.out);
            if run.stage() == Stage::Paused {
                self.status_after_silence = true;
            }
        }
        self.receive(now)?;
        self.report_end_of_run();
        self.heartbeat(now);
        if !self.io_guarded(now) {
            self.flush()?;
        }
        let next = self.next_deadline(now);
        if let Some(at) = next {
            self.clock.set_alarm(at);
        }
        Ok(next)
    }

    /// The state the host sees.
    pub fn state(&self) -> ControllerState {
        if !self.identified {
            return ControllerState::Unidentified;
        }
        match self.run.as_ref().map(Run::stage) {
            Some(Stage::Finished(_)) => ControllerState::Finished,
            Some(Stage::Paused) => ControllerState::Paused,
            Some(_) => ControllerState::Running,
            None if self.loader.is_loading() => ControllerState::Loading,
            None if self.armed => ControllerState::Armed,
            None if self.schedule.is_some() => ControllerState::Ready,
            None => ControllerState::Idle,
        }
    }

    /// True when the board may sleep until its next VSYNC interrupt: a run is in progress and
    /// only waits for VSYNC edges or a planned exposure end more than [`SLEEP_GUARD_US`] away,
    /// with no host answer outstanding and nothing left to send. (Under QEMU's
    /// `-icount sleep=off` such a sleep costs no real time; while the host is expected to
    /// answer, the board must keep running instructions so virtual time follows real time.)
    pub fn may_sleep(&mut self) -> bool {
        let now = self.clock.now_us();
        let feedback = self.exposure.is_some();
        self.out.is_empty()
            && self
                .run
                .as_ref()
                .is_some_and(|run| run.waits_for_edges_only(now, feedback, SLEEP_GUARD_US))
    }

    /// The (frame, attempt) of a pattern request that has been sent and not yet confirmed by
    /// the host (see [`Run::awaited_ack`]): the only host answer a run's timing depends on.
    /// `None` while the request is still in the outbox.
    pub fn awaits_host(&self) -> Option<(u16, u8)> {
        if !self.out.is_empty() {
            return None;
        }
        self.run.as_ref().and_then(Run::awaited_ack)
    }

    /// The VSYNC tracker of each projector.
    pub fn vsync(&self) -> &[VsyncTracker; N] {
        &self.vsync
    }

    /// The board's peripherals back (tests inspect them).
    pub fn release(self) -> (S, T, Option<X>, C) {
        (self.serial, self.trigger, self.exposure, self.clock)
    }

    /// Fires a due trigger edge and ends a due pulse, waiting on the clock for the exact time.
    fn trigger_edges(&mut self, now: u64) -> Result<(), Error<S::Error>> {
        let (Some(run), Some(schedule)) = (self.run.as_mut(), self.schedule.as_ref()) else {
            return Ok(());
        };
        if let Some(plan) = run.trigger_due(now, TRIGGER_SPIN_US) {
            let at = self.clock.wait_until(plan.trigger_at_us);
            if let FireDecision::Fire { .. } = run.fire(schedule, at, &self.vsync, &mut self.out) {
                self.trigger.set_high().map_err(|e| Error::Pin(e.kind()))?;
                self.trigger_high = true;
            }
        }
        let now = self.clock.now_us();
        if let Some(low_at) = run.pulse_low_at()
            && now + TRIGGER_SPIN_US >= low_at
        {
            self.clock.wait_until(low_at);
            self.trigger.set_low().map_err(|e| Error::Pin(e.kind()))?;
            self.trigger_high = false;
            run.pulse_ended();
        }
        // Safety net: the output never stays high outside a pulse (e.g. an abort mid-pulse).
        if self.trigger_high && run.pulse_low_at().is_none() {
            self.trigger.set_low().map_err(|e| Error::Pin(e.kind()))?;
            self.trigger_high = false;
        }
        Ok(())
    }

    /// Reads what the host sent and handles every completed frame.
    fn receive(&mut self, now: u64) -> Result<(), Error<S::Error>> {
        if !self.serial.read_ready().map_err(Error::Serial)? {
            return Ok(());
        }
        let mut buf = [0u8; READ_CHUNK];
        let n = self.serial.read(&mut buf).map_err(Error::Serial)?;
        for &byte in &buf[..n] {
            if let Some(frame) = self.decoder.push_byte(byte) {
                self.handle_frame(frame, now);
            }
        }
        Ok(())
    }

    fn handle_frame(&mut self, frame: Result<Received<HostMessage>, FrameError>, now: u64) {
        // Rejected frames are counted by the decoder and reported in `LinkStats`; the host
        // repeats what it does not see acked.
        let Ok(Received { seq, message, .. }) = frame else {
            return;
        };
        if let Some(run) = self.run.as_mut() {
            run.on_host_message(now);
        }
        if core::mem::take(&mut self.status_after_silence)
            && !matches!(message, HostMessage::Hello(_))
        {
            self.push(ControllerMessage::Status(self.status(now)));
        }
        match message {
            HostMessage::Hello(hello) => self.on_hello(seq, hello, now),
            HostMessage::Heartbeat(_) => {}
            _ if !self.identified => self.nack(seq, ErrorCode::NotIdentified),
            message => {
                let result = self.on_command(seq, &message, now);
                match result {
                    Ok(()) => {}
                    Err(code) => self.nack(seq, code),
                }
            }
        }
    }

    fn on_hello(&mut self, seq: u16, hello: Hello, now: u64) {
        self.push(ControllerMessage::HelloReply(HelloReply {
            protocol_version: PROTOCOL_VERSION,
            schema_hash: SCHEMA_HASH,
            board: self.info.board,
            firmware_version: self.info.firmware_version,
            projectors: N as u8,
            timer_tick_ns: self.info.timer_tick_ns,
        }));
        let refusal = if hello.protocol_version != PROTOCOL_VERSION {
            Some(ErrorCode::ProtocolVersionMismatch)
        } else if hello.schema_hash != SCHEMA_HASH {
            Some(ErrorCode::SchemaHashMismatch)
        } else {
            None
        };
        if let Some(code) = refusal {
            self.identified = false;
            self.nack(seq, code);
            return;
        }
        self.identified = true;
        self.status_after_silence = false;
        if self.run.is_some() {
            // A host reconnecting mid-run (or after it) learns where the run is.
            self.push(ControllerMessage::Status(self.status(now)));
        }
    }

    /// A command of an identified host; the Ack is queued before anything the command causes.
    fn on_command(&mut self, seq: u16, message: &HostMessage, now: u64) -> Result<(), ErrorCode> {
        let running = self.run.as_ref().is_some_and(|r| !r.is_finished());
        match message {
            HostMessage::ScheduleBegin(header) => {
                if running {
                    return Err(ErrorCode::InvalidState);
                }
                self.schedule = None;
                self.armed = false;
                self.run = None;
                self.loader.begin(*header)?;
                self.ack(seq);
            }
            HostMessage::ScheduleChunk(chunk) => {
                self.loader.chunk(chunk, N as u8)?;
                self.ack(seq);
            }
            HostMessage::ScheduleCommit(commit)
                if !self.loader.is_loading() && self.is_committed(commit) =>
            {
                // A resent commit whose Ack the host did not see in time.
                self.ack(seq);
            }
            HostMessage::ScheduleCommit(commit) => {
                self.schedule = Some(self.loader.commit(commit)?);
                log!(info, "schedule of {} frames committed", commit.frame_count);
                self.ack(seq);
            }
            HostMessage::Arm => {
                let schedule = self.schedule.as_ref().ok_or(ErrorCode::InvalidState)?;
                if running {
                    return Err(ErrorCode::InvalidState);
                }
                let nominal = schedule.header.refresh_period_us;
                self.vsync.iter_mut().for_each(|v| v.reset(nominal));
                self.run = None;
                self.armed = true;
                self.ack(seq);
            }
            HostMessage::Start => {
                if self.schedule.is_none() || !self.armed || running {
                    return Err(ErrorCode::InvalidState);
                }
                self.ack(seq);
                self.armed = false;
                self.done_sent = false;
                self.drop_cursor = None;
                if let Some(schedule) = self.schedule.as_ref() {
                    log!(
                        info,
                        "run of {} frames starts at {} us",
                        schedule.frame_count(),
                        now
                    );
                    self.run = Some(Run::start(schedule, now, &mut self.out));
                }
            }
            HostMessage::Abort => {
                self.ack(seq);
                self.armed = false;
                if let Some(run) = self.run.as_mut() {
                    run.abort(&mut self.out);
                }
            }
            HostMessage::StatusQuery => {
                self.ack(seq);
                self.push(ControllerMessage::Status(self.status(now)));
                self.push_projector_timing();
            }
            HostMessage::PatternShown(shown) => {
                let (Some(run), Some(schedule)) = (self.run.as_mut(), self.schedule.as_ref())
                else {
                    return Err(ErrorCode::UnexpectedPatternShown);
                };
                run.on_shown(schedule, shown, now)?;
                self.ack(seq);
            }
            HostMessage::Resume => {
                let (Some(run), Some(schedule)) = (self.run.as_mut(), self.schedule.as_ref())
                else {
                    return Err(ErrorCode::InvalidState);
                };
                // Ack first, then the new request that resuming queues.
                if run.stage() != Stage::Paused {
                    return Err(ErrorCode::InvalidState);
                }
                let _ = self.out.push_back(ControllerMessage::Ack(Ack { seq }));
                run.resume(schedule, now, &mut self.out);
            }
            HostMessage::Retrigger(rt) => {
                let (Some(run), Some(schedule)) = (self.run.as_mut(), self.schedule.as_ref())
                else {
                    return Err(ErrorCode::RetriggerNotTriggered);
                };
                run.check_retrigger(schedule, rt)?;
                // Ack first, then what the re-run queues (an extended run's request at once).
                let _ = self.out.push_back(ControllerMessage::Ack(Ack { seq }));
                let was_finished = run.is_finished();
                run.retrigger(schedule, rt, now, &mut self.out);
                if was_finished && !run.is_finished() {
                    // The extended run ends with its own Done.
                    self.done_sent = false;
                    self.drop_cursor = None;
                }
            }
            HostMessage::Hello(_) | HostMessage::Heartbeat(_) => {}
        }
        Ok(())
    }

    /// True when `commit` describes the committed schedule and no run has used it yet.
    fn is_committed(&self, commit: &ScheduleCommit) -> bool {
        self.run.is_none()
            && self.schedule.as_ref().is_some_and(|s| {
                commit.frame_count == s.frame_count()
                    && commit.checksum == mlsss_shared::schedule_checksum(&s.entries)
            })
    }

    /// Queues `Done` and the measured projector timing once, when the run has ended.
    fn report_end_of_run(&mut self) {
        let Some(run) = self.run.as_ref() else {
            return;
        };
        let Stage::Finished(outcome) = run.stage() else {
            return;
        };
        if self.done_sent {
            return;
        }
        let frame_count = self.schedule.as_ref().map_or(0, Schedule::frame_count);
        // The frames after the one in flight are never requested: each is reported dropped
        // before `Done` (a few per poll, the outbox is small), so none is lost silently.
        let not_reached = if outcome == RunOutcome::Completed {
            0
        } else {
            let first = run.next_unrun();
            let mut next = self.drop_cursor.unwrap_or(first);
            while next < frame_count && self.out.len() + DONE_MESSAGES < self.out.capacity() {
                let dropped = FrameDropped {
                    frame: next,
                    reason: DropReason::RunAborted,
                };
                let _ = self.out.push_back(ControllerMessage::FrameDropped(dropped));
                next += 1;
            }
            self.drop_cursor = Some(next);
            if next < frame_count {
                return;
            }
            frame_count.saturating_sub(first)
        };
        self.done_sent = true;
        let stats = run.stats();
        log!(
            info,
            "run done: {}, {} triggered, {} late, {} dropped",
            defmt::Debug2Format(&outcome),
            stats.triggered,
            stats.late,
            stats.dropped + not_reached
        );
        let summary = DoneSummary {
            outcome,
            frames_triggered: stats.triggered,
            frames_late: stats.late,
            frames_retried: stats.retried,
            frames_dropped: stats.dropped + not_reached,
            first_trigger_us: stats.first_trigger_us.unwrap_or(0),
            last_trigger_us: stats.last_trigger_us.unwrap_or(0),
            link: self.link_stats(),
        };
        self.push(ControllerMessage::Done(summary));
        self.push_projector_timing();
    }

    fn push_projector_timing(&mut self) {
        for (projector, v) in self.vsync.iter().enumerate() {
            let timing = ProjectorTiming {
                projector: projector as u8,
                vsync_count: v.count(),
                period_ns: v.period_ns(),
            };
            debug_assert!(!self.out.is_full(), "outbox full");
            let _ = self
                .out
                .push_back(ControllerMessage::ProjectorTiming(timing));
        }
    }

    fn heartbeat(&mut self, now: u64) {
        if !self.identified || now < self.next_heartbeat_us {
            return;
        }
        self.next_heartbeat_us = now + HEARTBEAT_US;
        let state = self.state();
        self.push(ControllerMessage::Heartbeat(ControllerHeartbeat {
            timestamp_us: now,
            state,
        }));
    }

    fn status(&self, now: u64) -> StatusReport {
        StatusReport {
            state: self.state(),
            schedule_frames: self.schedule.as_ref().map_or(0, Schedule::frame_count),
            next_frame: self.run.as_ref().map_or(0, Run::frame),
            frames_triggered: self.run.as_ref().map_or(0, |r| r.stats().triggered),
            timestamp_us: now,
            link: self.link_stats(),
        }
    }

    fn link_stats(&self) -> LinkStats {
        self.decoder.stats().into()
    }

    /// True while a trigger edge is close: sending could delay it.
    fn io_guarded(&self, now: u64) -> bool {
        match self.run.as_ref().map(Run::stage) {
            Some(Stage::Armed(plan)) => now + IO_GUARD_US >= plan.trigger_at_us,
            Some(Stage::Pulse { .. }) => true,
            _ => false,
        }
    }

    fn next_deadline(&self, now: u64) -> Option<u64> {
        let run = self
            .run
            .as_ref()
            .zip(self.schedule.as_ref())
            .and_then(|(run, schedule)| {
                // The exposure-active input has no interrupt: sample it while the camera exposes.
                if self.exposure.is_some() && matches!(run.stage(), Stage::Exposing { .. }) {
                    return Some(now + EXPOSURE_SAMPLE_US);
                }
                run.next_deadline(schedule, &self.vsync, TRIGGER_SPIN_US)
            });
        let heartbeat = self.identified.then_some(self.next_heartbeat_us);
        match (run, heartbeat) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    fn flush(&mut self) -> Result<(), Error<S::Error>> {
        let mut buf = [0u8; MAX_WIRE_FRAME_LEN];
        while let Some(message) = self.out.pop_front() {
            let (_, bytes) = self
                .encoder
                .encode(&message, &mut buf)
                .map_err(Error::Encode)?;
            self.serial.write_all(bytes).map_err(Error::Serial)?;
        }
        self.serial.flush().map_err(Error::Serial)
    }

    fn push(&mut self, message: ControllerMessage) {
        debug_assert!(!self.out.is_full(), "outbox full");
        let _ = self.out.push_back(message);
    }

    fn ack(&mut self, seq: u16) {
        self.push(ControllerMessage::Ack(Ack { seq }));
    }

    fn nack(&mut self, seq: u16, error: ErrorCode) {
        log!(warn, "nack seq {}: {}", seq, defmt::Debug2Format(&error));
        self.push(ControllerMessage::Nack(Nack { seq, error }));
    }
}

/// The exposure-active input of a board whose camera has none (never read).
#[derive(Debug, Clone, Copy, Default)]
pub struct NoExposureInput;

impl embedded_hal::digital::ErrorType for NoExposureInput {
    type Error = core::convert::Infallible;
}

impl InputPin for NoExposureInput {
    fn is_high(&mut self) -> Result<bool, Self::Error> {
        Ok(false)
    }

    fn is_low(&mut self) -> Result<bool, Self::Error> {
        Ok(true)
    }
}
