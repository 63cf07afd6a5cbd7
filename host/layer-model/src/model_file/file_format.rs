//! The model file's layout on disk (see [`super`]'s module doc): writing, reading, and the
//! layer model sections of formats 1 and 2.

use std::io::{Read, Write};
use std::path::Path;

use nalgebra::Vector3;
use rayon::prelude::*;

use super::{
    FORMAT_VERSION, MAGIC, ModelFileError, ModelHeader, OLDEST_READABLE_VERSION, SubsurfaceModel,
};
use crate::render::{LayerModel, SplatLayer};
use crate::surface::Surface;

/// Bytes per gzip member of the compressed part (compressed in parallel); small in the unit
/// tests so that their round trip crosses members.
const GZIP_CHUNK: usize = if cfg!(test) { 4096 } else { 64 << 20 };

impl SubsurfaceModel {
    /// Writes the model file.
    pub fn save(&self, path: &Path) -> Result<(), ModelFileError> {
        self.save_as(path, FORMAT_VERSION)
    }

    /// Writes the model file in layout `version` (format 1 only to test that it is still read).
    pub(super) fn save_as(&self, path: &Path, version: u32) -> Result<(), ModelFileError> {
        self.check()?;
        let io = |source| ModelFileError::Io {
            path: path.to_owned(),
            source,
        };
        // Written aside and renamed: a run killed while saving keeps the previous model whole.
        // An encoding error (not an I/O one) is kept here while the write is abandoned.
        let mut invalid = None;
        let written = mlsss_core::atomic_file::write_atomically(path, |out| {
            out.write_all(MAGIC)?;
            out.write_all(&version.to_le_bytes())?;
            let mut members = GzipMembers::new(out);
            match self.encode(version, &mut members) {
                Ok(()) => members.finish(),
                Err(EncodeError::Io(e)) => Err(e),
                Err(EncodeError::Model(e)) => {
                    invalid = Some(e);
                    Err(std::io::Error::other("the model cannot be encoded"))
                }
            }
        });
        match (invalid, written) {
            (Some(e), _) => Err(e),
            (None, w) => w.map_err(io),
        }
    }

    /// The uncompressed sections of layout `version`: header length and JSON, then the binary
    /// sections (see the module doc), into `members`, which compresses and writes them as they
    /// fill (the uncompressed file, 0.5 GB and more at full size, is never held whole).
    fn encode<W: Write>(
        &self,
        version: u32,
        members: &mut GzipMembers<'_, W>,
    ) -> Result<(), EncodeError> {
        let header = serde_json::to_vec(&self.header)
            .map_err(|e| ModelFileError::Inconsistent(e.to_string()))?;
        let buf = &mut members.pending;
        put_u32(buf, header.len() as u32);
        buf.extend_from_slice(&header);
        for p in &self.surface.points {
            put_f32s(buf, &[p.x as f32, p.y as f32, p.z as f32]);
        }
        for n in &self.surface.normals {
            put_f32s(buf, &[n.x as f32, n.y as f32, n.z as f32]);
        }
        buf.extend(self.surface.mask.iter().map(|&m| u8::from(m)));
        members.write_full_chunks()?;
        let buf = &mut members.pending;
        for a in self.albedo.iter().chain(&self.white_albedo) {
            put_f32s(buf, a);
        }
        for v in &self.visibility {
            buf.extend(v.iter().map(|&m| u8::from(m)));
        }
        members.write_full_chunks()?;
        let put = |members: &mut GzipMembers<'_, W>, model: &LayerModel| match version {
            1 => {
                put_layers_v1(&mut members.pending, model);
                Ok(())
            }
            _ => put_layers(members, model),
        };
        put(members, &self.layers)?;
        members.write_full_chunks()?;
        match &self.dipole {
            Some(d) => {
                members.pending.push(1);
                put(members, d)?;
            }
            None => members.pending.push(0),
        }
        Ok(())
    }

    /// Reads a model file.
    pub fn load(path: &Path) -> Result<Self, ModelFileError> {
        let (version, bytes) = read_payload(path)?;
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

/// Why a model could not be encoded: it is inconsistent, or the file could not be written.
enum EncodeError {
    Model(ModelFileError),
    Io(std::io::Error),
}

impl From<ModelFileError> for EncodeError {
    fn from(e: ModelFileError) -> Self {
        Self::Model(e)
    }
}

impl From<std::io::Error> for EncodeError {
    fn from(e: std::io::Error) -> Self {
        Self::Io(e)
    }
}

/// The encoded bytes written as consecutive gzip members of [`GZIP_CHUNK`] bytes each (one
/// gzip stream to a reader that reads them all, as `load` does), compressed on every core.
/// Bytes are appended to `pending`; whole chunks leave it once there are enough to keep the
/// cores busy, so the members are cut where a whole buffer's would be (the same file) while
/// memory holds a few chunks and the section being encoded.
struct GzipMembers<'w, W: Write> {
    out: &'w mut W,
    pending: Vec<u8>,
}

