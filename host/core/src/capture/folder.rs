//! The capture folder (DESIGN section 8):
//!
//! ```text
//! CAPTURE/
//!   capture.json      manifest: booth snapshot, frame plan, per-frame trigger log, units
//!   frames/NNNN.png   16-bit RGB PNG, sensor codes of `bit_depth` bits MSB-aligned (code << (16 - bits))
//!   truth/            optional ground truth written by the virtual booth
//! ```
//!
//! Frames are decoded to linear `f32` RGB in [0, 1] (code / (2^bits - 1)). Folders are written
//! atomically: everything goes to a hidden sibling folder that is renamed into place at the end.

use std::fs;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use image::Rgb32FImage;
use serde::{Deserialize, Serialize};

use super::exposure::{FrameNoise, ProjectorExposure};
use super::frame_plan::{FramePlan, FrameSpec};
use crate::atomic_file::{FolderLock, LOCK_FILE};
use crate::booth::{Booth, BoothError};

/// Version of the capture folder format.
pub const CAPTURE_FORMAT_VERSION: u32 = 1;
/// Name of the manifest file.
pub const MANIFEST_FILE: &str = "capture.json";

/// Errors reading or writing a capture folder.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CaptureError {
    /// A file or folder could not be read or written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// `capture.json` is missing fields or malformed.
    #[error("{path}: invalid capture manifest: {source}")]
    Manifest {
        path: PathBuf,
        source: serde_json::Error,
    },
    /// A frame image could not be decoded or encoded.
    #[error("frame {path}: {source}")]
    Image {
        path: PathBuf,
        source: image::ImageError,
    },
    /// A frame does not have the size or format the manifest promises.
    #[error("frame {path}: {reason}")]
    BadFrame { path: PathBuf, reason: String },
    /// The manifest names a frame index that does not exist.
    #[error("capture has no frame {index} (it has {count})")]
    NoSuchFrame { index: u32, count: usize },
    /// The output folder exists already.
    #[error("{0} exists already; remove it or choose another --out")]
    Exists(PathBuf),
    /// `capture.json` parsed but a value in it is invalid or disagrees with the rest.
    #[error("{path}: `{field}`: {reason}")]
    InvalidManifest {
        path: PathBuf,
        field: String,
        reason: String,
    },
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> CaptureError + '_ {
    move |source| CaptureError::Io {
        path: path.to_owned(),
        source,
    }
}

/// When and how one frame was triggered (from the controller, or synthetic for the virtual booth).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TriggerRecord {
    pub frame_index: u32,
    /// Controller time of the trigger edge, microseconds.
    pub timestamp_us: u64,
    /// VSYNC count of the lit projector at the trigger.
    pub vsync_count: u32,
    /// Slots lost before this frame was triggered (0 when on time).
    #[serde(default)]
    pub retries: u32,
    #[serde(default)]
    pub late: bool,
}

/// What kind of capture a folder holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CaptureKind {
    /// A subject scan ([`FramePlan::scan`]).
    Scan,
    /// One pose of a calibration target ([`FramePlan::calibration`]).
    Calibration,
}

/// The contents of `capture.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaptureManifest {
    pub format_version: u32,
    pub kind: CaptureKind,
    /// Snapshot of the booth the capture was made with.
    pub booth: Booth,
    pub plan: FramePlan,
    /// Bits per sample of the camera codes stored in the frames.
    pub bit_depth: u32,
    #[serde(default)]
    pub trigger_log: Vec<TriggerRecord>,
    /// Units of the numbers in this file and the frames.
    pub units: Units,
    /// Free-form description of where the capture came from (simulator settings, rig port, ...).
    #[serde(default)]
    pub source: serde_json::Value,
    /// Exposure of each projector's frames, chosen by metering before the scan
    /// (`capture::exposure`); a projector not listed was taken at the booth's nominal exposure.
    /// Frames are read back divided by the exposure's scale (nominal units).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub exposure: Vec<ProjectorExposure>,
}

/// The units of a capture (fixed; written so a reader never has to guess).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Units {
    pub length: String,
    pub time: String,
    pub pixel_values: String,
}

impl Default for Units {
    fn default() -> Self {
        Self {
            length: "mm".into(),
            time: "us".into(),
            pixel_values:
                "16-bit PNG, camera codes MSB-aligned; linear value = code / (2^bit_depth - 1)"
                    .into(),
        }
    }
}

impl CaptureManifest {
    pub fn new(kind: CaptureKind, booth: Booth, plan: FramePlan) -> Self {
        Self {
            format_version: CAPTURE_FORMAT_VERSION,
            kind,
            bit_depth: booth.camera.bit_depth,
            booth,
            plan,
            trigger_log: Vec::new(),
            units: Units::default(),
            source: serde_json::Value::Null,
            exposure: Vec::new(),
        }
    }

    /// The exposure projector `k`'s frames were taken with (nominal when not metered).
    pub fn exposure_of(&self, k: usize) -> ProjectorExposure {
        let nominal = ProjectorExposure::nominal(k as u8, &self.booth.timing);
        self.exposure
            .iter()
            .find(|e| e.projector as usize == k)
            .copied()
            .filter(|e| e.scale.is_finite() && e.scale > 0.0)
            .unwrap_or(nominal)
    }

    /// The camera noise of projector `k`'s frames as read back (nominal units).
    pub fn frame_noise_of(&self, k: usize) -> FrameNoise {
        let camera = &self.booth.camera;
        FrameNoise::of_camera(
            camera.full_well_e,
            camera.read_noise_dn,
            self.bit_depth,
            &self.exposure_of(k),
        )
    }

    /// Signal of frame `index` relative to the nominal exposure (1 for unlit or unknown frames).
    fn frame_exposure_scale(&self, index: u32) -> f64 {
        self.plan
            .frames
            .iter()
            .find(|f| f.index == index)
            .and_then(|f| f.projector)
            .map_or(1.0, |k| self.exposure_of(k as usize).scale)
    }
}

