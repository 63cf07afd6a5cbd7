//! The fitted model as one file (`OUT/fit/model.mlsss`), and rendering a projector's pattern from
//! it: everything `mlsss render`, `mlsss eval` and the demo need, with no other artefact.
//!
//! File layout: 8-byte magic [`MAGIC`], `u32` LE format version, then gzip data (one or more
//! gzip members, concatenated: one gzip stream to `gunzip`) holding a
//! `u32` LE header length, the UTF-8 JSON [`ModelHeader`], and little-endian binary sections in
//! this order (`n` = width x height camera pixels, row-major, pixel `i = y * width + x`):
//! points `n x 3 f32` (world mm), normals `n x 3 f32`, mask `n u8`, direct albedo `n x 3 f32`,
//! white albedo `n x 3 f32`,
//! visibility `projectors x n u8`, the layer model, a `u8` flag and, when set, the dipole baseline
//! in the same layout. Binary because the layer model of a full-size capture is tens of millions
//! of numbers; gzip because most pixels are background or share few layers.
//!
//! Layer model section, format 2: the layer count of every pixel and channel (`n x 3 u16`, row
//! `i * 3 + c`); a palette of the distinct `(index, sigma_mm, depth_mm)` triples (`u32` count,
//! then `u16 index, f32 sigma_mm, f32 depth_mm` each); the layer count `u32`; the byte width of a
//! palette id (`u8`: 1, 2 or 4) and every layer's palette id; every layer's `f32 weight` as four
//! byte planes (all first bytes, then all second bytes, ...). Why: with the spatial prior most
//! pixels share one shape, so the ids repeat and the planes of the weights' high bytes compress,
//! where format 1 (offsets `n x 3 + 1 u32`, layer count `u32`, layers `u16 index, f32 weight,
//! f32 sigma_mm, f32 depth_mm`) stored 14 incompressible bytes per layer (383 MB at full size).
//! Format 1 files are still read.
//!
//! Conventions: as [`super::surface`] and [`super::profiles`]; radiance in the frames' linear
//! units. A render holds projector `k`'s light only (its black level included, the stray light of
//! the other projectors' black level not).

use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::fit::{EmVariant, FitStats};
use super::profiles::{Falloff, ProjectorIllumination};
use super::relight::{Relit, relight};
use super::render::{LayerModel, RenderError, RenderOptions, SplatLayer};
use super::surface::{Surface, ViewRay};
use mlsss_core::booth::PatternSpec;
use mlsss_core::calibration::Calibration;
use mlsss_core::capture::Pattern;

/// First bytes of a model file.
pub const MAGIC: &[u8; 8] = b"MLSSSMDL";
/// Bytes per gzip member of the compressed part (compressed in parallel); small in the unit
/// tests so that their round trip crosses members.
const GZIP_CHUNK: usize = if cfg!(test) { 4096 } else { 64 << 20 };

/// Version of the layout written by this code.
pub const FORMAT_VERSION: u32 = 2;
/// Oldest layout this code still reads (its layer sections differ, see the module doc).
pub const OLDEST_READABLE_VERSION: u32 = 1;

/// Errors reading, writing or rendering a model file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ModelFileError {
    /// The file could not be read or written.
    #[error("model file {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The file is not a model file (wrong magic) or is of another version.
    #[error(
        "{path} is not an mlsss model file of format version {OLDEST_READABLE_VERSION} to \
         {FORMAT_VERSION} ({reason}); write one with `mlsss process CAPTURE --calib ... --until fit`"
    )]
    NotAModel { path: PathBuf, reason: String },
    /// The file ends early or its sections disagree with the header.
    #[error("model file {path} is corrupt: {reason}")]
    Corrupt { path: PathBuf, reason: String },
    /// The model has no such projector.
    #[error("projector {requested} is not in the model (it has {count} projectors: 0..{count})")]
    NoSuchProjector { requested: usize, count: usize },
    /// The dipole baseline was asked for but the model was saved without it.
    #[error("the model has no dipole baseline (fitted with dipole disabled)")]
    NoDipole,
    /// The in-memory model is inconsistent (sizes of its parts).
    #[error("inconsistent model: {0}")]
    Inconsistent(String),
    /// The renderer refused its input.
    #[error(transparent)]
    Render(#[from] RenderError),
}

/// One projector as a light of the model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProjectorLight {
    /// Optical centre, world mm.
    pub centre: [f64; 3],
    pub falloff: Falloff,
    /// Fraction of white the projector emits for level 0.
    pub black_level: f32,
    /// Blur of its pattern edges seen by a camera pixel (projector px, standard deviation).
    pub blur_px: f32,
}

