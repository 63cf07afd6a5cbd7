//! USB3 Vision cameras through `cameleon` (GenICam over libusb): enumerate, open, configure
//! (pixel format, exposure, gain, hardware trigger on the controller's trigger line), stream,
//! and hand each payload to the [`TriggerMatcher`].
//!
//! Only this file talks to cameleon; matching, unpacking and demosaicing are tested on recorded
//! payloads without hardware (see `matching` and `pixels`).

use std::sync::mpsc;
use std::thread;
use std::time::Duration;

use cameleon::genapi::{DefaultGenApiCtxt, ParamsCtxt};
use cameleon::payload::{Payload, PayloadReceiver};
use cameleon::u3v::{self, ControlHandle, StreamHandle};
use cameleon::{Camera, DeviceControl, PayloadStream, StreamError};
use image::Rgb32FImage;
use serde::Serialize;

use super::matching::{PayloadError, PayloadSource, RawPayload, SourceError, TriggerMatcher};
use super::pixels::PixelLayout;
use crate::RigError;
use crate::backend::{CameraBackend, Exposure};

/// Block id of the first payload after the stream is enabled. USB3 Vision numbers blocks from 0
/// (GigE Vision from 1); a camera that differs shows up as a dropped or stale first payload,
/// which is reported, never mismatched silently.
pub const FIRST_BLOCK_ID: u64 = 0;

/// How long a triggered frame's payload may take (exposure + readout + USB transfer).
pub const PAYLOAD_TIMEOUT: Duration = Duration::from_secs(2);

/// A camera found on USB.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct CameraSummary {
    /// Vendor name.
    pub vendor: String,
    /// Model name.
    pub model: String,
    /// Serial number (`--camera u3v:SERIAL`).
    pub serial: String,
    /// The transport.
    pub transport: &'static str,
}

/// How to configure the camera for a capture.
#[derive(Debug, Clone, PartialEq)]
pub struct U3vSettings {
    /// The camera's serial number; `None`: the only camera connected.
    pub serial: Option<String>,
    /// PFNC pixel format (`Mono12`, `Mono12p`, `BayerRG12`, `BayerRG12Packed`, ...).
    pub pixel_format: String,
    /// Exposure time, microseconds.
    pub exposure_us: f64,
    /// Analogue gain, dB.
    pub gain_db: f64,
    /// The camera input wired to the controller's trigger output (`Line0`, ...).
    pub trigger_line: String,
    /// Expected image size (the booth's camera).
    pub width: u32,
    /// See `width`.
    pub height: u32,
    /// How long a triggered frame's payload may take ([`PAYLOAD_TIMEOUT`]).
    pub payload_timeout: Duration,
}

fn camera_error(context: &str, e: impl std::fmt::Display) -> RigError {
    RigError::Backend {
        backend: "u3v camera",
        message: format!("{context}: {e}"),
    }
}

/// A payload that is missing, incomplete or of the wrong size can be had again by re-triggering
/// the frame ([`RigError::PayloadLost`]); an unplugged camera, a stream error or a pixel format
/// the backend cannot decode cannot.
fn payload_error(serial: &str, frame: u32, e: PayloadError) -> RigError {
    match e {
        PayloadError::NoPayload { .. }
        | PayloadError::Dropped { .. }
        | PayloadError::Incomplete { .. }
        | PayloadError::WrongSize { .. } => RigError::PayloadLost {
            backend: "u3v camera",
            frame,
            message: format!("{serial}: {e}"),
        },
        other => camera_error(serial, other),
    }
}

/// The cameras found, and why USB could not be searched if it could not.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct CameraList {
    /// Every USB3 Vision camera connected.
    pub cameras: Vec<CameraSummary>,
    /// `None` when libusb searched the bus; else why it could not start (then no camera can be
    /// reached and `cameras` is empty).
    pub usb_unavailable: Option<String>,
}

/// Every USB3 Vision camera connected (an empty list when there is none, or no USB at all).
pub fn list_cameras() -> Result<CameraList, RigError> {
    if let Err(e) = crate::ports::libusb_available() {
        return Ok(CameraList {
            cameras: vec![],
            usb_unavailable: Some(format!("libusb cannot start: {e}")),
        });
    }
    let cameras = u3v::enumerate_cameras().map_err(|e| camera_error("enumerating", e))?;
    Ok(CameraList {
        cameras: cameras.iter().map(|c| summary(c.info())).collect(),
        usb_unavailable: None,
    })
}

