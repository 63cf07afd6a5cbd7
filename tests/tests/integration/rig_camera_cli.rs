//! `mlsss rig cameras` / `rig ports` / `rig run --camera u3v` on a machine without cameras: the
//! listings succeed (empty) and a capture that needs a camera fails before touching the
//! controller, naming the cause.

use mlsss_tests::mlsss;

#[test]
fn rig_cameras_lists_no_camera_and_exits_zero() {
    let out = mlsss()
        .args(["rig", "cameras", "--json"])
        .output()
        .expect("mlsss runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    let cameras = json["cameras"].as_array().expect("cameras array");
    // This machine has no USB camera; where libusb cannot start the reason is given.
    assert!(cameras.is_empty(), "{json}");
    assert!(json["usb_unavailable"].is_null() || json["usb_unavailable"].is_string());
}

#[test]
fn rig_ports_names_where_its_usb_list_came_from() {
    let out = mlsss()
        .args(["rig", "ports", "--json"])
        .output()
        .expect("mlsss runs");
    assert!(out.status.success());
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    assert!(json["usb_devices"].is_array());
    assert!(matches!(
        json["usb_source"].as_str(),
        Some("libusb" | "sysfs")
    ));
}

#[test]
fn a_capture_with_a_u3v_camera_that_is_not_there_fails_clearly() {
    let dir = tempfile::tempdir().expect("temp dir");
    let out = mlsss()
        .args([
            "rig",
            "run",
            "--port",
            "/nonexistent/tty",
            "--quick",
            "--frames",
            "2",
        ])
        .args(["--camera", "u3v:12345", "--out"])
        .arg(dir.path().join("capture"))
        .output()
        .expect("mlsss runs");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("u3v camera"), "{err}");
    // The camera is opened before the controller's port.
    assert!(!err.contains("/nonexistent/tty"), "{err}");
}

/// A camera that loses the first payload of some frames (as the U3V backend reports a dropped
/// one, `RigError::PayloadLost`), or fails for good on one frame (an unplugged camera).
struct LosesPayloads {
    inner: mlsss::rig::backend::PatternCamera,
    lose_once: Vec<u32>,
    unplugged_at: Option<u32>,
}

impl mlsss::rig::backend::CameraBackend for LosesPayloads {
    fn capture(
        &mut self,
        exposure: &mlsss::rig::backend::Exposure,
    ) -> Result<image::Rgb32FImage, mlsss::rig::RigError> {
        if self.unplugged_at == Some(exposure.frame) {
            return Err(mlsss::rig::RigError::Backend {
                backend: "test camera",
                message: format!("frame {}: the camera was disconnected", exposure.frame),
            });
        }
        if let Some(i) = self.lose_once.iter().position(|&f| f == exposure.frame) {
            self.lose_once.swap_remove(i);
            return Err(mlsss::rig::RigError::PayloadLost {
                backend: "test camera",
                frame: exposure.frame,
                message: format!("frame {}: payload dropped", exposure.frame),
            });
        }
        self.inner.capture(exposure)
    }
}

/// Runs an 8-frame quick scan under QEMU through `camera`.
fn acquire_8_frames(camera: LosesPayloads, out: &std::path::Path) -> mlsss::rig::acquire::Acquired {
    use mlsss::booth::Booth;
    use mlsss::capture::FramePlan;
    use mlsss::rig::acquire::{CaptureTarget, acquire};
    use mlsss::rig::backend::VirtualProjectors;
    use mlsss::rig::link::ControllerLink;
    use mlsss::rig::qemu::{self, DEFAULT_ICOUNT_SHIFT};
    use mlsss::rig::schedule::RigSchedule;
    use mlsss::rig::session::{HostFaults, Session};

    let booth = Booth::builtin(true);
    let plan = FramePlan::scan(&booth.patterns, booth.projectors.len());
    let schedule = RigSchedule::from_plan(&plan, &booth.timing, Some(8)).expect("schedule");
    let (_qemu, port) =
        qemu::spawn(&qemu::default_firmware_image(), DEFAULT_ICOUNT_SHIFT).expect("QEMU starts");
    let mut session = Session::open(ControllerLink::new(port)).expect("handshake");
    acquire(
        &mut session,
        &schedule,
        CaptureTarget {
            booth: &booth,
            plan: &plan,
            out,
            source: serde_json::json!("lost-payload test"),
        },
        &mut VirtualProjectors::new(),
        Box::new(camera),
        &HostFaults::default(),
        &mut |_| {},
    )
    .expect("the run finishes and the folder is written")
}

