//! The host end of the controller link: framing over a byte transport, sequence numbers,
//! request/answer matching (Ack/Nack by sequence number) and optional fault injection.

use std::collections::VecDeque;
use std::io::{self, Read, Write};
use std::time::{Duration, Instant};

use mlsss_shared::framing::{ControllerDecoder, DecoderStats, HostEncoder, MAX_WIRE_FRAME_LEN};
use mlsss_shared::message::ErrorCode;
use mlsss_shared::{ControllerMessage, HostMessage};

use super::RigError;

/// A byte transport to the controller (serial port, pty, socket).
pub trait ByteLink: Send {
    /// Writes all bytes.
    fn send_bytes(&mut self, bytes: &[u8]) -> io::Result<()>;
    /// Reads what is available, waiting at most `timeout`; `Ok(0)` when nothing came.
    fn recv_bytes(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize>;
}

impl<T: serialport::SerialPort + ?Sized> ByteLink for Box<T> {
    fn send_bytes(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.write_all(bytes)?;
        self.flush()
    }

    fn recv_bytes(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        self.set_timeout(timeout.max(Duration::from_millis(1)))
            .map_err(io::Error::other)?;
        match self.read(buf) {
            Ok(n) => Ok(n),
            Err(e) if e.kind() == io::ErrorKind::TimedOut => Ok(0),
            Err(e) => Err(e),
        }
    }
}

/// Faults the host injects into what it sends (hardware-in-the-loop tests).
#[derive(Debug, Clone, Default)]
pub struct LinkFaults {
    /// Before every `garbage_every`-th frame sent (1-based count), send `garbage` first.
    pub garbage_every: Option<u32>,
    /// The garbage bytes (may contain delimiters).
    pub garbage: Vec<u8>,
    /// Frames (0-based count of frames sent) whose bytes get one bit flipped.
    pub corrupt_frames: Vec<u32>,
}

/// Counters of the host end of the link.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct HostLinkStats {
    /// Receive-side decoder counters.
    pub decoder: DecoderStats,
    /// Frames sent.
    pub frames_sent: u32,
    /// Commands sent again because no Ack/Nack came in time.
    pub retransmissions: u32,
    /// Frames the fault injector corrupted.
    pub frames_corrupted: u32,
}

/// How long a command waits for its Ack/Nack before it is sent again.
const ANSWER_TIMEOUT: Duration = Duration::from_millis(500);
/// How many times a command is sent before the controller is declared unresponsive.
const SEND_ATTEMPTS: u32 = 4;

/// A framed, numbered connection to the controller.
pub struct ControllerLink<L: ByteLink> {
    transport: L,
    encoder: HostEncoder,
    decoder: Box<ControllerDecoder>,
    /// Messages received while waiting for something else, in arrival order.
    pending: VecDeque<ControllerMessage>,
    faults: LinkFaults,
    stats: HostLinkStats,
}

impl<L: ByteLink> ControllerLink<L> {
    /// Wraps a transport.
    pub fn new(transport: L) -> Self {
        Self {
            transport,
            encoder: HostEncoder::new(),
            decoder: Box::default(),
            pending: VecDeque::new(),
            faults: LinkFaults::default(),
            stats: HostLinkStats::default(),
        }
    }

    /// Injects faults into everything sent from now on.
    pub fn set_faults(&mut self, faults: LinkFaults) {
        self.faults = faults;
    }

    /// Host-side counters.
    pub fn stats(&self) -> HostLinkStats {
        HostLinkStats {
            decoder: self.decoder.stats(),
            ..self.stats
        }
    }

    /// Sends one message; returns its sequence number.
    pub fn send(&mut self, message: &HostMessage) -> Result<u16, RigError> {
        let mut buf = [0u8; MAX_WIRE_FRAME_LEN];
        let (seq, frame) = self
            .encoder
            .encode(message, &mut buf)
            .map_err(RigError::Encode)?;
        let mut frame = frame.to_vec();
        let count = self.stats.frames_sent;
        self.stats.frames_sent += 1;
        if let Some(every) = self.faults.garbage_every.filter(|&n| n > 0)
            && (count + 1).is_multiple_of(every)
        {
            let garbage = self.faults.garbage.clone();
            self.transport.send_bytes(&garbage).map_err(RigError::Io)?;
        }
        if self.faults.corrupt_frames.contains(&count) {
            // Flip a bit in the middle of the frame, never in the delimiter.
            let at = frame.len() / 2;
            frame[at] ^= 0x10;
            self.stats.frames_corrupted += 1;
        }
        self.transport.send_bytes(&frame).map_err(RigError::Io)?;
        Ok(seq)
    }

