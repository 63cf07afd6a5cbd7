//! The messages exchanged between the host and the booth controller (DESIGN section 7).
//!
//! Compatibility rules (the wire format is postcard: enum variants are encoded by their index,
//! struct fields by their order):
//! - Every enum is **append-only**: new variants go at the end, existing variants are never
//!   reordered, removed or changed. Struct fields are never reordered or retyped.
//! - `HostMessage::Hello` and `ControllerMessage::HelloReply` are variant 0 and their layout is
//!   frozen for ever, so that two different protocol versions can always tell each other apart.
//! - Any change to this file changes [`crate::SCHEMA_HASH`]; an incompatible change also bumps
//!   [`crate::PROTOCOL_VERSION`].
//!
//! Units: times in microseconds (`_us`) of the controller's monotonic 64-bit clock, counts of
//! VSYNC edges per projector, frame indices from 0 in capture order.

use postcard::experimental::max_size::MaxSize;
use serde::{Deserialize, Serialize};

/// Most frames one schedule can hold (the controller stores the whole schedule in RAM).
pub const MAX_SCHEDULE_FRAMES: usize = 1024;
/// Schedule entries per [`ScheduleChunk`]; a 268-frame scan takes 9 chunks.
pub const SCHEDULE_CHUNK_LEN: usize = 32;
/// Most projectors a controller drives.
pub const MAX_PROJECTORS: usize = 8;

/// A bounded vector (heapless, no allocation) with a compile-time postcard size bound.
///
/// postcard only implements [`MaxSize`] for the older heapless 0.7, hence this thin wrapper.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(transparent)]
pub struct BoundedVec<T, const N: usize>(pub heapless::Vec<T, N>);

impl<T: MaxSize, const N: usize> MaxSize for BoundedVec<T, N> {
    // A varint length prefix (at most 5 bytes for a usize that fits in u32) then N elements.
    const POSTCARD_MAX_SIZE: usize = varint_max_len(N) + N * T::POSTCARD_MAX_SIZE;
}

/// Bytes of a postcard varint encoding `n`.
const fn varint_max_len(n: usize) -> usize {
    let mut len = 1;
    let mut rest = n >> 7;
    while rest > 0 {
        len += 1;
        rest >>= 7;
    }
    len
}

impl<T, const N: usize> BoundedVec<T, N> {
    /// An empty vector.
    pub const fn new() -> Self {
        Self(heapless::Vec::new())
    }

    /// Builds from a slice; `None` when the slice is longer than `N`.
    pub fn from_slice(items: &[T]) -> Option<Self>
    where
        T: Clone,
    {
        heapless::Vec::from_slice(items).ok().map(Self)
    }

    /// The elements.
    pub fn as_slice(&self) -> &[T] {
        &self.0
    }
}

// ---------------------------------------------------------------------------------------------
// Host -> controller
// ---------------------------------------------------------------------------------------------

/// Every message the host sends to the controller. Append-only.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub enum HostMessage {
    /// Opens (or re-opens after a disconnect) a session. Layout frozen (variant 0).
    Hello(Hello),
    /// Starts a schedule upload; discards any schedule not yet armed.
    ScheduleBegin(ScheduleHeader),
    /// A run of consecutive schedule entries, sent in order after [`HostMessage::ScheduleBegin`].
    ScheduleChunk(ScheduleChunk),
    /// Ends the upload; the controller validates the whole schedule and acks or nacks.
    ScheduleCommit(ScheduleCommit),
    /// Prepares the committed schedule for a run (timers armed, VSYNC measurement started).
    Arm,
    /// Starts the armed run at the next slot boundary.
    Start,
    /// Stops the run now; the controller answers with [`ControllerMessage::Done`].
    Abort,
    /// Asks for a [`ControllerMessage::Status`].
    StatusQuery,
    /// The host has put the requested pattern on the projector (the controller may now count the
    /// settle VSYNCs and trigger).
    PatternShown(PatternShown),
    /// Host liveness while nothing else is sent; the controller pauses a run when the host is
    /// silent for longer than the schedule's `host_silence_timeout_us`.
    Heartbeat(HostHeartbeat),
    /// Continues a run paused by host silence, from the controller's `next_frame`.
    Resume,
    /// The camera payload of a triggered frame was lost or incomplete: run the frame again (a
    /// new attempt, in the next free slot; after the last frame the run is extended by it).
    Retrigger(Retrigger),
}