impl CaptureManifest {
    /// Checks what a reader relies on: the format version, the booth snapshot (as a booth file
    /// is checked), the bit depth, and a frame plan that is the start of the plan of this kind
    /// for this booth (the rig truncates a capture it stopped early), so every frame index and
    /// pattern is what the readers expect. `path` names the manifest in errors.
    pub fn validate(&self, path: &Path) -> Result<(), CaptureError> {
        let invalid = |field: &str, reason: String| CaptureError::InvalidManifest {
            path: path.to_owned(),
            field: field.to_owned(),
            reason,
        };
        if self.format_version != CAPTURE_FORMAT_VERSION {
            return Err(invalid(
                "format_version",
                format!(
                    "version {} is not supported: this mlsss reads version {CAPTURE_FORMAT_VERSION}",
                    self.format_version
                ),
            ));
        }
        self.booth.validate(path).map_err(|e| match e {
            BoothError::Invalid { field, reason, .. } => invalid(&format!("booth.{field}"), reason),
            other => invalid("booth", other.to_string()),
        })?;
        if !(1..=16).contains(&self.bit_depth) {
            return Err(invalid(
                "bit_depth",
                format!(
                    "must be 1..=16 (frames are 16-bit PNG), got {}",
                    self.bit_depth
                ),
            ));
        }
        self.validate_plan()
            .map_err(|reason| invalid("plan", reason))
    }

    /// The frame plan against the plan of this kind for the booth: same entries, in order,
    /// possibly cut short.
    fn validate_plan(&self) -> Result<(), String> {
        if self.plan.is_empty() {
            return Err("the capture has no frames".into());
        }
        let expected = match self.kind {
            CaptureKind::Scan => FramePlan::scan(&self.booth.patterns, self.booth.projectors.len()),
            CaptureKind::Calibration => {
                FramePlan::calibration(&self.booth.patterns, self.booth.projectors.len())
            }
        };
        if self.plan.len() > expected.len() {
            return Err(format!(
                "{} frames, but a {:?} capture of this booth has {}",
                self.plan.len(),
                self.kind,
                expected.len()
            ));
        }
        for (position, (got, want)) in self.plan.frames.iter().zip(&expected.frames).enumerate() {
            if got != want {
                let describe = |f: &FrameSpec| {
                    let lit = f
                        .projector
                        .map_or_else(|| "no projector".to_owned(), |k| format!("projector {k}"));
                    format!("frame {} ({lit}, `{}`)", f.index, f.pattern.label())
                };
                return Err(format!(
                    "entry {position} is {}, but the booth's plan has {} there (entries \
                     swapped, duplicated or edited?)",
                    describe(got),
                    describe(want)
                ));
            }
        }
        Ok(())
    }
}

/// Relative path of frame `index` inside a capture folder.
pub fn frame_file(index: u32) -> String {
    format!("frames/{index:04}.png")
}

/// An opened capture folder.
#[derive(Debug, Clone)]
pub struct Capture {
    pub root: PathBuf,
    pub manifest: CaptureManifest,
}

impl Capture {
    /// Opens a capture folder and reads its manifest.
    pub fn open(root: &Path) -> Result<Self, CaptureError> {
        let path = root.join(MANIFEST_FILE);
        let text = fs::read_to_string(&path).map_err(io_err(&path))?;
        let manifest: CaptureManifest =
            serde_json::from_str(&text).map_err(|source| CaptureError::Manifest {
                path: path.clone(),
                source,
            })?;
        manifest.validate(&path)?;
        Ok(Self {
            root: root.to_owned(),
            manifest,
        })
    }

    /// The `truth/` folder, if this capture has ground truth.
    pub fn truth_dir(&self) -> Option<PathBuf> {
        let dir = self.root.join("truth");
        dir.is_dir().then_some(dir)
    }

    /// Reads frame `index` as linear RGB in [0, 1] at the nominal exposure (a metered frame is
    /// divided by its exposure scale, so it may exceed 1 where the camera did not saturate).
    pub fn read_frame(&self, index: u32) -> Result<Rgb32FImage, CaptureError> {
        let (path, (width, height, data)) =
            self.read_codes(index, |codes| (codes.width, codes.height, codes.samples()))?;
        Rgb32FImage::from_raw(width, height, data).ok_or_else(|| CaptureError::BadFrame {
            path,
            reason: "buffer size mismatch".into(),
        })
    }

    /// Frame `index` as linear RGB pixels in [0, 1], row-major: what the per-pixel stages index,
    /// made in one pass from the sensor codes (no `Rgb32FImage` to copy from).
    pub fn read_frame_pixels(&self, index: u32) -> Result<Vec<[f32; 3]>, CaptureError> {
        let (_, pixels) = self.read_codes(index, |codes| codes.map_pixels(|p| p))?;
        Ok(pixels)
    }

    /// Frame `index`'s luminance, the mean of its linear RGB, row-major (what Gray-code decoding
    /// compares), made in one pass from the sensor codes.
    pub fn read_frame_luminance(&self, index: u32) -> Result<Vec<f32>, CaptureError> {
        let mut luminance = Vec::new();
        self.read_frame_luminance_into(index, &mut luminance)?;
        Ok(luminance)
    }

    /// [`Capture::read_frame_luminance`] into `out`, whose allocation is reused when it is large
    /// enough. Why: a fresh 5.7 MB buffer per frame (full size) came from the system as new
    /// zeroed pages, and their page faults were a visible share of loading a projector's 42
    /// frames; the next projector's frames can go into the previous one's buffers.
    pub fn read_frame_luminance_into(
        &self,
        index: u32,
        out: &mut Vec<f32>,
    ) -> Result<(), CaptureError> {
        if !self.read_stored_luminance(index, out)? {
            self.read_codes(index, |codes| codes.luminance_into(out))?;
        }
        Ok(())
    }

    /// [`Capture::read_frame_luminance_into`] row by row from a frame stored as
    /// [`write_frame_png`] stores it ([`super::stored_png::for_each_stored_row`]: the samples
    /// are not packed first); the same values, pixel for pixel. `false` for any other file.
    fn read_stored_luminance(&self, index: u32, out: &mut Vec<f32>) -> Result<bool, CaptureError> {
        let (path, exposure) = self.frame_path_and_exposure(index)?;
        let cam = &self.manifest.booth.camera;
        // As `load_samples`: the codes' scale, then back to the nominal exposure.
        let (shift, scale) = code_shift_and_scale(self.manifest.bit_depth);
        let scale = scale / exposure;
        let width = cam.width as usize;
        resize_reusing(out, width * cam.height as usize);
        let mut bytes = take_frame_buffer();
        let mut scratch = Vec::new();
        let size = (cam.width, cam.height);
        let stored = super::stored_png::for_each_stored_row(
            &path,
            size,
            &mut bytes,
            &mut scratch,
            |y, row| {
                if let Some(out) = out.get_mut(y * width..(y + 1) * width) {
                    luminance_of(row, shift, scale, out);
                }
            },
        );
        give_back_frame_buffer(bytes);
        stored.map_err(|e| CaptureError::Image {
            path,
            source: image::ImageError::IoError(e),
        })
    }

