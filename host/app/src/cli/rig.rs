//! `mlsss rig`: find controllers, run a capture, measure the controller's timing.

use std::collections::BTreeSet;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use indicatif::{ProgressBar, ProgressStyle};
use mlsss::booth::Booth;
use mlsss::capture::exposure::MeteringTarget;
use mlsss::capture::{Capture, FramePlan};
use mlsss::rig::acquire::{CaptureTarget, acquire};
use mlsss::rig::backend::{
    CameraBackend, PatternCamera, ProjectorBackend, ReplayCamera, VirtualProjectors,
};
use mlsss::rig::camera::u3v::{PAYLOAD_TIMEOUT, U3vCamera, U3vSettings, list_cameras};
use mlsss::rig::display::{self, ProjectorWindows};
use mlsss::rig::link::{ByteLink, ControllerLink};
use mlsss::rig::metering::meter_projectors;
use mlsss::rig::pattern_label::pattern_by_label;
use mlsss::rig::qemu::{self, QemuGuard};
use mlsss::rig::schedule::RigSchedule;
use mlsss::rig::session::{HostFaults, RunHooks, Session};
use mlsss::rig::timing::timing_report;
use mlsss::rig::{RigError, ports};
use mlsss_shared::message::{PatternRequest, Triggered};
use serialport::SerialPort;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(subcommand)]
    command: RigCommand,
}

#[derive(Debug, clap::Subcommand)]
enum RigCommand {
    /// List serial ports and USB devices, marking those that look like a controller.
    Ports(PortsArgs),
    /// Run a capture on the controller and write the capture folder.
    Run(RunArgs),
    /// Run the full schedule against the firmware and report its timing.
    TimingTest(TimingArgs),
    /// List the USB3 Vision cameras (an empty list when there is none).
    Cameras(CamerasArgs),
    /// List the monitors of the X display and which projector maps to each.
    Displays(DisplaysArgs),
    /// Show one pattern fullscreen on a projector's monitor until --hold ends or a key is
    /// pressed (focusing and alignment).
    Show(ShowArgs),
}

/// Which booth file.
#[derive(Debug, clap::Args)]
struct BoothChoice {
    /// Booth file (default: the built-in hardware/booth.toml).
    #[arg(long)]
    booth: Option<PathBuf>,
    /// Use the built-in --quick booth (small images).
    #[arg(long, conflicts_with = "booth")]
    quick: bool,
}

impl BoothChoice {
    fn load(&self) -> anyhow::Result<Booth> {
        Ok(match &self.booth {
            Some(path) => Booth::from_file(path)
                .with_context(|| format!("loading booth {}", path.display()))?,
            None => Booth::builtin(self.quick),
        })
    }
}

#[derive(Debug, clap::Args)]
struct CamerasArgs {
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

/// How a real camera is configured (`--camera u3v[:SERIAL]`).
#[derive(Debug, clap::Args)]
struct CameraSettingsArgs {
    /// Pixel format of a u3v camera (GenICam PFNC): Mono12, Mono12p, Mono12Packed, BayerRG12,
    /// BayerRG12p, BayerRG12Packed (and GR/GB/BG), or 8-bit Mono8/BayerRG8.
    #[arg(long, default_value = "Mono12")]
    pixel_format: String,
    /// The camera input wired to the controller's trigger output (hardware/wiring.md).
    #[arg(long, default_value = "Line0")]
    trigger_line: String,
    /// Analogue gain of a u3v camera, dB.
    #[arg(long, default_value_t = 0.0, value_parser = super::number_arg::finite)]
    gain_db: f64,
}

#[derive(Debug, clap::Args)]
struct DisplaysArgs {
    #[command(flatten)]
    booth: BoothChoice,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, clap::Args)]
