//! Tallies: scalar moments for the standard errors, the 2-D exit grid and the radial rings.
//!
//! Spatial tallies are accumulated as raw weight per cell during transport and converted to weight
//! per unit area per incident photon once, at the end.

use super::McError;

/// A square grid in the surface plane, centred on the entry point.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GridSpec {
    /// Side of a cell, mm.
    pub cell_mm: f64,
    /// Cells per side; the grid spans `[-cells * cell_mm / 2, +cells * cell_mm / 2]` in x and y.
    /// Use an odd number to have a cell centred on the entry point.
    pub cells: usize,
}

impl GridSpec {
    pub(crate) fn validate(&self) -> Result<(), McError> {
        if !(self.cell_mm.is_finite() && self.cell_mm > 0.0) {
            return Err(McError::InvalidConfig {
                field: "grid.cell_mm",
                value: self.cell_mm,
                reason: "must be positive",
            });
        }
        if self.cells == 0 || self.cells > 4096 {
            return Err(McError::InvalidConfig {
                field: "grid.cells",
                value: self.cells as f64,
                reason: "must be in 1..=4096",
            });
        }
        Ok(())
    }

    fn min_mm(&self) -> f64 {
        -0.5 * self.cells as f64 * self.cell_mm
    }

    /// Flat index of the cell holding (x, y), or `None` outside the grid.
    #[inline]
    pub(crate) fn cell_index(&self, x: f64, y: f64) -> Option<usize> {
        let inv = 1.0 / self.cell_mm;
        let fx = (x - self.min_mm()) * inv;
        let fy = (y - self.min_mm()) * inv;
        let n = self.cells as f64;
        if fx >= 0.0 && fx < n && fy >= 0.0 && fy < n {
            Some(fy as usize * self.cells + fx as usize)
        } else {
            None
        }
    }
}

/// Rings of equal width around the entry point.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RadialSpec {
    /// Width of a ring, mm.
    pub dr_mm: f64,
    /// Number of rings; ring i spans [i dr, (i + 1) dr).
    pub rings: usize,
}

impl RadialSpec {
    pub(crate) fn validate(&self) -> Result<(), McError> {
        if !(self.dr_mm.is_finite() && self.dr_mm > 0.0) {
            return Err(McError::InvalidConfig {
                field: "radial.dr_mm",
                value: self.dr_mm,
                reason: "must be positive",
            });
        }
        if self.rings == 0 || self.rings > 1_000_000 {
            return Err(McError::InvalidConfig {
                field: "radial.rings",
                value: self.rings as f64,
                reason: "must be in 1..=1000000",
            });
        }
        Ok(())
    }

    #[inline]
    pub(crate) fn ring_index(&self, r: f64) -> Option<usize> {
        let i = r / self.dr_mm;
        (i < self.rings as f64).then_some(i as usize)
    }
}

/// Diffuse exit weight per unit area on a grid in the surface plane (see the module conventions:
/// +x points away from the light).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ExitResponse2D {
    /// Side of a cell, mm.
    pub cell_mm: f64,
    /// Cells per side (the grid is square).
    pub cells: usize,
    /// x (and y) of the outer edge of the first cell, mm.
    pub min_mm: f64,
    /// Row-major values, `values[iy * cells + ix]`, in 1/mm² per incident photon.
    pub values: Vec<f64>,
    /// Diffuse reflectance that left the top outside the grid (a fraction, not per area).
    pub outside: f64,
}

impl ExitResponse2D {
    /// Value of cell (ix, iy), 1/mm².
    pub fn value(&self, ix: usize, iy: usize) -> f64 {
        self.values[iy * self.cells + ix]
    }

    /// Centre of cell index i along x or y, mm.
    pub fn center_mm(&self, i: usize) -> f64 {
        self.min_mm + (i as f64 + 0.5) * self.cell_mm
    }

    /// Diffuse reflectance inside the grid (sum of value x cell area).
    pub fn total(&self) -> f64 {
        self.values.iter().sum::<f64>() * self.cell_mm * self.cell_mm
    }

    /// Weighted mean (x, y) of the tabulated response, mm.
    pub fn centroid_mm(&self) -> [f64; 2] {
        let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
        for iy in 0..self.cells {
            for ix in 0..self.cells {
                let w = self.value(ix, iy);
                sw += w;
                sx += w * self.center_mm(ix);
                sy += w * self.center_mm(iy);
            }
        }
        if sw > 0.0 {
            [sx / sw, sy / sw]
        } else {
            [0.0, 0.0]
        }
    }
}

/// Radially binned diffuse reflectance R(r), per unit area.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RadialProfile {
    /// Ring width, mm.
    pub dr_mm: f64,
    /// R of ring i (spanning [i dr, (i + 1) dr)), 1/mm² per incident photon.
    pub values: Vec<f64>,
    /// Diffuse reflectance beyond the last ring (a fraction).
    pub outside: f64,
}

impl RadialProfile {
    /// Area-weighted mean radius of ring i, mm.
    pub fn radius_mm(&self, i: usize) -> f64 {
        // Centroid radius of an annulus: 2/3 (b^3 - a^3) / (b^2 - a^2).
        let a = i as f64 * self.dr_mm;
        let b = a + self.dr_mm;
        2.0 / 3.0 * (b * b * b - a * a * a) / (b * b - a * a)
    }

    /// Diffuse reflectance inside the rings.
    pub fn total(&self) -> f64 {
        self.values
            .iter()
            .enumerate()
            .map(|(i, v)| v * ring_area(i, self.dr_mm))
            .sum()
    }
}