    /// Path of frame `index` and what `convert` makes of its sensor codes.
    fn read_codes<T>(
        &self,
        index: u32,
        convert: impl FnOnce(&FrameCodes) -> T,
    ) -> Result<(PathBuf, T), CaptureError> {
        let (path, samples) = self.load_samples(index)?;
        Ok((path, convert(&samples.codes())))
    }

    /// Frame `index`'s sensor codes held in memory, to read pixel by pixel
    /// ([`FrameSamples::rgb`]: the values of [`Capture::read_frame_pixels`]). Why: a stage that
    /// needs several frames at each pixel (the profiles: a projector's slit frames) reads them
    /// side by side from the codes, without a linear copy of each frame to allocate.
    pub fn read_frame_samples(&self, index: u32) -> Result<FrameSamples, CaptureError> {
        Ok(self.load_samples(index)?.1)
    }

    /// Path of frame `index` and its codes, scaled back to the nominal exposure.
    fn load_samples(&self, index: u32) -> Result<(PathBuf, FrameSamples), CaptureError> {
        let (path, exposure) = self.frame_path_and_exposure(index)?;
        let cam = &self.manifest.booth.camera;
        let size = (cam.width, cam.height);
        let mut samples = load_frame_codes(&path, self.manifest.bit_depth, size)?;
        samples.scale /= exposure;
        Ok((path, samples))
    }

    /// Path of frame `index` and its exposure relative to the nominal one (the codes are
    /// divided by it, so every stage sees the same units whatever the metering).
    fn frame_path_and_exposure(&self, index: u32) -> Result<(PathBuf, f32), CaptureError> {
        let count = self.manifest.plan.len();
        if index as usize >= count {
            return Err(CaptureError::NoSuchFrame { index, count });
        }
        let exposure = self.manifest.frame_exposure_scale(index) as f32;
        Ok((self.root.join(frame_file(index)), exposure))
    }

    /// Reads the frame described by `spec`.
    pub fn read(&self, spec: &FrameSpec) -> Result<Rgb32FImage, CaptureError> {
        self.read_frame(spec.index)
    }
}

/// A frame's sensor codes as stored (MSB-aligned in 16 bits) and their scale to linear [0, 1].
#[derive(Clone, Copy)]
struct FrameCodes<'a> {
    width: u32,
    height: u32,
    codes: Codes<'a>,
    /// Right shift from the stored 16 bits to the sensor's `bit_depth`.
    shift: u32,
    /// One sensor code in linear units: `1 / (2^bit_depth - 1)`.
    scale: f32,
}

/// R, G, B codes of each pixel in row-major order.
#[derive(Clone, Copy)]
enum Codes<'a> {
    /// As the PNG stores them: big-endian, 6 bytes a pixel.
    BigEndian(&'a [u8]),
    /// Native 16-bit values.
    Native(&'a [u16]),
}

impl FrameCodes<'_> {
    /// Linear samples, R, G, B of each pixel in row-major order.
    fn samples(&self) -> Vec<f32> {
        match self.codes {
            Codes::BigEndian(bytes) => bytes
                .chunks_exact(2)
                .map(|c| self.linear(u16::from_be_bytes([c[0], c[1]])))
                .collect(),
            Codes::Native(codes) => codes.iter().map(|&c| self.linear(c)).collect(),
        }
    }

    /// `f` of the linear RGB of each pixel, in row-major order.
    fn map_pixels<T>(&self, f: impl Fn([f32; 3]) -> T) -> Vec<T> {
        match self.codes {
            Codes::BigEndian(bytes) => bytes
                .chunks_exact(6)
                .map(|p| {
                    f([
                        self.linear(u16::from_be_bytes([p[0], p[1]])),
                        self.linear(u16::from_be_bytes([p[2], p[3]])),
                        self.linear(u16::from_be_bytes([p[4], p[5]])),
                    ])
                })
                .collect(),
            Codes::Native(codes) => codes
                .chunks_exact(3)
                .map(|p| f([self.linear(p[0]), self.linear(p[1]), self.linear(p[2])]))
                .collect(),
        }
    }

    /// `map_pixels(|p| (p[0] + p[1] + p[2]) / 3.0)`, the same operations in the same order per
    /// pixel, block by block: the block's samples made linear in one contiguous loop, then each
    /// pixel's three summed. Why: per pixel from the 6 big-endian bytes the loop ran one pixel at
    /// a time and was a sixth of the decode stage (perf, 2.3 ns a pixel); both loops of a block
    /// vectorise (test: bit for bit the per-pixel values).
    /// Written into `out` (resized to the frame, its allocation reused when large enough).
    fn luminance_into(&self, out: &mut Vec<f32>) {
        let Codes::BigEndian(bytes) = self.codes else {
            *out = self.map_pixels(|p| (p[0] + p[1] + p[2]) / 3.0);
            return;
        };
        resize_reusing(out, bytes.len() / 6);
        luminance_of(bytes, self.shift, self.scale, out);
    }

    /// [`FrameCodes::luminance_into`] a new buffer.
    #[cfg(test)]
    fn luminance(&self) -> Vec<f32> {
        let mut out = Vec::new();
        self.luminance_into(&mut out);
        out
    }

    #[inline(always)]
    fn linear(&self, code: u16) -> f32 {
        (code >> self.shift) as f32 * self.scale
    }
}

/// `out` resized to `pixels` values (contents unspecified), its allocation reused when large
/// enough.
fn resize_reusing(out: &mut Vec<f32>, pixels: usize) {
    if out.len() != pixels {
        if out.capacity() >= pixels {
            out.clear();
            out.resize(pixels, 0.0);
        } else {
            // Zeroed pages straight from the allocator, not written twice.
            *out = vec![0.0; pixels];
        }
    }
}

