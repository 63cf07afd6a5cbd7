//! Spatial maps of the skin's composition: freckles and moles (epidermal melanin), redness and a
//! network of superficial vessels (dermal blood), and beard stubble (pigmented hair shafts through
//! the layers). The maps give, at a surface point, the weights of the basis materials of
//! `skin_optics` that the subsurface response blends.
//!
//! Conventions
//! - Maps are functions of the world (x, y) of the surface point, mm (the subjects face the camera,
//!   so (x, y) is a good chart of the visible surface).
//! - Weights are in [0, 1]: `[melanin, blood, stubble]`, each the fraction of the basis material
//!   `MELANIN_RICH`, `BLOOD_RICH`, `STUBBLE` (the rest is `BASE`); their sum is at most 1.
//! - Everything is a pure function of the seed.

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

use super::subjects::SubjectKind;

/// A round spot with a soft edge (freckle, mole, redness blob).
#[derive(Debug, Clone, Copy)]
struct Spot {
    x: f64,
    y: f64,
    radius_mm: f64,
    weight: f64,
}

impl Spot {
    fn eval(&self, x: f64, y: f64) -> f64 {
        let r = ((x - self.x).powi(2) + (y - self.y).powi(2)).sqrt() / self.radius_mm;
        if r >= 1.0 {
            0.0
        } else {
            // Smooth falloff to zero at the rim.
            let s = 1.0 - r * r;
            self.weight * s * s
        }
    }
}

/// A straight piece of vessel with a Gaussian cross-section.
#[derive(Debug, Clone, Copy)]
struct VesselSegment {
    a: [f64; 2],
    b: [f64; 2],
    half_width_mm: f64,
    weight: f64,
}

impl VesselSegment {
    fn eval(&self, x: f64, y: f64) -> f64 {
        let (dx, dy) = (self.b[0] - self.a[0], self.b[1] - self.a[1]);
        let len2 = dx * dx + dy * dy;
        let t = (((x - self.a[0]) * dx + (y - self.a[1]) * dy) / len2).clamp(0.0, 1.0);
        let (px, py) = (self.a[0] + t * dx - x, self.a[1] + t * dy - y);
        let d2 = (px * px + py * py) / (self.half_width_mm * self.half_width_mm);
        if d2 > 12.0 {
            0.0
        } else {
            self.weight * (-0.5 * d2).exp()
        }
    }
}

/// Hair follicles on a jittered grid; pitch gives ~70 hairs/cm^2 (a dense beard).
const STUBBLE_PITCH_MM: f64 = 1.2;
/// Radius of a stubble hair shaft's absorbing footprint, mm.
const HAIR_RADIUS_MM: f64 = 0.12;

/// The composition maps of one subject.
#[derive(Debug, Clone)]
pub struct MaterialMaps {
    spots: Vec<Spot>,
    redness: Vec<Spot>,
    vessels: Vec<VesselSegment>,
    /// Where each of `spots`, `redness`, `vessels` is not zero.
    spot_grid: ReachGrid,
    redness_grid: ReachGrid,
    vessel_grid: ReachGrid,
    stubble: StubbleRegion,
    stubble_seed: u64,
}

/// Side of a [`ReachGrid`] cell, mm.
const REACH_GRID_MM: f64 = 4.0;

/// For every square cell of the plane, the items (in their order) whose bounding box meets it:
/// a point's non-zero items are among those of its cell. Evaluating those alone gives the same
/// maxima and (items in order, zeros left out) the same sums, bit for bit, as evaluating every
/// item, for a few items instead of hundreds.
#[derive(Debug, Clone, Default)]
struct ReachGrid {
    origin: [f64; 2],
    width: usize,
    height: usize,
    items: Vec<Vec<u32>>,
}