    /// Sends raw bytes (fault injection).
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<(), RigError> {
        self.transport.send_bytes(bytes).map_err(RigError::Io)
    }

    /// Next message from the controller, waiting at most `timeout`.
    pub fn recv(&mut self, timeout: Duration) -> Result<Option<ControllerMessage>, RigError> {
        if let Some(message) = self.pending.pop_front() {
            return Ok(Some(message));
        }
        let deadline = Instant::now() + timeout;
        loop {
            self.read_available(deadline.saturating_duration_since(Instant::now()))?;
            if let Some(message) = self.pending.pop_front() {
                return Ok(Some(message));
            }
            if Instant::now() >= deadline {
                return Ok(None);
            }
        }
    }

    /// Reads and decodes whatever arrives within `timeout` into the pending queue.
    fn read_available(&mut self, timeout: Duration) -> Result<(), RigError> {
        let mut buf = [0u8; 512];
        let n = self
            .transport
            .recv_bytes(&mut buf, timeout)
            .map_err(RigError::Io)?;
        // Rejected frames are counted by the decoder; a lost answer makes `command` resend.
        for received in self.decoder.feed(&buf[..n]).flatten() {
            self.pending.push_back(received.message);
        }
        Ok(())
    }

    /// Discards everything received so far and forgets the controller's sequence numbering
    /// (used when reconnecting).
    pub fn resync(&mut self) {
        self.pending.clear();
        self.decoder.reset_sequence();
    }

    /// Drops everything that arrives during `duration` (a host that is away).
    pub fn go_silent(&mut self, duration: Duration) -> Result<(), RigError> {
        let deadline = Instant::now() + duration;
        while Instant::now() < deadline {
            self.read_available(deadline.saturating_duration_since(Instant::now()))?;
            self.pending.clear();
        }
        Ok(())
    }

    /// Sends a command and waits for its Ack or Nack, resending when neither comes in time.
    /// Other messages that arrive meanwhile stay queued for [`ControllerLink::recv`].
    pub fn command(&mut self, message: &HostMessage) -> Result<(), RigError> {
        for attempt in 0..SEND_ATTEMPTS {
            if attempt > 0 {
                self.stats.retransmissions += 1;
            }
            let seq = self.send(message)?;
            match self.wait_answer(seq, ANSWER_TIMEOUT)? {
                Some(Ok(())) => return Ok(()),
                Some(Err(error)) => {
                    return Err(RigError::Refused {
                        command: command_name(message),
                        error,
                    });
                }
                None => continue,
            }
        }
        Err(RigError::NoAnswer {
            command: command_name(message),
            attempts: SEND_ATTEMPTS,
        })
    }

    /// Waits for the Ack/Nack of `seq`; `None` on timeout.
    fn wait_answer(
        &mut self,
        seq: u16,
        timeout: Duration,
    ) -> Result<Option<Result<(), ErrorCode>>, RigError> {
        let deadline = Instant::now() + timeout;
        let mut kept = VecDeque::new();
        let answer = loop {
            let Some(message) = self.next_raw(deadline)? else {
                break None;
            };
            match message {
                ControllerMessage::Ack(ack) if ack.seq == seq => break Some(Ok(())),
                ControllerMessage::Nack(nack) if nack.seq == seq => break Some(Err(nack.error)),
                other => kept.push_back(other),
            }
        };
        // Put back what was not ours, ahead of anything read later.
        kept.extend(self.pending.drain(..));
        self.pending = kept;
        Ok(answer)
    }

    /// Next message from the pending queue or the wire, until `deadline`.
    fn next_raw(&mut self, deadline: Instant) -> Result<Option<ControllerMessage>, RigError> {
        loop {
            if let Some(message) = self.pending.pop_front() {
                return Ok(Some(message));
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            self.read_available(deadline - now)?;
        }
    }
}

/// Name of a command for error messages.
pub fn command_name(message: &HostMessage) -> &'static str {
    match message {
        HostMessage::Hello(_) => "Hello",
        HostMessage::ScheduleBegin(_) => "ScheduleBegin",
        HostMessage::ScheduleChunk(_) => "ScheduleChunk",
        HostMessage::ScheduleCommit(_) => "ScheduleCommit",
        HostMessage::Arm => "Arm",
        HostMessage::Start => "Start",
        HostMessage::Abort => "Abort",
        HostMessage::StatusQuery => "StatusQuery",
        HostMessage::PatternShown(_) => "PatternShown",
        HostMessage::Heartbeat(_) => "Heartbeat",
        HostMessage::Resume => "Resume",
        HostMessage::Retrigger(_) => "Retrigger",
    }
}
