//! Projector output windows on a real X server: `mlsss rig show` / `rig displays` / `rig run
//! --projectors windows` under Xvfb, checked by reading the screen back (GetImage on the root
//! window) and comparing it pixel for pixel with the pattern definition.
//!
//! They need `Xvfb` (`apt-get install xvfb`, which `scripts/test.sh` does); without it they FAIL
//! with that command.

use std::io::{BufRead, BufReader};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

use mlsss::booth::Booth;
use mlsss::capture::{Axis, Pattern};
use mlsss_tests::mlsss;
use x11rb::connection::Connection;
use x11rb::protocol::xproto::{ConnectionExt as _, ImageFormat};
use x11rb::protocol::xtest::ConnectionExt as _;
use x11rb::rust_connection::RustConnection;

/// An Xvfb server on a free display number, killed on drop.
struct Xvfb {
    child: Child,
    display: String,
}

impl Xvfb {
    /// A server with one screen (one RandR monitor) of `width` x `height` at 24-bit depth.
    fn start(width: u32, height: u32) -> Self {
        let mut child = Command::new("Xvfb")
            // -noreset: by default Xvfb resets when its last client leaves (each `rig show` and
            // each screenshot connection here is one), and a connection that arrives during the
            // reset is refused; CI once failed on exactly that ("cannot open the X display").
            .args(["-displayfd", "1", "-nolisten", "tcp", "-noreset"])
            .args(["-screen", "0"])
            .arg(format!("{width}x{height}x24"))
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| {
                panic!("Xvfb cannot start ({e}): `apt-get install xvfb` (scripts/test.sh does)")
            });
        // With -displayfd the server writes its display number once it accepts connections.
        let mut line = String::new();
        BufReader::new(child.stdout.take().expect("piped stdout"))
            .read_line(&mut line)
            .expect("Xvfb reports its display");
        let number: u32 = line.trim().parse().expect("Xvfb display number");
        Self {
            child,
            display: format!(":{number}"),
        }
    }

    fn connect(&self) -> RustConnection {
        RustConnection::connect(Some(&self.display))
            .expect("connect to Xvfb")
            .0
    }

    /// The screen's pixels as 8-bit (r, g, b), row-major.
    fn screenshot(&self) -> (u32, u32, Vec<[u8; 3]>) {
        let conn = self.connect();
        let screen = &conn.setup().roots[0];
        let (w, h) = (
            u32::from(screen.width_in_pixels),
            u32::from(screen.height_in_pixels),
        );
        let image = conn
            .get_image(
                ImageFormat::Z_PIXMAP,
                screen.root,
                0,
                0,
                w as u16,
                h as u16,
                !0,
            )
            .expect("GetImage request")
            .reply()
            .expect("GetImage reply");
        assert_eq!(image.depth, 24);
        // Xvfb's 24-bit depth is stored 32 bits per pixel, least significant byte first: B G R X.
        assert_eq!(image.data.len(), (w * h * 4) as usize);
        let pixels = image
            .data
            .chunks_exact(4)
            .map(|p| [p[2], p[1], p[0]])
            .collect();
        (w, h, pixels)
    }

    /// Presses and releases a key (XTEST), as a booth builder would in the window.
    fn press_a_key(&self) {
        let conn = self.connect();
        let root = conn.setup().roots[0].root;
        let keycode = 36; // Return on the default Xvfb keymap; any key ends `rig show`
        for event in [2u8, 3u8] {
            // KeyPress, KeyRelease
            conn.xtest_fake_input(event, keycode, x11rb::CURRENT_TIME, root, 0, 0, 0)
                .expect("XTEST fake input");
        }
        // A reply means the server has handled the fake input before it.
        conn.get_input_focus()
            .expect("GetInputFocus request")
            .reply()
            .expect("X round trip");
    }
}