fn summary(info: &cameleon::CameraInfo) -> CameraSummary {
    CameraSummary {
        vendor: info.vendor_name.clone(),
        model: info.model_name.clone(),
        serial: info.serial_number.clone(),
        transport: "usb3-vision",
    }
}

/// A USB3 Vision camera streaming in hardware-trigger mode. Generic over cameleon's control and
/// stream handles so tests can put a recorded device behind the same code.
pub struct U3vCamera<Ctrl = ControlHandle, Strm = StreamHandle>
where
    Ctrl: DeviceControl,
    Strm: PayloadStream,
{
    camera: Camera<Ctrl, Strm>,
    matcher: TriggerMatcher<ForwardedPayloads>,
    summary: CameraSummary,
}

impl U3vCamera {
    /// Opens the camera `settings` names on USB, configures it and starts streaming.
    pub fn open(settings: &U3vSettings) -> Result<Self, RigError> {
        check_pixel_format(settings)?;
        Self::start(pick_camera(settings.serial.as_deref())?, settings)
    }
}

fn check_pixel_format(settings: &U3vSettings) -> Result<(), RigError> {
    if PixelLayout::from_pfnc(&settings.pixel_format).is_none() {
        return Err(camera_error(
            "pixel format",
            format!(
                "{} is not supported (Mono8/12/12p/12Packed, Bayer??8/12/12p/12Packed)",
                settings.pixel_format
            ),
        ));
    }
    Ok(())
}

impl<Ctrl: DeviceControl, Strm: PayloadStream> U3vCamera<Ctrl, Strm> {
    /// Opens `camera`, loads its GenApi description, configures it and starts streaming.
    pub fn start(mut camera: Camera<Ctrl, Strm>, settings: &U3vSettings) -> Result<Self, RigError> {
        check_pixel_format(settings)?;
        let summary = summary(camera.info());
        camera.open().map_err(|e| camera_error("opening", e))?;
        camera
            .load_context()
            .map_err(|e| camera_error("loading the GenApi description", e))?;
        configure(&mut camera, settings)?;
        let receiver = camera
            .start_streaming(8)
            .map_err(|e| camera_error("starting the stream", e))?;
        let matcher = TriggerMatcher::new(
            ForwardedPayloads::start(receiver),
            (settings.width, settings.height),
            FIRST_BLOCK_ID,
            settings.payload_timeout,
        );
        Ok(Self {
            camera,
            matcher,
            summary,
        })
    }

    /// Which camera this is.
    pub fn summary(&self) -> &CameraSummary {
        &self.summary
    }
}

impl<Ctrl, Strm> CameraBackend for U3vCamera<Ctrl, Strm>
where
    Ctrl: DeviceControl + Send,
    Strm: PayloadStream + Send,
{
    fn capture(&mut self, exposure: &Exposure) -> Result<Rgb32FImage, RigError> {
        self.matcher
            .next_image(exposure.frame)
            .map_err(|e| payload_error(&self.summary.serial, exposure.frame, e))
    }
}

impl<Ctrl: DeviceControl, Strm: PayloadStream> Drop for U3vCamera<Ctrl, Strm> {
    fn drop(&mut self) {
        let _ = self.camera.stop_streaming();
        let _ = self.camera.close();
    }
}

fn pick_camera(serial: Option<&str>) -> Result<Camera<ControlHandle, StreamHandle>, RigError> {
    crate::ports::libusb_available().map_err(|e| camera_error("libusb cannot start", e))?;
    let mut cameras = u3v::enumerate_cameras().map_err(|e| camera_error("enumerating", e))?;
    let serials: Vec<String> = cameras
        .iter()
        .map(|c| c.info().serial_number.clone())
        .collect();
    let index = match serial {
        Some(s) => serials.iter().position(|found| found == s),
        None if cameras.len() == 1 => Some(0),
        None => None,
    };
    match index {
        Some(i) => Ok(cameras.swap_remove(i)),
        None => Err(camera_error(
            "choosing the camera",
            match (serial, serials.is_empty()) {
                (_, true) => "no USB3 Vision camera is connected (see `mlsss rig cameras`)".into(),
                (Some(s), false) => format!("no camera with serial {s}; connected: {serials:?}"),
                (None, false) => format!(
                    "{} cameras are connected ({serials:?}): name one with --camera u3v:SERIAL",
                    serials.len()
                ),
            },
        )),
    }
}