fn ring_area(i: usize, dr: f64) -> f64 {
    let a = i as f64 * dr;
    let b = a + dr;
    std::f64::consts::PI * (b * b - a * a)
}

/// Sum and sum of squares of a per-photon quantity, for the mean and its standard error.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct Moments {
    sum: f64,
    sum_sq: f64,
}

impl Moments {
    #[inline]
    pub(crate) fn add(&mut self, x: f64) {
        self.sum += x;
        self.sum_sq += x * x;
    }

    pub(crate) fn merge(&mut self, other: &Moments) {
        self.sum += other.sum;
        self.sum_sq += other.sum_sq;
    }

    /// (mean, standard error of the mean) over `n` photons.
    pub(crate) fn mean_se(&self, n: u64) -> (f64, f64) {
        let n = n as f64;
        let mean = self.sum / n;
        if n < 2.0 {
            return (mean, f64::INFINITY);
        }
        let var = ((self.sum_sq / n - mean * mean) * n / (n - 1.0)).max(0.0);
        (mean, (var / n).sqrt())
    }
}

/// Everything one batch of photons accumulates; batches are merged in order.
#[derive(Debug, Clone)]
pub(crate) struct BatchTally {
    pub reflect: Moments,
    pub transmit: Moments,
    pub absorbed: Vec<Moments>,
    /// Sums of w x and w y over diffuse exits through the top.
    pub exit_wx: f64,
    pub exit_wy: f64,
    pub grid: Vec<f64>,
    pub grid_outside: f64,
    pub rings: Vec<f64>,
    pub rings_outside: f64,
    /// Scattering/absorption events (not boundary hits), for cost figures.
    pub interactions: u64,
}

impl BatchTally {
    pub(crate) fn new(layers: usize, grid: Option<&GridSpec>, radial: Option<&RadialSpec>) -> Self {
        Self {
            reflect: Moments::default(),
            transmit: Moments::default(),
            absorbed: vec![Moments::default(); layers],
            exit_wx: 0.0,
            exit_wy: 0.0,
            grid: grid.map_or(Vec::new(), |g| vec![0.0; g.cells * g.cells]),
            grid_outside: 0.0,
            rings: radial.map_or(Vec::new(), |r| vec![0.0; r.rings]),
            rings_outside: 0.0,
            interactions: 0,
        }
    }

    pub(crate) fn merge(&mut self, other: &BatchTally) {
        self.reflect.merge(&other.reflect);
        self.transmit.merge(&other.transmit);
        for (a, b) in self.absorbed.iter_mut().zip(&other.absorbed) {
            a.merge(b);
        }
        self.exit_wx += other.exit_wx;
        self.exit_wy += other.exit_wy;
        for (a, b) in self.grid.iter_mut().zip(&other.grid) {
            *a += b;
        }
        self.grid_outside += other.grid_outside;
        for (a, b) in self.rings.iter_mut().zip(&other.rings) {
            *a += b;
        }
        self.rings_outside += other.rings_outside;
        self.interactions += other.interactions;
    }

    /// The grid as weight per unit area per incident photon.
    pub(crate) fn response(&self, spec: &GridSpec, photons: u64) -> ExitResponse2D {
        let scale = 1.0 / (photons as f64 * spec.cell_mm * spec.cell_mm);
        ExitResponse2D {
            cell_mm: spec.cell_mm,
            cells: spec.cells,
            min_mm: spec.min_mm(),
            values: self.grid.iter().map(|w| w * scale).collect(),
            outside: self.grid_outside / photons as f64,
        }
    }

    /// The rings as weight per unit area per incident photon.
    pub(crate) fn radial(&self, spec: &RadialSpec, photons: u64) -> RadialProfile {
        let n = photons as f64;
        RadialProfile {
            dr_mm: spec.dr_mm,
            values: self
                .rings
                .iter()
                .enumerate()
                .map(|(i, w)| w / (n * ring_area(i, spec.dr_mm)))
                .collect(),
            outside: self.rings_outside / n,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_cells_are_centred_on_the_origin_for_odd_counts() {
        let spec = GridSpec {
            cell_mm: 0.5,
            cells: 5,
        };
        // Middle cell (2, 2) spans [-0.25, 0.25).
        assert_eq!(spec.cell_index(0.0, 0.0), Some(2 * 5 + 2));
        assert_eq!(spec.cell_index(0.3, 0.0), Some(2 * 5 + 3));
        assert_eq!(spec.cell_index(0.0, -0.3), Some(5 + 2));
        assert_eq!(spec.cell_index(1.25, 0.0), None);
        assert_eq!(spec.cell_index(-1.25, 0.0), Some(2 * 5));
    }

    #[test]
    fn moments_give_the_textbook_standard_error() {
        let mut m = Moments::default();
        for x in [1.0, 2.0, 3.0, 4.0] {
            m.add(x);
        }
        let (mean, se) = m.mean_se(4);
        assert!((mean - 2.5).abs() < 1e-15);
        // Sample variance 5/3, SE = sqrt(5/3 / 4).
        assert!((se - (5.0f64 / 12.0).sqrt()).abs() < 1e-15);
    }

    #[test]
    fn ring_centroid_radius_lies_inside_the_ring() {
        let p = RadialProfile {
            dr_mm: 0.1,
            values: vec![0.0; 3],
            outside: 0.0,
        };
        // Disc: 2/3 of the radius.
        assert!((p.radius_mm(0) - 0.2 / 3.0).abs() < 1e-15);
        assert!(p.radius_mm(2) > 0.2 && p.radius_mm(2) < 0.3);
    }
}
