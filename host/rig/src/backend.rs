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

/// What was on the projectors when the camera was triggered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Exposure {
    /// Frame index.
    pub frame: u32,
    /// The lit projector and its pattern, `None` if nothing was shown.
    pub lit: Option<(u8, Pattern)>,
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
}

impl PatternCamera {
    /// A camera of `booth`'s resolution.
    pub fn new(booth: &Booth) -> Self {
        Self {
            width: booth.camera.width,
            height: booth.camera.height,
            projector_sizes: booth
                .projectors
                .iter()
                .map(|p| (p.width, p.height))
                .collect(),
        }
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
            let value = pattern.value(u, v);
            *px = image::Rgb([value, value, value]);
        }
        Ok(img)
    }
}

/// A camera that replays the frames of a recorded capture, checking that the rig shows what
/// the recording showed.
pub struct ReplayCamera {
    capture: Capture,
}

impl ReplayCamera {
    /// Replays `capture`.
    pub fn new(capture: Capture) -> Self {
        Self { capture }
    }
}

impl CameraBackend for ReplayCamera {
    fn capture(&mut self, exposure: &Exposure) -> Result<Rgb32FImage, RigError> {
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
