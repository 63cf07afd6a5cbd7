//! Framing: postcard message + sequence number + CRC, COBS-encoded, terminated by `0x00`.
//!
//! A frame on the wire is `COBS(seq_le16 ++ postcard(message) ++ crc32c_le(seq ++ message)) 0x00`.
//! COBS guarantees that `0x00` appears only as the delimiter, so a receiver that lost sync (noise,
//! a reset peer, a frame too long for its buffer) throws bytes away up to the next `0x00` and is in
//! sync again from the following frame on. The CRC (CRC-32C, Castagnoli) rejects corrupted
//! frames; the 16-bit sequence number, counted per direction, lets the receiver see that frames
//! were lost between two it accepted.
//!
//! Nothing here allocates or panics on any input: the decoder works in a fixed buffer and every
//! failure is a counted [`FrameError`].

use core::marker::PhantomData;

use crc::{CRC_32_ISCSI, Crc};
use postcard::experimental::max_size::MaxSize;
use serde::{Serialize, de::DeserializeOwned};

use crate::message::{ControllerMessage, HostMessage, LinkStats};

/// The frame CRC: CRC-32C (Castagnoli), good Hamming distance for short frames.
const FRAME_CRC: Crc<u32> = Crc::<u32>::new(&CRC_32_ISCSI);

/// Bytes of the sequence number at the start of a frame.
const SEQ_LEN: usize = 2;
/// Bytes of the CRC at the end of a frame.
const CRC_LEN: usize = 4;

const fn max(a: usize, b: usize) -> usize {
    if a > b { a } else { b }
}

/// Largest postcard encoding of any message in either direction.
pub const MAX_MESSAGE_LEN: usize = max(
    HostMessage::POSTCARD_MAX_SIZE,
    ControllerMessage::POSTCARD_MAX_SIZE,
);

/// Largest frame before COBS encoding: sequence number, message, CRC.
pub const MAX_RAW_FRAME_LEN: usize = SEQ_LEN + MAX_MESSAGE_LEN + CRC_LEN;

/// Largest COBS-encoded frame, without the `0x00` delimiter (COBS adds one byte per 254 and one).
pub const MAX_ENCODED_FRAME_LEN: usize = MAX_RAW_FRAME_LEN + MAX_RAW_FRAME_LEN / 254 + 1;

/// Largest frame on the wire including its delimiter: the size of an encode buffer.
pub const MAX_WIRE_FRAME_LEN: usize = MAX_ENCODED_FRAME_LEN + 1;

/// Shortest valid raw frame: sequence number, a one-byte message, CRC.
const MIN_RAW_FRAME_LEN: usize = SEQ_LEN + 1 + CRC_LEN;

/// The frame delimiter.
pub const DELIMITER: u8 = 0x00;

/// Why a received frame was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum FrameError {
    /// The frame was longer than the receive buffer; its bytes were discarded.
    #[error("frame longer than the receive buffer")]
    Oversize,
    /// The bytes between two delimiters are not valid COBS.
    #[error("invalid COBS encoding")]
    Cobs,
    /// The frame is too short to hold a sequence number, a message and a CRC.
    #[error("frame too short")]
    TooShort,
    /// The CRC does not match the contents.
    #[error("CRC mismatch")]
    Crc,
    /// The CRC matches but the contents are not exactly one message of the expected direction.
    #[error("frame does not hold a valid message")]
    Deserialize,
}

/// Why a message could not be encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum EncodeError {
    /// The output buffer is smaller than the encoded frame (use [`MAX_WIRE_FRAME_LEN`]).
    #[error("output buffer too small for the frame")]
    BufferTooSmall,
    /// The message does not fit a frame (cannot happen for this crate's message types).
    #[error("message longer than a frame")]
    MessageTooLong,
}

/// A message accepted by a [`Decoder`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Received<M> {
    /// The sender's sequence number of this frame.
    pub seq: u16,
    /// Frames missing between the previously accepted frame and this one (0 when none, and 0
    /// when the sequence jumps backwards, which is how a restarted sender looks).
    pub missed: u16,
    /// The message.
    pub message: M,
}

/// Receive-side counters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct DecoderStats {
    /// Frames accepted.
    pub frames_ok: u32,
    /// Frames rejected for a CRC mismatch.
    pub crc_errors: u32,
    /// Frames rejected as invalid COBS, too short, or not a message.
    pub malformed: u32,
    /// Frames rejected for being longer than the buffer.
    pub oversize: u32,
    /// Sum of [`Received::missed`].
    pub sequence_gaps: u32,
    /// Rejected frames of any kind (each time bytes were thrown away up to a delimiter).
    pub resyncs: u32,
}