/// The luminance of the pixels of big-endian 16-bit RGB `bytes` into `out`
/// ([`luminance_portable`], compiled for AVX2 where the CPU has it).
fn luminance_of(bytes: &[u8], shift: u32, scale: f32, out: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, the one feature `luminance_avx2` is compiled for.
        unsafe { luminance_avx2(bytes, shift, scale, out) };
        return;
    }
    luminance_portable(bytes, shift, scale, out);
}

/// Right shift from a stored 16-bit code to `bit_depth` bits, and one code of that depth in
/// linear units (`1 / (2^bit_depth - 1)`).
fn code_shift_and_scale(bit_depth: u32) -> (u32, f32) {
    (
        16 - bit_depth.min(16),
        1.0 / ((1u32 << bit_depth.min(16)) - 1) as f32,
    )
}

/// Pixels per block of [`FrameCodes::luminance`] (its linear samples stay in the L1 cache).
const LUMINANCE_BLOCK: usize = 1024;

/// [`luminance_portable`] compiled with AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn luminance_avx2(bytes: &[u8], shift: u32, scale: f32, out: &mut [f32]) {
    luminance_portable(bytes, shift, scale, out);
}

/// The body of [`FrameCodes::luminance_into`] on big-endian 16-bit RGB `bytes`, one value per
/// pixel into `out` (inlined into each instruction-set variant; no FMA is enabled, so no product
/// is fused: the same bits).
#[inline(always)]
fn luminance_portable(bytes: &[u8], shift: u32, scale: f32, out: &mut [f32]) {
    let (samples, _) = bytes.as_chunks::<2>();
    let pixels = (samples.len() / 3).min(out.len());
    let mut linear = [0.0f32; 3 * LUMINANCE_BLOCK];
    for (out, codes) in out
        .chunks_mut(LUMINANCE_BLOCK)
        .zip(samples[..3 * pixels].chunks(3 * LUMINANCE_BLOCK))
    {
        let linear = &mut linear[..codes.len()];
        for (l, c) in linear.iter_mut().zip(codes) {
            *l = (u16::from_be_bytes(*c) >> shift) as f32 * scale;
        }
        let (rgb, _) = linear.as_chunks::<3>();
        for (o, p) in out.iter_mut().zip(rgb) {
            *o = (p[0] + p[1] + p[2]) / 3.0;
        }
    }
}

/// PNG bytes buffers of frames read before, for the next reads to reuse: a fresh buffer per
/// frame (8.5 MB at full size, hundreds of frames a run) was zeroed and page-faulted in by the
/// kernel each time. One per concurrent reader; [`release_frame_buffers`] empties it.
static FRAME_BYTES: Mutex<Vec<Vec<u8>>> = Mutex::new(Vec::new());

/// At most this many buffers are kept (one per thread reading frames at once).
const POOLED_FRAME_BUFFERS: usize = 16;

/// A buffer of [`FRAME_BYTES`], or a new one.
fn take_frame_buffer() -> Vec<u8> {
    FRAME_BYTES
        .lock()
        .ok()
        .and_then(|mut pool| pool.pop())
        .unwrap_or_default()
}

/// Returns `buffer` to [`FRAME_BYTES`] for the next read.
fn give_back_frame_buffer(buffer: Vec<u8>) {
    if let Ok(mut pool) = FRAME_BYTES.lock()
        && pool.len() < POOLED_FRAME_BUFFERS
    {
        pool.push(buffer);
    }
}

/// Frees the buffers kept for reading frames (`resources::release_free_memory` calls it between
/// phases, so they never add to a later phase's peak).
pub fn release_frame_buffers() {
    if let Ok(mut pool) = FRAME_BYTES.lock() {
        *pool = Vec::new();
    }
}

/// Bytes per read of a frame file. Why not `BufReader`'s 8 KiB: a full-size frame (8.5 MB,
/// stored uncompressed) took a thousand `read` calls, 172 000 for the decode stage's frames
/// (strace); 64 KiB cuts them eightfold and stays below the allocator's mmap threshold, so the
/// buffer is reused from the heap rather than page-faulted in per frame.
const READ_BUFFER: usize = 64 * 1024;

/// A frame's sensor codes in memory and their scale to linear units (see
/// [`Capture::read_frame_samples`]). The bytes of a 16-bit RGB PNG go back to the pool of
/// frame buffers when it is dropped.
pub struct FrameSamples {
    width: u32,
    height: u32,
    codes: OwnedCodes,
    /// Right shift from the stored 16 bits to the sensor's `bit_depth`.
    shift: u32,
    /// One sensor code in linear units.
    scale: f32,
}

/// The owned form of [`Codes`].
enum OwnedCodes {
    /// A pooled buffer and the length of the frame's bytes in it.
    BigEndian(Vec<u8>, usize),
    Native(Vec<u16>),
}

impl FrameSamples {
    /// The codes as [`FrameCodes`] reads them.
    fn codes(&self) -> FrameCodes<'_> {
        FrameCodes {
            width: self.width,
            height: self.height,
            codes: match &self.codes {
                OwnedCodes::BigEndian(bytes, len) => Codes::BigEndian(&bytes[..*len]),
                OwnedCodes::Native(codes) => Codes::Native(codes),
            },
            shift: self.shift,
            scale: self.scale,
        }
    }

    /// Pixels of the frame.
    pub fn len(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Whether the frame has no pixel.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The linear RGB of pixel `i` (row-major), as [`Capture::read_frame_pixels`] gives it;
    /// `None` outside the frame.
    #[inline]
    pub fn rgb(&self, i: usize) -> Option<[f32; 3]> {
        let codes: [u16; 3] = match &self.codes {
            OwnedCodes::BigEndian(bytes, len) => {
                let p = bytes[..*len].get(6 * i..6 * i + 6)?;
                [
                    u16::from_be_bytes([p[0], p[1]]),
                    u16::from_be_bytes([p[2], p[3]]),
                    u16::from_be_bytes([p[4], p[5]]),
                ]
            }
            OwnedCodes::Native(codes) => codes.get(3 * i..3 * i + 3)?.try_into().ok()?,
        };
        let view = self.codes();
        Some(codes.map(|c| view.linear(c)))
    }
}

impl Drop for FrameSamples {
    fn drop(&mut self) {
        if let OwnedCodes::BigEndian(bytes, _) = &mut self.codes {
            give_back_frame_buffer(std::mem::take(bytes));
        }
    }
}

