//! A capture run: drive the schedule, show each requested pattern, fetch the camera image of
//! each triggered frame (matched to its trigger by frame index), write the capture folder
//! atomically with the controller's trigger log.
//!
//! Camera images are fetched and written on a worker thread so the link loop always answers
//! the controller in time.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::thread;

use mlsss_shared::message::{PatternRequest, Triggered};

use super::RigError;
use super::backend::{CameraBackend, Exposure, ProjectorBackend};
use super::link::ByteLink;
use super::schedule::RigSchedule;
use super::session::{HostFaults, RunHooks, RunLog, Session};
use mlsss_core::booth::Booth;
use mlsss_core::capture::folder::CaptureKind;
use mlsss_core::capture::{CaptureManifest, CaptureWriter, FramePlan, Pattern, TriggerRecord};

/// The result of a capture run.
#[derive(Debug)]
pub struct Acquired {
    /// The capture folder written.
    pub folder: PathBuf,
    /// Frames in the folder.
    pub frames_written: u32,
    /// Whether every scheduled frame was captured (else the folder holds the captured prefix).
    pub complete: bool,
    /// Everything the controller reported.
    pub log: RunLog,
    /// Triggered frames whose image the camera could not deliver (dropped, incomplete or
    /// missing payload, camera gone), with the reason; the folder keeps the frames before the
    /// first of them.
    pub camera_failures: Vec<(u32, String)>,
}

/// Where a capture goes and what it records about its origin.
pub struct CaptureTarget<'a> {
    /// The booth (snapshot written to the manifest).
    pub booth: &'a Booth,
    /// The full frame plan; the first `schedule.entries.len()` frames are captured.
    pub plan: &'a FramePlan,
    /// Output folder (must not exist).
    pub out: &'a Path,
    /// Free-form description of the rig (port, controller) for the manifest.
    pub source: serde_json::Value,
}

/// Runs `schedule` and writes the capture folder.
pub fn acquire<L: ByteLink>(
    session: &mut Session<L>,
    schedule: &RigSchedule,
    target: CaptureTarget<'_>,
    projector: &mut dyn ProjectorBackend,
    mut camera: Box<dyn CameraBackend>,
    faults: &HostFaults,
    on_frame: &mut dyn FnMut(u32),
) -> Result<Acquired, RigError> {
    let count = schedule.entries.len();
    let plan = FramePlan {
        frames: target.plan.frames[..count.min(target.plan.len())].to_vec(),
    };
    let manifest = CaptureManifest::new(CaptureKind::Scan, target.booth.clone(), plan.clone());
    let writer = CaptureWriter::create(target.out, manifest)?;

    let (tx, rx) = mpsc::channel::<Exposure>();
    // A camera failure is recorded for its frame and the worker goes on (the next trigger's
    // payload may well arrive); only a failure to write the folder stops it.
    type WorkerResult = Result<(CaptureWriter, BTreeSet<u32>, Vec<(u32, String)>), RigError>;
    let worker = thread::spawn(move || -> WorkerResult {
        let mut written = BTreeSet::new();
        let mut failures = Vec::new();
        for exposure in rx {
            match camera.capture(&exposure) {
                Ok(image) => {
                    writer.write_frame(exposure.frame, &image)?;
                    written.insert(exposure.frame);
                }
                Err(e) => failures.push((exposure.frame, e.to_string())),
            }
        }
        Ok((writer, written, failures))
    });

    let mut hooks = AcquireHooks {
        schedule,
        projector,
        lit: None,
        frames: tx,
        on_frame,
    };
    let run = session.run(schedule, &mut hooks, faults);
    drop(hooks); // closes the channel: the worker finishes the queued frames and returns
    let (mut writer, written, camera_failures) =
        worker.join().map_err(|_| RigError::Backend {
            backend: "camera",
            message: "the camera worker panicked".into(),
        })??;
    let log = run?;

    // Keep the longest prefix of frames that were both triggered and written.
    let captured = (0..count as u32)
        .take_while(|f| written.contains(f) && log.triggers.contains_key(&(*f as u16)))
        .count();
    let complete = captured == count;
    let late: BTreeSet<u16> = log.late.iter().map(|l| l.frame).collect();
    let manifest = writer.manifest_mut();
    manifest.plan.frames.truncate(captured);
    manifest.trigger_log = log
        .triggers
        .values()
        .filter(|t| usize::from(t.frame) < captured)
        .map(|t| trigger_record(t, late.contains(&t.frame)))
        .collect();
    manifest.source = serde_json::json!({
        "rig": target.source,
        "controller": {
            "board": format!("{:?}", log.controller.board),
            "firmware_version": log.controller.firmware_version,
            "protocol_version": log.controller.protocol_version,
        },
        "frames_scheduled": count,
        "complete": complete,
    });
    let folder = writer.finish()?;
    Ok(Acquired {
        folder,
        frames_written: captured as u32,
        complete,
        log,
        camera_failures,
    })
}

fn trigger_record(t: &Triggered, late: bool) -> TriggerRecord {
    TriggerRecord {
        frame_index: u32::from(t.frame),
        timestamp_us: t.timestamp_us,
        vsync_count: t.vsync_count,
        retries: u32::from(t.attempt),
        late,
    }
}

struct AcquireHooks<'a> {
    schedule: &'a RigSchedule,
    projector: &'a mut dyn ProjectorBackend,
    /// What the host last put on screen.
    lit: Option<(u8, Pattern)>,
    frames: mpsc::Sender<Exposure>,
    on_frame: &'a mut dyn FnMut(u32),
}

impl RunHooks for AcquireHooks<'_> {
    fn show(&mut self, request: &PatternRequest) -> Result<(), RigError> {
        let pattern = checked_pattern(self.schedule, request)?;
        self.projector.show(request.projector, &pattern)?;
        self.lit = Some((request.projector, pattern));
        Ok(())
    }

    fn triggered(&mut self, trigger: &Triggered) -> Result<(), RigError> {
        let exposure = Exposure {
            frame: u32::from(trigger.frame),
            lit: self.lit,
        };
        self.frames.send(exposure).map_err(|_| RigError::Backend {
            backend: "camera",
            message: "the camera worker stopped (see the previous error)".into(),
        })?;
        (self.on_frame)(u32::from(trigger.frame));
        Ok(())
    }
}

/// The pattern a request names, checked against the schedule (a controller asking for something
/// the host never scheduled is an error, not something to show).
pub fn checked_pattern(
    schedule: &RigSchedule,
    request: &PatternRequest,
) -> Result<Pattern, RigError> {
    let unknown = || RigError::UnknownRequest {
        frame: request.frame,
        pattern: request.pattern,
    };
    let entry = schedule
        .entries
        .get(usize::from(request.frame))
        .ok_or_else(unknown)?;
    if entry.projector != request.projector || entry.pattern != request.pattern {
        return Err(unknown());
    }
    schedule
        .patterns
        .get(usize::from(request.pattern))
        .copied()
        .ok_or_else(unknown)
}