impl Drop for Xvfb {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `mlsss rig show` running, and its JSON line (printed once the pattern is on screen).
struct Showing {
    child: Child,
    json: serde_json::Value,
    _stdout: BufReader<ChildStdout>,
}

impl Drop for Showing {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn show(x: &Xvfb, args: &[&str]) -> Showing {
    let mut child = mlsss()
        .args(["rig", "show", "--quick", "--json"])
        .args(args)
        .env("DISPLAY", &x.display)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("mlsss runs");
    let mut stdout = BufReader::new(child.stdout.take().expect("piped stdout"));
    let mut line = String::new();
    stdout.read_line(&mut line).expect("rig show prints");
    let json = match serde_json::from_str(&line) {
        Ok(json) => json,
        Err(e) => {
            let out = child.wait_with_output().expect("rig show ends");
            panic!(
                "rig show printed {line:?} ({e}); stderr: {}",
                String::from_utf8_lossy(&out.stderr)
            )
        }
    };
    Showing {
        child,
        json,
        _stdout: stdout,
    }
}

/// The 8-bit code a window shows for a requested level: round(255 * value), independent of the
/// rig's raster code.
fn expected_code(pattern: &Pattern, u: u32, v: u32) -> u8 {
    (f64::from(pattern.value(u, v)) * 255.0).round() as u8
}

/// Asserts every screen pixel: the pattern at the projector's resolution from the top-left
/// corner, black beyond it.
fn assert_screen_shows(x: &Xvfb, pattern: &Pattern, (pw, ph): (u32, u32)) {
    let (w, h, pixels) = x.screenshot();
    let mut wrong = 0usize;
    let mut first = None;
    for y in 0..h {
        for u in 0..w {
            let want = if u < pw && y < ph {
                expected_code(pattern, u, y)
            } else {
                0
            };
            let got = pixels[(y * w + u) as usize];
            if got != [want; 3] {
                wrong += 1;
                first.get_or_insert((u, y, got, want));
            }
        }
    }
    assert_eq!(
        wrong,
        0,
        "{}: {wrong} of {} pixels differ; first (x, y, got, want) = {first:?}",
        pattern.label(),
        w * h
    );
}

#[test]
fn rig_show_puts_every_pattern_kind_on_screen_pixel_for_pixel() {
    let booth = Booth::builtin(true);
    let p = &booth.projectors[0];
    let spec = &booth.patterns;
    let x = Xvfb::start(p.width, p.height);
    let patterns = [
        Pattern::White,
        Pattern::Black,
        Pattern::Grey { level_milli: 500 },
        Pattern::Grey { level_milli: 125 },
        Pattern::Gray {
            axis: Axis::X,
            bit: 0,
            inverted: false,
        },
        Pattern::Gray {
            axis: Axis::Y,
            bit: spec.gray_bits_y - 1,
            inverted: true,
        },
        Pattern::Slit {
            axis: Axis::X,
            width: spec.slit_width_px,
            period: spec.slit_period_px,
            offset: 3 * spec.slit_width_px,
        },
        Pattern::Slit {
            axis: Axis::Y,
            width: spec.slit_width_px,
            period: spec.slit_period_px,
            offset: 0,
        },
        Pattern::HighFrequency {
            stripe: spec.hf_stripe_px,
            shift: 1,
        },
    ];
    let mut last_vblank = 0;
    for pattern in patterns {
        let label = pattern.label();
        let showing = show(&x, &["--projector", "0", "--pattern", &label]);
        assert_eq!(showing.json["pattern"], label.as_str());
        assert_eq!(showing.json["presented"], true);
        assert_eq!(showing.json["native_mode"], true);
        // Acknowledged at a vblank (Xvfb's Present extension counts them), each after the last.
        let vblank = showing.json["vblank_msc"]
            .as_u64()
            .expect("a vblank counter");
        assert!(vblank > last_vblank, "{vblank} after {last_vblank}");
        last_vblank = vblank;
        assert_screen_shows(&x, &pattern, (p.width, p.height));
    }
}

#[test]
fn a_monitor_larger_than_the_projector_shows_the_pattern_unscaled_in_its_corner() {
    let booth = Booth::builtin(true);
    let p = &booth.projectors[1];
    let x = Xvfb::start(p.width + 64, p.height + 48);
    let pattern = Pattern::Gray {
        axis: Axis::X,
        bit: 2,
        inverted: false,
    };
    let showing = show(
        &x,
        &[
            "--projector",
            "1",
            "--monitor",
            "0",
            "--pattern",
            &pattern.label(),
        ],
    );
    assert_eq!(showing.json["native_mode"], false);
    assert_eq!(showing.json["window_width"], p.width + 64);
    assert_screen_shows(&x, &pattern, (p.width, p.height));
}

#[test]
fn a_key_press_ends_rig_show() {
    let x = Xvfb::start(256, 192);
    let mut showing = show(&x, &["--projector", "0", "--pattern", "white"]);
    x.press_a_key();
    let deadline = Instant::now() + Duration::from_secs(20);
    let status = loop {
        if let Some(status) = showing.child.try_wait().expect("poll rig show") {
            break status;
        }
        assert!(Instant::now() < deadline, "rig show ignored the key press");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success());
}

#[test]
fn a_missing_monitor_is_an_error_naming_the_monitors_that_exist() {
    let x = Xvfb::start(256, 192);
    // The quick booth maps projector 2 to monitor 2; Xvfb has one monitor.
    for args in [
        &["--projector", "2", "--pattern", "white"][..],
        &["--projector", "0", "--monitor", "1", "--pattern", "white"][..],
    ] {
        let out = mlsss()
            .args(["rig", "show", "--quick", "--hold", "0"])
            .args(args)
            .env("DISPLAY", &x.display)
            .output()
            .expect("mlsss runs");
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("does not exist"), "{err}");
        assert!(err.contains("monitors: 0 \"screen\" 256x192+0+0"), "{err}");
    }
}

#[test]
fn rig_displays_lists_the_monitor_and_the_projector_mapping() {
    let x = Xvfb::start(256, 192);
    let out = mlsss()
        .args(["rig", "displays", "--quick", "--json"])
        .env("DISPLAY", &x.display)
        .output()
        .expect("mlsss runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    let monitors = json["monitors"].as_array().expect("monitors");
    assert_eq!(monitors.len(), 1);
    assert_eq!(monitors[0]["width"], 256);
    assert_eq!(monitors[0]["height"], 192);
    assert_eq!(monitors[0]["x"], 0);
    assert_eq!(monitors[0]["projectors"], serde_json::json!([0]));
    let projectors = json["projectors"].as_array().expect("projectors");
    assert_eq!(projectors.len(), 4);
    assert_eq!(projectors[0]["monitor_found"], true);
    assert_eq!(projectors[0]["native_mode"], true);
    assert_eq!(projectors[3]["monitor"], 3);
    assert_eq!(projectors[3]["monitor_found"], false);
}

#[test]
fn without_an_x_server_the_display_commands_fail_clearly() {
    let out = mlsss()
        .args(["rig", "displays"])
        .env("DISPLAY", ":59999")
        .output()
        .expect("mlsss runs");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cannot open the X display"), "{err}");
}

/// Named `rig_hil_*` so it runs in the quiet hardware-in-the-loop phase (it boots the firmware
/// under QEMU; see rig_hil.rs).
#[test]
fn rig_hil_run_with_projector_windows_captures_every_frame() {
    let booth = Booth::builtin(true);
    let p = &booth.projectors[0];
    let x = Xvfb::start(p.width, p.height);
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("capture");
    // The first frames of the scan plan are all projector 0's, so one monitor is enough.
    let run = mlsss()
        .args(["rig", "run", "--emulated", "--quick", "--frames", "6"])
        .args(["--projectors", "windows", "--json", "--out"])
        .arg(&out)
        .env("DISPLAY", &x.display)
        .output()
        .expect("mlsss runs");
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&run.stdout).expect("one JSON object");
    assert_eq!(json["complete"], true);
    assert_eq!(json["frames_written"], 6);
    let capture = mlsss::capture::Capture::open(&out).expect("capture folder");
    assert_eq!(capture.manifest.trigger_log.len(), 6);
}

#[test]
fn rig_run_refuses_a_monitor_not_at_the_projectors_native_mode() {
    let x = Xvfb::start(320, 240);
    let dir = tempfile::tempdir().expect("temp dir");
    // The windows open before the controller is contacted, so no controller is needed here.
    let run = mlsss()
        .args([
            "rig",
            "run",
            "--port",
            "/nonexistent/tty",
            "--quick",
            "--frames",
            "2",
        ])
        .args(["--projectors", "windows", "--out"])
        .arg(dir.path().join("capture"))
        .env("DISPLAY", &x.display)
        .output()
        .expect("mlsss runs");
    assert!(!run.status.success());
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(
        err.contains("runs at 320x240") && err.contains("--mode 256x192"),
        "{err}"
    );
}