/// Protocol identification, sent by the host first. Layout frozen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct Hello {
    /// [`crate::PROTOCOL_VERSION`] of the sender.
    pub protocol_version: u16,
    /// [`crate::SCHEMA_HASH`] of the sender.
    pub schema_hash: u32,
}

/// What the controller does when a frame's slot is missed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub enum ExhaustedAction {
    /// Abort the whole run.
    Abort,
    /// Report the frame dropped and go on with the next one.
    Drop,
}

/// Retry/abort policy for late frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct RetryPolicy {
    /// How many later slots a late frame may be retried in (0: never retried).
    pub max_retries: u8,
    /// What happens once the retries are used up.
    pub when_exhausted: ExhaustedAction,
}

/// The timing of a run and its length; sent once per upload.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct ScheduleHeader {
    /// Frames in the schedule (1..=[`MAX_SCHEDULE_FRAMES`]).
    pub frame_count: u16,
    /// Frame slot length (200 000 at 5 fps).
    pub period_us: u32,
    /// Nominal projector refresh period (16 667 at 60 Hz), for validating the timing.
    pub refresh_period_us: u32,
    /// Exposure as a whole number of refresh periods.
    pub exposure_periods: u8,
    /// VSYNCs of the lit projector to wait after the host's shown-ack before triggering.
    pub settle_vsyncs: u8,
    /// Delay of the trigger edge after the VSYNC edge it is aligned to.
    pub trigger_phase_us: u32,
    /// Trigger pulse width.
    pub trigger_width_us: u32,
    /// How long after a pattern request the shown-ack may arrive and still make the slot.
    pub ack_timeout_us: u32,
    /// Host silence (no message at all) after which a running schedule pauses.
    pub host_silence_timeout_us: u32,
    /// Late-frame policy.
    pub policy: RetryPolicy,
    /// Exposure of each projector's frames (metered per projector before the scan); an entry
    /// with `exposure_periods == 0` uses `exposure_periods` and `trigger_width_us` above.
    pub projector_exposure: [ProjectorExposure; MAX_PROJECTORS],
}

/// The exposure of one projector's frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, MaxSize)]
pub struct ProjectorExposure {
    /// Exposure as a whole number of the projector's refresh periods (0: the header's).
    pub exposure_periods: u8,
    /// Trigger pulse width (a camera in trigger-width mode exposes while the pulse is high).
    pub trigger_width_us: u32,
}

/// One frame of the schedule: which projector is lit with which pattern.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct ScheduleEntry {
    /// The lit projector (0-based); the others show black.
    pub projector: u8,
    /// Host-side pattern identifier (index in the host's pattern table), echoed back in requests.
    pub pattern: u16,
}

/// Consecutive schedule entries starting at `first_frame`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct ScheduleChunk {
    /// Frame index of `entries[0]`; chunks must arrive in order without holes.
    pub first_frame: u16,
    /// At most [`SCHEDULE_CHUNK_LEN`] entries.
    pub entries: BoundedVec<ScheduleEntry, SCHEDULE_CHUNK_LEN>,
}

/// Closes an upload.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct ScheduleCommit {
    /// Frames sent, must equal the header's `frame_count`.
    pub frame_count: u16,
    /// [`crate::schedule_checksum`] of all entries in order.
    pub checksum: u32,
}

/// The host's confirmation that a requested pattern is on screen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct PatternShown {
    /// Frame index from the [`PatternRequest`].
    pub frame: u16,
    /// Attempt number from the [`PatternRequest`].
    pub attempt: u8,
    /// Pattern identifier from the [`PatternRequest`] (checked by the controller).
    pub pattern: u16,
}

/// A request to run a triggered frame again.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct Retrigger {
    /// Frame index.
    pub frame: u16,
    /// The attempt whose payload was lost (from its [`Triggered`]); the re-run is `attempt + 1`.
    pub attempt: u8,
}

/// Host liveness.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct HostHeartbeat {
    /// Host monotonic time, microseconds (for logs only).
    pub host_time_us: u64,
}

// ---------------------------------------------------------------------------------------------
// Controller -> host
// ---------------------------------------------------------------------------------------------

