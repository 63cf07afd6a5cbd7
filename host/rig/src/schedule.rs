//! The schedule the host uploads: the frame plan as (projector, pattern id) entries plus the
//! booth's timing, and the pattern table that maps ids back to patterns.

use mlsss_shared::message::{
    BoundedVec, ExhaustedAction, MAX_PROJECTORS, ProjectorExposure as WireExposure, RetryPolicy,
    SCHEDULE_CHUNK_LEN, ScheduleChunk, ScheduleCommit, ScheduleEntry, ScheduleHeader,
};

use super::RigError;
use mlsss_core::booth::TimingSpec;
use mlsss_core::capture::exposure::ProjectorExposure;
use mlsss_core::capture::{FramePlan, Pattern};

/// Time the controller waits for the host's shown-ack after a request. Generous: the run is
/// paced by VSYNC, the request goes out ~150 ms before its slot.
const ACK_TIMEOUT_US: u32 = 150_000;
/// Host silence after which the controller pauses a run.
const HOST_SILENCE_TIMEOUT_US: u32 = 2_000_000;
/// Retries of a late frame before the run aborts.
const MAX_RETRIES: u8 = 3;

/// A schedule ready for upload.
#[derive(Debug, Clone, PartialEq)]
pub struct RigSchedule {
    /// Timing and policy.
    pub header: ScheduleHeader,
    /// One entry per frame, in capture order.
    pub entries: Vec<ScheduleEntry>,
    /// Pattern id -> pattern.
    pub patterns: Vec<Pattern>,
    /// The metered exposure of each projector (empty: the booth's nominal exposure), as
    /// `capture.json` records it; the header carries its periods and pulse width.
    pub exposure: Vec<ProjectorExposure>,
}

impl RigSchedule {
    /// The schedule of the first `frames` frames of `plan` (all when `None`) with `timing`.
    pub fn from_plan(
        plan: &FramePlan,
        timing: &TimingSpec,
        frames: Option<usize>,
    ) -> Result<Self, RigError> {
        let count = frames.unwrap_or(plan.len()).min(plan.len());
        let mut patterns: Vec<Pattern> = vec![];
        let mut entries = Vec::with_capacity(count);
        for spec in &plan.frames[..count] {
            let projector = spec.projector.ok_or(RigError::DarkFrame(spec.index))?;
            let id = match patterns.iter().position(|p| *p == spec.pattern) {
                Some(id) => id,
                None => {
                    patterns.push(spec.pattern);
                    patterns.len() - 1
                }
            };
            let pattern = u16::try_from(id).map_err(|_| RigError::TooManyPatterns)?;
            entries.push(ScheduleEntry { projector, pattern });
        }
        let frame_count = u16::try_from(count).map_err(|_| RigError::TooManyFrames(count))?;
        let header = ScheduleHeader {
            frame_count,
            period_us: timing.slot_us(),
            refresh_period_us: (1e6 / timing.refresh_hz).round() as u32,
            exposure_periods: saturating_u8(timing.exposure_periods),
            settle_vsyncs: saturating_u8(timing.settle_vsyncs),
            trigger_phase_us: timing.trigger_phase_us,
            trigger_width_us: timing.trigger_width_us,
            ack_timeout_us: ACK_TIMEOUT_US,
            host_silence_timeout_us: HOST_SILENCE_TIMEOUT_US,
            policy: RetryPolicy {
                max_retries: MAX_RETRIES,
                when_exhausted: ExhaustedAction::Abort,
            },
            // Nominal until metered (see `with_exposure`).
            projector_exposure: Default::default(),
        };
        Ok(Self {
            header,
            entries,
            patterns,
            exposure: vec![],
        })
    }

    /// Projector `projector`'s signal relative to the nominal exposure (1 unless metered).
    pub fn exposure_scale(&self, projector: u8) -> f64 {
        self.exposure
            .iter()
            .find(|e| e.projector == projector)
            .map_or(1.0, |e| e.scale)
    }

    /// The schedule with each projector's metered exposure (`capture::exposure::meter`): its
    /// frames are exposed for `periods` refresh periods, and the trigger pulse lasts the whole
    /// exposure (the camera in trigger-width exposure mode exposes while the pulse is high, so
    /// the exposure can change from frame to frame without reconfiguring the camera). The
    /// controller refuses an exposure its slot cannot hold (`PeriodTooShort`).
    pub fn with_exposure(mut self, exposure: &[ProjectorExposure]) -> Result<Self, RigError> {
        for e in exposure {
            let slot = self
                .header
                .projector_exposure
                .get_mut(usize::from(e.projector))
                .ok_or(RigError::TooManyProjectors {
                    projector: e.projector,
                    max: MAX_PROJECTORS,
                })?;
            let periods = saturating_u8(e.periods);
            *slot = WireExposure {
                exposure_periods: periods,
                trigger_width_us: u32::from(periods) * self.header.refresh_period_us,
            };
        }
        self.exposure = exposure.to_vec();
        Ok(self)
    }

