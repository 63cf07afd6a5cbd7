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
use cameleon::{Camera, StreamError};
use image::Rgb32FImage;
use serde::Serialize;

use super::matching::{PayloadSource, RawPayload, SourceError, TriggerMatcher};
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
}

fn camera_error(context: &str, e: impl std::fmt::Display) -> RigError {
    RigError::Backend {
        backend: "u3v camera",
        message: format!("{context}: {e}"),
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

/// A USB3 Vision camera streaming in hardware-trigger mode.
pub struct U3vCamera {
    camera: Camera<ControlHandle, StreamHandle>,
    matcher: TriggerMatcher<ForwardedPayloads>,
    summary: CameraSummary,
}

impl U3vCamera {
    /// Opens the camera `settings` names, configures it and starts streaming.
    pub fn open(settings: &U3vSettings) -> Result<Self, RigError> {
        if PixelLayout::from_pfnc(&settings.pixel_format).is_none() {
            return Err(camera_error(
                "pixel format",
                format!(
                    "{} is not supported (Mono8/12/12p/12Packed, Bayer??8/12/12p/12Packed)",
                    settings.pixel_format
                ),
            ));
        }
        let mut camera = pick_camera(settings.serial.as_deref())?;
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
            PAYLOAD_TIMEOUT,
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

impl CameraBackend for U3vCamera {
    fn capture(&mut self, exposure: &Exposure) -> Result<Rgb32FImage, RigError> {
        self.matcher
            .next_image(exposure.frame)
            .map_err(|e| camera_error(&self.summary.serial, e))
    }
}

impl Drop for U3vCamera {
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

type Params<'a> = ParamsCtxt<&'a mut ControlHandle, &'a mut DefaultGenApiCtxt>;

/// Sets the SFNC features a triggered capture needs; features a camera lacks are an error only
/// when the capture depends on them.
fn configure(
    camera: &mut Camera<ControlHandle, StreamHandle>,
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

fn set_enum(ctxt: &mut Params<'_>, name: &str, entry: &str) -> Result<(), RigError> {
    let node = ctxt
        .node(name)
        .and_then(|n| n.as_enumeration(ctxt))
        .ok_or_else(|| missing(name, "enumeration"))?;
    node.set_entry_by_symbolic(ctxt, entry)
        .map_err(|e| camera_error(&format!("setting {name} = {entry}"), e))
}

fn set_float(ctxt: &mut Params<'_>, name: &str, value: f64) -> Result<(), RigError> {
    let node = ctxt
        .node(name)
        .and_then(|n| n.as_float(ctxt))
        .ok_or_else(|| missing(name, "float"))?;
    node.set_value(ctxt, value)
        .map_err(|e| camera_error(&format!("setting {name} = {value}"), e))
}

fn get_int(ctxt: &mut Params<'_>, name: &str) -> Result<i64, RigError> {
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
