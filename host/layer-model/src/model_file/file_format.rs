//! The model file's layout on disk (see [`super`]'s module doc): writing, reading, and the
//! layer model sections of formats 1 and 2.

use std::io::{Read, Write};
use std::path::Path;

use nalgebra::Vector3;
use rayon::prelude::*;

use super::{
    FORMAT_VERSION, MAGIC, ModelFileError, ModelHeader, OLDEST_READABLE_VERSION, SubsurfaceModel,
};
use crate::render::{LayerModel, RowStorage, SplatLayer};
use crate::surface::Surface;

impl SubsurfaceModel {
    /// Writes the model file.
    pub fn save(&self, path: &Path) -> Result<(), ModelFileError> {
        self.save_as(path, FORMAT_VERSION)
    }

    /// Writes the model file in layout `version` (format 1 only to test that it is still read).
    /// Every part is encoded and compressed into its own gzip member on every core, then the
    /// members are written in order. Why: encoding one buffer and compressing its chunks in
    /// turn kept ~1 of 2 cores busy (full size, 360 MB of sections: 1.6 to 2.2 s wall for
    /// 1.9 CPU-s).
    pub(super) fn save_as(&self, path: &Path, version: u32) -> Result<(), ModelFileError> {
        self.check()?;
        let io = |source| ModelFileError::Io {
            path: path.to_owned(),
            source,
        };
        let members: Vec<Vec<Member>> = self
            .parts(version)?
            .par_iter()
            .map(Part::members)
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| match e {
                EncodeError::Model(e) => e,
                EncodeError::Io(source) => io(source),
            })?;
        // Written aside and renamed: a run killed while saving keeps the previous model whole.
        mlsss_core::atomic_file::write_atomically(path, |out| {
            out.write_all(MAGIC)?;
            out.write_all(&version.to_le_bytes())?;
            members
                .iter()
                .flatten()
                .try_for_each(|member| member.write_to(out))
        })
        .map_err(io)
    }

    /// The uncompressed sections of layout `version` as parts to encode side by side: header
    /// length and JSON, then the binary sections (see the module doc), in file order.
    fn parts(&self, version: u32) -> Result<Vec<Part<'_>>, ModelFileError> {
        let header = serde_json::to_vec(&self.header)
            .map_err(|e| ModelFileError::Inconsistent(e.to_string()))?;
        let surface = &self.surface;
        let mut parts = vec![
            Part::deflated(move || {
                let mut buf = Vec::with_capacity(4 + header.len());
                put_u32(&mut buf, header.len() as u32);
                buf.extend_from_slice(&header);
                Ok(buf)
            }),
            Part::deflated(|| Ok(vectors(&surface.points))),
            Part::deflated(|| Ok(vectors(&surface.normals))),
            Part::deflated(|| Ok(flags(&surface.mask))),
            Part::deflated(|| Ok(rgbs(&self.albedo))),
            Part::deflated(|| Ok(rgbs(&self.white_albedo))),
            Part::deflated(|| Ok(self.visibility.iter().flat_map(|v| flags(v)).collect())),
        ];
        parts.extend(layer_parts(&self.layers, version));
        let flag = u8::from(self.dipole.is_some());
        parts.push(Part::deflated(move || Ok(vec![flag])));
        if let Some(d) = &self.dipole {
            parts.extend(layer_parts(d, version));
        }
        Ok(parts)
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

/// Why a part could not be encoded: the model is inconsistent, or compressing failed.
enum EncodeError {
    Model(ModelFileError),
    Io(std::io::Error),
}

/// Encodes one part of the file's sections, as one or more pieces in file order.
type Encode<'m> = Box<dyn Fn() -> Result<Vec<Piece>, ModelFileError> + Send + Sync + 'm>;

/// Consecutive bytes of the sections, written as one gzip member (the members read as one
/// gzip stream, as `load` reads them).
struct Piece {
    bytes: Vec<u8>,
    /// Deflated, or stored as they are (bytes that are noise to deflate).
    deflate: bool,
}