impl ReachGrid {
    /// The grid of the bounding boxes `[x_min, x_max, y_min, y_max]`, in item order.
    fn new(boxes: &[[f64; 4]]) -> Self {
        let Some(bounds) = boxes.iter().copied().reduce(|a, b| {
            [
                a[0].min(b[0]),
                a[1].max(b[1]),
                a[2].min(b[2]),
                a[3].max(b[3]),
            ]
        }) else {
            return Self::default();
        };
        let origin = [bounds[0], bounds[2]];
        let cells = |lo: f64, hi: f64| ((hi - lo) / REACH_GRID_MM).floor() as usize + 1;
        let (width, height) = (cells(bounds[0], bounds[1]), cells(bounds[2], bounds[3]));
        let mut items = vec![Vec::new(); width * height];
        for (i, b) in boxes.iter().enumerate() {
            let col = |x: f64| ((x - origin[0]) / REACH_GRID_MM).floor() as usize;
            let row = |y: f64| ((y - origin[1]) / REACH_GRID_MM).floor() as usize;
            for r in row(b[2])..=row(b[3]).min(height - 1) {
                for c in col(b[0])..=col(b[1]).min(width - 1) {
                    items[r * width + c].push(i as u32);
                }
            }
        }
        Self {
            origin,
            width,
            height,
            items,
        }
    }

    /// The items whose bounding box may hold (x, y).
    fn at(&self, x: f64, y: f64) -> &[u32] {
        let (fx, fy) = (
            (x - self.origin[0]) / REACH_GRID_MM,
            (y - self.origin[1]) / REACH_GRID_MM,
        );
        if !(fx >= 0.0 && fy >= 0.0) {
            return &[];
        }
        let (c, r) = (fx.floor() as usize, fy.floor() as usize);
        if c >= self.width || r >= self.height {
            return &[];
        }
        &self.items[r * self.width + c]
    }
}

impl Spot {
    /// Where the spot is not zero (`r < 1`).
    fn bounding_box(&self) -> [f64; 4] {
        let r = self.radius_mm;
        [self.x - r, self.x + r, self.y - r, self.y + r]
    }
}

impl VesselSegment {
    /// Where the segment is not zero (within `sqrt(12)` half-widths, 3.47 < 3.5).
    fn bounding_box(&self) -> [f64; 4] {
        let reach = 3.5 * self.half_width_mm;
        [
            self.a[0].min(self.b[0]) - reach,
            self.a[0].max(self.b[0]) + reach,
            self.a[1].min(self.b[1]) - reach,
            self.a[1].max(self.b[1]) + reach,
        ]
    }
}

/// Where stubble grows.
#[derive(Debug, Clone, Copy, PartialEq)]
enum StubbleRegion {
    None,
    /// Below this y (mm) on a plane.
    Below(f64),
    /// The beard area of the head (upper lip, chin, jaw).
    Beard,
}

impl StubbleRegion {
    fn density(&self, x: f64, y: f64) -> f64 {
        match *self {
            StubbleRegion::None => 0.0,
            StubbleRegion::Below(y0) => smoothstep(y0, y0 + 4.0, y),
            StubbleRegion::Beard => {
                let upper_lip = smoothstep(22.0, 26.0, y) * (1.0 - smoothstep(36.0, 39.0, y));
                let chin = smoothstep(52.0, 58.0, y);
                let jaw = smoothstep(38.0, 46.0, x.abs()) * smoothstep(10.0, 20.0, y);
                upper_lip.max(chin).max(jaw)
            }
        }
    }
}

