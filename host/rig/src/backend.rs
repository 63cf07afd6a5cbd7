//! Projector output and camera input behind small traits, so the same run loop drives a real
//! booth, the virtual one, or a replay of a recorded capture.

use std::sync::{Arc, Mutex, PoisonError};

use image::Rgb32FImage;

use super::RigError;
use mlsss_core::booth::Booth;
use mlsss_core::capture::{Capture, Pattern};

/// Something that puts patterns on the projectors.
pub trait ProjectorBackend {
    /// Shows `pattern` on `projector` (the others go black); returns once it is on screen.
    fn show(&mut self, projector: u8, pattern: &Pattern) -> Result<(), RigError>;
}

/// What was on the projectors when the camera was triggered, and how long it exposed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Exposure {
    /// Frame index.
    pub frame: u32,
    /// The lit projector and its pattern, `None` if nothing was shown.
    pub lit: Option<(u8, Pattern)>,
    /// Signal relative to the booth's nominal exposure (the lit projector's metered
    /// `ProjectorExposure::scale`; 1 at the nominal exposure). A real camera's exposure follows
    /// the trigger pulse; the virtual cameras scale their images by it.
    pub scale: f64,
}

impl Exposure {
    /// Frame `frame` showing `lit` at the nominal exposure.
    pub fn nominal(frame: u32, lit: Option<(u8, Pattern)>) -> Self {
        Self {
            frame,
            lit,
            scale: 1.0,
        }
    }
}

/// `value` as a camera at exposure `scale` records it: scaled, clipped at full scale.
fn exposed(value: f32, scale: f64) -> f32 {
    (f64::from(value) * scale).min(1.0) as f32
}

/// Something that delivers the camera image of a triggered frame.
pub trait CameraBackend: Send {
    /// The image of `exposure` (linear RGB in [0, 1], camera resolution).
    fn capture(&mut self, exposure: &Exposure) -> Result<Rgb32FImage, RigError>;
}

/// Virtual projectors: remember what each one shows; the state is shared with the virtual camera.
#[derive(Debug, Clone, Default)]
pub struct VirtualProjectors {
    lit: Arc<Mutex<Option<(u8, Pattern)>>>,
}

impl VirtualProjectors {
    /// All dark.
    pub fn new() -> Self {
        Self::default()
    }

    /// What is on screen now.
    pub fn lit(&self) -> Option<(u8, Pattern)> {
        *self.lit.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

impl ProjectorBackend for VirtualProjectors {
    fn show(&mut self, projector: u8, pattern: &Pattern) -> Result<(), RigError> {
        *self.lit.lock().unwrap_or_else(PoisonError::into_inner) = Some((projector, *pattern));
        Ok(())
    }
}

/// A camera that sees the projector image directly: the lit pattern resampled (nearest) from the
/// projector's resolution to the camera's. Stands in for the virtual booth's renderer.
#[derive(Debug, Clone)]
pub struct PatternCamera {
    width: u32,
    height: u32,
    projector_sizes: Vec<(u32, u32)>,
    reflectance: f32,
}

impl PatternCamera {
    /// A camera of `booth`'s resolution looking at a white screen.
    pub fn new(booth: &Booth) -> Self {
        Self {
            width: booth.camera.width,
            height: booth.camera.height,
            projector_sizes: booth
                .projectors
                .iter()
                .map(|p| (p.width, p.height))
                .collect(),
            reflectance: 1.0,
        }
    }

    /// The same camera looking at a grey screen of `reflectance` (0-1) at the nominal
    /// exposure: a dim subject, for metering.
    pub fn with_reflectance(mut self, reflectance: f32) -> Self {
        self.reflectance = reflectance;
        self
    }
}

impl CameraBackend for PatternCamera {
    fn capture(&mut self, exposure: &Exposure) -> Result<Rgb32FImage, RigError> {
        let mut img = Rgb32FImage::new(self.width, self.height);
        let Some((projector, pattern)) = exposure.lit else {
            return Ok(img);
        };
        let &(pw, ph) = self
            .projector_sizes
            .get(usize::from(projector))
            .ok_or_else(|| RigError::Backend {
                backend: "pattern camera",
                message: format!("the booth has no projector {projector}"),
            })?;
        for (x, y, px) in img.enumerate_pixels_mut() {
            let u = (u64::from(x) * u64::from(pw) / u64::from(self.width)) as u32;
            let v = (u64::from(y) * u64::from(ph) / u64::from(self.height)) as u32;
            let value = exposed(pattern.value(u, v) * self.reflectance, exposure.scale);
            *px = image::Rgb([value, value, value]);
        }
        Ok(img)
    }
}

/// A camera that replays the frames of a recorded capture, checking that the rig shows what
/// the recording showed. Frames come back as the camera would record them at the requested
/// exposure: the recording in nominal units (`Capture::read_frame`) times the exposure's scale,
/// clipped at full scale (the recording's noise is not rescaled).
pub struct ReplayCamera {
    capture: Capture,
    by_pattern: bool,
}

impl ReplayCamera {
    /// Replays `capture` frame by frame: frame n of the run is frame n of the recording.
    pub fn new(capture: Capture) -> Self {
        Self {
            capture,
            by_pattern: false,
        }
    }

    /// Replays, for whatever the rig shows, the recording's frame of that projector and
    /// pattern (a metering run shows each projector's white, in an order of its own).
    pub fn by_pattern(capture: Capture) -> Self {
        Self {
            capture,
            by_pattern: true,
        }
    }

    fn recorded_frame(&self, exposure: &Exposure) -> Result<Rgb32FImage, RigError> {
        let Some((projector, pattern)) = exposure.lit.filter(|_| self.by_pattern) else {
            return self.same_index_frame(exposure);
        };
        let spec = self
            .capture
            .manifest
            .plan
            .find(projector, &pattern)
            .ok_or_else(|| RigError::Backend {
                backend: "replay camera",
                message: format!(
                    "the recording has no frame of projector {projector} showing {}",
                    pattern.label()
                ),
            })?;
        Ok(self.capture.read_frame(spec.index)?)
    }

    fn same_index_frame(&self, exposure: &Exposure) -> Result<Rgb32FImage, RigError> {
        let recorded = self
            .capture
            .manifest
            .plan
            .frames
            .get(exposure.frame as usize)
            .ok_or_else(|| RigError::Backend {
                backend: "replay camera",
                message: format!("the recording has no frame {}", exposure.frame),
            })?;
        let recorded_lit = recorded.projector.map(|p| (p, recorded.pattern));
        if recorded_lit != exposure.lit {
            return Err(RigError::Backend {
                backend: "replay camera",
                message: format!(
                    "frame {}: the recording shows {:?}, the rig showed {:?}",
                    exposure.frame, recorded_lit, exposure.lit
                ),
            });
        }
        Ok(self.capture.read_frame(exposure.frame)?)
    }
}

impl CameraBackend for ReplayCamera {
    fn capture(&mut self, exposure: &Exposure) -> Result<Rgb32FImage, RigError> {
        let mut frame = self.recorded_frame(exposure)?;
        for v in frame.iter_mut() {
            *v = exposed(*v, exposure.scale);
        }
        Ok(frame)
    }
}
