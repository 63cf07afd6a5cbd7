//! Camera payload bytes to linear RGB: unpacking 8/12-bit mono and Bayer layouts (GenICam PFNC
//! names) and bilinear demosaicing of Bayer mosaics.

use image::{Rgb, Rgb32FImage};

/// Which colour each pixel of a 2x2 Bayer tile sees, by its top-left 2x2 pattern.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BayerTile {
    /// R G / G B.
    Rggb,
    /// G R / B G.
    Grbg,
    /// G B / R G.
    Gbrg,
    /// B G / G R.
    Bggr,
}

impl BayerTile {
    /// The channel (0 = R, 1 = G, 2 = B) pixel (`x`, `y`) samples.
    pub fn channel(self, x: usize, y: usize) -> usize {
        let (even_row, odd_row) = match self {
            BayerTile::Rggb => ([0, 1], [1, 2]),
            BayerTile::Grbg => ([1, 0], [2, 1]),
            BayerTile::Gbrg => ([1, 2], [0, 1]),
            BayerTile::Bggr => ([2, 1], [1, 0]),
        };
        if y.is_multiple_of(2) {
            even_row[x % 2]
        } else {
            odd_row[x % 2]
        }
    }
}

/// How the samples are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SampleLayout {
    /// One byte per sample.
    Bits8,
    /// 12 bits in the low bits of a little-endian u16 (Mono12, BayerRG12, ...).
    Bits12Unpacked,
    /// Two samples in three bytes, GigE Vision style (Mono12Packed, BayerRG12Packed): byte 0 =
    /// s0 bits 11..4, byte 1 = s0 bits 3..0 | s1 bits 3..0 << 4, byte 2 = s1 bits 11..4.
    Bits12PackedMsb,
    /// Two samples in three bytes, PFNC LSB-first (Mono12p, BayerRG12p): s0 = b0 | (b1 & 0xf)
    /// << 8, s1 = b1 >> 4 | b2 << 4.
    Bits12PackedLsb,
}

impl SampleLayout {
    /// Full-scale sample value.
    pub fn max_value(self) -> f32 {
        match self {
            SampleLayout::Bits8 => 255.0,
            _ => 4095.0,
        }
    }

    /// Bytes `count` samples take.
    pub fn bytes_for(self, count: usize) -> usize {
        match self {
            SampleLayout::Bits8 => count,
            SampleLayout::Bits12Unpacked => 2 * count,
            SampleLayout::Bits12PackedMsb | SampleLayout::Bits12PackedLsb => count.div_ceil(2) * 3,
        }
    }
}

/// A camera pixel format the backend accepts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelLayout {
    /// Storage of the samples.
    pub samples: SampleLayout,
    /// `None` for a monochrome sensor.
    pub bayer: Option<BayerTile>,
}

impl PixelLayout {
    /// The layout of a GenICam PFNC pixel format name (`Mono12`, `BayerRG12Packed`, `Mono12p`...).
    pub fn from_pfnc(name: &str) -> Option<Self> {
        let (bayer, rest) = match name.get(..7) {
            Some("BayerRG") => (Some(BayerTile::Rggb), &name[7..]),
            Some("BayerGR") => (Some(BayerTile::Grbg), &name[7..]),
            Some("BayerGB") => (Some(BayerTile::Gbrg), &name[7..]),
            Some("BayerBG") => (Some(BayerTile::Bggr), &name[7..]),
            _ => (None, name.strip_prefix("Mono")?),
        };
        let samples = match rest {
            "8" => SampleLayout::Bits8,
            "12" => SampleLayout::Bits12Unpacked,
            "12Packed" => SampleLayout::Bits12PackedMsb,
            "12p" => SampleLayout::Bits12PackedLsb,
            _ => return None,
        };
        Some(Self { samples, bayer })
    }

    /// Bytes of a `width` x `height` image.
    pub fn image_bytes(&self, width: u32, height: u32) -> usize {
        self.samples.bytes_for(width as usize * height as usize)
    }
}