impl From<DecoderStats> for LinkStats {
    fn from(s: DecoderStats) -> Self {
        LinkStats {
            frames_ok: s.frames_ok,
            crc_errors: s.crc_errors,
            malformed: s.malformed,
            oversize: s.oversize,
            sequence_gaps: s.sequence_gaps,
            resyncs: s.resyncs,
        }
    }
}

/// Encodes messages of one direction (`M`) into wire frames, numbering them.
#[derive(Debug)]
pub struct Encoder<M> {
    next_seq: u16,
    direction: PhantomData<fn(&M)>,
}

impl<M: Serialize> Default for Encoder<M> {
    fn default() -> Self {
        Self::new()
    }
}

impl<M: Serialize> Encoder<M> {
    /// An encoder whose first frame has sequence number 0.
    pub const fn new() -> Self {
        Self {
            next_seq: 0,
            direction: PhantomData,
        }
    }

    /// The sequence number the next frame will carry.
    pub fn next_seq(&self) -> u16 {
        self.next_seq
    }

    /// Encodes `message` as one wire frame (delimiter included) into `out`; returns the frame's
    /// sequence number and the bytes to send. The sequence number advances only on success.
    pub fn encode<'b>(
        &mut self,
        message: &M,
        out: &'b mut [u8],
    ) -> Result<(u16, &'b [u8]), EncodeError> {
        let seq = self.next_seq;
        let len = encode_frame(seq, message, out)?;
        self.next_seq = seq.wrapping_add(1);
        Ok((seq, &out[..len]))
    }
}

/// Encodes one frame with an explicit sequence number; returns its length including the
/// delimiter. Prefer [`Encoder`], which numbers frames itself.
pub fn encode_frame<M: Serialize>(
    seq: u16,
    message: &M,
    out: &mut [u8],
) -> Result<usize, EncodeError> {
    let mut raw = [0u8; MAX_RAW_FRAME_LEN];
    raw[..SEQ_LEN].copy_from_slice(&seq.to_le_bytes());
    let body_len = postcard::to_slice(message, &mut raw[SEQ_LEN..MAX_RAW_FRAME_LEN - CRC_LEN])
        .map_err(|_| EncodeError::MessageTooLong)?
        .len();
    let crc_at = SEQ_LEN + body_len;
    let crc = FRAME_CRC.checksum(&raw[..crc_at]);
    raw[crc_at..crc_at + CRC_LEN].copy_from_slice(&crc.to_le_bytes());
    let raw = &raw[..crc_at + CRC_LEN];

    let encoded_len = cobs::try_encode(raw, out).map_err(|_| EncodeError::BufferTooSmall)?;
    let delimiter = out
        .get_mut(encoded_len)
        .ok_or(EncodeError::BufferTooSmall)?;
    *delimiter = DELIMITER;
    Ok(encoded_len + 1)
}

/// Streaming decoder for messages of one direction (`M`): feed it bytes in chunks of any size,
/// get messages and errors out. `N` is the receive buffer (encoded bytes of one frame).
#[derive(Debug)]
pub struct Decoder<M, const N: usize = MAX_ENCODED_FRAME_LEN> {
    buf: [u8; N],
    len: usize,
    /// Set when the current frame overflowed `buf`: bytes are dropped up to the next delimiter.
    discarding: bool,
    expected_seq: Option<u16>,
    stats: DecoderStats,
    direction: PhantomData<fn() -> M>,
}

impl<M: DeserializeOwned, const N: usize> Default for Decoder<M, N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<M: DeserializeOwned, const N: usize> Decoder<M, N> {
    /// An empty decoder.
    pub const fn new() -> Self {
        Self {
            buf: [0; N],
            len: 0,
            discarding: false,
            expected_seq: None,
            stats: DecoderStats {
                frames_ok: 0,
                crc_errors: 0,
                malformed: 0,
                oversize: 0,
                sequence_gaps: 0,
                resyncs: 0,
            },
            direction: PhantomData,
        }
    }

    /// Counters since creation.
    pub fn stats(&self) -> DecoderStats {
        self.stats
    }

    /// Forgets the expected sequence number (e.g. after a deliberate reconnect), so the next
    /// frame counts no gap.
    pub fn reset_sequence(&mut self) {
        self.expected_seq = None;
    }

    /// Takes one byte; returns a result when the byte completes a frame.
    pub fn push_byte(&mut self, byte: u8) -> Option<Result<Received<M>, FrameError>> {
        if byte == DELIMITER {
            return self.end_of_frame();
        }
        if self.discarding {
            return None;
        }
        match self.buf.get_mut(self.len) {
            Some(slot) => {
                *slot = byte;
                self.len += 1;
            }
            None => self.discarding = true,
        }
        None
    }