/// Calls `convert` with the sensor codes of the 16-bit PNG frame at `path` written by
/// [`write_frame_png`] ([`load_frame_codes`]).
#[cfg(test)]
fn with_frame_codes<T>(
    path: &Path,
    bit_depth: u32,
    expected_size: (u32, u32),
    convert: impl FnOnce(&FrameCodes) -> T,
) -> Result<T, CaptureError> {
    Ok(convert(
        &load_frame_codes(path, bit_depth, expected_size)?.codes(),
    ))
}

/// The sensor codes of the 16-bit PNG frame at `path` written by [`write_frame_png`]: into a
/// buffer from the pool [`FRAME_BYTES`], packed from the file's stored blocks when it is laid
/// out as that writer lays it out ([`super::stored_png`]), else decoded by `png` when it is
/// 16-bit RGB, else through `image` ([`read_frame_codes`], which also refuses what is not a
/// frame).
fn load_frame_codes(
    path: &Path,
    bit_depth: u32,
    expected_size: (u32, u32),
) -> Result<FrameSamples, CaptureError> {
    let (shift, scale) = code_shift_and_scale(bit_depth);
    let image_error = |source| CaptureError::Image {
        path: path.to_owned(),
        source,
    };
    let mut bytes = take_frame_buffer();
    match super::stored_png::read_stored_rgb16(path, expected_size, &mut bytes) {
        Ok(Some(len)) => {
            return Ok(FrameSamples {
                width: expected_size.0,
                height: expected_size.1,
                codes: OwnedCodes::BigEndian(bytes, len),
                shift,
                scale,
            });
        }
        // Not laid out as the frame writer lays it out: `png` reads it (or says why not).
        Ok(None) => {}
        Err(e) => {
            give_back_frame_buffer(bytes);
            return Err(image_error(image::ImageError::IoError(e)));
        }
    }
    let file = fs::File::open(path).map_err(|e| image_error(image::ImageError::IoError(e)))?;
    let png_error = |e: png::DecodingError| {
        image_error(image::ImageError::Decoding(
            image::error::DecodingError::new(image::ImageFormat::Png.into(), e),
        ))
    };
    let mut reader = png::Decoder::new(std::io::BufReader::with_capacity(READ_BUFFER, file))
        .read_info()
        .map_err(png_error)?;
    let info = reader.info();
    let plain_rgb16 = info.color_type == png::ColorType::Rgb
        && info.bit_depth == png::BitDepth::Sixteen
        && !info.interlaced
        && (info.width, info.height) == expected_size;
    if !plain_rgb16 {
        give_back_frame_buffer(bytes);
        let codes = read_frame_codes(path, expected_size)?;
        return Ok(FrameSamples {
            width: codes.width(),
            height: codes.height(),
            codes: OwnedCodes::Native(codes.into_raw()),
            shift,
            scale,
        });
    }
    let len = reader
        .output_buffer_size()
        .ok_or_else(|| CaptureError::BadFrame {
            path: path.to_owned(),
            reason: "too large".into(),
        })?;
    bytes.resize(len, 0);
    match reader.next_frame(&mut bytes) {
        Ok(frame) => Ok(FrameSamples {
            width: frame.width,
            height: frame.height,
            codes: OwnedCodes::BigEndian(bytes, frame.buffer_size()),
            shift,
            scale,
        }),
        Err(e) => {
            give_back_frame_buffer(bytes);
            Err(png_error(e))
        }
    }
}

/// Reads a 16-bit RGB, RGBA or grey PNG as 16-bit RGB sensor codes through `image`, refusing
/// 8-bit frames and frames of the wrong size.
fn read_frame_codes(
    path: &Path,
    expected_size: (u32, u32),
) -> Result<image::ImageBuffer<image::Rgb<u16>, Vec<u16>>, CaptureError> {
    let img = image::open(path).map_err(|source| CaptureError::Image {
        path: path.to_owned(),
        source,
    })?;
    if !matches!(
        img.color(),
        image::ColorType::Rgb16 | image::ColorType::Rgba16 | image::ColorType::L16
    ) {
        return Err(CaptureError::BadFrame {
            path: path.to_owned(),
            reason: format!(
                "is {:?}: capture frames are 16-bit PNGs (camera codes MSB-aligned); an 8-bit \
                 frame has lost the sensor's low bits, convert it with its bit depth instead",
                img.color()
            ),
        });
    }
    if (img.width(), img.height()) != expected_size {
        return Err(CaptureError::BadFrame {
            path: path.to_owned(),
            reason: format!(
                "is {}x{}, the capture's camera is {}x{}",
                img.width(),
                img.height(),
                expected_size.0,
                expected_size.1
            ),
        });
    }
    Ok(img.into_rgb16())
}

/// The sensor code of linear value `v` for codes up to `max_code` (at most 65535): `v` clamped
/// to [0, 1] (NaN reads 0), times `max_code`, rounded half away from zero.
#[inline(always)]
#[allow(clippy::manual_clamp)]
fn sensor_code(v: f32, max_code: f32) -> u16 {
    // `max`/`min`, not `clamp`: they turn a NaN into 0, `clamp` would keep it.
    round_non_negative(v.max(0.0).min(1.0) * max_code)
}

/// `x.round() as u16` for `0 <= x <= 65535`: halves away from zero.
///
/// Without `round` (a `roundf` call on the baseline x86-64 target, a twentieth of a calibration
/// pose's CPU time) and without `as` casts from float to integer (Rust's saturating casts, whose
/// NaN and range checks kept the frame's loop scalar): adding 2^23 rounds x in [0, 2^23) to the
/// nearest integer, ties to even, in the float's low mantissa bits, and a tie that went down is
/// put up. Every step is exact (test below). The frame's loop vectorises: 0.45 ms per quick frame
/// (473k values) against 1.2 ms with the truncate-and-compare this replaced.
#[inline(always)]
fn round_non_negative(x: f32) -> u16 {
    const TWO_POW_23: f32 = 8_388_608.0;
    let shifted = x + TWO_POW_23;
    let nearest_even = shifted.to_bits() - TWO_POW_23.to_bits();
    let tie_down = x - (shifted - TWO_POW_23) >= 0.5;
    (nearest_even + u32::from(tie_down)) as u16
}