/// The samples of `data` (row-major, `count` of them), as stored integers.
pub fn unpack(layout: SampleLayout, data: &[u8], count: usize) -> Option<Vec<u16>> {
    if data.len() < layout.bytes_for(count) {
        return None;
    }
    let mut out = Vec::with_capacity(count + 1);
    match layout {
        SampleLayout::Bits8 => out.extend(data[..count].iter().map(|&b| u16::from(b))),
        SampleLayout::Bits12Unpacked => out.extend(
            data.chunks_exact(2)
                .take(count)
                .map(|b| u16::from_le_bytes([b[0], b[1]]) & 0x0fff),
        ),
        SampleLayout::Bits12PackedMsb => {
            for b in data.chunks_exact(3).take(count.div_ceil(2)) {
                let (b0, b1, b2) = (u16::from(b[0]), u16::from(b[1]), u16::from(b[2]));
                out.push((b0 << 4) | (b1 & 0x0f));
                out.push((b2 << 4) | (b1 >> 4));
            }
        }
        SampleLayout::Bits12PackedLsb => {
            for b in data.chunks_exact(3).take(count.div_ceil(2)) {
                let (b0, b1, b2) = (u16::from(b[0]), u16::from(b[1]), u16::from(b[2]));
                out.push(b0 | ((b1 & 0x0f) << 8));
                out.push((b1 >> 4) | (b2 << 4));
            }
        }
    }
    out.truncate(count);
    Some(out)
}

/// A payload's image as linear RGB in [0, 1]: grey on all channels for a mono sensor,
/// bilinearly demosaiced for a Bayer one. `None` if `data` is too short.
pub fn decode(layout: PixelLayout, width: u32, height: u32, data: &[u8]) -> Option<Rgb32FImage> {
    let samples = unpack(layout.samples, data, width as usize * height as usize)?;
    let scale = 1.0 / layout.samples.max_value();
    let normalised: Vec<f32> = samples.iter().map(|&s| f32::from(s) * scale).collect();
    Some(match layout.bayer {
        None => Rgb32FImage::from_fn(width, height, |x, y| {
            let v = normalised[(y * width + x) as usize];
            Rgb([v, v, v])
        }),
        Some(tile) => demosaic_bilinear(&normalised, width, height, tile),
    })
}

/// Bilinear demosaicing: each missing channel is the mean of the nearest samples of that channel
/// in the 3x3 neighbourhood (edge pixels use the neighbours that exist), so a flat field and a
/// linear ramp are reproduced exactly away from the border.
pub fn demosaic_bilinear(mosaic: &[f32], width: u32, height: u32, tile: BayerTile) -> Rgb32FImage {
    let (w, h) = (width as usize, height as usize);
    Rgb32FImage::from_fn(width, height, |x, y| {
        let (x, y) = (x as usize, y as usize);
        let own = tile.channel(x, y);
        let mut rgb = [0.0f32; 3];
        for (c, value) in rgb.iter_mut().enumerate() {
            if c == own {
                *value = mosaic[y * w + x];
                continue;
            }
            // Prefer the 4-neighbourhood (where green lives next to R/B); the diagonals hold
            // R or B next to the other one.
            let mut sum = 0.0;
            let mut n = 0;
            for ring in [&CROSS[..], &DIAGONAL[..]] {
                for (dx, dy) in ring {
                    let (nx, ny) = (x as isize + dx, y as isize + dy);
                    if nx < 0 || ny < 0 || nx >= w as isize || ny >= h as isize {
                        continue;
                    }
                    let (nx, ny) = (nx as usize, ny as usize);
                    if tile.channel(nx, ny) == c {
                        sum += mosaic[ny * w + nx];
                        n += 1;
                    }
                }
                if n > 0 {
                    break;
                }
            }
            *value = if n > 0 { sum / n as f32 } else { 0.0 };
        }
        Rgb(rgb)
    })
}