struct ShowArgs {
    #[command(flatten)]
    booth: BoothChoice,
    /// The projector (0-based, as in the booth file).
    #[arg(long)]
    projector: u8,
    /// The monitor to show on (default: the one the booth maps the projector to).
    #[arg(long)]
    monitor: Option<usize>,
    /// The pattern by its capture label: white, black, grey-N (thousandths), gray-x-bN[-inv],
    /// gray-y-bN[-inv], slit-x-oN, slit-y-oN, hf-sN.
    #[arg(long)]
    pattern: String,
    /// Seconds to show it (default: until a key is pressed in the window; 0: present and leave).
    #[arg(long, value_parser = super::number_arg::non_negative_finite)]
    hold: Option<f64>,
    /// Print one JSON object on stdout once the pattern is on screen.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, clap::Args)]
struct PortsArgs {
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

/// Where the controller is.
#[derive(Debug, clap::Args)]
struct ControllerArgs {
    /// Serial port of a real controller (e.g. /dev/ttyACM0).
    #[arg(
        long,
        conflicts_with = "emulated",
        required_unless_present = "emulated"
    )]
    port: Option<String>,
    /// Baud rate of --port.
    #[arg(long, default_value_t = 115_200)]
    baud: u32,
    /// Boot the real firmware image under QEMU (mps2-an386) instead of using a board.
    #[arg(long)]
    emulated: bool,
    /// Firmware image for --emulated (default: the one scripts/test.sh builds).
    #[arg(long, requires = "emulated")]
    firmware: Option<PathBuf>,
    /// QEMU -icount shift (2^N ns of virtual time per instruction) for --emulated.
    #[arg(long, default_value_t = qemu::DEFAULT_ICOUNT_SHIFT, requires = "emulated")]
    icount_shift: u8,
}

#[derive(Debug, clap::Args)]
struct BoothArgs {
    /// Booth file (default: the built-in hardware/booth.toml).
    #[arg(long)]
    booth: Option<PathBuf>,
    /// Use the built-in --quick booth (small images).
    #[arg(long, conflicts_with = "booth")]
    quick: bool,
    /// Run only the first N frames of the scan plan (default: all).
    #[arg(long)]
    frames: Option<usize>,
}

#[derive(Debug, clap::Args)]
struct RunArgs {
    #[command(flatten)]
    controller: ControllerArgs,
    #[command(flatten)]
    booth: BoothArgs,
    /// Output capture folder (must not exist).
    #[arg(long, default_value = "out/rig-capture")]
    out: PathBuf,
    /// Projector backend: `virtual` keeps the patterns in memory; `windows` shows them fullscreen
    /// on the monitors the booth maps the projectors to (X11), acknowledging each frame to the
    /// controller once it has been presented.
    #[arg(long, default_value = "virtual")]
    projectors: String,
    /// Camera backend: `virtual` renders the pattern on screen (`virtual:R`: on a grey screen
    /// of reflectance R, a dim subject); `replay:DIR` replays the frames of a recorded capture
    /// folder; `u3v` or `u3v:SERIAL` streams a USB3 Vision camera in hardware-trigger mode
    /// (exposure from the booth's camera.exposure_ms, lengthened by metering through the
    /// trigger pulse).
    #[arg(long, default_value = "virtual")]
    camera: String,
    #[command(flatten)]
    camera_settings: CameraSettingsArgs,
    /// Skip the metering step (one white frame per projector before the scan, from which each
    /// projector's exposure is chosen): every frame at the booth's nominal exposure.
    #[arg(long)]
    fixed_exposure: bool,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, clap::Args)]
struct TimingArgs {
    #[command(flatten)]
    controller: ControllerArgs,
    #[command(flatten)]
    booth: BoothArgs,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    match args.command {
        RigCommand::Ports(a) => run_ports(a),
        RigCommand::Run(a) => run_capture(a),
        RigCommand::TimingTest(a) => run_timing(a),
        RigCommand::Cameras(a) => run_cameras(a),
        RigCommand::Displays(a) => run_displays(a),
        RigCommand::Show(a) => run_show(a),
    }
}

fn run_ports(args: PortsArgs) -> anyhow::Result<()> {
    let serial = ports::serial_ports().context("enumerating serial ports")?;
    let (usb, usb_source) = ports::usb_devices_any(std::path::Path::new("/sys/bus/usb/devices"));
    if args.json {
        println!(
            "{}",
            serde_json::json!({ "serial_ports": serial, "usb_devices": usb, "usb_source": usb_source })
        );
        return Ok(());
    }
    println!("serial ports:");
    if serial.is_empty() {
        println!("  (none)");
    }
    for p in &serial {
        let ids = match (p.vid, p.pid) {
            (Some(v), Some(d)) => format!(" {v:04x}:{d:04x}"),
            _ => String::new(),
        };
        let mark = p
            .controller
            .as_deref()
            .map(|r| format!("  <- controller? {r}"));
        println!("  {}{ids}{}", p.path, mark.unwrap_or_default());
    }
    println!(
        "usb devices ({}):",
        match usb_source {
            ports::UsbSource::Libusb => "libusb",
            ports::UsbSource::Sysfs => "sysfs; libusb could not start",
        }
    );
    if usb.is_empty() {
        println!("  (none)");
    }
    for d in &usb {
        let mark = d
            .controller
            .as_deref()
            .map(|r| format!("  <- controller? {r}"));
        println!(
            "  {} {:04x}:{:04x} {}{}",
            d.bus_path,
            d.vid,
            d.pid,
            d.product.as_deref().unwrap_or(""),
            mark.unwrap_or_default()
        );
    }
    Ok(())
}

