//! The booth's metering step on the rig (DESIGN section 3): before the scan, each projector the
//! scan lights shows white once at the booth's nominal exposure, the camera takes that frame,
//! and the projector's exposure is chosen from it by the rule the virtual booth meters with
//! (`mlsss_core::capture::exposure::meter`). The scan's schedule then carries the exposures
//! (`RigSchedule::with_exposure`).

use std::path::Path;

use super::RigError;
use super::acquire::{CaptureTarget, acquire};
use super::backend::{CameraBackend, ProjectorBackend};
use super::link::ByteLink;
use super::schedule::RigSchedule;
use super::session::{HostFaults, Session};
use mlsss_core::booth::Booth;
use mlsss_core::capture::exposure::{MeteringTarget, ProjectorExposure, meter};
use mlsss_core::capture::{Capture, FramePlan, FrameSpec, Pattern};

/// The metering run's frames: white on each of `projectors` in turn.
pub fn metering_plan(projectors: &[u8]) -> FramePlan {
    FramePlan {
        frames: projectors
            .iter()
            .zip(0u32..)
            .map(|(&projector, index)| FrameSpec {
                index,
                projector: Some(projector),
                pattern: Pattern::White,
            })
            .collect(),
    }
}

/// Meters `projectors` on the rig: runs the metering frames through `session` (written as a
/// capture under `scratch`, a folder that must not exist and that the caller removes), and
/// returns each projector's exposure, chosen for `target` (whose `max_analog_gain` must be 1
/// for a camera whose gain the rig does not set per projector).
pub fn meter_projectors<L: ByteLink>(
    session: &mut Session<L>,
    booth: &Booth,
    projectors: &[u8],
    scratch: &Path,
    backends: (&mut dyn ProjectorBackend, Box<dyn CameraBackend>),
    target: &MeteringTarget,
) -> Result<Vec<ProjectorExposure>, RigError> {
    let (projector, camera) = backends;
    let plan = metering_plan(projectors);
    let schedule = RigSchedule::from_plan(&plan, &booth.timing, None)?;
    let acquired = acquire(
        session,
        &schedule,
        CaptureTarget {
            booth,
            plan: &plan,
            out: scratch,
            source: serde_json::json!({ "metering": true }),
        },
        projector,
        camera,
        &HostFaults::default(),
        &mut |_| {},
    )?;
    if !acquired.complete {
        return Err(RigError::Backend {
            backend: "camera",
            message: format!(
                "the metering run captured {} of its {} white frames{}",
                acquired.frames_written,
                projectors.len(),
                acquired
                    .camera_failures
                    .first()
                    .map(|(frame, why)| format!(" (frame {frame}: {why})"))
                    .unwrap_or_default()
            ),
        });
    }
    let capture = Capture::open(&acquired.folder)?;
    plan.frames
        .iter()
        .zip(projectors)
        .map(|(spec, &k)| {
            let white = capture.read_frame(spec.index)?;
            let brightest: Vec<f32> = white
                .pixels()
                .map(|p| p.0[0].max(p.0[1]).max(p.0[2]))
                .collect();
            Ok(meter(k, &brightest, &booth.timing, target))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_plan_shows_white_on_each_projector_once_in_order() {
        let plan = metering_plan(&[2, 0]);
        let lit: Vec<_> = plan
            .frames
            .iter()
            .map(|f| (f.index, f.projector, f.pattern))
            .collect();
        assert_eq!(
            lit,
            [(0, Some(2), Pattern::White), (1, Some(0), Pattern::White)]
        );
    }
}
