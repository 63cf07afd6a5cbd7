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
