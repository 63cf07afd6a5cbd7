//! The samples of a frame PNG as [`super::folder::write_frame_png`] writes it (16-bit RGB, one
//! image data chunk holding a zlib stream of stored deflate blocks, every row unfiltered), read
//! without a PNG decoder: the file is read whole into a buffer and its samples are moved to the
//! front of that buffer, dropping the chunk, block and row headers.
//!
//! Why: `png` streams the file through a 64 KiB read buffer, its inflater's window and a row
//! buffer before the frame's bytes reach their place (three copies and per-row work), which was
//! a third of the full-size decode stage's CPU time (perf: `memmove`, the kernel's copy, the
//! reader's closures). Here the kernel copies the file once and one `copy_within` per row or
//! block part packs the samples. The chunks' CRCs are checked as `png` checks them; like `png`
//! (by default), the zlib stream's Adler-32 is not. Any other layout (compressed or filtered
//! rows, several data chunks, another colour type or size) is left to `png`: the caller falls
//! back when [`read_stored_rgb16`] says no.

use std::io::Read;
use std::path::Path;

/// The eight bytes every PNG starts with.
const SIGNATURE: [u8; 8] = [137, 80, 78, 71, 13, 10, 26, 10];

/// Reads the PNG at `path` into `bytes` (emptied first, its allocation reused) and, when it is a
/// 16-bit RGB frame of `size` laid out as the frame writer lays it out (module doc), leaves its
/// big-endian samples, row-major, at the front of `bytes` and returns their length. `None` for
/// any other file (the contents of `bytes` are then unspecified): a PNG decoder must read it.
pub(super) fn read_stored_rgb16(
    path: &Path,
    size: (u32, u32),
    bytes: &mut Vec<u8>,
) -> std::io::Result<Option<usize>> {
    read_whole(path, bytes)?;
    Ok(stored_segments(bytes, size).map(|segments| pack(bytes, &segments)))
}

/// [`read_stored_rgb16`] without packing the samples: `row(y, samples)` is called for every row
/// `y` of the frame, top to bottom, with its big-endian samples (in place where the row lies
/// in one stored block, else copied into `scratch`). Why: the luminance of a frame reads each
/// row once; packing first moved every byte of the frame once more (5 % of the full-size
/// decode stage's CPU time, perf). `false` (and no call) for any other file.
pub(super) fn for_each_stored_row(
    path: &Path,
    size: (u32, u32),
    bytes: &mut Vec<u8>,
    scratch: &mut Vec<u8>,
    mut row: impl FnMut(usize, &[u8]),
) -> std::io::Result<bool> {
    read_whole(path, bytes)?;
    let Some(segments) = stored_segments(bytes, size) else {
        return Ok(false);
    };
    let row_len = size.0 as usize * 6;
    let mut y = 0;
    let mut pending = segments.iter();
    while let Some(first) = pending.next() {
        if first.len() == row_len {
            row(y, &bytes[first.clone()]);
        } else {
            // A row across blocks: its parts, gathered.
            scratch.clear();
            scratch.extend_from_slice(&bytes[first.clone()]);
            while scratch.len() < row_len {
                let Some(part) = pending.next() else {
                    return Ok(false);
                };
                scratch.extend_from_slice(&bytes[part.clone()]);
            }
            row(y, scratch);
        }
        y += 1;
    }
    Ok(true)
}

/// Reads the file at `path` into `bytes`, emptied first.
fn read_whole(path: &Path, bytes: &mut Vec<u8>) -> std::io::Result<()> {
    let mut file = std::fs::File::open(path)?;
    let file_len = file.metadata().map_or(0, |m| m.len() as usize);
    bytes.clear();
    bytes.reserve(file_len);
    file.read_to_end(bytes)?;
    Ok(())
}

/// The samples' byte ranges in `bytes` of a stored frame of `size` ([`image_data`],
/// [`sample_segments`]).
fn stored_segments(bytes: &[u8], size: (u32, u32)) -> Option<Vec<std::ops::Range<usize>>> {
    image_data(bytes, size).and_then(|data| sample_segments(bytes, data, size))
}

/// Moves the samples at `segments` (in order, ascending) to the front of `bytes`; their length.
fn pack(bytes: &mut [u8], segments: &[std::ops::Range<usize>]) -> usize {
    let mut written = 0;
    for segment in segments {
        bytes.copy_within(segment.clone(), written);
        written += segment.len();
    }
    written
}