    /// The upload chunks, in order.
    pub fn chunks(&self) -> Vec<ScheduleChunk> {
        self.entries
            .chunks(SCHEDULE_CHUNK_LEN)
            .enumerate()
            .map(|(i, entries)| ScheduleChunk {
                first_frame: (i * SCHEDULE_CHUNK_LEN) as u16,
                entries: BoundedVec::from_slice(entries)
                    .unwrap_or_else(|| unreachable!("chunks() yields at most the chunk length")),
            })
            .collect()
    }

    /// The closing commit.
    pub fn commit(&self) -> ScheduleCommit {
        ScheduleCommit {
            frame_count: self.entries.len() as u16,
            checksum: mlsss_shared::schedule_checksum(&self.entries),
        }
    }
}

/// Values from the booth file that the wire carries as u8 (they are small counts).
fn saturating_u8(v: u32) -> u8 {
    u8::try_from(v).unwrap_or(u8::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;
    use mlsss_core::booth::Booth;

    #[test]
    fn the_default_scan_is_268_frames_of_67_patterns_in_9_chunks() {
        let booth = Booth::builtin(false);
        let plan = FramePlan::scan(&booth.patterns, booth.projectors.len());
        let s = RigSchedule::from_plan(&plan, &booth.timing, None).unwrap();
        assert_eq!(s.entries.len(), 268);
        assert_eq!(s.patterns.len(), 67);
        // Projector k lights frames 67k..67k+66 with pattern ids 0..66 in plan order.
        for (i, e) in s.entries.iter().enumerate() {
            assert_eq!(usize::from(e.projector), i / 67);
            assert_eq!(usize::from(e.pattern), i % 67);
            assert_eq!(s.patterns[usize::from(e.pattern)], plan.frames[i].pattern);
        }
        let chunks = s.chunks();
        assert_eq!(chunks.len(), 9);
        assert_eq!(chunks[8].first_frame, 256);
        assert_eq!(chunks[8].entries.as_slice().len(), 12);
        let rejoined: Vec<_> = chunks
            .iter()
            .flat_map(|c| c.entries.as_slice().to_vec())
            .collect();
        assert_eq!(rejoined, s.entries);
        assert_eq!(s.commit().frame_count, 268);
        assert_eq!(s.header.period_us, 200_000);
        assert_eq!(s.header.refresh_period_us, 16_667);
        assert_eq!((s.header.exposure_periods, s.header.settle_vsyncs), (2, 2));
    }

    #[test]
    fn metered_exposure_sets_each_projectors_periods_and_a_pulse_as_long_as_the_exposure() {
        let booth = Booth::builtin(true);
        let plan = FramePlan::scan(&booth.patterns, booth.projectors.len());
        let nominal = ProjectorExposure::nominal(2, &booth.timing);
        let longer = ProjectorExposure {
            projector: 1,
            periods: 6,
            analog_gain: 1.5,
            scale: 4.5,
        };
        let s = RigSchedule::from_plan(&plan, &booth.timing, Some(8))
            .unwrap()
            .with_exposure(&[longer, nominal])
            .unwrap();
        // 6 periods of 16 667 us; projector 2 at the booth's 2 periods; 0 and 3 not metered.
        assert_eq!(
            s.header.projector_exposure[1],
            WireExposure {
                exposure_periods: 6,
                trigger_width_us: 100_002
            }
        );
        assert_eq!(s.header.projector_exposure[2].exposure_periods, 2);
        assert_eq!(s.header.projector_exposure[2].trigger_width_us, 33_334);
        assert_eq!(s.header.projector_exposure[0], WireExposure::default());
        assert_eq!(s.exposure, [longer, nominal]);
        let too_many = ProjectorExposure {
            projector: 8,
            ..longer
        };
        assert!(
            RigSchedule::from_plan(&plan, &booth.timing, Some(8))
                .unwrap()
                .with_exposure(&[too_many])
                .is_err()
        );
    }

    #[test]
    fn frames_limits_the_schedule() {
        let booth = Booth::builtin(true);
        let plan = FramePlan::scan(&booth.patterns, booth.projectors.len());
        let s = RigSchedule::from_plan(&plan, &booth.timing, Some(5)).unwrap();
        assert_eq!(s.entries.len(), 5);
        assert_eq!(s.header.frame_count, 5);
    }
}