type Params<'a, Ctrl> = ParamsCtxt<&'a mut Ctrl, &'a mut DefaultGenApiCtxt>;

/// Sets the SFNC features a triggered capture needs; features a camera lacks are an error only
/// when the capture depends on them.
fn configure<Ctrl: DeviceControl, Strm: PayloadStream>(
    camera: &mut Camera<Ctrl, Strm>,
    settings: &U3vSettings,
) -> Result<(), RigError> {
    let mut ctxt = camera
        .params_ctxt()
        .map_err(|e| camera_error("GenApi context", e))?;
    set_enum(&mut ctxt, "PixelFormat", &settings.pixel_format)?;
    set_enum(&mut ctxt, "TriggerSelector", "FrameStart")?;
    set_enum(&mut ctxt, "TriggerMode", "On")?;
    set_enum(&mut ctxt, "TriggerSource", &settings.trigger_line)?;
    // Optional: rising edge and timed exposure are the SFNC defaults.
    let _ = set_enum(&mut ctxt, "TriggerActivation", "RisingEdge");
    let _ = set_enum(&mut ctxt, "ExposureMode", "Timed");
    let _ = set_enum(&mut ctxt, "GainAuto", "Off");
    let _ = set_enum(&mut ctxt, "ExposureAuto", "Off");
    set_float(&mut ctxt, "ExposureTime", settings.exposure_us)?;
    set_float(&mut ctxt, "Gain", settings.gain_db)?;
    let width = get_int(&mut ctxt, "Width")?;
    let height = get_int(&mut ctxt, "Height")?;
    if (width, height) != (i64::from(settings.width), i64::from(settings.height)) {
        return Err(camera_error(
            "image size",
            format!(
                "the camera sends {width}x{height}, the booth expects {}x{} (set the ROI or \
                 the booth's camera size)",
                settings.width, settings.height
            ),
        ));
    }
    Ok(())
}

fn missing(name: &str, kind: &str) -> RigError {
    camera_error(name, format!("the camera has no {kind} feature {name}"))
}

fn set_enum<Ctrl: DeviceControl>(
    ctxt: &mut Params<'_, Ctrl>,
    name: &str,
    entry: &str,
) -> Result<(), RigError> {
    let node = ctxt
        .node(name)
        .and_then(|n| n.as_enumeration(ctxt))
        .ok_or_else(|| missing(name, "enumeration"))?;
    node.set_entry_by_symbolic(ctxt, entry)
        .map_err(|e| camera_error(&format!("setting {name} = {entry}"), e))
}

fn set_float<Ctrl: DeviceControl>(
    ctxt: &mut Params<'_, Ctrl>,
    name: &str,
    value: f64,
) -> Result<(), RigError> {
    let node = ctxt
        .node(name)
        .and_then(|n| n.as_float(ctxt))
        .ok_or_else(|| missing(name, "float"))?;
    node.set_value(ctxt, value)
        .map_err(|e| camera_error(&format!("setting {name} = {value}"), e))
}

fn get_int<Ctrl: DeviceControl>(ctxt: &mut Params<'_, Ctrl>, name: &str) -> Result<i64, RigError> {
    let node = ctxt
        .node(name)
        .and_then(|n| n.as_integer(ctxt))
        .ok_or_else(|| missing(name, "integer"))?;
    node.value(ctxt)
        .map_err(|e| camera_error(&format!("reading {name}"), e))
}

/// cameleon's payload channel has no receive-with-timeout: a thread forwards it to a std channel.
struct ForwardedPayloads {
    rx: mpsc::Receiver<Result<RawPayload, SourceError>>,
}

impl ForwardedPayloads {
    fn start(receiver: PayloadReceiver) -> Self {
        let (tx, rx) = mpsc::channel();
        thread::spawn(move || {
            loop {
                let item = match receiver.recv_blocking() {
                    Ok(payload) => {
                        let raw = raw_payload(&payload);
                        receiver.send_back(payload);
                        Ok(raw)
                    }
                    // The channel closes when the stream loop ends (camera gone or stopped).
                    Err(StreamError::Disconnected | StreamError::ReceiveError(_)) => {
                        let _ = tx.send(Err(SourceError::Disconnected));
                        return;
                    }
                    Err(e) => Err(SourceError::Stream(e.to_string())),
                };
                if tx.send(item).is_err() {
                    return;
                }
            }
        });
        Self { rx }
    }
}