/// Every message the controller sends to the host. Append-only.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub enum ControllerMessage {
    /// Answer to [`HostMessage::Hello`]. Layout frozen (variant 0).
    HelloReply(HelloReply),
    /// A host message was accepted.
    Ack(Ack),
    /// A host message was refused.
    Nack(Nack),
    /// Show this pattern now and answer with [`HostMessage::PatternShown`].
    PatternRequest(PatternRequest),
    /// The camera trigger fired for a frame.
    Triggered(Triggered),
    /// The exposure of a frame ended.
    ExposureDone(ExposureDone),
    /// A frame missed its slot.
    FrameLate(FrameLate),
    /// A late frame is tried again in a later slot.
    FrameRetried(FrameRetried),
    /// A frame is given up (never triggered).
    FrameDropped(FrameDropped),
    /// Receive-side statistics of the controller's link.
    LinkStats(LinkStats),
    /// The run ended (completed or aborted).
    Done(DoneSummary),
    /// Controller liveness, sent periodically.
    Heartbeat(ControllerHeartbeat),
    /// Answer to [`HostMessage::StatusQuery`], and sent unasked after a host reconnects.
    Status(StatusReport),
    /// Measured VSYNC rate of one projector (projectors are not genlocked).
    ProjectorTiming(ProjectorTiming),
}

/// Controller identification. Layout frozen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct HelloReply {
    /// [`crate::PROTOCOL_VERSION`] of the controller.
    pub protocol_version: u16,
    /// [`crate::SCHEMA_HASH`] of the controller.
    pub schema_hash: u32,
    /// Which board runs the firmware.
    pub board: Board,
    /// Firmware version (major, minor, patch).
    pub firmware_version: [u8; 3],
    /// Projectors (VSYNC inputs) this board drives.
    pub projectors: u8,
    /// Resolution of the trigger timer, nanoseconds.
    pub timer_tick_ns: u32,
}

/// The board the firmware runs on. Append-only.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub enum Board {
    /// QEMU `mps2-an386` (Cortex-M4), VSYNCs generated by timers.
    QemuMps2An386,
    /// STM32F4 Nucleo board.
    Stm32f4Nucleo,
    /// The sequencer core running on the host (tests).
    HostSimulation,
}

/// Acceptance of the host message with sequence number `seq`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct Ack {
    /// Frame sequence number of the accepted host message.
    pub seq: u16,
}

/// Refusal of the host message with sequence number `seq`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct Nack {
    /// Frame sequence number of the refused host message.
    pub seq: u16,
    /// Why.
    pub error: ErrorCode,
}

/// Why the controller refused a host message. Append-only.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub enum ErrorCode {
    /// The host speaks another protocol version.
    ProtocolVersionMismatch,
    /// Same version, different message definitions.
    SchemaHashMismatch,
    /// A command arrived before a successful `Hello`.
    NotIdentified,
    /// The command is not valid in the controller's current state.
    InvalidState,
    /// The schedule has zero frames.
    ScheduleEmpty,
    /// The schedule has more than [`MAX_SCHEDULE_FRAMES`] frames.
    ScheduleTooLong,
    /// An entry names a projector the board does not have.
    UnknownProjector,
    /// The period cannot hold settle + phase + exposure.
    PeriodTooShort,
    /// Exposure of zero periods, or a trigger width of zero or longer than the exposure.
    InvalidExposure,
    /// A chunk does not start where the previous one ended, or overruns `frame_count`.
    ChunkOutOfOrder,
    /// The commit's frame count or checksum does not match what was received.
    ScheduleMismatch,
    /// A shown-ack names a frame, attempt or pattern that is not the one requested.
    UnexpectedPatternShown,
    /// A re-trigger names a frame that has not been triggered yet (or not in this run).
    RetriggerNotTriggered,
    /// Too many re-triggers are waiting for a slot.
    RetriggerQueueFull,
}

/// The controller wants a pattern on screen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct PatternRequest {
    /// Frame index.
    pub frame: u16,
    /// 0 for the first try, then 1, 2, ... for retries.
    pub attempt: u8,
    /// The projector to light.
    pub projector: u8,
    /// Pattern identifier from the schedule.
    pub pattern: u16,
}

/// A camera trigger edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct Triggered {
    /// Frame index.
    pub frame: u16,
    /// Attempt that made it (0 when on time).
    pub attempt: u8,
    /// The lit projector.
    pub projector: u8,
    /// Time of the trigger edge.
    pub timestamp_us: u64,
    /// VSYNC count of the lit projector at the VSYNC the trigger is aligned to.
    pub vsync_count: u32,
    /// Time of that VSYNC edge.
    pub vsync_timestamp_us: u64,
    /// VSYNC count of the lit projector when the host's shown-ack arrived (settle is counted from
    /// here: `vsync_count - shown_vsync_count >= settle_vsyncs`).
    pub shown_vsync_count: u32,
}