/// Writes linear RGB in [0, 1] as sensor codes of `bit_depth` bits, MSB-aligned in a 16-bit PNG.
/// Values are clamped (saturation) and rounded (quantisation).
///
/// The PNG is stored uncompressed (deflate's stored blocks, no filter): a camera frame's noise
/// leaves deflate little to find (the fast setting saved 20 % of the bytes of a quick capture's
/// frames) for most of the time spent writing and reading it (DESIGN section 8: frames load
/// fast; any PNG reader still reads them).
pub fn write_frame_png(path: &Path, img: &Rgb32FImage, bit_depth: u32) -> Result<(), CaptureError> {
    if !(1..=16).contains(&bit_depth) {
        return Err(CaptureError::BadFrame {
            path: path.to_owned(),
            reason: format!("cannot store {bit_depth}-bit codes in a 16-bit PNG"),
        });
    }
    let max_code = ((1u32 << bit_depth) - 1) as f32;
    let shift = 16 - bit_depth;
    let image_err = |e: png::EncodingError| CaptureError::Image {
        path: path.to_owned(),
        source: image::ImageError::IoError(e.into()),
    };
    let idat = stored_zlib_rows(img, max_code, shift).map_err(io_err(path))?;
    let file = fs::File::create(path).map_err(io_err(path))?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), img.width(), img.height());
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Sixteen);
    encoder.set_compression(png::Compression::NoCompression);
    encoder.set_filter(png::Filter::NoFilter);
    let mut writer = encoder.write_header().map_err(image_err)?;
    writer
        .write_chunk(png::chunk::IDAT, &idat)
        .map_err(image_err)?;
    writer.finish().map_err(image_err)
}

/// The zlib stream of a frame's PNG image data, stored (no compression), rows unfiltered: what
/// `png`'s `write_image_data` makes of the big-endian samples with `NoCompression` (the same
/// `fdeflate` compressor fed the same bytes, so the file is the same byte for byte; test below),
/// without its two frame-sized copies: the samples are converted a row at a time into a buffer
/// that stays in L1 (`png` takes them as one frame-sized slice), and the compressor writes into
/// a buffer of its final size (`png` grows its buffer from empty, reallocating).
fn stored_zlib_rows(img: &Rgb32FImage, max_code: f32, shift: u32) -> std::io::Result<Vec<u8>> {
    let row_values = img.width() as usize * 3;
    let raw_size = (2 * row_values + 1) * img.height() as usize;
    let out = Vec::with_capacity(fdeflate::StoredOnlyCompressor::<()>::compressed_size(
        raw_size,
    ));
    let mut zlib = fdeflate::StoredOnlyCompressor::new(std::io::Cursor::new(out))?;
    let mut row = vec![[0u8; 2]; row_values];
    for values in img.as_raw().chunks_exact(row_values.max(1)) {
        // Big-endian samples, as PNG stores them, behind the row's filter byte (0: none).
        for (out, &v) in row.iter_mut().zip(values) {
            *out = (sensor_code(v, max_code) << shift).to_be_bytes();
        }
        zlib.write_data(&[0])?;
        zlib.write_data(row.as_flattened())?;
    }
    Ok(zlib.finish()?.into_inner())
}

/// Writes a capture folder atomically: frames go to a hidden sibling folder, renamed into place by
/// [`CaptureWriter::finish`]. Dropping the writer without finishing removes the partial folder.
pub struct CaptureWriter {
    target: PathBuf,
    staging: PathBuf,
    manifest: CaptureManifest,
    finished: bool,
    lock: Option<FolderLock>,
}

/// Removes staging folders `parent/{prefix}PID` left by writers that were killed (their lock is
/// free); folders of writers still running are left alone. Best effort: a folder that cannot be
/// removed stays.
fn remove_abandoned_staging(parent: &Path, prefix: &str) {
    let Ok(entries) = fs::read_dir(parent) else {
        return;
    };
    for entry in entries.flatten() {
        let abandoned_name = entry.file_name().to_string_lossy().starts_with(prefix);
        let path = entry.path();
        if !abandoned_name || !path.is_dir() {
            continue;
        }
        if let Ok(lock) = FolderLock::acquire(&path) {
            drop(lock);
            let _ = fs::remove_dir_all(&path);
        }
    }
}

impl CaptureWriter {
    /// Starts a capture folder at `target`, which must not exist.
    pub fn create(target: &Path, manifest: CaptureManifest) -> Result<Self, CaptureError> {
        if target.exists() {
            return Err(CaptureError::Exists(target.to_owned()));
        }
        let parent = target
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        fs::create_dir_all(parent).map_err(io_err(parent))?;
        let name = target
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "capture".into());
        let prefix = format!(".{name}.partial-");
        remove_abandoned_staging(parent, &prefix);
        let staging = parent.join(format!("{prefix}{}", std::process::id()));
        if staging.exists() {
            fs::remove_dir_all(&staging).map_err(io_err(&staging))?;
        }
        let frames = staging.join("frames");
        fs::create_dir_all(&frames).map_err(io_err(&frames))?;
        // Held while the capture is written: a later writer can tell a killed run's staging
        // folder (lock free) from one still being written (lock held).
        let lock = FolderLock::acquire(&staging).map_err(|e| CaptureError::Io {
            path: staging.clone(),
            source: std::io::Error::other(e.to_string()),
        })?;
        Ok(Self {
            target: target.to_owned(),
            staging,
            manifest,
            finished: false,
            lock: Some(lock),
        })
    }

    /// Folder where extra files (e.g. `truth/`) can be written before [`CaptureWriter::finish`].
    pub fn staging_dir(&self) -> &Path {
        &self.staging
    }

    pub fn manifest(&self) -> &CaptureManifest {
        &self.manifest
    }

    pub fn manifest_mut(&mut self) -> &mut CaptureManifest {
        &mut self.manifest
    }

    /// Writes frame `index` (linear RGB in [0, 1]).
    pub fn write_frame(&self, index: u32, img: &Rgb32FImage) -> Result<(), CaptureError> {
        let cam = &self.manifest.booth.camera;
        if (img.width(), img.height()) != (cam.width, cam.height) {
            return Err(CaptureError::BadFrame {
                path: PathBuf::from(frame_file(index)),
                reason: format!(
                    "is {}x{}, the camera is {}x{}",
                    img.width(),
                    img.height(),
                    cam.width,
                    cam.height
                ),
            });
        }
        write_frame_png(
            &self.staging.join(frame_file(index)),
            img,
            self.manifest.bit_depth,
        )
    }

    /// Writes the manifest and moves the folder into place.
    pub fn finish(mut self) -> Result<PathBuf, CaptureError> {
        let manifest_path = self.staging.join(MANIFEST_FILE);
        let text = serde_json::to_string_pretty(&self.manifest).map_err(|source| {
            CaptureError::Manifest {
                path: manifest_path.clone(),
                source,
            }
        })?;
        fs::write(&manifest_path, text).map_err(io_err(&manifest_path))?;
        // The lock file is the writer's, not the capture's.
        let lock_path = self.staging.join(LOCK_FILE);
        fs::remove_file(&lock_path).map_err(io_err(&lock_path))?;
        fs::rename(&self.staging, &self.target).map_err(io_err(&self.target))?;
        self.lock = None;
        self.finished = true;
        Ok(self.target.clone())
    }
}

