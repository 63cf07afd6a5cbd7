//! Schedule upload (begin, chunks, commit) and validation.
//!
//! The host uploads the run's timing in a [`ScheduleHeader`], then the frames (which projector,
//! which pattern) in chunks, then a commit with the frame count and a checksum. Every refusal is
//! a typed [`ErrorCode`] the controller sends back in a `Nack`; nothing is accepted half-way.

use heapless::Vec;
use mlsss_shared::ScheduleChecksum;
use mlsss_shared::message::{
    ErrorCode, MAX_SCHEDULE_FRAMES, ScheduleChunk, ScheduleCommit, ScheduleEntry, ScheduleHeader,
};

/// A validated schedule, ready to run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Schedule {
    /// Timing and policy.
    pub header: ScheduleHeader,
    /// One entry per frame, in capture order.
    pub entries: Vec<ScheduleEntry, MAX_SCHEDULE_FRAMES>,
}

impl Schedule {
    /// Frames in the schedule.
    pub fn frame_count(&self) -> u16 {
        // Bounded by MAX_SCHEDULE_FRAMES (1024), so it fits.
        self.entries.len() as u16
    }

    /// Refresh periods of the lit projector per slot (12 for 200 ms at 60 Hz).
    pub fn slot_vsyncs(&self) -> u32 {
        slot_vsyncs(&self.header)
    }

    /// Exposure (refresh periods) and trigger pulse width (us) of `projector`'s frames.
    pub fn exposure_of(&self, projector: u8) -> (u8, u32) {
        exposure_of(&self.header, projector)
    }
}

/// Exposure (refresh periods) and trigger width (us) of `projector`'s frames: its own entry of
/// `projector_exposure`, or the header's nominal values when that entry is 0 periods.
pub fn exposure_of(h: &ScheduleHeader, projector: u8) -> (u8, u32) {
    match h.projector_exposure.get(usize::from(projector)) {
        Some(e) if e.exposure_periods > 0 => (e.exposure_periods, e.trigger_width_us),
        _ => (h.exposure_periods, h.trigger_width_us),
    }
}

/// Every exposure the header uses: the nominal one and each projector's own.
fn exposures(h: &ScheduleHeader) -> impl Iterator<Item = (u8, u32)> + '_ {
    let own = h
        .projector_exposure
        .iter()
        .filter(|e| e.exposure_periods > 0)
        .map(|e| (e.exposure_periods, e.trigger_width_us));
    core::iter::once((h.exposure_periods, h.trigger_width_us)).chain(own)
}

/// Refresh periods per slot, rounded (a header that passed [`validate_header`] gives >= 1).
pub fn slot_vsyncs(h: &ScheduleHeader) -> u32 {
    let refresh = h.refresh_period_us.max(1);
    (h.period_us + refresh / 2) / refresh
}

/// Shortest slot that holds the settle VSYNCs, the trigger phase and the longest exposure.
pub fn min_period_us(h: &ScheduleHeader) -> u64 {
    let longest = exposures(h).map(|(periods, _)| periods).max().unwrap_or(0);
    (u64::from(h.settle_vsyncs.max(1)) + u64::from(longest)) * u64::from(h.refresh_period_us)
        + u64::from(h.trigger_phase_us)
}

/// Checks the timing of a header on its own (frame entries are checked as they arrive).
pub fn validate_header(h: &ScheduleHeader) -> Result<(), ErrorCode> {
    if h.frame_count == 0 {
        return Err(ErrorCode::ScheduleEmpty);
    }
    if usize::from(h.frame_count) > MAX_SCHEDULE_FRAMES {
        return Err(ErrorCode::ScheduleTooLong);
    }
    // Each exposure (nominal and per projector) is at least a period, with a pulse inside it.
    let invalid = |(periods, width_us): (u8, u32)| {
        let exposure_us = u64::from(periods) * u64::from(h.refresh_period_us);
        periods == 0 || width_us == 0 || u64::from(width_us) > exposure_us
    };
    if h.refresh_period_us == 0 || exposures(h).any(invalid) {
        return Err(ErrorCode::InvalidExposure);
    }
    // The phase must stay inside the refresh period it is aligned to, and the slot must hold
    // settle + phase + exposure.
    if h.trigger_phase_us >= h.refresh_period_us || u64::from(h.period_us) < min_period_us(h) {
        return Err(ErrorCode::PeriodTooShort);
    }
    Ok(())
}

