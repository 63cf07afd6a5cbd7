//! The release image of the QEMU board (`mlsss-fw-qemu`) under `qemu-system-arm -machine
//! mps2-an386 -icount shift=N,sleep=off`, driven over UART0 through a unix socket: a short
//! schedule runs with every frame triggered on its VSYNC, the measured refresh periods are the
//! generating timers' periods, and two runs give identical trigger logs (virtual time is
//! deterministic).
//!
//! Needs the image (`./build.sh` builds it before the tests) and qemu-system-arm; set
//! `MLSSS_FW_IMAGE` to test another image.

mod common;

use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{booth_entries, booth_header, hello};
use mlsss_shared::framing::{ControllerDecoder, HostEncoder, MAX_WIRE_FRAME_LEN};
use mlsss_shared::message::{
    BoundedVec, ControllerMessage, HostMessage, PatternShown, ProjectorTiming, RunOutcome,
    SCHEDULE_CHUNK_LEN, ScheduleChunk, ScheduleCommit, Triggered,
};
use mlsss_shared::schedule_checksum;

/// Virtual nanoseconds per instruction: 2^ICOUNT_SHIFT.
const ICOUNT_SHIFT: u32 = 4;

fn image() -> PathBuf {
    std::env::var_os("MLSSS_FW_IMAGE")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(env!("CARGO_MANIFEST_DIR"))
                .join("../target/thumbv7em-none-eabihf/release/mlsss-fw-qemu")
        })
}

/// QEMU, killed when dropped (also when a test fails).
struct Qemu {
    child: Child,
    socket: PathBuf,
    /// UART1: the firmware's defmt log frames.
    log: PathBuf,
}

impl Drop for Qemu {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_file(&self.socket);
        let _ = std::fs::remove_file(&self.log);
        let _ = std::fs::remove_file(self.socket.with_extension("stderr"));
    }
}

fn start_qemu(tag: &str) -> (Qemu, UnixStream) {
    let image = image();
    assert!(
        image.exists(),
        "no firmware image at {} (run firmware/build.sh)",
        image.display()
    );
    let socket = std::env::temp_dir().join(format!("mlsss-fw-{}-{tag}.sock", std::process::id()));
    let _ = std::fs::remove_file(&socket);
    let log = socket.with_extension("defmt");
    // QEMU's stderr, shown when it does not come up.
    let stderr = socket.with_extension("stderr");
    let child = Command::new("qemu-system-arm")
        .args(["-machine", "mps2-an386", "-nographic", "-monitor", "none"])
        .args(["-icount", &format!("shift={ICOUNT_SHIFT},sleep=off")])
        .args([
            "-chardev",
            &format!(
                "socket,id=proto,path={},server=on,wait=on",
                socket.display()
            ),
        ])
        .args(["-serial", "chardev:proto", "-serial"])
        .arg(format!("file:{}", log.display()))
        .arg("-kernel")
        .arg(&image)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&stderr).expect("QEMU stderr file"))
        .spawn()
        .expect("qemu-system-arm runs (apt-get install qemu-system-arm)");
    let qemu = Qemu { child, socket, log };
    let deadline = Instant::now() + Duration::from_secs(10);
    let stream = loop {
        match UnixStream::connect(&qemu.socket) {
            Ok(s) => break s,
            Err(_) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(20)),
            Err(e) => panic!(
                "connect to QEMU's UART0 socket: {e}; QEMU said: {}",
                std::fs::read_to_string(&stderr).unwrap_or_default()
            ),
        }
    };
    stream
        .set_read_timeout(Some(Duration::from_millis(5)))
        .expect("socket timeout");
    (qemu, stream)
}

struct Outcome {
    triggers: Vec<Triggered>,
    timing: Vec<ProjectorTiming>,
    late: usize,
    outcome: RunOutcome,
    wall: Duration,
    /// Bytes of defmt log frames the image wrote to UART1.
    log_bytes: u64,
}