impl<'w, W: Write> GzipMembers<'w, W> {
    fn new(out: &'w mut W) -> Self {
        Self {
            out,
            pending: Vec::new(),
        }
    }

    /// Compresses and writes the whole chunks of `pending` once there are at least as many as
    /// threads (fewer would leave cores idle); the rest stays pending.
    fn write_full_chunks(&mut self) -> std::io::Result<()> {
        let whole = self.pending.len() / GZIP_CHUNK;
        if whole < rayon::current_num_threads() {
            return Ok(());
        }
        self.write_members(whole * GZIP_CHUNK)?;
        self.pending.drain(..whole * GZIP_CHUNK);
        Ok(())
    }

    /// Writes everything still pending (the last member may be short).
    fn finish(mut self) -> std::io::Result<()> {
        self.write_members(self.pending.len())
    }

    /// Compresses `pending[..len]` in chunks, in parallel, and writes the members in order.
    fn write_members(&mut self, len: usize) -> std::io::Result<()> {
        let members: Vec<Vec<u8>> = self.pending[..len]
            .par_chunks(GZIP_CHUNK)
            .map(|chunk| {
                let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
                gz.write_all(chunk)?;
                gz.finish()
            })
            .collect::<Result<_, _>>()?;
        for member in &members {
            self.out.write_all(member)?;
        }
        Ok(())
    }
}

/// The version and decompressed sections of the model file at `path`, after checking its
/// preamble.
fn read_payload(path: &Path) -> Result<(u32, Vec<u8>), ModelFileError> {
    let io = |source| ModelFileError::Io {
        path: path.to_owned(),
        source,
    };
    let not_a_model = |reason: &str| ModelFileError::NotAModel {
        path: path.to_owned(),
        reason: reason.to_owned(),
    };
    if path.is_dir() {
        let inside = path.join("fit").join("model.mlsss");
        let hint = if inside.is_file() {
            format!("a folder; did you mean {}?", inside.display())
        } else {
            "a folder, not a model file (the fit stage writes OUT/fit/model.mlsss)".to_owned()
        };
        return Err(not_a_model(&hint));
    }
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
    Ok((version, bytes))
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

/// Writes the layer model section of format 2 (see the module doc) into `members`, letting
/// whole chunks leave between its parts. Why: a full-size dipole model's section (~170 MB of
/// ids and weights) was held whole before any of it was compressed, at the fit stage's peak;
/// the members are cut at the same places either way (the same file).
fn put_layers<W: Write>(
    members: &mut GzipMembers<'_, W>,
    model: &LayerModel,
) -> Result<(), EncodeError> {
    let buf = &mut members.pending;
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
    drop(palette);
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
    members.write_full_chunks()?;
    for plane in 0..4 {
        members
            .pending
            .extend(layers.iter().map(|l| l.weight.to_le_bytes()[plane]));
        members.write_full_chunks()?;
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Streamed in uneven pieces, flushed as they come, the members are those of the whole
    /// buffer cut into chunks and compressed at once (the file the one-shot save wrote).
    #[test]
    fn streamed_members_are_the_whole_buffers_members() {
        let data: Vec<u8> = (0..GZIP_CHUNK * 21 / 2)
            .map(|i| ((i * 7) % 251) as u8 ^ (i / 97) as u8)
            .collect();
        let whole: Vec<u8> = data
            .chunks(GZIP_CHUNK)
            .flat_map(|chunk| {
                let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
                gz.write_all(chunk).unwrap();
                gz.finish().unwrap()
            })
            .collect();
        let mut out = Vec::new();
        let mut members = GzipMembers::new(&mut out);
        let mut most_pending = 0;
        for piece in data.chunks(1500) {
            members.pending.extend_from_slice(piece);
            members.write_full_chunks().unwrap();
            most_pending = most_pending.max(members.pending.len());
        }
        members.finish().unwrap();
        assert_eq!(out, whole);
        assert!(most_pending < (rayon::current_num_threads() + 1) * GZIP_CHUNK);
    }
}