impl PayloadSource for ForwardedPayloads {
    fn next_payload(&mut self, timeout: Duration) -> Result<RawPayload, SourceError> {
        match self.rx.recv_timeout(timeout) {
            Ok(item) => item,
            Err(mpsc::RecvTimeoutError::Timeout) => Err(SourceError::Timeout),
            Err(mpsc::RecvTimeoutError::Disconnected) => Err(SourceError::Disconnected),
        }
    }
}

fn raw_payload(payload: &Payload) -> RawPayload {
    let Some(info) = payload.image_info() else {
        return RawPayload {
            block_id: payload.id(),
            width: 0,
            height: 0,
            pixel_format: "none (chunk payload)".into(),
            complete: false,
            data: vec![],
        };
    };
    let whole = payload.payload();
    let image = &whole[..info.image_size.min(whole.len())];
    RawPayload {
        block_id: payload.id(),
        width: info.width as u32,
        height: info.height as u32,
        pixel_format: format!("{:?}", info.pixel_format),
        complete: whole.len() >= info.image_size,
        data: image.to_vec(),
    }
}

#[cfg(test)]
mod tests {
    //! The backend against a recorded device: cameleon's own `Camera` drives a fake control
    //! handle (a register memory described by `fake_device.xml`, every GenCP-level write logged)
    //! and a fake stream whose payload channel the test feeds.

    use std::sync::{Arc, Mutex, PoisonError};

    use cameleon::payload::PayloadSender;
    use cameleon::{CameraInfo, ControlResult, StreamResult};

    use super::*;

    const XML: &str = include_str!("fake_device.xml");
    const PIXEL_FORMAT: u64 = 0x100;
    const TRIGGER_MODE: u64 = 0x108;
    const TRIGGER_SOURCE: u64 = 0x10C;
    const EXPOSURE_TIME: u64 = 0x110;
    const GAIN: u64 = 0x118;
    const WIDTH: u64 = 0x120;
    const HEIGHT: u64 = 0x124;
    const ACQUISITION_START: u64 = 0x130;

    #[derive(Clone)]
    struct Memory(Arc<Mutex<Vec<u8>>>);

    impl Memory {
        fn new(width: u32, height: u32) -> Self {
            let memory = Memory(Arc::new(Mutex::new(vec![0; 0x200])));
            memory.put(WIDTH, &width.to_le_bytes());
            memory.put(HEIGHT, &height.to_le_bytes());
            memory
        }
        fn put(&self, address: u64, data: &[u8]) {
            let mut m = self.0.lock().unwrap_or_else(PoisonError::into_inner);
            m[address as usize..address as usize + data.len()].copy_from_slice(data);
        }
        fn get<const N: usize>(&self, address: u64) -> [u8; N] {
            let m = self.0.lock().unwrap_or_else(PoisonError::into_inner);
            m[address as usize..address as usize + N]
                .try_into()
                .unwrap()
        }
        fn u32_at(&self, address: u64) -> u32 {
            u32::from_le_bytes(self.get(address))
        }
        fn f64_at(&self, address: u64) -> f64 {
            f64::from_le_bytes(self.get(address))
        }
    }

    struct FakeControl {
        memory: Memory,
        opened: bool,
    }

    impl DeviceControl for FakeControl {
        fn open(&mut self) -> ControlResult<()> {
            self.opened = true;
            Ok(())
        }
        fn close(&mut self) -> ControlResult<()> {
            self.opened = false;
            Ok(())
        }
        fn is_opened(&self) -> bool {
            self.opened
        }
        fn read(&mut self, address: u64, buf: &mut [u8]) -> ControlResult<()> {
            let m = self.memory.0.lock().unwrap_or_else(PoisonError::into_inner);
            buf.copy_from_slice(&m[address as usize..address as usize + buf.len()]);
            Ok(())
        }
        fn write(&mut self, address: u64, data: &[u8]) -> ControlResult<()> {
            self.memory.put(address, data);
            Ok(())
        }
        fn genapi(&mut self) -> ControlResult<String> {
            Ok(XML.to_owned())
        }
        fn enable_streaming(&mut self) -> ControlResult<()> {
            Ok(())
        }
        fn disable_streaming(&mut self) -> ControlResult<()> {
            Ok(())
        }
    }