/// The byte range of the one `IDAT` chunk's data, once the signature, the header (16-bit RGB of
/// `size`, not interlaced) and every chunk's CRC are checked; `None` if any check fails, a
/// critical chunk other than `IHDR`, `IDAT` and `IEND` appears or the image data is split.
fn image_data(bytes: &[u8], size: (u32, u32)) -> Option<std::ops::Range<usize>> {
    if bytes.get(..SIGNATURE.len())? != SIGNATURE {
        return None;
    }
    let mut pos = SIGNATURE.len();
    let mut header_ok = false;
    let mut data = None;
    loop {
        let len = u32::from_be_bytes(bytes.get(pos..pos + 4)?.try_into().ok()?) as usize;
        let kind: [u8; 4] = bytes.get(pos + 4..pos + 8)?.try_into().ok()?;
        let body = pos + 8..(pos + 8).checked_add(len)?;
        let crc = u32::from_be_bytes(bytes.get(body.end..body.end + 4)?.try_into().ok()?);
        let mut hasher = crc32fast::Hasher::new();
        hasher.update(&kind);
        hasher.update(bytes.get(body.clone())?);
        if hasher.finalize() != crc {
            return None;
        }
        let next = body.end + 4;
        match &kind {
            b"IHDR" => header_ok = pos == SIGNATURE.len() && is_rgb16_header(&bytes[body], size),
            b"IDAT" if data.is_none() && header_ok => data = Some(body),
            b"IEND" => return if header_ok { data } else { None },
            // Ancillary chunks (lower-case first letter) carry nothing the samples need.
            _ if kind[0].is_ascii_lowercase() => {}
            _ => return None,
        }
        pos = next;
    }
}

/// Whether an `IHDR` chunk's data describes a 16-bit RGB image of `size`, not interlaced.
fn is_rgb16_header(header: &[u8], size: (u32, u32)) -> bool {
    let (w, h) = (size.0.to_be_bytes(), size.1.to_be_bytes());
    // Width, height, bit depth 16, colour type 2 (RGB), compression 0, filter 0, interlace 0.
    header.len() == 13 && header[..4] == w && header[4..8] == h && header[8..] == [16, 2, 0, 0, 0]
}