impl Drop for CaptureWriter {
    fn drop(&mut self) {
        if !self.finished {
            let _ = fs::remove_dir_all(&self.staging);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::FramePlan;

    #[test]
    fn codes_round_as_f32_round_does() {
        // Every code's neighbourhood: halves, the floats just below and above them, and
        // values on a fine grid.
        let max_code = 4095.0f32;
        let mut values = vec![0.0f32, 0.49999997, 0.5, 0.50000006, max_code];
        for c in 0..4095 {
            let half = c as f32 + 0.5;
            values.extend([half, half.next_down(), half.next_up(), c as f32]);
        }
        values.extend((0..1_000_000).map(|i| i as f32 * max_code / 1e6));
        values.extend([65534.5, 65534.5f32.next_down(), 65535.0, 32767.5, 4096.5]);
        for x in values {
            assert_eq!(round_non_negative(x), x.round() as u16, "{x}");
        }
        // Linear values outside [0, 1], and NaN, clamp to the end codes.
        for bits in [16, 12, 8, 1] {
            let max_code = ((1u32 << bits) - 1) as f32;
            for v in [
                -1.0,
                -0.0,
                0.0,
                1e-9,
                0.25,
                0.999_999_9,
                1.0,
                1.5,
                f32::INFINITY,
            ] {
                let want = (v.clamp(0.0, 1.0) * max_code).round() as u16;
                assert_eq!(sensor_code(v, max_code), want, "{v} at {bits} bits");
            }
            assert_eq!(sensor_code(f32::NAN, max_code), 0);
            assert_eq!(sensor_code(f32::NEG_INFINITY, max_code), 0);
        }
    }

    /// The frame writer's file against `png`'s own encoder fed the codes computed the plain way
    /// (`f32::round`): byte for byte, over several stored blocks, with values out of range.
    #[test]
    fn frames_are_written_as_png_writes_them() {
        let (w, h, bits) = (37u32, 1213u32, 12u32);
        let img = Rgb32FImage::from_fn(w, h, |x, y| {
            let t = (x * 7919 + y * 104_729) as f32;
            image::Rgb([
                (t * 0.618_034).fract() * 1.2 - 0.1,
                if (x + y) % 97 == 0 {
                    f32::NAN
                } else {
                    (t * 0.414_214).fract()
                },
                (x as f32 + 0.5) / 4095.0,
            ])
        });
        let dir = tempfile::tempdir().unwrap();
        let ours = dir.path().join("ours.png");
        write_frame_png(&ours, &img, bits).unwrap();

        let max_code = ((1u32 << bits) - 1) as f32;
        let bytes: Vec<u8> = img
            .as_raw()
            .iter()
            .flat_map(|&v| {
                let code = if v.is_nan() {
                    0.0
                } else {
                    (v.clamp(0.0, 1.0) * max_code).round()
                };
                ((code as u16) << (16 - bits)).to_be_bytes()
            })
            .collect();
        let mut want = Vec::new();
        let mut encoder = png::Encoder::new(&mut want, w, h);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Sixteen);
        encoder.set_compression(png::Compression::NoCompression);
        encoder.set_filter(png::Filter::NoFilter);
        let mut writer = encoder.write_header().unwrap();
        writer.write_image_data(&bytes).unwrap();
        writer.finish().unwrap();
        assert!(bytes.len() > 3 * 65_535, "several stored blocks");
        assert_eq!(fs::read(&ours).unwrap(), want);
    }

    fn tiny_booth() -> Booth {
        let mut booth = Booth::builtin(true);
        booth.camera.width = 8;
        booth.camera.height = 5;
        booth
    }

    #[test]
    fn frames_round_trip_through_12_bit_codes() {
        let dir = tempfile::tempdir().unwrap();
        let booth = tiny_booth();
        let plan = FramePlan::scan(&booth.patterns, 1);
        let manifest = CaptureManifest::new(CaptureKind::Scan, booth, plan);
        let target = dir.path().join("cap");
        let writer = CaptureWriter::create(&target, manifest).unwrap();
        let img = Rgb32FImage::from_fn(8, 5, |x, y| {
            image::Rgb([
                x as f32 / 7.0,
                y as f32 / 4.0,
                if x == 0 { 2.0 } else { -1.0 },
            ])
        });
        writer.write_frame(0, &img).unwrap();
        assert!(!target.exists(), "nothing visible before finish");
        writer.finish().unwrap();
        let cap = Capture::open(&target).unwrap();
        let back = cap.read_frame(0).unwrap();
        for (a, b) in img.pixels().zip(back.pixels()) {
            for c in 0..3 {
                let expected = a.0[c].clamp(0.0, 1.0);
                assert!(
                    (expected - b.0[c]).abs() <= 0.5 / 4095.0 + 1e-6,
                    "{a:?} {b:?}"
                );
            }
        }
        // The per-pixel and luminance readers give the same numbers as the image reader.
        let pixels = cap.read_frame_pixels(0).unwrap();
        let luminance = cap.read_frame_luminance(0).unwrap();
        assert_eq!(pixels.len(), 40);
        for ((p, l), b) in pixels.iter().zip(&luminance).zip(back.pixels()) {
            assert_eq!(*p, b.0);
            assert_eq!(*l, (b.0[0] + b.0[1] + b.0[2]) / 3.0);
        }
        // Held in memory and read pixel by pixel: the same values; outside: none.
        let samples = cap.read_frame_samples(0).unwrap();
        assert_eq!(samples.len(), 40);
        for (i, b) in back.pixels().enumerate() {
            assert_eq!(samples.rgb(i), Some(b.0), "pixel {i}");
        }
        assert_eq!(samples.rgb(40), None);
        assert!(matches!(
            cap.read_frame_pixels(999),
            Err(CaptureError::NoSuchFrame { .. })
        ));
        assert!(matches!(
            cap.read_frame(999),
            Err(CaptureError::NoSuchFrame { .. })
        ));
    }

    /// Every reader's numbers straight from the PNG bytes equal those through `image` (the
    /// plain path before the reused buffers), bit for bit, frame after frame, buffers reused
    /// (smaller or larger than the frame) or freed.
    #[test]
    fn frames_read_from_the_png_bytes_equal_those_read_through_image() {
        let dir = tempfile::tempdir().unwrap();
        for bit_depth in [12, 16] {
            let path = dir.path().join(format!("frame{bit_depth}.png"));
            for (w, h, seed) in [(37u32, 23u32, 1u32), (8, 5, 2), (64, 48, 3), (50, 45, 4)] {
                if seed == 2 {
                    // Reads after the kept buffers were freed (between stages) are the same.
                    release_frame_buffers();
                }
                let img = Rgb32FImage::from_fn(w, h, |x, y| {
                    let v = ((x * 7919 + y * 104_729 + seed * 31) % 5000) as f32 / 4500.0;
                    image::Rgb([v, 1.0 - v, if x % 5 == 0 { 2.0 } else { v * 0.3 }])
                });
                write_frame_png(&path, &img, bit_depth).unwrap();
                let by_image = read_frame_codes(&path, (w, h)).unwrap();
                let plain = FrameCodes {
                    width: w,
                    height: h,
                    codes: Codes::Native(by_image.as_raw()),
                    shift: 16 - bit_depth,
                    scale: 1.0 / ((1u32 << bit_depth) - 1) as f32 / 0.7,
                };
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                let (samples, pixels, luminance, blocked, reused) =
                    with_frame_codes(&path, bit_depth, (w, h), |c| {
                        let c = FrameCodes {
                            scale: c.scale / 0.7,
                            ..*c
                        };
                        assert!(matches!(c.codes, Codes::BigEndian(_)));
                        (
                            c.samples(),
                            c.map_pixels(|p| p),
                            c.map_pixels(|p| (p[0] + p[1] + p[2]) / 3.0),
                            c.luminance(),
                            // Into a reused buffer, smaller or larger than the frame or of its
                            // size.
                            [0, 7, w as usize * h as usize, 5000].map(|len| {
                                let mut reused = vec![9.0f32; len];
                                c.luminance_into(&mut reused);
                                reused
                            }),
                        )
                    })
                    .unwrap();
                assert_eq!(bits(&blocked), bits(&luminance));
                for reused in &reused {
                    assert_eq!(bits(reused), bits(&luminance));
                }
                assert_eq!(bits(&plain.luminance()), bits(&luminance));
                assert_eq!(bits(&samples), bits(&plain.samples()));
                assert_eq!(
                    bits(pixels.as_flattened()),
                    bits(plain.map_pixels(|p| p).as_flattened())
                );
                assert_eq!(
                    bits(&luminance),
                    bits(&plain.map_pixels(|p| (p[0] + p[1] + p[2]) / 3.0))
                );
            }
        }
    }

    #[test]
    fn an_eight_bit_or_wrongly_sized_frame_is_still_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frame.png");
        let img = Rgb32FImage::from_fn(8, 5, |x, _| image::Rgb([x as f32 / 7.0; 3]));
        write_frame_png(&path, &img, 12).unwrap();
        let wrong = with_frame_codes(&path, 12, (9, 5), |c| c.samples());
        assert!(
            matches!(wrong, Err(CaptureError::BadFrame { .. })),
            "{wrong:?}"
        );
        image::DynamicImage::ImageRgb32F(img)
            .to_rgb8()
            .save(&path)
            .unwrap();
        let eight = with_frame_codes(&path, 12, (8, 5), |c| c.samples());
        assert!(
            matches!(eight, Err(CaptureError::BadFrame { .. })),
            "{eight:?}"
        );
        let missing = with_frame_codes(&dir.path().join("none.png"), 12, (8, 5), |c| c.samples());
        assert!(
            matches!(missing, Err(CaptureError::Image { .. })),
            "{missing:?}"
        );
    }