/// Named `rig_hil_*`: boots the firmware under QEMU, so it runs in the quiet phase.
#[test]
fn rig_hil_lost_camera_payloads_are_retriggered_and_the_capture_has_every_frame() {
    use mlsss::booth::Booth;
    use mlsss::capture::{Capture, FramePlan};
    use mlsss::rig::backend::{CameraBackend, Exposure, PatternCamera};
    use mlsss_shared::message::Retrigger;

    let booth = Booth::builtin(true);
    let plan = FramePlan::scan(&booth.patterns, booth.projectors.len());
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("capture");
    // Frame 2 mid-run, frame 7 (the last one) after the controller's first Done.
    let acquired = acquire_8_frames(
        LosesPayloads {
            inner: PatternCamera::new(&booth),
            lose_once: vec![2, 7],
            unplugged_at: None,
        },
        &out,
    );
    assert!(acquired.complete, "{:?}", acquired.camera_failures);
    assert_eq!(acquired.frames_written, 8);
    assert!(acquired.camera_failures.is_empty());
    let log = &acquired.log;
    assert_eq!(
        log.retriggers,
        [
            Retrigger {
                frame: 2,
                attempt: 0
            },
            Retrigger {
                frame: 7,
                attempt: 0
            }
        ]
    );
    assert!(log.retrigger_refusals.is_empty());
    assert!(log.duplicate_triggers.is_empty());
    for frame in [2u16, 7] {
        assert_eq!(log.triggers[&frame].attempt, 1, "frame {frame} re-run");
        assert!(
            log.retried
                .iter()
                .any(|r| r.frame == frame && r.attempt == 1)
        );
    }
    assert_eq!(
        log.done.outcome,
        mlsss_shared::message::RunOutcome::Completed
    );
    assert_eq!(log.done.frames_triggered, 10, "8 frames + 2 re-runs");

    // capture.json: every frame, the re-triggered ones with their re-run's record, and each
    // image the pattern of its own frame.
    let capture = Capture::open(&out).expect("capture folder");
    assert_eq!(capture.manifest.trigger_log.len(), 8);
    assert_eq!(
        capture.manifest.source["retriggered_frames"],
        serde_json::json!([2, 7])
    );
    let mut camera = PatternCamera::new(&booth);
    for frame in 0..8u32 {
        let record = &capture.manifest.trigger_log[frame as usize];
        let rerun = frame == 2 || frame == 7;
        assert_eq!(record.retries, u32::from(rerun), "frame {frame}");
        let spec = &plan.frames[frame as usize];
        let expected = camera
            .capture(&Exposure::nominal(
                frame,
                spec.projector.map(|p| (p, spec.pattern)),
            ))
            .expect("pattern image");
        let image = capture.read_frame(frame).expect("frame written");
        let max_diff = image
            .pixels()
            .zip(expected.pixels())
            .map(|(a, b)| (a.0[0] - b.0[0]).abs())
            .fold(0.0f32, f32::max);
        assert!(max_diff < 1e-3, "frame {frame} shows another pattern");
    }
}

/// Named `rig_hil_*`: boots the firmware under QEMU, so it runs in the quiet phase.
#[test]
fn rig_hil_a_camera_failure_that_is_no_lost_payload_keeps_the_frames_before_it() {
    use mlsss::booth::Booth;
    use mlsss::capture::Capture;
    use mlsss::rig::backend::PatternCamera;

    let booth = Booth::builtin(true);
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("capture");
    let acquired = acquire_8_frames(
        LosesPayloads {
            inner: PatternCamera::new(&booth),
            lose_once: vec![],
            unplugged_at: Some(5),
        },
        &out,
    );
    assert!(!acquired.complete);
    assert_eq!(acquired.frames_written, 5);
    assert_eq!(acquired.camera_failures.len(), 1);
    assert_eq!(acquired.camera_failures[0].0, 5);
    assert!(acquired.camera_failures[0].1.contains("disconnected"));
    assert!(
        acquired.log.retriggers.is_empty(),
        "not a payload to re-trigger"
    );
    let capture = Capture::open(&out).expect("capture folder");
    assert_eq!(capture.manifest.plan.frames.len(), 5);
    assert_eq!(capture.manifest.trigger_log.len(), 5);
}
