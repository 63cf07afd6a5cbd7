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

/// A camera that loses one frame's payload (as the U3V backend reports a dropped one).
struct LosesFrame {
    inner: mlsss::rig::backend::PatternCamera,
    lost: u32,
}

impl mlsss::rig::backend::CameraBackend for LosesFrame {
    fn capture(
        &mut self,
        exposure: &mlsss::rig::backend::Exposure,
    ) -> Result<image::Rgb32FImage, mlsss::rig::RigError> {
        if exposure.frame == self.lost {
            return Err(mlsss::rig::RigError::Backend {
                backend: "test camera",
                message: format!("frame {}: payload dropped", exposure.frame),
            });
        }
        self.inner.capture(exposure)
    }
}

/// Named `rig_hil_*`: boots the firmware under QEMU, so it runs in the quiet phase.
#[test]
fn rig_hil_a_lost_camera_frame_is_reported_and_the_frames_before_it_are_kept() {
    use mlsss::booth::Booth;
    use mlsss::capture::{Capture, FramePlan};
    use mlsss::rig::acquire::{CaptureTarget, acquire};
    use mlsss::rig::backend::{PatternCamera, VirtualProjectors};
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
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("capture");
    let acquired = acquire(
        &mut session,
        &schedule,
        CaptureTarget {
            booth: &booth,
            plan: &plan,
            out: &out,
            source: serde_json::json!("lost-frame test"),
        },
        &mut VirtualProjectors::new(),
        Box::new(LosesFrame {
            inner: PatternCamera::new(&booth),
            lost: 5,
        }),
        &HostFaults::default(),
        &mut |_| {},
    )
    .expect("the run finishes and the folder is written");
    assert!(!acquired.complete);
    assert_eq!(acquired.frames_written, 5);
    assert_eq!(acquired.camera_failures.len(), 1);
    assert_eq!(acquired.camera_failures[0].0, 5);
    assert!(acquired.camera_failures[0].1.contains("payload dropped"));
    let capture = Capture::open(&out).expect("capture folder");
    assert_eq!(capture.manifest.plan.frames.len(), 5);
    assert_eq!(capture.manifest.trigger_log.len(), 5);
}