    /// The stream side: hands cameleon's payload sender to the test.
    #[derive(Default)]
    struct FakeStream {
        sender: Arc<Mutex<Option<PayloadSender>>>,
    }

    impl PayloadStream for FakeStream {
        fn open(&mut self) -> StreamResult<()> {
            Ok(())
        }
        fn close(&mut self) -> StreamResult<()> {
            Ok(())
        }
        fn start_streaming_loop(
            &mut self,
            sender: PayloadSender,
            _ctrl: &mut dyn DeviceControl,
        ) -> StreamResult<()> {
            *self.sender.lock().unwrap_or_else(PoisonError::into_inner) = Some(sender);
            Ok(())
        }
        fn stop_streaming_loop(&mut self) -> StreamResult<()> {
            self.sender
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .take();
            Ok(())
        }
        fn is_loop_running(&self) -> bool {
            self.sender
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .is_some()
        }
    }

    fn settings() -> U3vSettings {
        U3vSettings {
            serial: None,
            pixel_format: "BayerRG12".into(),
            exposure_us: 33_300.0,
            gain_db: 1.5,
            trigger_line: "Line1".into(),
            width: 64,
            height: 48,
            payload_timeout: Duration::from_millis(200),
        }
    }

    type FakeCamera = (
        Result<U3vCamera<FakeControl, FakeStream>, RigError>,
        Memory,
        Arc<Mutex<Option<PayloadSender>>>,
    );

    fn start(width: u32, height: u32, settings: &U3vSettings) -> FakeCamera {
        let memory = Memory::new(width, height);
        let stream = FakeStream::default();
        let sender = stream.sender.clone();
        let control = FakeControl {
            memory: memory.clone(),
            opened: false,
        };
        let info = CameraInfo {
            vendor_name: "mlsss".into(),
            model_name: "FakeCam".into(),
            serial_number: "0001".into(),
        };
        let camera = Camera::new(control, stream, None, info);
        (U3vCamera::start(camera, settings), memory, sender)
    }

    fn exposure(frame: u32) -> Exposure {
        Exposure::nominal(frame, None)
    }

    #[test]
    fn the_camera_is_configured_for_hardware_trigger_through_genapi() {
        let (camera, memory, _sender) = start(64, 48, &settings());
        let camera = camera.expect("the fake camera starts");
        assert_eq!(camera.summary().serial, "0001");
        assert_eq!(memory.u32_at(PIXEL_FORMAT), 0x0110_0011); // BayerRG12 (PFNC)
        assert_eq!(memory.u32_at(TRIGGER_MODE), 1); // On
        assert_eq!(memory.u32_at(TRIGGER_SOURCE), 1); // Line1
        assert_eq!(memory.f64_at(EXPOSURE_TIME), 33_300.0);
        assert_eq!(memory.f64_at(GAIN), 1.5);
        assert_eq!(memory.u32_at(ACQUISITION_START), 1); // executed by start_streaming
    }

    #[test]
    fn a_camera_whose_image_size_differs_from_the_booth_is_refused() {
        let (camera, _, _) = start(640, 480, &settings());
        let err = camera.err().expect("refused").to_string();
        assert!(err.contains("640x480") && err.contains("64x48"), "{err}");
    }

    #[test]
    fn a_pixel_format_the_camera_lacks_is_an_error() {
        let mut s = settings();
        s.pixel_format = "Mono12p".into(); // decodable, but not in the camera's enumeration
        let (camera, _, _) = start(64, 48, &s);
        let err = camera.err().expect("refused").to_string();
        assert!(err.contains("PixelFormat = Mono12p"), "{err}");
    }

    #[test]
    fn a_trigger_without_a_payload_then_an_unplugged_camera_are_reported_per_frame() {
        let (camera, _memory, sender) = start(64, 48, &settings());
        let mut camera = camera.expect("the fake camera starts");
        let err = camera.capture(&exposure(0)).unwrap_err().to_string();
        assert!(err.contains("frame 0: triggered, but no payload"), "{err}");
        // The device disappears: cameleon's stream loop reports it on the payload channel.
        let sender = sender
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take()
            .expect("streaming");
        sender
            .try_send(Err(StreamError::Disconnected))
            .expect("channel open");
        let err = camera.capture(&exposure(1)).unwrap_err().to_string();
        assert!(
            err.contains("frame 1: the camera was disconnected"),
            "{err}"
        );
    }
}
