//! A capture run: drive the schedule, show each requested pattern, fetch the camera image of
//! each triggered frame (matched to its trigger by frame index), write the capture folder
//! atomically with the controller's trigger log.
//!
//! Camera images are fetched and written on a worker thread so the link loop always answers
//! the controller in time. A payload the camera lost (dropped, incomplete, wrong size, never
//! arrived: [`RigError::PayloadLost`]) is re-triggered: the worker reports it, the run loop sends
//! `Retrigger`, and the controller runs the frame again in a later slot (up to
//! [`MAX_RETRIGGERS_PER_FRAME`] times); every re-trigger is in the run log and `capture.json`.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::thread;

use mlsss_shared::message::{PatternRequest, Retrigger, Triggered};

use super::RigError;
use super::backend::{CameraBackend, Exposure, ProjectorBackend};
use super::link::ByteLink;
use super::schedule::RigSchedule;
use super::session::{HostFaults, RunHooks, RunLog, Session};
use mlsss_core::booth::Booth;
use mlsss_core::capture::folder::CaptureKind;
use mlsss_core::capture::{CaptureManifest, CaptureWriter, FramePlan, Pattern, TriggerRecord};

/// Re-triggers of one frame before its lost payload counts as a camera failure.
pub const MAX_RETRIGGERS_PER_FRAME: u32 = 3;

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
    camera: Box<dyn CameraBackend>,
    faults: &HostFaults,
    on_frame: &mut dyn FnMut(u32),
) -> Result<Acquired, RigError> {
    let count = schedule.entries.len();
    let plan = FramePlan {
        frames: target.plan.frames[..count.min(target.plan.len())].to_vec(),
    };
    let mut manifest = CaptureManifest::new(CaptureKind::Scan, target.booth.clone(), plan.clone());
    // The exposure each projector's frames are taken with (the schedule carries it).
    manifest.exposure = schedule.exposure.clone();
    let writer = CaptureWriter::create(target.out, manifest)?;

    let (tx, rx) = mpsc::channel::<(Exposure, u8)>();
    let (report_tx, report_rx) = mpsc::channel::<Option<Retrigger>>();
    let worker = thread::spawn(move || camera_worker(camera, writer, rx, report_tx));

    let mut hooks = AcquireHooks {
        schedule,
        projector,
        lit: None,
        frames: tx,
        reports: report_rx,
        sent: 0,
        processed: 0,
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
    let retriggered: BTreeSet<u16> = log.retriggers.iter().map(|r| r.frame).collect();
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
        // Frames run again because the camera lost their payload (their trigger record is the
        // re-run's, `retries` >= 1).
        "retriggered_frames": retriggered,
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

/// What the camera worker returns: the writer, the frames written, and the frames whose image
/// could not be had (with the reason) after any re-triggers.
type WorkerResult = Result<(CaptureWriter, BTreeSet<u32>, Vec<(u32, String)>), RigError>;

/// Fetches and writes the image of each triggered frame (with the attempt that triggered it).
/// For each one it reports to the run loop `Some(retrigger)` when the payload was lost and the
/// frame may be re-triggered, else `None`. Other camera failures are recorded for their frame
/// and the worker goes on (the next trigger's payload may well arrive); only a failure to write
/// the folder stops it.
fn camera_worker(
    mut camera: Box<dyn CameraBackend>,
    writer: CaptureWriter,
    exposures: mpsc::Receiver<(Exposure, u8)>,
    reports: mpsc::Sender<Option<Retrigger>>,
) -> WorkerResult {
    let mut written = BTreeSet::new();
    let mut failures = Vec::new();
    let mut retriggers: BTreeMap<u32, u32> = BTreeMap::new();
    for (exposure, attempt) in exposures {
        let mut report = None;
        match camera.capture(&exposure) {
            Ok(image) => {
                writer.write_frame(exposure.frame, &image)?;
                written.insert(exposure.frame);
            }
            Err(RigError::PayloadLost { frame, .. })
                if retriggers.get(&frame).copied().unwrap_or(0) < MAX_RETRIGGERS_PER_FRAME =>
            {
                *retriggers.entry(frame).or_default() += 1;
                report = u16::try_from(frame)
                    .ok()
                    .map(|frame| Retrigger { frame, attempt });
            }
            Err(e) => failures.push((exposure.frame, e.to_string())),
        }
        // The run loop may be gone (it failed); the frame is then reported by the folder.
        let _ = reports.send(report);
    }
    Ok((writer, written, failures))
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
    frames: mpsc::Sender<(Exposure, u8)>,
    /// One report per frame the worker processed: a lost payload to re-trigger, or none.
    reports: mpsc::Receiver<Option<Retrigger>>,
    /// Frames sent to the worker, and reports received back.
    sent: usize,
    processed: usize,
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
            scale: self.lit.map_or(1.0, |(projector, _)| {
                self.schedule.exposure_scale(projector)
            }),
        };
        self.frames
            .send((exposure, trigger.attempt))
            .map_err(|_| RigError::Backend {
                backend: "camera",
                message: "the camera worker stopped (see the previous error)".into(),
            })?;
        self.sent += 1;
        (self.on_frame)(u32::from(trigger.frame));
        Ok(())
    }

    fn lost_payloads(&mut self, wait_for_all: bool) -> Result<Vec<Retrigger>, RigError> {
        let mut lost = vec![];
        loop {
            let report = if wait_for_all && self.processed < self.sent {
                // A stopped worker ends the wait (its error is reported after the run).
                self.reports.recv().ok()
            } else {
                self.reports.try_recv().ok()
            };
            let Some(report) = report else {
                return Ok(lost);
            };
            self.processed += 1;
            lost.extend(report);
        }
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