const CROSS: [(isize, isize); 4] = [(-1, 0), (1, 0), (0, -1), (0, 1)];
const DIAGONAL: [(isize, isize); 4] = [(-1, -1), (1, -1), (-1, 1), (1, 1)];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pfnc_names_map_to_layouts() {
        let l = PixelLayout::from_pfnc("BayerGB12Packed").unwrap();
        assert_eq!(l.samples, SampleLayout::Bits12PackedMsb);
        assert_eq!(l.bayer, Some(BayerTile::Gbrg));
        assert_eq!(
            PixelLayout::from_pfnc("Mono12p").unwrap().samples,
            SampleLayout::Bits12PackedLsb
        );
        assert_eq!(PixelLayout::from_pfnc("Mono12").unwrap().bayer, None);
        assert!(PixelLayout::from_pfnc("RGB8").is_none());
        assert!(PixelLayout::from_pfnc("Mono10").is_none());
        assert_eq!(
            PixelLayout::from_pfnc("Mono12Packed")
                .unwrap()
                .image_bytes(3, 1),
            6
        );
    }

    #[test]
    fn twelve_bit_layouts_unpack_hand_packed_bytes() {
        // Samples 0xABC and 0x123.
        let unpacked = [0xBC, 0x0A, 0x23, 0x01];
        let msb = [0xAB, 0x3C, 0x12]; // 0xAB | (0xC | 0x3 << 4) | 0x12
        let lsb = [0xBC, 0x3A, 0x12]; // 0xBC | (0xA | 0x3 << 4) | 0x12
        let want = vec![0xABC, 0x123];
        assert_eq!(
            unpack(SampleLayout::Bits12Unpacked, &unpacked, 2).unwrap(),
            want
        );
        assert_eq!(
            unpack(SampleLayout::Bits12PackedMsb, &msb, 2).unwrap(),
            want
        );
        assert_eq!(
            unpack(SampleLayout::Bits12PackedLsb, &lsb, 2).unwrap(),
            want
        );
        // An odd count reads the first sample of the last triple only.
        assert_eq!(
            unpack(SampleLayout::Bits12PackedLsb, &lsb, 1).unwrap(),
            vec![0xABC]
        );
        assert!(unpack(SampleLayout::Bits12Unpacked, &unpacked[..3], 2).is_none());
    }

    /// Mosaics an RGB function with `tile` into 12-bit unpacked bytes.
    fn mosaic(tile: BayerTile, w: u32, h: u32, rgb: impl Fn(u32, u32) -> [u16; 3]) -> Vec<u8> {
        let mut bytes = vec![];
        for y in 0..h {
            for x in 0..w {
                let s = rgb(x, y)[tile.channel(x as usize, y as usize)];
                bytes.extend_from_slice(&s.to_le_bytes());
            }
        }
        bytes
    }

    #[test]
    fn a_flat_colour_demosaics_exactly_for_every_tile() {
        for tile in [
            BayerTile::Rggb,
            BayerTile::Grbg,
            BayerTile::Gbrg,
            BayerTile::Bggr,
        ] {
            let data = mosaic(tile, 6, 5, |_, _| [4095, 2048, 819]);
            let layout = PixelLayout {
                samples: SampleLayout::Bits12Unpacked,
                bayer: Some(tile),
            };
            let img = decode(layout, 6, 5, &data).unwrap();
            let want = [1.0, 2048.0 / 4095.0, 819.0 / 4095.0];
            for px in img.pixels() {
                // Exact up to the rounding of a mean of equal floats.
                let close = px.0.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-6);
                assert!(close, "{tile:?}: {:?}", px.0);
            }
        }
    }

    #[test]
    fn a_linear_ramp_demosaics_exactly_inside_the_border() {
        // R rises along x, B along y, G along both: bilinear interpolation is exact on planes.
        let rgb = |x: u32, y: u32| {
            [
                100 + 40 * x as u16,
                500 + 10 * (x + y) as u16,
                50 * y as u16,
            ]
        };
        let data = mosaic(BayerTile::Rggb, 8, 8, rgb);
        let layout = PixelLayout::from_pfnc("BayerRG12").unwrap();
        let img = decode(layout, 8, 8, &data).unwrap();
        for y in 1..7 {
            for x in 1..7 {
                let want = rgb(x, y).map(|v| f32::from(v) / 4095.0);
                let got = img.get_pixel(x, y).0;
                for c in 0..3 {
                    assert!(
                        (got[c] - want[c]).abs() < 1e-6,
                        "({x},{y}) {got:?} {want:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn mono_is_grey_on_every_channel() {
        let img = decode(PixelLayout::from_pfnc("Mono8").unwrap(), 2, 1, &[0, 255]).unwrap();
        assert_eq!(img.get_pixel(0, 0).0, [0.0; 3]);
        assert_eq!(img.get_pixel(1, 0).0, [1.0; 3]);
    }
}