/// An open controller connection, and QEMU if emulated (killed when this drops).
struct Connection {
    port: Box<dyn SerialPort>,
    _qemu: Option<QemuGuard>,
    description: serde_json::Value,
}

fn connect(args: &ControllerArgs) -> anyhow::Result<Connection> {
    if args.emulated {
        let image = args
            .firmware
            .clone()
            .unwrap_or_else(qemu::default_firmware_image);
        let (guard, port) = qemu::spawn(&image, args.icount_shift)?;
        Ok(Connection {
            port,
            _qemu: Some(guard),
            description: serde_json::json!({
                "emulated": true,
                "firmware": image.display().to_string(),
                "icount_shift": args.icount_shift,
            }),
        })
    } else {
        let path = args.port.as_deref().unwrap_or_default();
        let port = serialport::new(path, args.baud)
            .timeout(Duration::from_millis(50))
            .open()
            .with_context(|| format!("opening serial port {path} (see `mlsss rig ports`)"))?;
        Ok(Connection {
            port,
            _qemu: None,
            description: serde_json::json!({ "port": path, "baud": args.baud }),
        })
    }
}

fn load_booth(args: &BoothArgs) -> anyhow::Result<(Booth, FramePlan)> {
    let booth = match &args.booth {
        Some(path) => {
            Booth::from_file(path).with_context(|| format!("loading booth {}", path.display()))?
        }
        None => Booth::builtin(args.quick),
    };
    let plan = FramePlan::scan(&booth.patterns, booth.projectors.len());
    if args.frames == Some(0) {
        bail!("--frames must be at least 1");
    }
    Ok((booth, plan))
}