fn smoothstep(a: f64, b: f64, x: f64) -> f64 {
    let t = ((x - a) / (b - a)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Visible extent of the subject, mm: `[x_min, x_max, y_min, y_max]`.
pub type Extent = [f64; 4];

impl MaterialMaps {
    /// Maps with no variation (pure base skin).
    pub fn uniform() -> Self {
        Self {
            spots: Vec::new(),
            redness: Vec::new(),
            vessels: Vec::new(),
            spot_grid: ReachGrid::default(),
            redness_grid: ReachGrid::default(),
            vessel_grid: ReachGrid::default(),
            stubble: StubbleRegion::None,
            stubble_seed: 0,
        }
    }

    /// Random maps for a subject seen over `extent`, reproducible from `seed`.
    pub fn generate(subject: SubjectKind, extent: Extent, seed: u64) -> Self {
        let mut rng = Pcg64::seed_from_u64(seed ^ 0x6d61_7073);
        // The draws below come in a fixed order (spots, redness, vessels, stubble seed): the maps
        // of a seed must not change.
        let spots = pigment_spots(&mut rng, subject, extent);
        let redness = redness_blobs(&mut rng, subject, extent);
        let vessels = vessel_network(&mut rng, extent);
        let boxes_of_spots =
            |spots: &[Spot]| spots.iter().map(Spot::bounding_box).collect::<Vec<_>>();
        Self {
            spot_grid: ReachGrid::new(&boxes_of_spots(&spots)),
            redness_grid: ReachGrid::new(&boxes_of_spots(&redness)),
            vessel_grid: ReachGrid::new(
                &vessels
                    .iter()
                    .map(VesselSegment::bounding_box)
                    .collect::<Vec<_>>(),
            ),
            spots,
            redness,
            vessels,
            stubble: stubble_region(subject, extent),
            stubble_seed: rng.r#gen(),
        }
    }

    /// Weights `[melanin, blood, stubble]` at (x, y).
    pub fn weights(&self, x: f64, y: f64) -> [f64; 3] {
        let melanin = self
            .spot_grid
            .at(x, y)
            .iter()
            .map(|&i| self.spots[i as usize].eval(x, y))
            .fold(0.0, f64::max)
            .min(1.0);
        let blood_red = self
            .redness_grid
            .at(x, y)
            .iter()
            .map(|&i| self.redness[i as usize].eval(x, y))
            .sum::<f64>();
        let blood_vessel = self
            .vessel_grid
            .at(x, y)
            .iter()
            .map(|&i| self.vessels[i as usize].eval(x, y))
            .fold(0.0, f64::max);
        let blood = blood_red.max(blood_vessel).min(1.0);
        let stubble = self.stubble_at(x, y);
        let sum = melanin + blood + stubble;
        let scale = if sum > 1.0 { 1.0 / sum } else { 1.0 };
        [melanin * scale, blood * scale, stubble * scale]
    }

    fn stubble_at(&self, x: f64, y: f64) -> f64 {
        if self.stubble == StubbleRegion::None {
            return 0.0;
        }
        let (ci, cj) = (
            (x / STUBBLE_PITCH_MM).floor() as i64,
            (y / STUBBLE_PITCH_MM).floor() as i64,
        );
        let mut cover: f64 = 0.0;
        for dj in -1..=1 {
            for di in -1..=1 {
                let (i, j) = (ci + di, cj + dj);
                let h = hash3(self.stubble_seed, i, j);
                let jx = (h & 0xffff) as f64 / 65535.0;
                let jy = ((h >> 16) & 0xffff) as f64 / 65535.0;
                let keep = ((h >> 32) & 0xffff) as f64 / 65535.0;
                let fx = (i as f64 + jx) * STUBBLE_PITCH_MM;
                let fy = (j as f64 + jy) * STUBBLE_PITCH_MM;
                if keep >= self.stubble.density(fx, fy) {
                    continue;
                }
                let d2 = (x - fx).powi(2) + (y - fy).powi(2);
                let r2 = HAIR_RADIUS_MM * HAIR_RADIUS_MM;
                cover = cover.max((-0.5 * d2 / r2).exp());
            }
        }
        cover
    }
}

/// Skin area seen over `extent`, cm^2: the number of freckles, moles and vessel trees scales
/// with it.
fn area_cm2(extent: Extent) -> f64 {
    let [x0, x1, y0, y1] = extent;
    (x1 - x0) * (y1 - y0) / 100.0
}

/// A point drawn uniformly over `extent` (x first, then y).
fn uniform_xy(rng: &mut Pcg64, extent: Extent) -> (f64, f64) {
    let [x0, x1, y0, y1] = extent;
    (rng.gen_range(x0..x1), rng.gen_range(y0..y1))
}

/// Relative freckle density at (x, y): freckles cluster on the nose and cheeks of a face;
/// elsewhere they are uniform.
fn freckle_density(subject: SubjectKind, x: f64, y: f64) -> f64 {
    match subject {
        SubjectKind::Head => {
            let cheeks_nose = smoothstep(-25.0, -5.0, y) * (1.0 - smoothstep(25.0, 35.0, y));
            0.15 + 0.85 * cheeks_nose * (1.0 - smoothstep(55.0, 65.0, x.abs()))
        }
        _ => 1.0,
    }
}

/// Epidermal melanin spots: ~0.8 faint freckles per cm^2 (placed by rejection against
/// [`freckle_density`]), then a few dark moles.
fn pigment_spots(rng: &mut Pcg64, subject: SubjectKind, extent: Extent) -> Vec<Spot> {
    let area_cm2 = area_cm2(extent);
    let mut spots = Vec::new();
    let freckles = (area_cm2 * 0.8).round() as usize;
    while spots.len() < freckles {
        let (x, y) = uniform_xy(rng, extent);
        if rng.r#gen::<f64>() < freckle_density(subject, x, y) {
            spots.push(Spot {
                x,
                y,
                radius_mm: rng.gen_range(0.5..1.6),
                weight: rng.gen_range(0.25..0.6),
            });
        }
    }
    let moles = 1 + (area_cm2 / 60.0).round() as usize;
    for _ in 0..moles {
        let (x, y) = uniform_xy(rng, extent);
        spots.push(Spot {
            x,
            y,
            radius_mm: rng.gen_range(1.2..2.5),
            weight: 1.0,
        });
    }
    spots
}

/// Broad patches of dermal blood: a face's flushed cheeks and nose (fixed, no draws); three
/// random blobs on the other subjects.
fn redness_blobs(rng: &mut Pcg64, subject: SubjectKind, extent: Extent) -> Vec<Spot> {
    match subject {
        SubjectKind::Head => vec![
            Spot {
                x: -38.0,
                y: 18.0,
                radius_mm: 22.0,
                weight: 0.35,
            },
            Spot {
                x: 38.0,
                y: 18.0,
                radius_mm: 22.0,
                weight: 0.35,
            },
            Spot {
                x: 0.0,
                y: 6.0,
                radius_mm: 12.0,
                weight: 0.3,
            },
        ],
        _ => (0..3)
            .map(|_| {
                let (x, y) = uniform_xy(rng, extent);
                Spot {
                    x,
                    y,
                    radius_mm: rng.gen_range(8.0..18.0),
                    weight: rng.gen_range(0.2..0.4),
                }
            })
            .collect(),
    }
}

/// Superficial vessels: branching trees (two, plus one per 25 cm^2) grown from random roots in
/// random directions.
fn vessel_network(rng: &mut Pcg64, extent: Extent) -> Vec<VesselSegment> {
    let trees = 2 + (area_cm2(extent) / 25.0).round() as usize;
    let mut vessels = Vec::new();
    for _ in 0..trees {
        let (x, y) = uniform_xy(rng, extent);
        let heading = rng.gen_range(0.0..std::f64::consts::TAU);
        grow_vessel(rng, &mut vessels, [x, y], heading, 0.2, 3);
    }
    vessels
}

/// Where the subject grows stubble: a head's beard area, the lower 28 % of a plane, nowhere
/// else.
fn stubble_region(subject: SubjectKind, extent: Extent) -> StubbleRegion {
    let [_, _, y0, y1] = extent;
    match subject {
        SubjectKind::Head => StubbleRegion::Beard,
        SubjectKind::Plane => StubbleRegion::Below(y0 + 0.72 * (y1 - y0)),
        SubjectKind::Sphere | SubjectKind::Chessboard => StubbleRegion::None,
    }
}

/// A vessel: a wiggly path that branches, each branch thinner.
fn grow_vessel(
    rng: &mut Pcg64,
    out: &mut Vec<VesselSegment>,
    start: [f64; 2],
    mut heading: f64,
    half_width_mm: f64,
    depth: u32,
) {
    let mut p = start;
    let steps = rng.gen_range(8..16);
    for step in 0..steps {
        heading += rng.gen_range(-0.45..0.45);
        let len = rng.gen_range(0.8..2.0);
        let q = [p[0] + len * heading.cos(), p[1] + len * heading.sin()];
        out.push(VesselSegment {
            a: p,
            b: q,
            half_width_mm,
            weight: 0.85,
        });
        p = q;
        if depth > 1 && step > 2 && rng.r#gen::<f64>() < 0.18 {
            let side = if rng.r#gen::<bool>() { 1.0 } else { -1.0 };
            let branch_heading = heading + side * rng.gen_range(0.5..1.1);
            grow_vessel(rng, out, p, branch_heading, half_width_mm * 0.7, depth - 1);
        }
    }
}