impl Piece {
    /// The piece as a gzip member.
    fn member(self) -> std::io::Result<Member> {
        if !self.deflate {
            let crc = crc32fast::hash(&self.bytes);
            return Ok(Member::Stored {
                bytes: self.bytes,
                crc,
            });
        }
        let capacity = self.bytes.len() / 2;
        let mut gz = flate2::write::GzEncoder::new(
            Vec::with_capacity(capacity),
            flate2::Compression::fast(),
        );
        gz.write_all(&self.bytes)?;
        gz.finish().map(Member::Compressed)
    }
}

/// Bytes per stored deflate block (the most its 16-bit length holds).
const STORED_BLOCK: usize = 0xffff;

/// One gzip member of the file, ready to write.
enum Member {
    /// Written as it is.
    Compressed(Vec<u8>),
    /// Bytes to write as stored deflate blocks, with their CRC-32.
    Stored { bytes: Vec<u8>, crc: u32 },
}

impl Member {
    fn write_to(&self, out: &mut impl Write) -> std::io::Result<()> {
        match self {
            Self::Compressed(member) => out.write_all(member),
            Self::Stored { bytes, crc } => write_stored_member(out, bytes, *crc),
        }
    }
}

/// Writes `bytes` (CRC-32 `crc`) as one gzip member of stored deflate blocks (RFC 1951
/// section 3.2.4, RFC 1952), straight from `bytes`. Why: `flate2` at level 0 went through
/// miniz_oxide's stored path at about 310 MB/s (the full-size weight planes' 88 MB: 70 perf
/// samples at 250 Hz, 0.28 CPU-s), and a member built in memory first was an 88 MB copy.
fn write_stored_member(out: &mut impl Write, bytes: &[u8], crc: u32) -> std::io::Result<()> {
    // Magic, deflate, no flags, no time, no extra flags, operating system unknown.
    out.write_all(&[0x1f, 0x8b, 8, 0, 0, 0, 0, 0, 0, 255])?;
    let mut chunks = bytes.chunks(STORED_BLOCK).peekable();
    let mut block = |chunk: &[u8], last: bool| {
        // BFINAL, BTYPE 00 (stored) and the padding to the byte, then LEN and its complement.
        let len = chunk.len() as u16;
        let [l0, l1] = len.to_le_bytes();
        let [n0, n1] = (!len).to_le_bytes();
        out.write_all(&[u8::from(last), l0, l1, n0, n1])?;
        out.write_all(chunk)
    };
    if chunks.peek().is_none() {
        block(&[], true)?;
    }
    while let Some(chunk) = chunks.next() {
        block(chunk, chunks.peek().is_none())?;
    }
    out.write_all(&crc.to_le_bytes())?;
    // ISIZE: the length modulo 2^32.
    out.write_all(&(bytes.len() as u32).to_le_bytes())
}

/// A part of the file's uncompressed sections, encoded beside the others.
struct Part<'m> {
    encode: Encode<'m>,
}

impl<'m> Part<'m> {
    /// A part of one deflated piece.
    fn deflated(encode: impl Fn() -> Result<Vec<u8>, ModelFileError> + Send + Sync + 'm) -> Self {
        Self {
            encode: Box::new(move || {
                Ok(vec![Piece {
                    bytes: encode()?,
                    deflate: true,
                }])
            }),
        }
    }