    /// Takes a chunk of bytes; the iterator yields every completed frame's result in order.
    /// Bytes of an incomplete frame stay buffered for the next call. Dropping the iterator
    /// early leaves the unread bytes of `chunk` unconsumed.
    pub fn feed<'d, 'c>(&'d mut self, chunk: &'c [u8]) -> Feed<'d, 'c, M, N> {
        Feed {
            decoder: self,
            rest: chunk,
        }
    }

    fn end_of_frame(&mut self) -> Option<Result<Received<M>, FrameError>> {
        let len = core::mem::replace(&mut self.len, 0);
        if core::mem::replace(&mut self.discarding, false) {
            return Some(Err(self.reject(FrameError::Oversize)));
        }
        if len == 0 {
            // Back-to-back delimiters: allowed as line fill / explicit resync, not an error.
            return None;
        }
        Some(match self.decode_frame(len) {
            Ok((seq, message)) => Ok(self.accept(seq, message)),
            Err(e) => Err(self.reject(e)),
        })
    }

    fn decode_frame(&mut self, len: usize) -> Result<(u16, M), FrameError> {
        let encoded = self.buf.get_mut(..len).ok_or(FrameError::Oversize)?;
        let raw_len = cobs::decode_in_place(encoded).map_err(|_| FrameError::Cobs)?;
        let raw = encoded.get(..raw_len).ok_or(FrameError::Cobs)?;
        if raw.len() < MIN_RAW_FRAME_LEN {
            return Err(FrameError::TooShort);
        }
        let (covered, crc_bytes) = raw.split_at(raw.len() - CRC_LEN);
        let received_crc =
            u32::from_le_bytes([crc_bytes[0], crc_bytes[1], crc_bytes[2], crc_bytes[3]]);
        if FRAME_CRC.checksum(covered) != received_crc {
            return Err(FrameError::Crc);
        }
        let (seq_bytes, body) = covered.split_at(SEQ_LEN);
        let seq = u16::from_le_bytes([seq_bytes[0], seq_bytes[1]]);
        match postcard::take_from_bytes::<M>(body) {
            Ok((message, [])) => Ok((seq, message)),
            _ => Err(FrameError::Deserialize),
        }
    }

    fn accept(&mut self, seq: u16, message: M) -> Received<M> {
        let missed = match self.expected_seq {
            // A forward jump of less than half the sequence space is a gap; anything else is a
            // restarted sender.
            Some(expected) if seq.wrapping_sub(expected) < 0x8000 => seq.wrapping_sub(expected),
            _ => 0,
        };
        self.expected_seq = Some(seq.wrapping_add(1));
        self.stats.frames_ok = self.stats.frames_ok.wrapping_add(1);
        self.stats.sequence_gaps = self.stats.sequence_gaps.wrapping_add(u32::from(missed));
        Received {
            seq,
            missed,
            message,
        }
    }

    fn reject(&mut self, error: FrameError) -> FrameError {
        let counter = match error {
            FrameError::Crc => &mut self.stats.crc_errors,
            FrameError::Oversize => &mut self.stats.oversize,
            FrameError::Cobs | FrameError::TooShort | FrameError::Deserialize => {
                &mut self.stats.malformed
            }
        };
        *counter = counter.wrapping_add(1);
        self.stats.resyncs = self.stats.resyncs.wrapping_add(1);
        error
    }
}

/// Iterator over the frames completed by one chunk (see [`Decoder::feed`]).
#[derive(Debug)]
pub struct Feed<'d, 'c, M, const N: usize> {
    decoder: &'d mut Decoder<M, N>,
    rest: &'c [u8],
}

impl<M: DeserializeOwned, const N: usize> Iterator for Feed<'_, '_, M, N> {
    type Item = Result<Received<M>, FrameError>;

    fn next(&mut self) -> Option<Self::Item> {
        while let Some((&byte, rest)) = self.rest.split_first() {
            self.rest = rest;
            if let Some(result) = self.decoder.push_byte(byte) {
                return Some(result);
            }
        }
        None
    }
}

/// Decoder of host -> controller frames (the controller side).
pub type HostDecoder = Decoder<HostMessage>;
/// Decoder of controller -> host frames (the host side).
pub type ControllerDecoder = Decoder<ControllerMessage>;
/// Encoder of host -> controller frames (the host side).
pub type HostEncoder = Encoder<HostMessage>;
/// Encoder of controller -> host frames (the controller side).
pub type ControllerEncoder = Encoder<ControllerMessage>;