fn progress_bar(frames: usize) -> ProgressBar {
    let bar = ProgressBar::new(frames as u64);
    bar.set_style(
        ProgressStyle::with_template("{prefix} [{bar:40}] {pos}/{len} frames {elapsed}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_prefix("rig");
    bar
}

fn open_session<L: ByteLink>(link: ControllerLink<L>) -> anyhow::Result<Session<L>> {
    let session = Session::open(link).context("handshake with the controller")?;
    let c = session.controller();
    eprintln!(
        "controller: {:?}, firmware {}.{}.{}, protocol {}, {} projectors",
        c.board,
        c.firmware_version[0],
        c.firmware_version[1],
        c.firmware_version[2],
        c.protocol_version,
        c.projectors
    );
    Ok(session)
}

/// What a camera is opened for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum CameraRole {
    /// The metering run (white per projector, in an order of its own).
    Metering,
    /// The scan.
    Scan,
}

/// Whether `--camera` names a USB3 Vision camera.
fn is_u3v(camera: &str) -> bool {
    camera == "u3v" || camera.starts_with("u3v:")
}

/// The camera backend `--camera` names.
fn open_camera(
    args: &RunArgs,
    booth: &Booth,
    role: CameraRole,
) -> anyhow::Result<Box<dyn CameraBackend>> {
    if let Some(dir) = args.camera.strip_prefix("replay:") {
        let capture = Capture::open(std::path::Path::new(dir))
            .with_context(|| format!("opening the capture to replay, {dir}"))?;
        return Ok(Box::new(match role {
            CameraRole::Metering => ReplayCamera::by_pattern(capture),
            CameraRole::Scan => ReplayCamera::new(capture),
        }));
    }
    if let Some(rest) = args.camera.strip_prefix("virtual") {
        let reflectance = match rest.strip_prefix(':') {
            None if rest.is_empty() => 1.0,
            Some(r) => r
                .parse::<f32>()
                .ok()
                .filter(|r| r.is_finite() && (0.0..=1.0).contains(r))
                .with_context(|| {
                    format!(
                        "--camera {}: the reflectance must be a number in 0-1",
                        args.camera
                    )
                })?,
            None => bail!(
                "unknown --camera '{}': use `virtual`, `virtual:R`, `replay:DIR`, `u3v` or `u3v:SERIAL`",
                args.camera
            ),
        };
        return Ok(Box::new(
            PatternCamera::new(booth).with_reflectance(reflectance),
        ));
    }
    match args.camera.as_str() {
        c if is_u3v(c) => {
            let settings = U3vSettings {
                serial: args.camera.strip_prefix("u3v:").map(str::to_owned),
                pixel_format: args.camera_settings.pixel_format.clone(),
                exposure_us: booth.camera.exposure_ms * 1000.0,
                gain_db: args.camera_settings.gain_db,
                trigger_line: args.camera_settings.trigger_line.clone(),
                width: booth.camera.width,
                height: booth.camera.height,
                payload_timeout: PAYLOAD_TIMEOUT,
            };
            let camera = U3vCamera::open(&settings)?;
            let c = camera.summary();
            if role == CameraRole::Scan {
                eprintln!("camera: {} {} serial {}", c.vendor, c.model, c.serial);
            }
            Ok(Box::new(camera))
        }
        _ => bail!(
            "unknown --camera '{}': use `virtual`, `virtual:R`, `replay:DIR`, `u3v` or `u3v:SERIAL`",
            args.camera
        ),
    }
}

/// The metering step: each projector `schedule` lights shows white once at the nominal
/// exposure; returns the schedule with the exposures chosen from those frames. `out` is the
/// scan's capture folder. Without `gain_per_projector` (a real camera, whose exposure follows
/// the trigger pulse but whose analog gain the rig does not yet set per projector) metering
/// lengthens the exposure only.
fn metered<L: ByteLink>(
    session: &mut Session<L>,
    schedule: RigSchedule,
    booth: &Booth,
    projectors: &mut dyn ProjectorBackend,
    camera: Box<dyn CameraBackend>,
    out: &std::path::Path,
    gain_per_projector: bool,
) -> anyhow::Result<RigSchedule> {
    let lit: Vec<u8> = schedule
        .entries
        .iter()
        .map(|e| e.projector)
        .collect::<BTreeSet<u8>>()
        .into_iter()
        .collect();
    // The metering frames go to a hidden folder beside the capture, removed once read (also
    // one a killed run left behind).
    let name = out.file_name().unwrap_or_default().to_string_lossy();
    let scratch = out.with_file_name(format!(".{name}.metering"));
    let remove_scratch = || match std::fs::remove_dir_all(&scratch) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
        _ => Ok(()),
    };
    remove_scratch().with_context(|| format!("removing {}", scratch.display()))?;
    let target = MeteringTarget {
        max_analog_gain: if gain_per_projector {
            MeteringTarget::default().max_analog_gain
        } else {
            1.0
        },
        ..MeteringTarget::default()
    };
    let exposure = meter_projectors(
        session,
        booth,
        &lit,
        &scratch,
        (projectors, camera),
        &target,
    )
    .context("metering (run with --fixed-exposure to skip it)");
    remove_scratch().with_context(|| format!("removing {}", scratch.display()))?;
    let exposure = exposure?;
    for e in &exposure {
        eprintln!(
            "projector {}: exposure {} refresh periods, analog gain {:.2} ({:.2}x nominal)",
            e.projector, e.periods, e.analog_gain, e.scale
        );
    }
    Ok(schedule.with_exposure(&exposure)?)
}

fn run_capture(args: RunArgs) -> anyhow::Result<()> {
    let (booth, plan) = load_booth(&args.booth)?;
    let mut schedule = RigSchedule::from_plan(&plan, &booth.timing, args.booth.frames)?;
    let metering_camera = match args.fixed_exposure {
        true => None,
        false => Some(open_camera(&args, &booth, CameraRole::Metering)?),
    };
    // Windows first: a missing monitor or a wrong mode fails before the controller is touched.
    let mut projectors = projector_backend(&args.projectors, &booth, &schedule)?;
    let connection = connect(&args.controller)?;
    let mut session = open_session(ControllerLink::new(connection.port))?;
    if let Some(camera) = metering_camera {
        schedule = metered(
            &mut session,
            schedule,
            &booth,
            projectors.as_mut(),
            camera,
            &args.out,
            !is_u3v(&args.camera),
        )?;
    }
    let camera = open_camera(&args, &booth, CameraRole::Scan)?;
    let bar = progress_bar(schedule.entries.len());
    let acquired = acquire(
        &mut session,
        &schedule,
        CaptureTarget {
            booth: &booth,
            plan: &plan,
            out: &args.out,
            source: connection.description,
        },
        projectors.as_mut(),
        camera,
        &HostFaults::default(),
        &mut |_| bar.inc(1),
    )?;
    bar.finish_and_clear();
    let report = timing_report(&acquired.log, 0.0);
    if args.json {
        println!(
            "{}",
            serde_json::json!({
                "capture": acquired.folder.display().to_string(),
                "frames_written": acquired.frames_written,
                "complete": acquired.complete,
                "frames_late": report.frames_late,
                "frames_dropped": report.frames_dropped,
                "exposure": schedule.exposure,
                "camera_failures": acquired
                    .camera_failures
                    .iter()
                    .map(|(frame, reason)| serde_json::json!({ "frame": frame, "reason": reason }))
                    .collect::<Vec<_>>(),
            })
        );
    } else {
        println!(
            "wrote {} ({} frames{})",
            acquired.folder.display(),
            acquired.frames_written,
            if acquired.complete {
                ""
            } else {
                ", INCOMPLETE"
            }
        );
    }
    for (frame, reason) in &acquired.camera_failures {
        eprintln!("camera: frame {frame}: {reason}");
    }
    if !acquired.complete {
        bail!(
            "the run did not capture every frame: {:?}, {} camera failure(s)",
            acquired.log.done.outcome,
            acquired.camera_failures.len()
        );
    }
    Ok(())
}