    /// The part encoded, as gzip members (its pieces compressed side by side).
    fn members(&self) -> Result<Vec<Member>, EncodeError> {
        let pieces = (self.encode)().map_err(EncodeError::Model)?;
        pieces
            .into_par_iter()
            .map(Piece::member)
            .collect::<Result<_, _>>()
            .map_err(EncodeError::Io)
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
    let mut offset = 0u32;
    put_u32(buf, offset);
    for len in model.row_lens() {
        offset += len as u32;
        put_u32(buf, offset);
    }
    put_u32(buf, offset);
    for l in model.all_layers() {
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

/// The layer model section of layout `version` as parts (see the module doc): format 2's layer
/// counts, palette with ids, and the weights' byte planes apart, so they are encoded side by
/// side.
fn layer_parts(model: &LayerModel, version: u32) -> Vec<Part<'_>> {
    if version == 1 {
        return vec![Part::deflated(move || {
            let mut buf = Vec::new();
            put_layers_v1(&mut buf, model);
            Ok(buf)
        })];
    }
    let mut parts = vec![
        Part::deflated(move || layer_counts(model)),
        Part::deflated(move || Ok(palette_ids(model))),
    ];
    parts.push(Part {
        encode: Box::new(move || Ok(weight_planes(model))),
    });
    parts
}

/// Every layer's `f32` weight as four byte planes (LE byte 0 of all, then byte 1, ...), taken
/// in one pass over the layers (one pass per plane read the 16-byte layers four times: a third
/// of the save's encoding at full size). Planes 0 and 1 are stored, not deflated: the weights'
/// two lowest bytes are noise to deflate (full size: plane 0 30.52 MB deflated to 30.50 MB;
/// plane 1 of the layers 30.52 to 25.95 MB and of the dipole 13.84 to 13.71 MB, for about a
/// quarter of the deflate time: the file is 3.7 % larger for it).
fn weight_planes(model: &LayerModel) -> Vec<Piece> {
    let count = model.layer_count();
    let mut planes: [Vec<u8>; 4] = std::array::from_fn(|_| vec![0; count]);
    // Written in place, not pushed: no capacity check per byte (tens of millions of layers).
    let [p0, p1, p2, p3] = &mut planes;
    let mut slots = p0.iter_mut().zip(p1).zip(p2).zip(p3);
    let shapes = model.shapes();
    for row in model.row_storage() {
        match row {
            RowStorage::Own(layers) => put_bytes(layers.iter().map(|l| l.weight), &mut slots),
            RowStorage::Scaled { shape, scale } => {
                put_bytes(
                    shapes[shape].iter().map(|s| s.scaled(scale).weight),
                    &mut slots,
                );
            }
        }
    }
    planes
        .into_iter()
        .enumerate()
        .map(|(k, bytes)| Piece {
            bytes,
            deflate: k > 1,
        })
        .collect()
}

/// Writes each weight's LE bytes into the next slot of the four planes.
fn put_bytes<'p>(
    weights: impl Iterator<Item = f32>,
    slots: &mut impl Iterator<Item = (((&'p mut u8, &'p mut u8), &'p mut u8), &'p mut u8)>,
) {
    for (w, (((b0, b1), b2), b3)) in weights.zip(slots) {
        [*b0, *b1, *b2, *b3] = w.to_le_bytes();
    }
}

/// Every pixel and channel's layer count, `u16` LE (format 2).
fn layer_counts(model: &LayerModel) -> Result<Vec<u8>, ModelFileError> {
    let mut buf = Vec::with_capacity(model.row_lens().len() * 2);
    for len in model.row_lens() {
        let count = u16::try_from(len).map_err(|_| {
            ModelFileError::Inconsistent("a pixel has more than 65535 layers".into())
        })?;
        buf.extend_from_slice(&count.to_le_bytes());
    }
    Ok(buf)
}

/// The palette of distinct `(index, sigma, depth)` triples, the layer count, the palette id
/// width and every layer's palette id (format 2).
fn palette_ids(model: &LayerModel) -> Vec<u8> {
    let mut palette: Palette = Default::default();
    let mut entries: Vec<PaletteKey> = Vec::new();
    let mut id_of = |index: u16, sigma_mm: f32, depth_mm: f32| {
        let key = (index, sigma_mm.to_bits(), depth_mm.to_bits());
        *palette.entry(key).or_insert_with(|| {
            entries.push(key);
            (entries.len() - 1) as u32
        })
    };
    // A shared shape's layers are looked up once, by the first row that scales it, so the
    // palette lists its entries in the layers' order, as when every layer was looked up.
    const UNSEEN: u32 = u32::MAX;
    let shapes = model.shapes();
    let mut shape_ids = vec![UNSEEN; shapes.len()];
    let mut ids: Vec<u32> = Vec::with_capacity(model.layer_count());
    for row in model.row_storage() {
        match row {
            RowStorage::Own(layers) => {
                ids.extend(
                    layers
                        .iter()
                        .map(|l| id_of(l.index, l.sigma_mm, l.depth_mm)),
                );
            }
            RowStorage::Scaled { shape, .. } => {
                for (id, s) in shape_ids[shape.clone()].iter_mut().zip(&shapes[shape]) {
                    if *id == UNSEEN {
                        *id = id_of(s.index, s.sigma_mm, s.depth_mm);
                    }
                    ids.push(*id);
                }
            }
        }
    }
    drop(palette);
    let id_bytes: u8 = match entries.len() {
        0..=0x100 => 1,
        0x101..=0x1_0000 => 2,
        _ => 4,
    };
    let mut buf = Vec::with_capacity(9 + entries.len() * 10 + ids.len() * usize::from(id_bytes));
    put_u32(&mut buf, entries.len() as u32);
    for &(index, sigma, depth) in &entries {
        buf.extend_from_slice(&index.to_le_bytes());
        put_u32(&mut buf, sigma);
        put_u32(&mut buf, depth);
    }
    put_u32(&mut buf, ids.len() as u32);
    buf.push(id_bytes);
    match id_bytes {
        1 => put_le(&mut buf, &ids, |id| [id as u8]),
        2 => put_le(&mut buf, &ids, |id| (id as u16).to_le_bytes()),
        _ => put_le(&mut buf, &ids, u32::to_le_bytes),
    }
    buf
}

/// Appends `encode(v)` of every value, in order, into room made at once: not a growing push and
/// a copy of runtime length per value (tens of millions of palette ids at full size).
fn put_le<T: Copy, const N: usize>(buf: &mut Vec<u8>, values: &[T], encode: impl Fn(T) -> [u8; N]) {
    let start = buf.len();
    buf.resize(start + values.len() * N, 0);
    let (out, _) = buf[start..].as_chunks_mut::<N>();
    for (o, &v) in out.iter_mut().zip(values) {
        *o = encode(v);
    }
}

/// Vectors as `f32` triples, LE.
fn vectors(vs: &[Vector3<f64>]) -> Vec<u8> {
    let mut buf = Vec::new();
    put_le(&mut buf, vs, |v| {
        f32_triple([v.x as f32, v.y as f32, v.z as f32])
    });
    buf
}

/// RGB triples, LE.
fn rgbs(vs: &[[f32; 3]]) -> Vec<u8> {
    let mut buf = Vec::new();
    put_le(&mut buf, vs, f32_triple);
    buf
}

/// Three `f32` as 12 bytes, LE.
fn f32_triple(v: [f32; 3]) -> [u8; 12] {
    let mut out = [0u8; 12];
    for (o, x) in out.as_chunks_mut::<4>().0.iter_mut().zip(v) {
        *o = x.to_le_bytes();
    }
    out
}

/// Flags as bytes 0 and 1.
fn flags(fs: &[bool]) -> Vec<u8> {
    fs.iter().map(|&f| u8::from(f)).collect()
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

    /// A stored member is a gzip member `flate2` reads back to its bytes, at lengths around the
    /// block size (none, one block, a full block, a full one and one byte, several).
    #[test]
    fn stored_members_read_back_through_a_gzip_decoder() {
        for len in [
            0,
            1,
            STORED_BLOCK - 1,
            STORED_BLOCK,
            STORED_BLOCK + 1,
            200_000,
        ] {
            let bytes: Vec<u8> = (0..len).map(|i| (i * 7 + i / 300) as u8).collect();
            let mut member = Vec::new();
            write_stored_member(&mut member, &bytes, crc32fast::hash(&bytes)).unwrap();
            assert_eq!(
                member.len(),
                18 + len + 5 * len.div_ceil(STORED_BLOCK).max(1)
            );
            // Two members in a row read as one stream, as `load` reads the file.
            let twice = [member.as_slice(), member.as_slice()].concat();
            let mut back = Vec::new();
            flate2::read::MultiGzDecoder::new(twice.as_slice())
                .read_to_end(&mut back)
                .unwrap();
            assert!(
                back == [bytes.as_slice(), bytes.as_slice()].concat(),
                "{len}"
            );
        }
    }
}