/// Runs `per_projector` frames on each projector against the image, answering every pattern
/// request at once.
fn run_image(tag: &str, per_projector: u16) -> Outcome {
    let (qemu, mut stream) = start_qemu(tag);
    let entries = booth_entries(per_projector);
    let mut header = booth_header(entries.len() as u16);
    header.policy.max_retries = 0;
    let mut enc = HostEncoder::new();
    let mut dec = ControllerDecoder::new();
    let mut send = |stream: &mut UnixStream, m: HostMessage| {
        let mut buf = [0u8; MAX_WIRE_FRAME_LEN];
        let (_, bytes) = enc.encode(&m, &mut buf).expect("encode");
        stream.write_all(bytes).expect("write to QEMU");
    };
    let started = Instant::now();
    send(&mut stream, hello());
    send(&mut stream, HostMessage::ScheduleBegin(header));
    for (i, chunk) in entries.chunks(SCHEDULE_CHUNK_LEN).enumerate() {
        send(
            &mut stream,
            HostMessage::ScheduleChunk(ScheduleChunk {
                first_frame: (i * SCHEDULE_CHUNK_LEN) as u16,
                entries: BoundedVec::from_slice(chunk).expect("fits"),
            }),
        );
    }
    send(
        &mut stream,
        HostMessage::ScheduleCommit(ScheduleCommit {
            frame_count: entries.len() as u16,
            checksum: schedule_checksum(&entries),
        }),
    );
    send(&mut stream, HostMessage::Arm);
    send(&mut stream, HostMessage::Start);

    let mut triggers = Vec::new();
    let mut timing = Vec::new();
    let mut late = 0;
    let mut outcome = None;
    let deadline = started + Duration::from_secs(60);
    let mut buf = [0u8; 512];
    while timing.len() < 4 {
        assert!(
            Instant::now() < deadline,
            "no Done from the image within 60 s"
        );
        let n = match stream.read(&mut buf) {
            Ok(0) => panic!("QEMU closed the UART"),
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                continue;
            }
            Err(e) => panic!("read: {e}"),
        };
        let mut replies = Vec::new();
        for frame in dec.feed(&buf[..n]) {
            match frame.expect("valid frame from the image").message {
                ControllerMessage::PatternRequest(r) => {
                    replies.push(HostMessage::PatternShown(PatternShown {
                        frame: r.frame,
                        attempt: r.attempt,
                        pattern: r.pattern,
                    }))
                }
                ControllerMessage::Triggered(t) => triggers.push(t),
                ControllerMessage::FrameLate(l) => {
                    eprintln!("late: {l:?}");
                    late += 1;
                }
                ControllerMessage::Done(d) => outcome = Some(d.outcome),
                ControllerMessage::ProjectorTiming(t) if outcome.is_some() => timing.push(t),
                ControllerMessage::Nack(n) => panic!("nack {n:?}"),
                _ => {}
            }
        }
        for r in replies {
            send(&mut stream, r);
        }
    }
    let log_bytes = std::fs::metadata(&qemu.log).map_or(0, |m| m.len());
    Outcome {
        log_bytes,
        triggers,
        timing,
        late,
        outcome: outcome.expect("Done"),
        wall: started.elapsed(),
    }
}

/// Frames per projector: 2 by default (fast); `MLSSS_FW_FRAMES_PER_PROJECTOR=67` runs the
/// full 268-frame scan (to measure its wall time).
fn frames_per_projector() -> u16 {
    std::env::var("MLSSS_FW_FRAMES_PER_PROJECTOR")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2)
}

#[test]
fn image_runs_a_schedule_on_its_timer_vsyncs_deterministically() {
    let per_projector = frames_per_projector();
    let frames = 4 * usize::from(per_projector);
    let a = run_image("a", per_projector);
    let virtual_s = a
        .triggers
        .last()
        .map_or(0.0, |t| t.timestamp_us as f64 / 1e6);
    eprintln!(
        "{frames} frames under QEMU icount shift={ICOUNT_SHIFT}: {:.2} s wall, {virtual_s:.2} s virtual",
        a.wall.as_secs_f64()
    );
    assert_eq!(a.outcome, RunOutcome::Completed);
    // The defmt logs went to UART1 (and every UART0 frame decoded: nothing mixed in).
    assert!(a.log_bytes > 0, "no defmt log frames on UART1");
    assert_eq!(a.late, 0);
    assert_eq!(a.triggers.len(), frames);
    for t in &a.triggers {
        assert_eq!(t.vsync_count - t.shown_vsync_count, 2);
        let alignment = t.timestamp_us - t.vsync_timestamp_us;
        assert!(
            (500..=503).contains(&alignment),
            "frame {} alignment {alignment}",
            t.frame
        );
    }
    for pair in a
        .triggers
        .windows(2)
        .filter(|p| p[0].projector == p[1].projector)
    {
        assert_eq!(pair[1].vsync_count - pair[0].vsync_count, 12);
    }
    // The generators: 25 MHz / round(25 MHz / f) ticks, f of hardware/booth.toml.
    for t in &a.timing {
        let hz = [60.00, 59.94, 60.02, 59.97][usize::from(t.projector)];
        let ticks = (25e6f64 / hz).round();
        let expected_ns = ticks * 40.0;
        assert!(
            (f64::from(t.period_ns) - expected_ns).abs() < 100.0,
            "projector {} period {} ns, timer {expected_ns} ns",
            t.projector,
            t.period_ns
        );
    }
    let b = run_image("b", per_projector);
    assert_eq!(a.triggers, b.triggers, "trigger logs of two runs differ");
}