/// The projector backend `--projectors` names; windows are opened for the projectors the
/// schedule lights, each at its native resolution.
fn projector_backend(
    name: &str,
    booth: &Booth,
    schedule: &RigSchedule,
) -> anyhow::Result<Box<dyn ProjectorBackend>> {
    match name {
        "virtual" => Ok(Box::new(VirtualProjectors::new())),
        "windows" => {
            let lit: BTreeSet<u8> = schedule.entries.iter().map(|e| e.projector).collect();
            let specs = lit
                .into_iter()
                .map(|k| display::window_spec(booth, k, None))
                .collect::<Result<Vec<_>, _>>()?;
            let windows = ProjectorWindows::open(&specs)?;
            for spec in &specs {
                display::check_native_mode(&windows.monitors()[spec.monitor], spec)?;
            }
            Ok(Box::new(windows))
        }
        other => bail!("unknown --projectors '{other}': use `virtual` or `windows`"),
    }
}

fn run_cameras(args: CamerasArgs) -> anyhow::Result<()> {
    let list = list_cameras()?;
    if args.json {
        println!("{}", serde_json::to_string(&list)?);
        return Ok(());
    }
    println!("USB3 Vision cameras:");
    if list.cameras.is_empty() {
        println!(
            "  (none{})",
            list.usb_unavailable
                .as_deref()
                .map(|why| format!("; {why}"))
                .unwrap_or_default()
        );
    }
    for c in &list.cameras {
        println!(
            "  {} {}  serial {}  (--camera u3v:{})",
            c.vendor, c.model, c.serial, c.serial
        );
    }
    Ok(())
}

fn run_displays(args: DisplaysArgs) -> anyhow::Result<()> {
    let booth = args.booth.load()?;
    let monitors = display::list_monitors()?;
    let projectors: Vec<serde_json::Value> = booth
        .projectors
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let monitor = display::projector_monitor(&booth, k as u8);
            let found = monitors.get(monitor);
            serde_json::json!({
                "projector": k,
                "name": p.name,
                "width": p.width,
                "height": p.height,
                "monitor": monitor,
                "monitor_found": found.is_some(),
                "native_mode": found.is_some_and(|m| (m.width, m.height) == (p.width, p.height)),
            })
        })
        .collect();
    if args.json {
        let monitors: Vec<serde_json::Value> = monitors
            .iter()
            .map(|m| {
                let mut v = serde_json::to_value(m).unwrap_or_default();
                v["projectors"] = projectors_on(&booth, m.index).into();
                v
            })
            .collect();
        println!(
            "{}",
            serde_json::json!({
                "display": std::env::var("DISPLAY").unwrap_or_default(),
                "monitors": monitors,
                "projectors": projectors,
            })
        );
        return Ok(());
    }
    println!("monitors:");
    if monitors.is_empty() {
        println!("  (none)");
    }
    for m in &monitors {
        let on = projectors_on(&booth, m.index);
        let mapped = if on.is_empty() {
            String::new()
        } else {
            format!("  <- projector {on:?}")
        };
        println!("  {}{mapped}", m.describe());
    }
    println!("projectors ({}):", booth.name);
    for p in &projectors {
        println!(
            "  {} {} {}x{} -> monitor {}{}",
            p["projector"],
            p["name"].as_str().unwrap_or_default(),
            p["width"],
            p["height"],
            p["monitor"],
            match (p["monitor_found"].as_bool(), p["native_mode"].as_bool()) {
                (Some(false), _) => "  MISSING",
                (_, Some(false)) => "  (mode is not the projector's native resolution)",
                _ => "",
            }
        );
    }
    Ok(())
}