    #[test]
    fn unfinished_capture_leaves_nothing_behind() {
        let dir = tempfile::tempdir().unwrap();
        let booth = tiny_booth();
        let plan = FramePlan::scan(&booth.patterns, 1);
        let target = dir.path().join("cap");
        {
            let _w = CaptureWriter::create(
                &target,
                CaptureManifest::new(CaptureKind::Scan, booth, plan),
            )
            .unwrap();
        }
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn a_killed_writers_staging_folder_is_removed_by_the_next_writer() {
        let dir = tempfile::tempdir().unwrap();
        // What a `simulate` killed mid-run leaves: a staging folder whose lock nobody holds.
        let abandoned = dir.path().join(".cap.partial-999999999");
        fs::create_dir_all(abandoned.join("frames")).unwrap();
        fs::write(abandoned.join("frames/0000.png"), b"frame").unwrap();
        // A writer still at work holds its staging folder's lock: that folder stays.
        let busy = dir.path().join(".cap.partial-1");
        let busy_lock = FolderLock::acquire(&busy).unwrap();
        let booth = tiny_booth();
        let plan = FramePlan::scan(&booth.patterns, 1);
        let writer = CaptureWriter::create(
            &dir.path().join("cap"),
            CaptureManifest::new(CaptureKind::Scan, booth, plan),
        )
        .unwrap();
        assert!(!abandoned.exists(), "abandoned staging removed");
        assert!(busy.is_dir(), "a running writer's staging is kept");
        drop(busy_lock);
        let target = writer.finish().unwrap();
        assert!(
            !target.join(LOCK_FILE).exists(),
            "the lock is not part of the capture"
        );
    }

    #[test]
    fn wrong_frame_size_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let booth = tiny_booth();
        let plan = FramePlan::scan(&booth.patterns, 1);
        let w = CaptureWriter::create(
            &dir.path().join("cap"),
            CaptureManifest::new(CaptureKind::Scan, booth, plan),
        )
        .unwrap();
        let err = w.write_frame(0, &Rgb32FImage::new(3, 3)).unwrap_err();
        assert!(err.to_string().contains("3x3"), "{err}");
    }
}