/// Metadata of a model (the JSON header of the file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelHeader {
    pub format_version: u32,
    pub width: usize,
    pub height: usize,
    pub em: EmVariant,
    /// Components requested per fit (the paper: 20).
    pub components: usize,
    /// Layer spacing D (mm), subject-wide.
    pub depth_spacing_mm: f64,
    pub eta: f64,
    pub view_ray: ViewRay,
    pub training_projectors: Vec<usize>,
    pub holdout: Option<usize>,
    /// Every projector of the capture as a light, index = projector number.
    pub projectors: Vec<ProjectorLight>,
    /// The calibration the model was built with (projections for rendering).
    pub calibration: Calibration,
    /// The booth's pattern geometry (slit width and period, stripes) the capture used.
    pub patterns: PatternSpec,
    pub camera_centre: [f64; 3],
    pub stats: FitStats,
}

/// Which model renders the subsurface light.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Baseline {
    /// The fitted multi-layer model, per pixel.
    Mlsss,
    /// Its layers averaged over the skin (paper Fig. 11d).
    Homogeneous,
    /// A per-pixel isotropic dipole (Jensen 2001).
    Dipole,
    /// No subsurface light at all.
    Direct,
}

/// A fitted model and what rendering needs.
#[derive(Debug, Clone, PartialEq)]
pub struct SubsurfaceModel {
    pub header: ModelHeader,
    pub surface: Surface,
    /// Direct radiance per unit irradiance, RGB per pixel: the part of the light the layer model
    /// does not hold (zero when the profiles kept all light, `DirectPart::None`).
    pub albedo: Vec<[f32; 3]>,
    /// All light (direct + subsurface) per unit irradiance under white, RGB per pixel: the
    /// direct-only baseline re-emits it where it entered (no subsurface transport).
    pub white_albedo: Vec<[f32; 3]>,
    /// Per projector: pixels it lights (decoded, not shadowed).
    pub visibility: Vec<Vec<bool>>,
    pub layers: LayerModel,
    pub dipole: Option<LayerModel>,
}

impl SubsurfaceModel {
    /// Checks that the parts agree in size.
    pub fn check(&self) -> Result<(), ModelFileError> {
        let n = self.header.width * self.header.height;
        let bad = |what: &str| Err(ModelFileError::Inconsistent(what.to_owned()));
        if self.surface.width != self.header.width || self.surface.height != self.header.height {
            return bad("surface size differs from the header");
        }
        if self.surface.points.len() != n
            || self.surface.normals.len() != n
            || self.surface.mask.len() != n
            || self.albedo.len() != n
            || self.white_albedo.len() != n
        {
            return bad("per-pixel arrays differ from width x height");
        }
        if self.visibility.len() != self.header.projectors.len()
            || self.visibility.iter().any(|v| v.len() != n)
        {
            return bad("visibility maps differ from the projectors or the image size");
        }
        for m in std::iter::once(&self.layers).chain(self.dipole.as_ref()) {
            if m.width != self.header.width || m.height != self.header.height {
                return bad("a layer model differs from the image size");
            }
        }
        Ok(())
    }

    /// The homogeneous baseline: layers averaged over the pixels that have a fit, applied to the
    /// whole surface.
    pub fn homogeneous(&self) -> LayerModel {
        let (w, h) = (self.header.width, self.header.height);
        LayerModel::uniform(w, h, &self.homogeneous_layers(), &self.surface.mask)
    }

    /// The layers every skin pixel of [`SubsurfaceModel::homogeneous`] gets, per channel: the
    /// mean over the fitted pixels.
    pub fn homogeneous_layers(&self) -> [Vec<SplatLayer>; 3] {
        self.layers.mean_layers(&self.layers.fitted())
    }

    /// The model of image rows `rows` alone (clamped to the image): renders it gives agree with
    /// the whole model's on the rows [`SubsurfaceModel::rows_reaching`] says they need.
    pub fn rows(&self, rows: std::ops::Range<usize>) -> Self {
        let end = rows.end.min(self.header.height);
        let start = rows.start.min(end);
        let span = start * self.header.width..end * self.header.width;
        Self {
            header: ModelHeader {
                height: end - start,
                ..self.header.clone()
            },
            surface: self.surface.rows(start..end),
            albedo: self.albedo[span.clone()].to_vec(),
            white_albedo: self.white_albedo[span.clone()].to_vec(),
            visibility: self
                .visibility
                .iter()
                .map(|v| v[span.clone()].to_vec())
                .collect(),
            layers: self.layers.rows(start..end),
            dipole: self.dipole.as_ref().map(|d| d.rows(start..end)),
        }
    }