/// The byte ranges of the samples in the zlib stream at `data` in `bytes`, in order, each
/// within one row and one block, when the stream is stored deflate blocks only and every row of
/// `size` has filter type 0 (none); `None` for any other stream.
fn sample_segments(
    bytes: &[u8],
    data: std::ops::Range<usize>,
    size: (u32, u32),
) -> Option<Vec<std::ops::Range<usize>>> {
    let row = (size.0 as usize).checked_mul(6)?;
    let rows = size.1 as usize;
    let [cmf, flg] = bytes.get(data.start..data.start + 2)?.try_into().ok()?;
    // Deflate, no preset dictionary, a valid header check.
    if cmf & 0x0f != 8 || flg & 0x20 != 0 || (u16::from(cmf) << 8 | u16::from(flg)) % 31 != 0 {
        return None;
    }
    let mut segments = Vec::with_capacity(rows + rows / 4 + 1);
    let mut read = data.start + 2;
    let mut rows_begun = 0;
    // Sample bytes of the current row still to come (0: a filter byte comes next).
    let mut row_left = 0;
    loop {
        // A stored block: its 3 header bits, padding to the byte, then LEN and its complement
        // (little-endian). Each block ends on a byte, so the next header starts on one.
        let header = *bytes.get(read)?;
        let [l0, l1, n0, n1] = bytes.get(read + 1..read + 5)?.try_into().ok()?;
        let len = u16::from_le_bytes([l0, l1]);
        if (header >> 1) & 3 != 0 || len != !u16::from_le_bytes([n0, n1]) {
            return None;
        }
        read += 5;
        let block_end = read + usize::from(len);
        if block_end > data.end {
            return None;
        }
        while read < block_end {
            if row_left == 0 {
                if rows_begun == rows || bytes[read] != 0 {
                    return None;
                }
                read += 1;
                rows_begun += 1;
                row_left = row;
                continue;
            }
            let n = row_left.min(block_end - read);
            segments.push(read..read + n);
            (read, row_left) = (read + n, row_left - n);
        }
        if header & 1 == 1 {
            break;
        }
    }
    (rows_begun == rows && row_left == 0).then_some(segments)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The samples of `size` (big-endian 16-bit RGB, a pattern no two rows share).
    fn samples(size: (u32, u32)) -> Vec<u8> {
        (0..size.0 as usize * size.1 as usize * 3)
            .flat_map(|i| ((i * 7919 + i / 11) as u16).to_be_bytes())
            .collect()
    }

    /// A PNG of `samples` written by `png` itself with `compression` and `filter`.
    fn encoded(
        samples: &[u8],
        size: (u32, u32),
        compression: png::Compression,
        filter: png::Filter,
    ) -> Vec<u8> {
        let mut out = Vec::new();
        let mut encoder = png::Encoder::new(&mut out, size.0, size.1);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Sixteen);
        encoder.set_compression(compression);
        encoder.set_filter(filter);
        let mut writer = encoder.write_header().unwrap();
        writer.write_image_data(samples).unwrap();
        writer.finish().unwrap();
        out
    }

    /// A PNG of `samples` as the frame writer stores it (no compression, no row filter),
    /// written by `png` itself.
    fn stored(samples: &[u8], size: (u32, u32)) -> Vec<u8> {
        encoded(
            samples,
            size,
            png::Compression::NoCompression,
            png::Filter::NoFilter,
        )
    }

    /// What `png` decodes from `file`.
    fn decoded_by_png(file: &[u8]) -> Vec<u8> {
        let mut reader = png::Decoder::new(std::io::Cursor::new(file))
            .read_info()
            .unwrap();
        let mut out = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut out).unwrap();
        out.truncate(info.buffer_size());
        out
    }

    /// Stored, unfiltered frames of many shapes (rows split across the 65 535-byte blocks at
    /// every offset the sizes give, one-pixel rows and columns): the packed samples are what
    /// `png` decodes, byte for byte.
    #[test]
    fn stored_frames_pack_to_what_png_decodes() {
        for size in [
            (1, 1),
            (1, 3000),
            (3000, 1),
            (37, 1213),
            (1379, 29),
            (11_000, 3),
        ] {
            let want = samples(size);
            let mut file = stored(&want, size);
            assert_eq!(decoded_by_png(&file), want, "{size:?}");
            let segments = stored_segments(&file, size).unwrap();
            let len = pack(&mut file, &segments);
            assert_eq!(len, want.len(), "{size:?}");
            assert_eq!(&file[..want.len()], want, "{size:?}");
        }
    }

    /// Compressed or filtered data, another size, a damaged chunk or a missing end: no samples
    /// (`png` reads or refuses those).
    #[test]
    fn other_layouts_and_damaged_files_are_left_to_png() {
        let size = (40, 30);
        let want = samples(size);
        let stored = stored(&want, size);
        let packed = |mut file: Vec<u8>, size| {
            stored_segments(&file, size).map(|segments| pack(&mut file, &segments))
        };
        assert_eq!(packed(stored.clone(), size), Some(want.len()));
        // Flat samples, which deflate compresses (noise could come out stored anyway).
        let flat = vec![0u8; want.len()];
        let compressed = encoded(&flat, size, png::Compression::Fast, png::Filter::NoFilter);
        assert_eq!(decoded_by_png(&compressed), flat);
        assert_eq!(packed(compressed, size), None, "compressed");
        // The first row's filter set to Sub (1), its chunk's CRC made again: `png` reads other
        // samples than the stored ones.
        let mut filtered = stored.clone();
        let data = image_data(&filtered, size).unwrap();
        filtered[data.start + 2 + 5] = 1;
        let crc = crc32fast::hash(&filtered[data.start - 4..data.end]);
        filtered[data.end..data.end + 4].copy_from_slice(&crc.to_be_bytes());
        assert_ne!(decoded_by_png(&filtered), want);
        assert_eq!(packed(filtered, size), None, "filtered");
        assert_eq!(packed(stored.clone(), (30, 40)), None, "other size");
        let mut damaged = stored.clone();
        let middle = damaged.len() / 2;
        damaged[middle] ^= 1;
        assert_eq!(packed(damaged, size), None, "CRC");
        assert_eq!(
            packed(stored[..stored.len() - 12].to_vec(), size),
            None,
            "no IEND"
        );
        assert_eq!(packed(stored[..100].to_vec(), size), None, "cut short");
        assert_eq!(packed(Vec::new(), size), None, "empty");
    }

    /// The file is read from disk into a reused buffer, larger or smaller than the file.
    #[test]
    fn reads_a_file_into_a_reused_buffer() {
        let size = (64, 48);
        let want = samples(size);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frame.png");
        let file = stored(&want, size);
        std::fs::write(&path, file).unwrap();
        for start in [Vec::new(), vec![7u8; 5], vec![9u8; 100_000]] {
            let mut bytes = start;
            let len = read_stored_rgb16(&path, size, &mut bytes).unwrap();
            assert_eq!(len, Some(want.len()));
            assert_eq!(&bytes[..want.len()], want);
        }
        let missing = dir.path().join("none.png");
        assert!(read_stored_rgb16(&missing, size, &mut Vec::new()).is_err());
    }

    /// Row by row, without packing: every row's samples in order, rows split across blocks
    /// included; a file of another layout gives no row.
    #[test]
    fn rows_come_whole_and_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frame.png");
        let (mut bytes, mut scratch) = (Vec::new(), Vec::new());
        for size in [(1, 1), (37, 1213), (1379, 29), (11_000, 3)] {
            let want = samples(size);
            let file = stored(&want, size);
            std::fs::write(&path, file).unwrap();
            let mut rows = Vec::new();
            let stored = for_each_stored_row(&path, size, &mut bytes, &mut scratch, |y, row| {
                rows.push((y, row.to_vec()));
            });
            assert!(stored.unwrap(), "{size:?}");
            let row_len = size.0 as usize * 6;
            assert_eq!(rows.len(), size.1 as usize, "{size:?}");
            for (k, (y, row)) in rows.iter().enumerate() {
                assert_eq!(*y, k);
                assert_eq!(
                    row[..],
                    want[k * row_len..(k + 1) * row_len],
                    "{size:?} row {k}"
                );
            }
        }
        let flat = vec![0u8; 40 * 30 * 6];
        let compressed = encoded(
            &flat,
            (40, 30),
            png::Compression::Fast,
            png::Filter::NoFilter,
        );
        std::fs::write(&path, compressed).unwrap();
        let mut called = false;
        let stored = for_each_stored_row(&path, (40, 30), &mut bytes, &mut scratch, |_, _| {
            called = true
        });
        assert!(!stored.unwrap() && !called);
    }
}
