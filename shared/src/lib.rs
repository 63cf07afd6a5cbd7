//! Wire protocol between the MLSSS booth controller (firmware) and the host (DESIGN section 7).
//!
//! - [`message`]: the messages in each direction ([`HostMessage`], [`ControllerMessage`]);
//!   every enum is append-only.
//! - [`framing`]: postcard + sequence number + CRC-32C, COBS-framed with `0x00` delimiters;
//!   a streaming [`framing::Decoder`] that never panics, never allocates and resynchronises at
//!   the next delimiter.
//!
//! Session: the host sends `Hello`; the controller answers `HelloReply` (and nacks every other
//! command until a `Hello` with the same [`PROTOCOL_VERSION`] and [`SCHEMA_HASH`] arrived). The host
//! uploads the schedule (`ScheduleBegin`, `ScheduleChunk`s, `ScheduleCommit`), then `Arm` and
//! `Start`; each command is acked or nacked by its frame sequence number. During the run the
//! controller sends `PatternRequest`, the host shows the pattern and answers `PatternShown`, the
//! controller triggers after the settle VSYNCs and reports `Triggered` and `ExposureDone`;
//! misses are reported as `FrameLate` / `FrameRetried` / `FrameDropped`; `Done` ends the run.
//! A frame whose camera payload the host lost is run again on the host's `Retrigger`
//! (`FrameRetried`, then a new request and trigger; after `Done` the run is extended and ends
//! with another `Done`).
//!
//! Version 2: per-projector exposure in the schedule header, `Retrigger`.
#![no_std]
#![forbid(unsafe_code)]

pub mod framing;
pub mod message;

pub use message::{ControllerMessage, HostMessage};

/// Version of the wire protocol; bumped on any incompatible change.
pub const PROTOCOL_VERSION: u16 = 2;

/// Hash of the message definitions (`src/message.rs` without comments and whitespace): two builds
/// with the same [`PROTOCOL_VERSION`] but different message types refuse to talk.
pub const SCHEMA_HASH: u32 = schema_hash(include_str!("message.rs"));

/// FNV-1a over the source text, skipping ASCII whitespace and `//` comments (so documentation
/// edits and formatting do not change the hash; `message.rs` has no `//` inside string literals).
const fn schema_hash(source: &str) -> u32 {
    const FNV_OFFSET: u32 = 0x811c_9dc5;
    const FNV_PRIME: u32 = 0x0100_0193;
    let bytes = source.as_bytes();
    let mut hash = FNV_OFFSET;
    let mut i = 0;
    while i < bytes.len() {
        let b = bytes[i];
        if b == b'/' && i + 1 < bytes.len() && bytes[i + 1] == b'/' {
            while i < bytes.len() && bytes[i] != b'\n' {
                i += 1;
            }
            continue;
        }
        if !b.is_ascii_whitespace() {
            hash ^= b as u32;
            hash = hash.wrapping_mul(FNV_PRIME);
        }
        i += 1;
    }
    hash
}

/// Checksum of a whole schedule for [`message::ScheduleCommit`]: CRC-32C over each entry's
/// projector byte and little-endian pattern id, in frame order.
pub fn schedule_checksum(entries: &[message::ScheduleEntry]) -> u32 {
    let mut checksum = ScheduleChecksum::new();
    checksum.update(entries);
    checksum.finalize()
}

/// Incremental [`schedule_checksum`] for a receiver that gets the entries chunk by chunk.
pub struct ScheduleChecksum {
    digest: crc::Digest<'static, u32>,
}

static SCHEDULE_CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISCSI);

impl Default for ScheduleChecksum {
    fn default() -> Self {
        Self::new()
    }
}

impl ScheduleChecksum {
    /// Checksum of no entries yet.
    pub fn new() -> Self {
        Self {
            digest: SCHEDULE_CRC.digest(),
        }
    }

    /// Adds entries in frame order.
    pub fn update(&mut self, entries: &[message::ScheduleEntry]) {
        for entry in entries {
            self.digest.update(&[entry.projector]);
            self.digest.update(&entry.pattern.to_le_bytes());
        }
    }

    /// The checksum of everything added.
    pub fn finalize(self) -> u32 {
        self.digest.finalize()
    }
}