    /// The rows a render with `opts` needs to get rows `rows` right when pixel `i` is rendered
    /// with layers of `extent(i)` (widest sigma, deepest layer; mm): every source whose light
    /// can reach them (its widest layer, shifted by the steepest refracted incidence `eta`
    /// allows plus its own view term, over its smallest stretch), widened to the pyramid's grid
    /// so every level is sampled as on the whole image. Serves figures that show a scanline.
    pub fn rows_reaching(
        &self,
        rows: std::ops::Range<usize>,
        extent: impl Fn(usize) -> (f64, f64) + Sync,
        opts: &RenderOptions,
    ) -> std::ops::Range<usize> {
        let height = self.header.height;
        let eta = self.header.eta;
        if eta.is_nan() || eta <= 1.0 {
            return 0..height;
        }
        // Shift per depth: a refracted incident ray at most tan(asin(1 / eta)); the view term
        // as `ViewRay` says, from the pixel's own view angle.
        let incident = 1.0 / (eta * eta - 1.0).sqrt();
        let view_term = |i: usize| {
            let to_camera = (self.surface.camera_centre - self.surface.points[i]).normalize();
            let cos = self.surface.normals[i].dot(&to_camera).abs().min(1.0);
            let sin = (1.0 - cos * cos).sqrt();
            match self.header.view_ray {
                ViewRay::ExitPoint => 0.0,
                ViewRay::Unrefracted => sin / cos,
                ViewRay::Refracted => (sin / eta) / (1.0 - (sin / eta).powi(2)).sqrt(),
            }
        };
        let width = self.header.width;
        // Per image row: how far its sources' light can travel (0 without sources), and the
        // coarsest pyramid level they use.
        let per_row: Vec<(f64, usize)> = (0..height)
            .into_par_iter()
            .map(|y| {
                (y * width..(y + 1) * width)
                    .filter_map(|i| {
                        let stretch = self.surface.footprint(i)?.smallest_stretch();
                        let (sigma, depth) = extent(i);
                        if stretch <= 0.0 {
                            return Some((f64::INFINITY, usize::MAX));
                        }
                        let shift = (incident + view_term(i)) * depth;
                        let sigma_px = sigma / stretch;
                        Some((
                            opts.reach_px(sigma_px, shift / stretch),
                            opts.level_factor(sigma_px),
                        ))
                    })
                    .fold((0.0f64, 1usize), |a, b| (a.0.max(b.0), a.1.max(b.1)))
            })
            .collect();
        // A row is needed when its light reaches one of `rows` (plus two rows: a crop's edge
        // rows see their surface one-sidedly).
        let reaches = |y: usize| {
            let (reach, _) = per_row[y];
            let gap = if y < rows.start {
                rows.start - y
            } else {
                y.saturating_sub(rows.end.saturating_sub(1))
            };
            gap as f64 <= reach + 2.0
        };
        let (Some(first), Some(last)) = (
            (0..height).find(|&y| reaches(y)),
            (0..height).rev().find(|&y| reaches(y)),
        ) else {
            return rows.start.min(height)..rows.end.min(height);
        };
        let factor = per_row[first..=last].iter().map(|r| r.1).max().unwrap_or(1);
        if factor > height {
            return 0..height;
        }
        let start = first.min(rows.start) / factor * factor;
        start..(last + 1).max(rows.end).min(height)
    }

    /// Projector `k`'s coordinates of every visible surface pixel, projected through the
    /// calibration (distortion included).
    pub fn projector_coords(&self, k: usize) -> Result<Vec<Option<(f32, f32)>>, ModelFileError> {
        let count = self.header.projectors.len();
        let (Some(device), Some(visible)) = (
            self.header.calibration.projectors.get(k),
            self.visibility.get(k),
        ) else {
            return Err(ModelFileError::NoSuchProjector {
                requested: k,
                count,
            });
        };
        let device = &device.device;
        Ok(self
            .surface
            .points
            .iter()
            .zip(visible)
            .zip(&self.surface.mask)
            .map(|((p, &vis), &on)| {
                if !(vis && on) {
                    return None;
                }
                device
                    .project(&Point3::from(*p))
                    .map(|q| (q.x as f32, q.y as f32))
            })
            .collect())
    }

    /// Writes the model file.
    pub fn save(&self, path: &Path) -> Result<(), ModelFileError> {
        self.save_as(path, FORMAT_VERSION)
    }

    /// Writes the model file in layout `version` (format 1 only to test that it is still read).
    fn save_as(&self, path: &Path, version: u32) -> Result<(), ModelFileError> {
        self.check()?;
        let io = |source| ModelFileError::Io {
            path: path.to_owned(),
            source,
        };
        let file = std::fs::File::create(path).map_err(io)?;
        let mut out = std::io::BufWriter::new(file);
        out.write_all(MAGIC).map_err(io)?;
        out.write_all(&version.to_le_bytes()).map_err(io)?;
        let header = serde_json::to_vec(&self.header)
            .map_err(|e| ModelFileError::Inconsistent(e.to_string()))?;
        let mut buf = Vec::with_capacity(header.len() + 64 * self.surface.len());
        put_u32(&mut buf, header.len() as u32);
        buf.extend_from_slice(&header);
        for p in &self.surface.points {
            put_f32s(&mut buf, &[p.x as f32, p.y as f32, p.z as f32]);
        }
        for n in &self.surface.normals {
            put_f32s(&mut buf, &[n.x as f32, n.y as f32, n.z as f32]);
        }
        buf.extend(self.surface.mask.iter().map(|&m| u8::from(m)));
        for a in self.albedo.iter().chain(&self.white_albedo) {
            put_f32s(&mut buf, a);
        }
        for v in &self.visibility {
            buf.extend(v.iter().map(|&m| u8::from(m)));
        }
        let put = |buf: &mut Vec<u8>, model: &LayerModel| match version {
            1 => {
                put_layers_v1(buf, model);
                Ok(())
            }
            _ => put_layers(buf, model),
        };
        put(&mut buf, &self.layers)?;
        match &self.dipole {
            Some(d) => {
                buf.push(1);
                put(&mut buf, d)?;
            }
            None => buf.push(0),
        }
        // Compressed in chunks on every core, written as consecutive gzip members (one gzip
        // stream to a reader that reads them all, as `load` does).
        let members: Vec<Vec<u8>> = buf
            .par_chunks(GZIP_CHUNK)
            .map(|chunk| {
                let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
                gz.write_all(chunk)?;
                gz.finish()
            })
            .collect::<Result<_, _>>()
            .map_err(io)?;
        for member in &members {
            out.write_all(member).map_err(io)?;
        }
        out.flush().map_err(io)
    }

