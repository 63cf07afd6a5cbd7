//! A small reader (and writer, for tests and generated data) of MATLAB level-5 `.mat` files:
//! numeric arrays only, optionally zlib-compressed (`miCOMPRESSED`), little-endian. Enough for
//! photometric-stereo ground truth such as DiLiGenT's `Normal_gt.mat`. MATLAB 7.3 files are HDF5
//! and are refused with a clear error.
//!
//! Conventions: arrays are returned with MATLAB's dimensions and column-major data (the first
//! index varies fastest), converted to `f64`.

use std::io::Read;
use std::path::{Path, PathBuf};

/// Errors reading a `.mat` file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MatError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// Not a level-5 MAT file (e.g. a v7.3/HDF5 file or a v4 file).
    #[error("{path}: {reason}")]
    Format { path: PathBuf, reason: String },
    /// The variable is not in the file.
    #[error("{path}: no numeric variable named '{name}' (found: {found})")]
    NoVariable {
        path: PathBuf,
        name: String,
        found: String,
    },
}

/// A numeric MATLAB array.
#[derive(Debug, Clone, PartialEq)]
pub struct MatArray {
    pub name: String,
    pub dims: Vec<usize>,
    /// Column-major values (real part only).
    pub data: Vec<f64>,
}

const MI_INT8: u32 = 1;
const MI_UINT8: u32 = 2;
const MI_INT16: u32 = 3;
const MI_UINT16: u32 = 4;
const MI_INT32: u32 = 5;
const MI_UINT32: u32 = 6;
const MI_SINGLE: u32 = 7;
const MI_DOUBLE: u32 = 9;
const MI_INT64: u32 = 12;
const MI_UINT64: u32 = 13;
const MI_MATRIX: u32 = 14;
const MI_COMPRESSED: u32 = 15;

/// Reads the numeric variable `name` from a level-5 MAT file.
pub fn read_variable(path: &Path, name: &str) -> Result<MatArray, MatError> {
    let bytes = std::fs::read(path).map_err(|source| MatError::Io {
        path: path.to_owned(),
        source,
    })?;
    let format = |reason: &str| MatError::Format {
        path: path.to_owned(),
        reason: reason.to_owned(),
    };
    if bytes.len() < 128 {
        return Err(format("too short for a MAT file header"));
    }
    if bytes.starts_with(b"\x89HDF") || bytes[..128].windows(4).any(|w| w == b"7.3 ") {
        return Err(format(
            "MATLAB 7.3 (HDF5) files are not supported; save with -v7 or -v6",
        ));
    }
    if &bytes[126..128] != b"IM" {
        return Err(format(
            "not a little-endian level-5 MAT file (no 'IM' marker at byte 126)",
        ));
    }
    let mut found = Vec::new();
    let mut pos = 128;
    while pos + 8 <= bytes.len() {
        let (kind, size, header) = tag(&bytes[pos..]).ok_or_else(|| format("truncated tag"))?;
        let body_start = pos + header;
        let body = bytes
            .get(body_start..body_start + size)
            .ok_or_else(|| format("element runs past the end of the file"))?;
        let element = match kind {
            MI_COMPRESSED => {
                let mut out = Vec::new();
                flate2::read::ZlibDecoder::new(body)
                    .read_to_end(&mut out)
                    .map_err(|e| format(&format!("bad compressed element: {e}")))?;
                let (inner, inner_size, inner_header) =
                    tag(&out).ok_or_else(|| format("truncated compressed element"))?;
                let inner_body = out
                    .get(inner_header..inner_header + inner_size)
                    .ok_or_else(|| format("compressed element is truncated"))?
                    .to_vec();
                (inner == MI_MATRIX).then_some(inner_body)
            }
            MI_MATRIX => Some(body.to_vec()),
            _ => None,
        };
        if let Some(body) = element
            && let Some(array) = parse_matrix(&body)
        {
            if array.name == name {
                return Ok(array);
            }
            found.push(array.name);
        }
        pos = body_start + size.div_ceil(8) * 8;
        if kind == MI_COMPRESSED {
            // Compressed elements are not padded.
            pos = body_start + size;
        }
    }
    Err(MatError::NoVariable {
        path: path.to_owned(),
        name: name.to_owned(),
        found: if found.is_empty() {
            "none".into()
        } else {
            found.join(", ")
        },
    })
}

/// Tag at the start of `b`: (type, byte count, header length). Handles the small-element format
/// (type and size packed in 4 bytes, data in the next 4).
fn tag(b: &[u8]) -> Option<(u32, usize, usize)> {
    let word = u32::from_le_bytes(b.get(0..4)?.try_into().ok()?);
    if word >> 16 != 0 {
        Some((word & 0xffff, (word >> 16) as usize, 4))
    } else {
        let size = u32::from_le_bytes(b.get(4..8)?.try_into().ok()?);
        Some((word, size as usize, 8))
    }
}

/// Sub-elements of a matrix body: flags, dimensions, name, real part (then maybe imaginary).
fn parse_matrix(body: &[u8]) -> Option<MatArray> {
    let mut pos = 0;
    let mut next = || -> Option<(u32, Vec<u8>)> {
        let (kind, size, header) = tag(&body[pos..])?;
        let data = body.get(pos + header..pos + header + size)?.to_vec();
        pos += if header == 4 {
            8
        } else {
            header + size.div_ceil(8) * 8
        };
        Some((kind, data))
    };
    let (_, flags) = next()?;
    let class = *flags.first()?;
    // Classes 6..=15 are double, single and the integer types; cells, structs, chars are skipped.
    if !(6..=15).contains(&class) {
        return None;
    }
    let (dim_kind, dims) = next()?;
    let dims: Vec<usize> = numbers(dim_kind, &dims)?
        .into_iter()
        .map(|d| d as usize)
        .collect();
    let (_, name) = next()?;
    let (kind, real) = next()?;
    let data = numbers(kind, &real)?;
    (data.len() == dims.iter().product::<usize>()).then(|| MatArray {
        name: String::from_utf8_lossy(&name).into_owned(),
        dims,
        data,
    })
}