/// End of an exposure.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct ExposureDone {
    /// Frame index.
    pub frame: u16,
    /// Time the exposure ended (trigger + exposure, or the camera's exposure-active falling edge).
    pub timestamp_us: u64,
}

/// Why a frame missed its slot. Append-only.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub enum LateReason {
    /// The host's shown-ack came after `ack_timeout_us`.
    AckLate,
    /// No VSYNC of the lit projector arrived when expected.
    VsyncMissing,
    /// The host was silent for longer than `host_silence_timeout_us`.
    HostSilent,
    /// The controller could not fire within its tolerance of VSYNC + phase (it was busy), so
    /// the frame was not exposed off its VSYNC.
    TriggerMissed,
    /// The camera's exposure-active input never went high after the trigger.
    ExposureMissing,
}

/// A frame missed its slot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct FrameLate {
    /// Frame index.
    pub frame: u16,
    /// Attempt that was late.
    pub attempt: u8,
    /// Why.
    pub reason: LateReason,
}

/// A late frame is tried again.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct FrameRetried {
    /// Frame index.
    pub frame: u16,
    /// The new attempt number.
    pub attempt: u8,
}

/// Why a frame was given up. Append-only.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub enum DropReason {
    /// All retries were late.
    RetriesExhausted,
    /// The run was aborted before the frame was triggered.
    RunAborted,
}

/// A frame given up.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct FrameDropped {
    /// Frame index.
    pub frame: u16,
    /// Why.
    pub reason: DropReason,
}

/// Receive-side counters of a link endpoint (see [`crate::framing::DecoderStats`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, MaxSize)]
pub struct LinkStats {
    /// Frames decoded and accepted.
    pub frames_ok: u32,
    /// Frames whose CRC did not match.
    pub crc_errors: u32,
    /// Frames that were not valid COBS, too short, or did not deserialise.
    pub malformed: u32,
    /// Frames longer than the receive buffer.
    pub oversize: u32,
    /// Sequence numbers missing between accepted frames.
    pub sequence_gaps: u32,
    /// Times the decoder discarded bytes and resynchronised at a delimiter.
    pub resyncs: u32,
}

/// How a run ended. Append-only.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub enum RunOutcome {
    /// Every frame was triggered or dropped per policy.
    Completed,
    /// The host sent `Abort`.
    AbortedByHost,
    /// A frame ran out of retries and the policy is `Abort`.
    AbortedRetriesExhausted,
    /// The host stayed silent and never resumed.
    AbortedHostSilent,
}

/// Summary sent when a run ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct DoneSummary {
    /// How the run ended.
    pub outcome: RunOutcome,
    /// Frames triggered.
    pub frames_triggered: u16,
    /// Late reports.
    pub frames_late: u16,
    /// Retries.
    pub frames_retried: u16,
    /// Frames dropped.
    pub frames_dropped: u16,
    /// Time of the first trigger.
    pub first_trigger_us: u64,
    /// Time of the last trigger.
    pub last_trigger_us: u64,
    /// The controller's receive counters at the end.
    pub link: LinkStats,
}

/// The controller's state machine. Append-only.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub enum ControllerState {
    /// Waiting for `Hello`.
    Unidentified,
    /// Identified, no committed schedule.
    Idle,
    /// Receiving schedule chunks.
    Loading,
    /// A schedule is committed.
    Ready,
    /// Armed, waiting for `Start`.
    Armed,
    /// Running the schedule.
    Running,
    /// Paused by host silence; `Resume` continues, `Abort` ends.
    Paused,
    /// The run ended; a new schedule may be uploaded.
    Finished,
}

/// Controller liveness.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct ControllerHeartbeat {
    /// Controller clock.
    pub timestamp_us: u64,
    /// Current state.
    pub state: ControllerState,
}

/// Full state, for a host that (re)connects.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct StatusReport {
    /// Current state.
    pub state: ControllerState,
    /// Frames in the committed schedule (0 when none).
    pub schedule_frames: u16,
    /// Next frame to be requested.
    pub next_frame: u16,
    /// Frames triggered so far in this run.
    pub frames_triggered: u16,
    /// Controller clock.
    pub timestamp_us: u64,
    /// Receive counters.
    pub link: LinkStats,
}

/// Measured VSYNC timing of one projector.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, MaxSize)]
pub struct ProjectorTiming {
    /// Projector index.
    pub projector: u8,
    /// VSYNC edges counted since arming.
    pub vsync_count: u32,
    /// Mean measured refresh period, nanoseconds.
    pub period_ns: u32,
}