    /// Reads a model file.
    pub fn load(path: &Path) -> Result<Self, ModelFileError> {
        let io = |source| ModelFileError::Io {
            path: path.to_owned(),
            source,
        };
        let not_a_model = |reason: &str| ModelFileError::NotAModel {
            path: path.to_owned(),
            reason: reason.to_owned(),
        };
        let mut file = std::io::BufReader::new(std::fs::File::open(path).map_err(io)?);
        let mut magic = [0u8; 12];
        file.read_exact(&mut magic)
            .map_err(|_| not_a_model("shorter than its 12-byte preamble"))?;
        if &magic[..8] != MAGIC {
            return Err(not_a_model("wrong magic bytes"));
        }
        let version = u32::from_le_bytes([magic[8], magic[9], magic[10], magic[11]]);
        if !(OLDEST_READABLE_VERSION..=FORMAT_VERSION).contains(&version) {
            return Err(not_a_model(&format!("it has version {version}")));
        }
        let mut bytes = Vec::new();
        flate2::read::MultiGzDecoder::new(file)
            .read_to_end(&mut bytes)
            .map_err(io)?;
        let mut r = Reader {
            bytes: &bytes,
            at: 0,
            path,
        };
        let header_len = r.u32()? as usize;
        let header: ModelHeader =
            serde_json::from_slice(r.take(header_len)?).map_err(|e| ModelFileError::Corrupt {
                path: path.to_owned(),
                reason: format!("header: {e}"),
            })?;
        let n = header
            .width
            .checked_mul(header.height)
            .ok_or_else(|| r.corrupt("image size overflows"))?;
        let points = r.vectors(n)?;
        let normals = r.vectors(n)?;
        let mask = r.flags(n)?;
        let mut rgb = || {
            (0..n)
                .map(|_| Ok([r.f32()?, r.f32()?, r.f32()?]))
                .collect::<Result<Vec<_>, ModelFileError>>()
        };
        let albedo = rgb()?;
        let white_albedo = rgb()?;
        let visibility = (0..header.projectors.len())
            .map(|_| r.flags(n))
            .collect::<Result<Vec<_>, _>>()?;
        let layer_model = |r: &mut Reader| match version {
            1 => r.layers_v1(header.width, header.height),
            _ => r.layers(header.width, header.height),
        };
        let layers = layer_model(&mut r)?;
        let dipole = match r.take(1)?[0] {
            0 => None,
            _ => Some(layer_model(&mut r)?),
        };
        if r.at != bytes.len() {
            return Err(r.corrupt("trailing bytes after the last section"));
        }
        let surface = Surface {
            width: header.width,
            height: header.height,
            points,
            normals,
            mask,
            camera_centre: Vector3::from(header.camera_centre),
        };
        let model = Self {
            header,
            surface,
            albedo,
            white_albedo,
            visibility,
            layers,
            dipole,
        };
        model.check().map_err(|e| r.corrupt(&e.to_string()))?;
        Ok(model)
    }
}

fn put_u32(buf: &mut Vec<u8>, v: u32) {
    buf.extend_from_slice(&v.to_le_bytes());
}

fn put_f32s(buf: &mut Vec<u8>, vs: &[f32]) {
    for v in vs {
        buf.extend_from_slice(&v.to_le_bytes());
    }
}

/// Writes the layer model section of format 1 (see the module doc).
fn put_layers_v1(buf: &mut Vec<u8>, model: &LayerModel) {
    let (offsets, layers) = model.parts();
    for &o in offsets {
        put_u32(buf, o);
    }
    put_u32(buf, layers.len() as u32);
    for l in layers {
        buf.extend_from_slice(&l.index.to_le_bytes());
        put_f32s(buf, &[l.weight, l.sigma_mm, l.depth_mm]);
    }
}

/// A layer's identity in the palette: index and the bits of sigma and depth.
type PaletteKey = (u16, u32, u32);

/// Hashes palette keys by multiply-rotate (as rustc's FxHasher): one lookup per stored layer
/// (tens of millions at full size), where the default SipHash took a tenth of the save. The keys
/// are our own numbers, so flooding resistance buys nothing here.
#[derive(Default)]
struct PaletteHasher(u64);