fn numbers(kind: u32, b: &[u8]) -> Option<Vec<f64>> {
    macro_rules! decode {
        ($t:ty) => {
            b.chunks_exact(std::mem::size_of::<$t>())
                .map(|c| <$t>::from_le_bytes(c.try_into().unwrap_or_default()) as f64)
                .collect()
        };
    }
    Some(match kind {
        MI_INT8 => b.iter().map(|&v| v as i8 as f64).collect(),
        MI_UINT8 => b.iter().map(|&v| v as f64).collect(),
        MI_INT16 => decode!(i16),
        MI_UINT16 => decode!(u16),
        MI_INT32 => decode!(i32),
        MI_UINT32 => decode!(u32),
        MI_SINGLE => decode!(f32),
        MI_DOUBLE => decode!(f64),
        MI_INT64 => decode!(i64),
        MI_UINT64 => decode!(u64),
        _ => return None,
    })
}

fn element(kind: u32, data: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(8 + data.len() + 8);
    out.extend_from_slice(&kind.to_le_bytes());
    out.extend_from_slice(&(data.len() as u32).to_le_bytes());
    out.extend_from_slice(data);
    out.resize(out.len().div_ceil(8) * 8, 0);
    out
}

/// Writes one double array as a level-5 MAT file, zlib-compressed when `compress` is set (as
/// MATLAB's default `-v7`).
pub fn write_double(path: &Path, array: &MatArray, compress: bool) -> Result<(), MatError> {
    let io = |source| MatError::Io {
        path: path.to_owned(),
        source,
    };
    let mut flags = vec![0u8; 8];
    flags[0] = 6; // mxDOUBLE_CLASS
    let dims: Vec<u8> = array
        .dims
        .iter()
        .flat_map(|&d| (d as i32).to_le_bytes())
        .collect();
    let real: Vec<u8> = array.data.iter().flat_map(|v| v.to_le_bytes()).collect();
    let mut body = element(MI_UINT32, &flags);
    body.extend(element(MI_INT32, &dims));
    body.extend(element(MI_INT8, array.name.as_bytes()));
    body.extend(element(MI_DOUBLE, &real));
    let matrix = element(MI_MATRIX, &body);
    let mut out = Vec::new();
    let mut header = format!(
        "MATLAB 5.0 MAT-file, Platform: mlsss, Created by: mlsss {}",
        env!("CARGO_PKG_VERSION")
    )
    .into_bytes();
    header.resize(116, b' ');
    out.extend(header);
    out.extend([0u8; 8]); // subsystem data offset
    out.extend(0x0100u16.to_le_bytes());
    out.extend(b"IM");
    if compress {
        use std::io::Write;
        let mut encoder =
            flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
        encoder.write_all(&matrix).map_err(io)?;
        let packed = encoder.finish().map_err(io)?;
        out.extend(MI_COMPRESSED.to_le_bytes());
        out.extend((packed.len() as u32).to_le_bytes());
        out.extend(packed);
    } else {
        out.extend(matrix);
    }
    std::fs::write(path, out).map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_plain_and_compressed_and_names_what_it_found() {
        let dir = tempfile::tempdir().unwrap();
        let array = MatArray {
            name: "Normal_gt".into(),
            dims: vec![2, 3, 3],
            data: (0..18).map(|v| v as f64 * 0.25 - 1.0).collect(),
        };
        for compress in [false, true] {
            let path = dir.path().join(format!("n{compress}.mat"));
            write_double(&path, &array, compress).unwrap();
            assert_eq!(read_variable(&path, "Normal_gt").unwrap(), array);
            let err = read_variable(&path, "Other").unwrap_err().to_string();
            assert!(err.contains("Normal_gt"), "{err}");
        }
    }

    #[test]
    fn small_element_format_and_bad_files() {
        // A hand-built uncompressed matrix whose name "a" uses the packed small-element tag.
        let mut body = element(MI_UINT32, &[6, 0, 0, 0, 0, 0, 0, 0]);
        body.extend(element(MI_INT32, &[1, 0, 0, 0, 2, 0, 0, 0]));
        body.extend((MI_INT8 | (1 << 16)).to_le_bytes());
        body.extend([b'a', 0, 0, 0]);
        body.extend(element(
            MI_SINGLE,
            &[1.5f32.to_le_bytes(), (-2.0f32).to_le_bytes()].concat(),
        ));
        let mut file = vec![b' '; 124];
        file.extend(0x0100u16.to_le_bytes());
        file.extend(b"IM");
        file.extend(element(MI_MATRIX, &body));
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.mat");
        std::fs::write(&path, &file).unwrap();
        let a = read_variable(&path, "a").unwrap();
        assert_eq!(
            (a.dims.clone(), a.data.clone()),
            (vec![1, 2], vec![1.5, -2.0])
        );

        let hdf = dir.path().join("h.mat");
        let mut bytes = b"MATLAB 7.3 MAT-file".to_vec();
        bytes.resize(200, 0);
        std::fs::write(&hdf, bytes).unwrap();
        assert!(
            read_variable(&hdf, "a")
                .unwrap_err()
                .to_string()
                .contains("7.3")
        );
    }
}