/// Receives a schedule piece by piece.
#[derive(Default)]
pub struct ScheduleLoader {
    header: Option<ScheduleHeader>,
    entries: Vec<ScheduleEntry, MAX_SCHEDULE_FRAMES>,
    checksum: Option<ScheduleChecksum>,
}

// Manual: the checksum digest has no `Debug`.
impl core::fmt::Debug for ScheduleLoader {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("ScheduleLoader")
            .field("header", &self.header)
            .field("received", &self.entries.len())
            .finish()
    }
}

impl ScheduleLoader {
    /// A loader with nothing received.
    pub fn new() -> Self {
        Self::default()
    }

    /// True between an accepted begin and the commit.
    pub fn is_loading(&self) -> bool {
        self.header.is_some()
    }

    /// Starts an upload (discarding any upload in progress).
    pub fn begin(&mut self, header: ScheduleHeader) -> Result<(), ErrorCode> {
        self.abandon();
        validate_header(&header)?;
        self.header = Some(header);
        self.checksum = Some(ScheduleChecksum::new());
        Ok(())
    }

    /// Adds a chunk; chunks must be consecutive and name only the board's projectors.
    pub fn chunk(&mut self, chunk: &ScheduleChunk, projectors: u8) -> Result<(), ErrorCode> {
        let header = self.header.ok_or(ErrorCode::InvalidState)?;
        let entries = chunk.entries.as_slice();
        if self.is_repeat_of_last_chunk(chunk) {
            // The host resent a chunk whose Ack it did not see in time: accept it again.
            return Ok(());
        }
        if usize::from(chunk.first_frame) != self.entries.len()
            || self.entries.len() + entries.len() > usize::from(header.frame_count)
        {
            return Err(ErrorCode::ChunkOutOfOrder);
        }
        if entries.iter().any(|e| e.projector >= projectors) {
            // A schedule naming a projector the board cannot see is refused as a whole.
            self.abandon();
            return Err(ErrorCode::UnknownProjector);
        }
        // Cannot fail: the length was checked against frame_count <= MAX_SCHEDULE_FRAMES.
        self.entries
            .extend_from_slice(entries)
            .map_err(|_| ErrorCode::ScheduleTooLong)?;
        if let Some(c) = self.checksum.as_mut() {
            c.update(entries);
        }
        Ok(())
    }

    /// True for a non-empty chunk equal to the entries received last.
    fn is_repeat_of_last_chunk(&self, chunk: &ScheduleChunk) -> bool {
        let entries = chunk.entries.as_slice();
        let first = usize::from(chunk.first_frame);
        !entries.is_empty()
            && first + entries.len() == self.entries.len()
            && self.entries.get(first..) == Some(entries)
    }

    /// Ends the upload: the schedule, when count and checksum match what was received.
    pub fn commit(&mut self, commit: &ScheduleCommit) -> Result<Schedule, ErrorCode> {
        let header = self.header.ok_or(ErrorCode::InvalidState)?;
        let checksum = self.checksum.take().map(ScheduleChecksum::finalize);
        let received = self.entries.len();
        let matches = usize::from(commit.frame_count) == received
            && received == usize::from(header.frame_count)
            && checksum == Some(commit.checksum);
        let entries = core::mem::take(&mut self.entries);
        self.abandon();
        if !matches {
            return Err(ErrorCode::ScheduleMismatch);
        }
        Ok(Schedule { header, entries })
    }

    /// Drops an upload in progress.
    pub fn abandon(&mut self) {
        self.header = None;
        self.entries.clear();
        self.checksum = None;
    }
}