impl std::hash::Hasher for PaletteHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(u64::from(b));
        }
    }

    fn write_u16(&mut self, v: u16) {
        self.write_u64(u64::from(v));
    }

    fn write_u32(&mut self, v: u32) {
        self.write_u64(u64::from(v));
    }

    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(5) ^ v).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }
}

type Palette =
    std::collections::HashMap<PaletteKey, u32, std::hash::BuildHasherDefault<PaletteHasher>>;

/// Writes the layer model section of format 2 (see the module doc).
fn put_layers(buf: &mut Vec<u8>, model: &LayerModel) -> Result<(), ModelFileError> {
    let (offsets, layers) = model.parts();
    for row in offsets.windows(2) {
        let count = u16::try_from(row[1] - row[0]).map_err(|_| {
            ModelFileError::Inconsistent("a pixel has more than 65535 layers".into())
        })?;
        buf.extend_from_slice(&count.to_le_bytes());
    }
    let mut palette: Palette = Default::default();
    let mut entries: Vec<PaletteKey> = Vec::new();
    let ids: Vec<u32> = layers
        .iter()
        .map(|l| {
            let key = (l.index, l.sigma_mm.to_bits(), l.depth_mm.to_bits());
            *palette.entry(key).or_insert_with(|| {
                entries.push(key);
                (entries.len() - 1) as u32
            })
        })
        .collect();
    put_u32(buf, entries.len() as u32);
    for &(index, sigma, depth) in &entries {
        buf.extend_from_slice(&index.to_le_bytes());
        put_u32(buf, sigma);
        put_u32(buf, depth);
    }
    put_u32(buf, layers.len() as u32);
    let id_bytes: u8 = match entries.len() {
        0..=0x100 => 1,
        0x101..=0x1_0000 => 2,
        _ => 4,
    };
    buf.push(id_bytes);
    for id in ids {
        buf.extend_from_slice(&id.to_le_bytes()[..usize::from(id_bytes)]);
    }
    for plane in 0..4 {
        buf.extend(layers.iter().map(|l| l.weight.to_le_bytes()[plane]));
    }
    Ok(())
}

/// Cursor over the decompressed sections.
struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
    path: &'a Path,
}

impl<'a> Reader<'a> {
    fn corrupt(&self, reason: &str) -> ModelFileError {
        ModelFileError::Corrupt {
            path: self.path.to_owned(),
            reason: reason.to_owned(),
        }
    }

    fn take(&mut self, len: usize) -> Result<&'a [u8], ModelFileError> {
        let end = self
            .at
            .checked_add(len)
            .filter(|&e| e <= self.bytes.len())
            .ok_or_else(|| self.corrupt("ends before its last section"))?;
        let out = &self.bytes[self.at..end];
        self.at = end;
        Ok(out)
    }

    fn u32(&mut self) -> Result<u32, ModelFileError> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn f32(&mut self) -> Result<f32, ModelFileError> {
        let b = self.take(4)?;
        let v = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        if v.is_finite() {
            Ok(v)
        } else {
            Err(self.corrupt("a non-finite number"))
        }
    }

    fn vectors(&mut self, n: usize) -> Result<Vec<Vector3<f64>>, ModelFileError> {
        (0..n)
            .map(|_| {
                Ok(Vector3::new(
                    f64::from(self.f32()?),
                    f64::from(self.f32()?),
                    f64::from(self.f32()?),
                ))
            })
            .collect()
    }

    fn flags(&mut self, n: usize) -> Result<Vec<bool>, ModelFileError> {
        Ok(self.take(n)?.iter().map(|&b| b != 0).collect())
    }

    /// The layer model section of format 2 (see the module doc).
    fn layers(&mut self, width: usize, height: usize) -> Result<LayerModel, ModelFileError> {
        let rows = width * height * 3;
        let counts = self.take(rows.checked_mul(2).ok_or_else(|| self.corrupt("size"))?)?;
        let mut offsets = Vec::with_capacity(rows + 1);
        let mut total = 0u32;
        offsets.push(0);
        for c in counts.chunks_exact(2) {
            total = total
                .checked_add(u32::from(u16::from_le_bytes([c[0], c[1]])))
                .ok_or_else(|| self.corrupt("more than 2^32 layers"))?;
            offsets.push(total);
        }
        let entries = self.u32()? as usize;
        if entries > self.bytes.len() / 10 {
            return Err(self.corrupt("palette larger than the file"));
        }
        let palette = (0..entries)
            .map(|_| {
                let b = self.take(2)?;
                Ok((u16::from_le_bytes([b[0], b[1]]), self.f32()?, self.f32()?))
            })
            .collect::<Result<Vec<_>, ModelFileError>>()?;
        let count = self.u32()? as usize;
        if count != total as usize {
            return Err(self.corrupt("layer count differs from the pixels' layer counts"));
        }
        let id_bytes = usize::from(self.take(1)?[0]);
        if ![1, 2, 4].contains(&id_bytes) {
            return Err(self.corrupt("palette id width is not 1, 2 or 4 bytes"));
        }
        let ids = self.take(
            count
                .checked_mul(id_bytes)
                .ok_or_else(|| self.corrupt("size"))?,
        )?;
        let planes = self.take(count.checked_mul(4).ok_or_else(|| self.corrupt("size"))?)?;
        let layers = (0..count)
            .map(|j| {
                let mut id = [0u8; 4];
                id[..id_bytes].copy_from_slice(&ids[j * id_bytes..(j + 1) * id_bytes]);
                let &(index, sigma_mm, depth_mm) = palette
                    .get(u32::from_le_bytes(id) as usize)
                    .ok_or_else(|| self.corrupt("a palette id beyond the palette"))?;
                let weight = f32::from_le_bytes(std::array::from_fn(|k| planes[k * count + j]));
                if !weight.is_finite() {
                    return Err(self.corrupt("a non-finite number"));
                }
                Ok(SplatLayer {
                    index,
                    weight,
                    sigma_mm,
                    depth_mm,
                })
            })
            .collect::<Result<Vec<_>, ModelFileError>>()?;
        LayerModel::from_parts(width, height, offsets, layers)
            .ok_or_else(|| self.corrupt("layer counts do not index the layers"))
    }

    /// The layer model section of format 1: offsets, then 14 bytes per layer.
    fn layers_v1(&mut self, width: usize, height: usize) -> Result<LayerModel, ModelFileError> {
        let rows = width * height * 3 + 1;
        let offsets = (0..rows)
            .map(|_| self.u32())
            .collect::<Result<Vec<_>, _>>()?;
        let count = self.u32()? as usize;
        if count > self.bytes.len() / 14 {
            return Err(self.corrupt("layer count larger than the file"));
        }
        let layers = (0..count)
            .map(|_| {
                let b = self.take(2)?;
                Ok(SplatLayer {
                    index: u16::from_le_bytes([b[0], b[1]]),
                    weight: self.f32()?,
                    sigma_mm: self.f32()?,
                    depth_mm: self.f32()?,
                })
            })
            .collect::<Result<Vec<_>, ModelFileError>>()?;
        LayerModel::from_parts(width, height, offsets, layers)
            .ok_or_else(|| self.corrupt("layer offsets do not index the layers"))
    }
}