/// A well-mixed 64-bit hash of a seed and a grid cell (SplitMix64 finaliser).
fn hash3(seed: u64, i: i64, j: i64) -> u64 {
    let mut z = seed
        ^ (i as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15)
        ^ (j as u64).wrapping_mul(0xc2b2_ae3d_27d4_eb4f);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn maps_are_reproducible_and_bounded() {
        let extent = [-60.0, 60.0, -45.0, 45.0];
        let a = MaterialMaps::generate(SubjectKind::Head, extent, 7);
        let b = MaterialMaps::generate(SubjectKind::Head, extent, 7);
        let c = MaterialMaps::generate(SubjectKind::Head, extent, 8);
        let mut differs = false;
        for i in 0..400 {
            let (x, y) = (-60.0 + 0.3 * i as f64, -40.0 + 0.21 * i as f64);
            let wa = a.weights(x, y);
            assert_eq!(wa, b.weights(x, y));
            assert!(wa.iter().all(|w| (0.0..=1.0).contains(w)));
            assert!(wa.iter().sum::<f64>() <= 1.0 + 1e-12);
            differs |= wa != c.weights(x, y);
        }
        assert!(differs, "a different seed must give different maps");
    }

    #[test]
    fn the_reach_grid_gives_what_every_item_gives() {
        let maps = MaterialMaps::generate(SubjectKind::Head, [-80.0, 80.0, -110.0, 100.0], 3);
        let (mut spots, mut reds, mut vessels) = (0, 0, 0);
        for i in 0..200_000 {
            // A dense scatter over (and beyond) the extent.
            let (x, y) = (
                -90.0 + 180.0 * ((i as f64 * 0.618_034) % 1.0),
                -120.0 + 240.0 * ((i as f64 * 0.414_214) % 1.0),
            );
            let melanin = maps.spots.iter().map(|s| s.eval(x, y)).fold(0.0, f64::max);
            let red = maps.redness.iter().map(|s| s.eval(x, y)).sum::<f64>();
            let vessel = maps
                .vessels
                .iter()
                .map(|v| v.eval(x, y))
                .fold(0.0, f64::max);
            let blood = red.max(vessel).min(1.0);
            let stubble = maps.stubble_at(x, y);
            let (m, b) = (melanin.min(1.0), blood);
            let sum = m + b + stubble;
            let scale = if sum > 1.0 { 1.0 / sum } else { 1.0 };
            let every_item = [m * scale, b * scale, stubble * scale];
            assert_eq!(maps.weights(x, y), every_item, "at ({x}, {y})");
            spots += usize::from(melanin > 0.0);
            reds += usize::from(red > 0.0);
            vessels += usize::from(vessel > 0.0);
        }
        assert!(
            spots > 1000 && reds > 1000 && vessels > 1000,
            "{spots} {reds} {vessels}"
        );
    }

    #[test]
    fn beard_grows_on_the_chin_not_the_forehead() {
        let maps = MaterialMaps::generate(SubjectKind::Head, [-60.0, 60.0, -80.0, 80.0], 1);
        let covered = |y0: f64| {
            (0..2000)
                .filter(|k| {
                    let (x, y) = (-20.0 + 0.02 * *k as f64, y0 + 0.013 * *k as f64);
                    maps.weights(x, y)[2] > 0.5
                })
                .count()
        };
        assert!(covered(60.0) > 20, "{}", covered(60.0));
        assert_eq!(covered(-60.0), 0);
    }
}
