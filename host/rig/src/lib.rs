//! Rig control (DESIGN section 7): talking to the booth controller over the wire protocol of
//! `mlsss-shared`, running a capture schedule, and measuring its timing.
//!
//! - [`link`]: framing, sequence numbers, command/answer matching, fault injection.
//! - [`session`]: handshake, schedule upload, the run loop.
//! - [`schedule`]: frame plan + booth timing -> the schedule on the wire.
//! - [`backend`]: projector output and camera input behind small traits (virtual, replay).
//! - [`camera`]: real cameras: USB3 Vision through cameleon, payload decoding and matching.
//! - [`display`]: projector output windows on real monitors (winit + softbuffer).
//! - [`acquire`]: a run that writes a capture folder.
//! - [`metering`]: the metering step before a scan: one white per projector, the exposure from it.
//! - [`timing`]: timing statistics of a run (the `rig timing-test` report).
//! - [`pattern_label`]: patterns by capture label (`rig show`).
//! - [`qemu`]: the real firmware image under QEMU, as an emulated controller.
//! - [`ports`]: finding controllers on serial ports and USB.

pub mod acquire;
pub mod backend;
pub mod camera;
pub mod display;
pub mod link;
pub mod metering;
pub mod pattern_label;
pub mod ports;
pub mod qemu;
pub mod schedule;
pub mod session;
pub mod timing;

use std::path::PathBuf;
use std::time::Duration;

use mlsss_shared::message::ErrorCode;

/// Errors of rig control.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RigError {
    /// Reading or writing the transport failed.
    #[error("controller link I/O: {0}")]
    Io(#[source] std::io::Error),
    /// Opening or configuring a serial port failed.
    #[error("serial port: {0}")]
    Serial(#[source] serialport::Error),
    /// A message did not fit a frame (a bug: every message type fits by construction).
    #[error("encoding a message: {0}")]
    Encode(mlsss_shared::framing::EncodeError),
    /// The controller speaks another protocol version.
    #[error(
        "protocol version mismatch: host speaks {host}, controller speaks {controller}; \
         flash firmware built from the same source as this mlsss"
    )]
    ProtocolMismatch {
        /// Host version.
        host: u16,
        /// Controller version.
        controller: u16,
    },
    /// Same version, different message definitions.
    #[error(
        "protocol schema mismatch: host {host:#010x}, controller {controller:#010x}; \
         flash firmware built from the same source as this mlsss"
    )]
    SchemaMismatch {
        /// Host schema hash.
        host: u32,
        /// Controller schema hash.
        controller: u32,
    },
    /// The controller refused a command with a typed error.
    #[error("controller refused {command}: {error:?}")]
    Refused {
        /// The refused command.
        command: &'static str,
        /// The controller's reason.
        error: ErrorCode,
    },
    /// A command got neither Ack nor Nack.
    #[error("no answer to {command} after {attempts} attempt(s): is the controller connected?")]
    NoAnswer {
        /// The command.
        command: &'static str,
        /// How many times it was sent.
        attempts: u32,
    },
    /// A running controller sent nothing for too long.
    #[error("the controller has been silent for {0:?}")]
    ControllerSilent(Duration),
    /// A running controller kept talking but the run made no progress for too long.
    #[error("the run made no progress for {0:?} (controller state stuck): aborted")]
    RunStalled(Duration),
    /// The event stream ended without a `Done` summary.
    #[error("the run ended without a Done summary")]
    NoDone,
    /// The frame plan has a frame with no lit projector, which the controller cannot sequence.
    #[error(
        "frame {0} has no lit projector; the rig only runs plans with one lit projector per frame"
    )]
    DarkFrame(u32),
    /// More distinct patterns than a pattern id can name.
    #[error("more than 65535 distinct patterns in the plan")]
    TooManyPatterns,
    /// A metered exposure names a projector the protocol cannot address.
    #[error("projector {projector}: the controller drives at most {max} projectors")]
    TooManyProjectors {
        /// The projector.
        projector: u8,
        /// The protocol's limit.
        max: usize,
    },
    /// More frames than the protocol can number.
    #[error("{0} frames: the protocol numbers at most 65535")]
    TooManyFrames(usize),
    /// The firmware image is not there.
    #[error(
        "firmware image {path} not found: build it with `{build}` (or run scripts/test.sh), or pass --firmware PATH"
    )]
    FirmwareMissing {
        /// Where it was looked for.
        path: PathBuf,
        /// The command that builds it.
        build: &'static str,
    },
    /// `qemu-system-arm` is not installed.
    #[error("qemu-system-arm not found: install it with `apt-get install qemu-system-arm`")]
    QemuMissing,
    /// QEMU could not be started.
    #[error("starting qemu-system-arm: {0}")]
    QemuSpawn(#[source] std::io::Error),
    /// QEMU exited while the host was talking to it.
    #[error("qemu-system-arm exited unexpectedly")]
    QemuExited,
    /// The pseudo-terminal for QEMU has no name.
    #[error("the pseudo-terminal for QEMU has no device name")]
    PtyName,
    /// The controller asked for a pattern id or frame the schedule does not have.
    #[error(
        "controller requested frame {frame} / pattern {pattern}, which the schedule does not have"
    )]
    UnknownRequest {
        /// Requested frame.
        frame: u16,
        /// Requested pattern id.
        pattern: u16,
    },
    /// The camera payload of a triggered frame was lost, incomplete or unusable; the frame can
    /// be run again (`acquire` re-triggers it).
    #[error("{backend} backend: {message}")]
    PayloadLost {
        /// Which backend.
        backend: &'static str,
        /// The frame whose payload is missing.
        frame: u32,
        /// What happened.
        message: String,
    },
    /// A camera or projector backend failed.
    #[error("{backend} backend: {message}")]
    Backend {
        /// Which backend.
        backend: &'static str,
        /// What went wrong.
        message: String,
    },
    /// The booth maps a projector to a monitor the display server does not have.
    #[error(
        "projector {projector} maps to monitor {monitor}, which does not exist; monitors: {available}"
    )]
    MissingMonitor {
        /// The projector.
        projector: u8,
        /// The monitor it maps to.
        monitor: usize,
        /// The monitors that exist, described.
        available: String,
    },
    /// The display server could not be used (no `DISPLAY`, no X server, a window failed).
    #[error("display: {0}")]
    Display(String),
    /// A pattern label that names no pattern of the booth.
    #[error("unknown pattern label '{label}' (labels as in capture frame names, e.g. {examples})")]
    UnknownPattern {
        /// The label.
        label: String,
        /// Labels that exist.
        examples: String,
    },
    /// Writing the capture folder failed.
    #[error(transparent)]
    Capture(#[from] mlsss_core::capture::CaptureError),
}