/// Renders projector `k` showing `pattern` with the chosen model: the direct part from the
/// albedo, the subsurface part from the layers. [`Baseline::Direct`] has no subsurface part: all
/// light (the white albedo) is re-emitted where it enters. Pure function of the model: no files.
pub fn render_projector(
    model: &SubsurfaceModel,
    k: usize,
    pattern: &Pattern,
    baseline: Baseline,
    opts: &RenderOptions,
) -> Result<Relit, ModelFileError> {
    let black_level = |light: &ProjectorLight| light.black_level;
    render_with_black_level(model, k, pattern, baseline, opts, black_level)
}

/// As [`render_projector`] with the projector's black level taken as 0: the pattern's own light
/// alone (for a slit, what `(G_slit - b G_white) / (1 - b)` gives from two renders with the
/// black level `b`; the renderer is linear in the irradiance), in one render.
pub fn render_pattern_alone(
    model: &SubsurfaceModel,
    k: usize,
    pattern: &Pattern,
    baseline: Baseline,
    opts: &RenderOptions,
) -> Result<Relit, ModelFileError> {
    render_with_black_level(model, k, pattern, baseline, opts, |_| 0.0)
}

fn render_with_black_level(
    model: &SubsurfaceModel,
    k: usize,
    pattern: &Pattern,
    baseline: Baseline,
    opts: &RenderOptions,
    black_level: impl Fn(&ProjectorLight) -> f32,
) -> Result<Relit, ModelFileError> {
    let light = model
        .header
        .projectors
        .get(k)
        .ok_or(ModelFileError::NoSuchProjector {
            requested: k,
            count: model.header.projectors.len(),
        })?;
    let coords = model.projector_coords(k)?;
    let view = ProjectorIllumination {
        centre: Vector3::from(light.centre),
        falloff: light.falloff,
        coords: &coords,
    };
    let homogeneous;
    let empty;
    let (layers, albedo) = match baseline {
        Baseline::Mlsss => (&model.layers, &model.albedo),
        Baseline::Homogeneous => {
            homogeneous = model.homogeneous();
            (&homogeneous, &model.albedo)
        }
        Baseline::Dipole => (
            model.dipole.as_ref().ok_or(ModelFileError::NoDipole)?,
            &model.albedo,
        ),
        Baseline::Direct => {
            empty = LayerModel::from_fn(model.header.width, model.header.height, |_, _| Vec::new());
            (&empty, &model.white_albedo)
        }
    };
    Ok(relight(
        &model.surface,
        &view,
        pattern,
        black_level(light),
        light.blur_px,
        layers,
        albedo,
        model.header.eta,
        model.header.view_ray,
        opts,
    )?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use mlsss_core::booth::Booth;
    use mlsss_core::capture::Axis;

    /// A small model of the plane z = 0 seen by the quick booth's calibration.
    fn plane_model() -> SubsurfaceModel {
        plane_model_sized(24, 16)
    }

    fn plane_model_sized(w: usize, h: usize) -> SubsurfaceModel {
        let booth = Booth::builtin(true);
        let calibration = booth.calibration();
        let cam = booth.camera_calibration();
        // A patch of the camera image around its centre, scaled down to w x h.
        let points: Vec<Vector3<f64>> = (0..w * h)
            .map(|i| {
                let x = cam.width as f64 / 2.0 + ((i % w) as f64 - w as f64 / 2.0);
                let y = cam.height as f64 / 2.0 + ((i / w) as f64 - h as f64 / 2.0);
                let (o, d) = cam.ray(x, y);
                (o + d * (-o.z / d.z)).coords
            })
            .collect();
        let projectors: Vec<ProjectorLight> = calibration
            .projectors
            .iter()
            .map(|p| ProjectorLight {
                centre: p.device.extrinsics.centre().coords.into(),
                falloff: Falloff::Projector {
                    axis: p
                        .device
                        .extrinsics
                        .device_to_world_dir(&Vector3::z())
                        .into(),
                    scale: p.device.extrinsics.centre().coords.norm_squared(),
                },
                black_level: 0.01,
                blur_px: 0.5,
            })
            .collect();
        let layers = LayerModel::from_fn(w, h, |i, c| {
            vec![SplatLayer {
                index: 1,
                weight: 0.1 + 0.01 * c as f32 + 1e-4 * i as f32,
                sigma_mm: 0.5,
                depth_mm: 0.2,
            }]
        });
        SubsurfaceModel {
            header: ModelHeader {
                format_version: FORMAT_VERSION,
                width: w,
                height: h,
                em: EmVariant::Layered,
                components: 20,
                depth_spacing_mm: 0.2,
                eta: 1.4,
                view_ray: ViewRay::Refracted,
                training_projectors: vec![0, 1, 2],
                holdout: Some(3),
                projectors: projectors.clone(),
                camera_centre: cam.extrinsics.centre().coords.into(),
                patterns: booth.patterns.clone(),
                calibration,
                stats: FitStats::default(),
            },
            surface: Surface {
                width: w,
                height: h,
                points,
                // The camera looks along +z from z = -500: the skin faces -z.
                normals: vec![-Vector3::z(); w * h],
                mask: (0..w * h).map(|i| i % 7 != 3).collect(),
                camera_centre: cam.extrinsics.centre().coords,
            },
            albedo: (0..w * h)
                .map(|i| [0.3, 0.2, 0.1 + 1e-3 * i as f32])
                .collect(),
            white_albedo: vec![[0.5, 0.4, 0.3]; w * h],
            visibility: vec![vec![true; w * h]; projectors.len()],
            layers,
            dipole: None,
        }
    }

    /// A scanline rendered from the band of rows `rows_reaching` names is the whole model's
    /// (how the fit stage draws Fig. 10 without rendering the whole image twice); a band half
    /// as wide is not, so the reach is not padding.
    #[test]
    fn a_band_of_rows_renders_its_scanline_as_the_whole_model_does() {
        let (w, h, row) = (24, 140, 70);
        let mut model = plane_model_sized(w, h);
        model.layers = LayerModel::from_fn(w, h, |i, c| {
            [(0.05, 0.4, 0.0), (0.03, 2.5, 0.6)].map(|(weight, sigma_mm, depth_mm)| SplatLayer {
                index: 1,
                weight: weight + 0.01 * c as f32 + 1e-5 * i as f32,
                sigma_mm,
                depth_mm,
            })
        });
        model.header.view_ray = ViewRay::Refracted;
        let opts = RenderOptions::default();
        let band = model.rows_reaching(row..row + 1, |i| model.layers.extent(i), &opts);
        assert!(band.start > 0 && band.end < h, "{band:?}");
        let slit = Pattern::Slit {
            axis: Axis::Y,
            width: 2,
            period: 6,
            offset: 0,
        };
        let scanline = |m: &SubsurfaceModel, r: usize| -> Vec<[f32; 3]> {
            let g = render_pattern_alone(m, 1, &slit, Baseline::Mlsss, &opts)
                .unwrap()
                .global;
            g[r * w..(r + 1) * w].to_vec()
        };
        let whole = scanline(&model, row);
        let peak = whole.iter().flatten().fold(0.0f32, |a, &b| a.max(b));
        assert!(peak > 0.0);
        let gap = |part: &[[f32; 3]]| {
            whole
                .iter()
                .flatten()
                .zip(part.iter().flatten())
                .map(|(a, b)| (a - b).abs() / peak)
                .fold(0.0f32, f32::max)
        };
        let banded = scanline(&model.rows(band.clone()), row - band.start);
        assert!(gap(&banded) < 1e-5, "{}", gap(&banded));
        let half = band.len() / 4;
        let narrow = row - half..row + half;
        let short = scanline(&model.rows(narrow.clone()), row - narrow.start);
        assert!(gap(&short) > 1e-3, "{}", gap(&short));
    }

    #[test]
    fn a_model_survives_the_file_bit_for_bit_and_bad_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.mlsss");
        let mut model = plane_model();
        model.surface.points = model
            .surface
            .points
            .iter()
            .map(|p| p.map(|v| f64::from(v as f32)))
            .collect();
        // A second layer model with a palette of more than 256 entries (2-byte ids) and rows of
        // 0 to 2 layers.
        model.dipole = Some(LayerModel::from_fn(
            model.header.width,
            model.header.height,
            |i, c| {
                (0..(i + c) % 3)
                    .map(|k| SplatLayer {
                        index: k as u16,
                        weight: 1e-3 * (i * 3 + c) as f32,
                        sigma_mm: 0.1 + 1e-3 * i as f32,
                        depth_mm: 0.0,
                    })
                    .collect::<Vec<_>>()
            },
        ));
        // Format 1 files are still read, bit for bit.
        model.save_as(&path, 1).unwrap();
        let old = SubsurfaceModel::load(&path).unwrap();
        assert_eq!(
            (old.layers, old.dipole),
            (model.layers.clone(), model.dipole.clone())
        );
        model.save(&path).unwrap();
        let back = SubsurfaceModel::load(&path).unwrap();
        // Binary sections are exact; the JSON header's floats may differ in the last digit.
        assert_eq!(back.surface, model.surface);
        assert_eq!(back.layers, model.layers);
        assert_eq!(back.dipole, model.dipole);
        assert_eq!(back.albedo, model.albedo);
        assert_eq!(back.white_albedo, model.white_albedo);
        assert_eq!(back.visibility, model.visibility);
        assert_eq!(back.header.patterns, model.header.patterns);
        assert_eq!(back.header.holdout, Some(3));
        let (a, b) = (&back.header.projectors[2], &model.header.projectors[2]);
        assert!((a.centre[0] - b.centre[0]).abs() < 1e-9 && a.black_level == b.black_level);

        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        assert!(SubsurfaceModel::load(&path).is_err());
        std::fs::write(&path, b"MLSSSMDL\x09\0\0\0").unwrap();
        let err = SubsurfaceModel::load(&path).unwrap_err().to_string();
        assert!(err.contains("version 9"), "{err}");
        std::fs::write(&path, b"not a model at all").unwrap();
        assert!(matches!(
            SubsurfaceModel::load(&path),
            Err(ModelFileError::NotAModel { .. })
        ));
    }

    #[test]
    fn renders_white_and_slits_with_every_baseline() {
        let model = plane_model();
        let opts = RenderOptions::default();
        let white = render_projector(&model, 0, &Pattern::White, Baseline::Mlsss, &opts).unwrap();
        let direct = render_projector(&model, 0, &Pattern::White, Baseline::Direct, &opts).unwrap();
        assert!(direct.global.iter().all(|g| *g == [0.0; 3]));
        // Direct only re-emits the white albedo locally: ratio to the model's direct part.
        let j = 5 * 24 + 5;
        assert!((direct.direct[j][0] / white.direct[j][0] - 0.5 / 0.3).abs() < 1e-4);
        let i = 8 * 24 + 12;
        assert!(model.surface.mask[i]);
        assert!(white.global[i][0] > 0.0 && white.direct[i][0] > 0.0);
        // Under white light with a uniform model, global / direct = weight / albedo, up to the
        // small per-pixel weight ramp and the border.
        let ratio = white.global[i][0] / white.direct[i][0];
        assert!((ratio - 0.1 / 0.3).abs() < 0.05, "{ratio}");
        let homog =
            render_projector(&model, 0, &Pattern::White, Baseline::Homogeneous, &opts).unwrap();
        assert!((homog.global[i][0] - white.global[i][0]).abs() < 0.02 * white.global[i][0]);
        // A slit through the patch's centre pixel.
        let u = model.projector_coords(1).unwrap()[i].unwrap().0.round() as u32;
        let slit = Pattern::Slit {
            axis: Axis::X,
            width: 3,
            period: 30,
            offset: (u + 29) % 30,
        };
        let s = render_projector(&model, 1, &slit, Baseline::Mlsss, &opts).unwrap();
        let (lo, hi) = s
            .total()
            .iter()
            .zip(&model.surface.mask)
            .filter(|(_, m)| **m)
            .fold((f32::MAX, 0.0f32), |(lo, hi), (v, _)| {
                (lo.min(v[0]), hi.max(v[0]))
            });
        assert!(hi > 3.0 * lo, "slits must show: {lo} .. {hi}");
        assert!(matches!(
            render_projector(&model, 0, &Pattern::White, Baseline::Dipole, &opts),
            Err(ModelFileError::NoDipole)
        ));
        assert!(matches!(
            render_projector(&model, 9, &Pattern::White, Baseline::Mlsss, &opts),
            Err(ModelFileError::NoSuchProjector { .. })
        ));
    }
}