/// The projectors the booth maps to monitor `index`.
fn projectors_on(booth: &Booth, index: usize) -> Vec<usize> {
    (0..booth.projectors.len())
        .filter(|&k| display::projector_monitor(booth, k as u8) == index)
        .collect()
}

fn run_show(args: ShowArgs) -> anyhow::Result<()> {
    let booth = args.booth.load()?;
    let pattern = pattern_by_label(&booth.patterns, &args.pattern)?;
    let spec = display::window_spec(&booth, args.projector, args.monitor)?;
    let hold = match args.hold {
        Some(s) if !(s.is_finite() && s >= 0.0) => bail!("--hold must be a number of seconds"),
        Some(s) => Some(Duration::from_secs_f64(s)),
        None => None,
    };
    let mut windows = ProjectorWindows::open(&[spec])?;
    let monitor = windows.monitors()[spec.monitor].clone();
    if let Err(e) = display::check_native_mode(&monitor, &spec) {
        eprintln!("warning: {e}; drawing unscaled from the top-left corner");
    }
    let presented = windows.present(args.projector, &pattern)?;
    if args.json {
        println!(
            "{}",
            serde_json::json!({
                "projector": args.projector,
                "pattern": pattern.label(),
                "width": spec.width,
                "height": spec.height,
                "monitor": presented.monitor,
                "window_width": presented.window_width,
                "window_height": presented.window_height,
                "native_mode": (monitor.width, monitor.height) == (spec.width, spec.height),
                "presented": true,
                "vblank_msc": presented.vblank.map(|v| v.msc),
            })
        );
    } else {
        println!(
            "projector {} shows {} ({}x{}) on monitor {}; {}",
            args.projector,
            pattern.label(),
            spec.width,
            spec.height,
            monitor.describe(),
            match hold {
                Some(h) => format!("holding {:.1} s or until a key is pressed", h.as_secs_f64()),
                None => "press a key in the window to end".into(),
            }
        );
    }
    let key = windows.wait_for_key(hold);
    eprintln!("{}", if key { "key pressed" } else { "hold ended" });
    Ok(())
}

/// Timing test hooks: nothing to show or capture, only progress.
struct TimingHooks {
    schedule: RigSchedule,
    bar: ProgressBar,
}

impl RunHooks for TimingHooks {
    fn show(&mut self, request: &PatternRequest) -> Result<(), RigError> {
        mlsss::rig::acquire::checked_pattern(&self.schedule, request).map(|_| ())
    }

    fn triggered(&mut self, _trigger: &Triggered) -> Result<(), RigError> {
        self.bar.inc(1);
        Ok(())
    }
}

fn run_timing(args: TimingArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let (booth, plan) = load_booth(&args.booth)?;
    let schedule = RigSchedule::from_plan(&plan, &booth.timing, args.booth.frames)?;
    let Connection {
        port, _qemu: qemu, ..
    } = connect(&args.controller)?;
    let mut session = open_session(ControllerLink::new(port))?;
    let mut hooks = TimingHooks {
        schedule: schedule.clone(),
        bar: progress_bar(schedule.entries.len()),
    };
    let log = session.run(&schedule, &mut hooks, &HostFaults::default())?;
    hooks.bar.finish_and_clear();
    drop(session);
    drop(qemu); // QEMU shut down before the wall clock stops
    let report = timing_report(&log, started.elapsed().as_secs_f64());
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!(
            "{} of {} frames triggered, {} lost, {} late; period {:.1} us mean, max error {:.1} us \
             ({:.1} us vs the measured refresh); VSYNC alignment max {:.1} us; {} settle violations; \
             {} CRC errors; {:.1} s virtual in {:.1} s wall",
            report.frames_triggered,
            report.frames_requested,
            report.frames_lost,
            report.frames_late,
            report.period_us_mean,
            report.period_us_max_abs_error,
            report.period_us_max_abs_error_vs_refresh,
            report.vsync_alignment_us_max,
            report.settle_violations,
            report.crc_errors,
            report.virtual_duration_s,
            report.wall_duration_s
        );
    }
    Ok(())
}
