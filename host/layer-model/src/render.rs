//! Relighting with the layer model (paper eqs. 3-5): every lit surface pixel `x` is a source with
//! incident irradiance `E(x)`; layer `l` re-emits `w_l E(x) dA(x)` as an isotropic Gaussian of
//! standard deviation `sigma_l` (mm) around `x + z_l (t_i + t_o)` (see [`super::surface`]).
//!
//! Fast path (why it is shaped like this): splatting an individual 2-D Gaussian per pixel and
//! layer costs `pixels x layers x kernel area`. Instead each source is forward-warped by its shift
//! (bilinear) into one of a few images per sigma bin (geometric bins; a source's weight is split
//! between the two bins around its sigma, linear in log sigma), and each bin image is blurred once
//! with a separable Gaussian of the bin's sigma. Wide bins live on a pyramid level: a bin of sigma
//! `s >= 2 f c` pixels (`f` a power of two, `c` = [`RenderOptions::coarse_sigma_px`]) is splatted
//! on the image downsampled by `f`, blurred there by `sqrt(s^2 - f^2/3) / f` (the bilinear splat
//! and read-back each add a tent of variance `f^2/6`) and read back bilinearly, so every bin costs
//! about `pixels / f^2 x 7 c` instead of `pixels x 7 s`. Bins are blurred in parallel; layers with
//! negligible weight are skipped. `coarse_sigma_px = inf` is the full-resolution reference (a test
//! holds the pyramid to it).
//!
//! Approximations (documented limits): the Gaussian is isotropic in pixels with the source's
//! mean pixel size (surface tilt foreshortening of the kernel is ignored; the *shift* is mapped
//! exactly through the pixel footprint); sigma is quantised by interpolation between bins.
//!
//! Conventions as in [`super::surface`]; output radiance per pixel is in the frames' units when
//! `E` and the weights are.

use nalgebra::Vector3;
use rayon::prelude::*;

use super::inline_floor::floor;
use super::surface::Surface;
use mlsss_core::gaussian_blur::{BlurError, Border, GaussianKernel, Normalisation, blur_2d};

/// Errors of the renderer.
#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum RenderError {
    /// An input image does not have the surface's size.
    #[error("{what} has {got} pixels; the surface has {want}")]
    SizeMismatch {
        what: &'static str,
        got: usize,
        want: usize,
    },
    /// A render option is out of range.
    #[error("invalid render option: {0}")]
    BadOption(&'static str),
    /// A bin's image does not have its level's size (an internal inconsistency).
    #[error("blurring a bin: {0}")]
    Blur(#[from] BlurError),
}

/// One layer of one pixel and channel.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SplatLayer {
    /// Layer identity shared across pixels (depth index, or rank by mean for free fits).
    pub index: u16,
    /// Absolute weight `w_l` of DESIGN section 5: radiance x mm^2 re-emitted per unit irradiance
    /// and unit source area (frames' radiance units per irradiance unit).
    pub weight: f32,
    /// Standard deviation in the layer plane (mm).
    pub sigma_mm: f32,
    /// Depth of the layer (mm).
    pub depth_mm: f32,
}

/// One layer of a shape that rows share (see [`LayerModel::from_shapes`]): a [`SplatLayer`]
/// whose weight each row scales. The weight is `f64` so that a row's weight,
/// `(weight * scale) as f32`, is rounded once, as the builders that wrote every row's layers
/// out rounded it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShapeLayer {
    /// Layer identity, as [`SplatLayer::index`].
    pub index: u16,
    /// Weight per unit of the row's scale.
    pub weight: f64,
    /// Standard deviation in the layer plane (mm).
    pub sigma_mm: f32,
    /// Depth of the layer (mm).
    pub depth_mm: f32,
}

impl ShapeLayer {
    /// The layer of a row that scales this shape by `scale`.
    pub fn scaled(&self, scale: f64) -> SplatLayer {
        SplatLayer {
            index: self.index,
            weight: (self.weight * scale) as f32,
            sigma_mm: self.sigma_mm,
            depth_mm: self.depth_mm,
        }
    }
}

/// Where one row (pixel `i`, channel `c`: row `i * 3 + c`) keeps its layers.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Row {
    /// Its own layers: `own[start..start + len]`.
    Own { start: u32, len: u32 },
    /// A shared shape, `shapes[start..start + len]`, every weight times `scale`.
    Scaled { scale: f64, start: u32, len: u16 },
}

// 16 bytes a row: a full-size model has ~4.3 million.
const _: () = assert!(std::mem::size_of::<Row>() == 16);

const EMPTY_ROW: Row = Row::Own { start: 0, len: 0 };

impl Row {
    /// Own layers `own[start..start + len]`; every empty row is the one [`EMPTY_ROW`].
    fn own(start: u32, len: u32) -> Self {
        if len == 0 {
            EMPTY_ROW
        } else {
            Row::Own { start, len }
        }
    }

    fn len(&self) -> usize {
        match *self {
            Row::Own { len, .. } => len as usize,
            Row::Scaled { len, .. } => usize::from(len),
        }
    }

    /// The row with its start moved by the buffers' bases (own, shapes).
    fn rebased(self, own: u32, shapes: u32) -> Self {
        match self {
            Row::Own { start, len } => Row::own(start + own, len),
            Row::Scaled { scale, start, len } => Row::Scaled {
                scale,
                start: start + shapes,
                len,
            },
        }
    }
}

/// The layers of one pixel and channel ([`LayerModel::layers`]): a row's own layers, or a
/// shared shape with the row's scale. Iterates [`SplatLayer`]s by value.
#[derive(Debug, Clone, Copy)]
pub enum RowLayers<'a> {
    /// Layers stored for this row.
    Own(&'a [SplatLayer]),
    /// A shape shared with other rows, its weights times the scale.
    Scaled(&'a [ShapeLayer], f64),
}

impl<'a> RowLayers<'a> {
    /// Number of layers.
    pub fn len(&self) -> usize {
        match self {
            RowLayers::Own(l) => l.len(),
            RowLayers::Scaled(s, _) => s.len(),
        }
    }

    /// No layers.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The layers, by value.
    pub fn iter(&self) -> RowIter<'a> {
        RowIter(match *self {
            RowLayers::Own(l) => RowIterKind::Own(l.iter()),
            RowLayers::Scaled(s, scale) => RowIterKind::Scaled(s.iter(), scale),
        })
    }

    /// The layers in a vector.
    pub fn to_vec(&self) -> Vec<SplatLayer> {
        self.iter().collect()
    }
}

impl PartialEq for RowLayers<'_> {
    /// Equal layers, however each row stores them.
    fn eq(&self, other: &Self) -> bool {
        self.len() == other.len() && self.iter().eq(other.iter())
    }
}

impl<'a> IntoIterator for RowLayers<'a> {
    type Item = SplatLayer;
    type IntoIter = RowIter<'a>;

    fn into_iter(self) -> RowIter<'a> {
        self.iter()
    }
}

/// Iterator over a row's layers ([`RowLayers::iter`]).
#[derive(Debug, Clone)]
pub struct RowIter<'a>(RowIterKind<'a>);

#[derive(Debug, Clone)]
enum RowIterKind<'a> {
    Own(std::slice::Iter<'a, SplatLayer>),
    Scaled(std::slice::Iter<'a, ShapeLayer>, f64),
}

impl Iterator for RowIter<'_> {
    type Item = SplatLayer;

    fn next(&mut self) -> Option<SplatLayer> {
        match &mut self.0 {
            RowIterKind::Own(it) => it.next().copied(),
            RowIterKind::Scaled(it, scale) => it.next().map(|s| s.scaled(*scale)),
        }
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        match &self.0 {
            RowIterKind::Own(it) => it.size_hint(),
            RowIterKind::Scaled(it, _) => it.size_hint(),
        }
    }
}

impl ExactSizeIterator for RowIter<'_> {}

/// How one row stores its layers ([`LayerModel::row_storage`]), for writers that treat a shared
/// shape once rather than once per row.
#[derive(Debug, Clone)]
pub enum RowStorage<'a> {
    /// The row's own layers.
    Own(&'a [SplatLayer]),
    /// Layers `shape` of [`LayerModel::shapes`], every weight times `scale`.
    Scaled {
        shape: std::ops::Range<usize>,
        scale: f64,
    },
}

/// What [`LayerModel::from_shapes`] puts in one row.
#[derive(Debug, Clone, Copy)]
pub enum RowSource<'a, K> {
    /// No layers.
    Empty,
    /// These layers, copied into the row.
    Own(RowLayers<'a>),
    /// The shape named `key`, its weights times `scale`.
    Shape { key: K, scale: f64 },
}

/// Per-pixel, per-channel layers. A row either owns its layers or scales a shape it shares with
/// other rows: the spatial prior gives every pixel of a tile its tile's shape times the pixel's
/// amplitude, the dipole baseline every pixel its table row's shape. Why shared: written out,
/// those two models were ~30 and ~14 million 16-byte layers at full size (0.7 GB of fresh
/// memory in the fit stage, its peak); shared, their shapes are a few per cent of that.
#[derive(Debug, Clone, Default)]
pub struct LayerModel {
    pub width: usize,
    pub height: usize,
    /// Row `i * 3 + c`: where pixel `i`, channel `c` keeps its layers.
    rows: Vec<Row>,
    /// The layers of the rows that own theirs.
    own: Vec<SplatLayer>,
    /// The shapes that scaled rows share.
    shapes: Vec<ShapeLayer>,
}

impl PartialEq for LayerModel {
    /// Same size and the same layers in every row, however the rows store them.
    fn eq(&self, other: &Self) -> bool {
        self.width == other.width
            && self.height == other.height
            && self.rows.len() == other.rows.len()
            && (0..self.rows.len()).all(|k| self.row(k) == other.row(k))
    }
}

/// Widest sigma and deepest layer (mm) of `layers` (0 without layers).
pub fn extent(layers: impl IntoIterator<Item = SplatLayer>) -> (f64, f64) {
    layers.into_iter().fold((0.0, 0.0), |(s, d), l| {
        (
            s.max(f64::from(l.sigma_mm)),
            d.max(f64::from(l.depth_mm).abs()),
        )
    })
}

/// Pixels per run of the parallel builders.
const RUN: usize = 4096;

impl LayerModel {
    /// Builds the model from a function giving each pixel's layers per channel, every row owning
    /// its layers. Runs of pixels are built in parallel, so the result does not depend on the
    /// threads (a full-size model is ~10^7 rows: serial, this was seconds of one core). Two
    /// passes over `f`: the first counts each row's layers, the second writes them straight into
    /// the model's one buffer. Why: the single pass collected every run's layers and then copied
    /// them into the model, holding the model twice at its peak (up to ~500 MB more at full
    /// size) and copying it on one thread. `f` must give the same layers on both calls (it is a
    /// pure function of the pixel everywhere).
    pub fn from_fn<I, F>(width: usize, height: usize, f: F) -> Self
    where
        I: IntoIterator<Item = SplatLayer>,
        F: Fn(usize, usize) -> I + Sync,
    {
        let n = width * height;
        let run_pixels = |r: usize| r * RUN..((r + 1) * RUN).min(n);
        // Pass 1: per run, its rows' layer counts.
        let run_counts: Vec<Vec<u32>> = (0..n.div_ceil(RUN))
            .into_par_iter()
            .map(|r| {
                run_pixels(r)
                    .flat_map(|i| (0..3).map(move |c| (i, c)))
                    .map(|(i, c)| f(i, c).into_iter().count() as u32)
                    .collect()
            })
            .collect();
        let mut rows = Vec::with_capacity(n * 3);
        let mut run_lens = Vec::with_capacity(run_counts.len());
        let mut total = 0u32;
        for counts in &run_counts {
            let run_start = total;
            for &len in counts {
                rows.push(Row::own(total, len));
                total += len;
            }
            run_lens.push((total - run_start) as usize);
        }
        drop(run_counts);
        let total = total as usize;
        // Pass 2: each run writes its own slice of the buffer, untouched until then. Why not
        // `vec![EMPTY; total]` first: that one-core fill faulted every page of the buffer in
        // before the runs overwrote it, 4 % of the full-size `process --until fit` CPU time.
        const EMPTY: SplatLayer = SplatLayer {
            index: 0,
            weight: 0.0,
            sigma_mm: 0.0,
            depth_mm: 0.0,
        };
        let mut own: Vec<SplatLayer> = Vec::with_capacity(total);
        let mut slices = Vec::with_capacity(run_lens.len());
        let mut rest = &mut own.spare_capacity_mut()[..total];
        for (r, &len) in run_lens.iter().enumerate() {
            let (run, tail) = std::mem::take(&mut rest).split_at_mut(len);
            slices.push((run_pixels(r), run));
            rest = tail;
        }
        slices.into_par_iter().for_each(|(pixels, run)| {
            let mut produced = pixels
                .flat_map(|i| (0..3).map(move |c| (i, c)))
                .flat_map(|(i, c)| f(i, c));
            // Every slot is written (EMPTY where `f` gave fewer layers than it counted).
            for slot in run.iter_mut() {
                slot.write(produced.next().unwrap_or(EMPTY));
            }
        });
        // The runs' slices tile the first `total` slots (their lengths sum to `total`), and
        // each run wrote every slot of its slice.
        debug_assert!(rest.is_empty());
        // SAFETY: the capacity is at least `total`, and every one of the first `total` slots
        // was initialised by the loop above.
        unsafe { own.set_len(total) };
        Self {
            width,
            height,
            rows,
            own,
            shapes: Vec::new(),
        }
    }

    /// Builds the model from a function naming each row's source: nothing, layers to copy, or
    /// a shape (by `key`) and the row's scale. `shape(key)` gives a shape's layers; each run of
    /// pixels stores a shape once, however many of its rows scale it (so a shape is stored once
    /// per run that uses it, never per row). Runs are built in parallel; the result does not
    /// depend on the threads.
    pub fn from_shapes<'a, K, S, F, G>(width: usize, height: usize, row: F, shape: G) -> Self
    where
        K: std::hash::Hash + Eq + Copy,
        S: IntoIterator<Item = ShapeLayer>,
        F: Fn(usize, usize) -> RowSource<'a, K> + Sync,
        G: Fn(K) -> S + Sync,
    {
        let n = width * height;
        let mut rows: Vec<Row> = Vec::with_capacity(n * 3);
        // Written by the runs in parallel: one core filling it first faulted its pages in.
        let run_buffers: Vec<(Vec<SplatLayer>, Vec<ShapeLayer>)> = rows.spare_capacity_mut()
            [..n * 3]
            .par_chunks_mut(RUN * 3)
            .enumerate()
            .map(|(r, slots)| {
                let mut built = RunBuilder::new();
                for (j, slot) in slots.iter_mut().enumerate() {
                    let k = r * RUN * 3 + j;
                    slot.write(built.row(row(k / 3, k % 3), &shape));
                }
                (built.own, built.shapes)
            })
            .collect();
        // SAFETY: the capacity is `n * 3` and the chunks above wrote every one of those slots.
        unsafe { rows.set_len(n * 3) };
        // The runs' rows index their own buffers: moved by the buffers' bases once joined.
        let mut bases = Vec::with_capacity(run_buffers.len());
        let (mut own_base, mut shape_base) = (0u32, 0u32);
        for (own, shapes) in &run_buffers {
            bases.push((own_base, shape_base));
            own_base += own.len() as u32;
            shape_base += shapes.len() as u32;
        }
        rows.par_chunks_mut(RUN * 3)
            .zip(bases)
            .for_each(|(run, (own, shapes))| {
                for r in run {
                    *r = r.rebased(own, shapes);
                }
            });
        let (own, shapes): (Vec<_>, Vec<_>) = run_buffers.into_iter().unzip();
        Self {
            width,
            height,
            rows,
            own: own.concat(),
            shapes: shapes.concat(),
        }
    }

    /// How `row` stores its layers.
    fn storage(&self, row: Row) -> RowStorage<'_> {
        match row {
            Row::Own { start, len } => {
                RowStorage::Own(&self.own[start as usize..(start + len) as usize])
            }
            Row::Scaled { scale, start, len } => RowStorage::Scaled {
                shape: start as usize..start as usize + usize::from(len),
                scale,
            },
        }
    }

    /// Layers of row `k` (pixel `k / 3`, channel `k % 3`).
    fn row(&self, k: usize) -> RowLayers<'_> {
        match self.storage(self.rows[k]) {
            RowStorage::Own(layers) => RowLayers::Own(layers),
            RowStorage::Scaled { shape, scale } => RowLayers::Scaled(&self.shapes[shape], scale),
        }
    }

    /// Layers of pixel `i`, channel `c`.
    pub fn layers(&self, i: usize, c: usize) -> RowLayers<'_> {
        self.row(i * 3 + c)
    }

    /// Every row's layer count, pixel by pixel and channel by channel.
    pub fn row_lens(&self) -> impl ExactSizeIterator<Item = usize> + '_ {
        self.rows.iter().map(Row::len)
    }

    /// How every row stores its layers, pixel by pixel and channel by channel.
    pub fn row_storage(&self) -> impl ExactSizeIterator<Item = RowStorage<'_>> + '_ {
        self.rows.iter().map(|&row| self.storage(row))
    }

    /// The shapes that scaled rows share ([`RowStorage::Scaled`] indexes them).
    pub fn shapes(&self) -> &[ShapeLayer] {
        &self.shapes
    }

    /// Every layer, row after row.
    pub fn all_layers(&self) -> impl Iterator<Item = SplatLayer> + '_ {
        (0..self.rows.len()).flat_map(|k| self.row(k))
    }

    /// Gives every empty row (pixel `i`, channel `c`) for which `with(i, c)` has layers those
    /// layers, appended to the rows' own layers. The rows filled are a few thousand.
    pub fn fill_empty<'a>(&mut self, with: impl Fn(usize, usize) -> Option<&'a [SplatLayer]>) {
        let fill = |rows: &[Row], k: usize| {
            (rows[k].len() == 0)
                .then(|| with(k / 3, k % 3))
                .flatten()
                .filter(|l| !l.is_empty())
        };
        let extra: usize = (0..self.rows.len())
            .filter_map(|k| fill(&self.rows, k))
            .map(<[SplatLayer]>::len)
            .sum();
        // Reserved once: growing by doubling could hold the buffer twice.
        self.own.reserve_exact(extra);
        for k in 0..self.rows.len() {
            if let Some(layers) = fill(&self.rows, k) {
                self.rows[k] = Row::own(self.own.len() as u32, layers.len() as u32);
                self.own.extend_from_slice(layers);
            }
        }
    }

    /// Total number of layers of the rows.
    pub fn layer_count(&self) -> usize {
        self.row_lens().sum()
    }

    /// Builds the model from its rows' layers as a file stores them: offsets
    /// (`width x height x 3 + 1`) and the layers they index; `None` when the offsets do not
    /// describe `width x height x 3` rows of `layers`.
    pub fn from_parts(
        width: usize,
        height: usize,
        offsets: Vec<u32>,
        layers: Vec<SplatLayer>,
    ) -> Option<Self> {
        let rows_ok = offsets.len() == width * height * 3 + 1
            && offsets.first() == Some(&0)
            && offsets.last().map(|&l| l as usize) == Some(layers.len())
            && offsets.windows(2).all(|w| w[0] <= w[1]);
        rows_ok.then(|| Self {
            width,
            height,
            rows: offsets
                .windows(2)
                .map(|w| Row::own(w[0], w[1] - w[0]))
                .collect(),
            own: layers,
            shapes: Vec::new(),
        })
    }

    /// The homogeneous model (paper Fig. 11d): every pixel of `apply_to` gets, per channel and
    /// layer index, the mean weight over the pixels of `average_over` and the weight-averaged
    /// sigma and depth.
    pub fn homogeneous(&self, average_over: &[bool], apply_to: &[bool]) -> Self {
        Self::uniform(
            self.width,
            self.height,
            &self.mean_layers(average_over),
            apply_to,
        )
    }

    /// The model giving every pixel of `apply_to` the same layers per channel, `layers` (one
    /// shape per channel that every row shares).
    pub fn uniform(
        width: usize,
        height: usize,
        layers: &[Vec<SplatLayer>; 3],
        apply_to: &[bool],
    ) -> Self {
        Self::from_shapes(
            width,
            height,
            |i, c| match apply_to.get(i).copied().unwrap_or(false) && !layers[c].is_empty() {
                true => RowSource::Shape { key: c, scale: 1.0 },
                false => RowSource::Empty,
            },
            |c| layers[c].iter().map(ShapeLayer::from),
        )
    }

    /// The model of rows `rows` alone (clamped to the image), every row owning its layers.
    pub fn rows(&self, rows: std::ops::Range<usize>) -> Self {
        let end = rows.end.min(self.height);
        let start = rows.start.min(end);
        let first = start * self.width;
        Self::from_fn(self.width, end - start, |i, c| self.layers(first + i, c))
    }

    /// Widest sigma and deepest layer (mm) of pixel `i`, over the channels.
    pub fn extent(&self, i: usize) -> (f64, f64) {
        extent((0..3).flat_map(|c| self.layers(i, c)))
    }

    /// Pixels with layers in some channel (on every core: Fig. 10 asks at full size, beside
    /// nothing else).
    pub fn fitted(&self) -> Vec<bool> {
        (0..self.width * self.height)
            .into_par_iter()
            .map(|i| (0..3).any(|c| !self.layers(i, c).is_empty()))
            .collect()
    }
    /// Per channel and layer index, the mean weight over the pixels of `average_over` and the
    /// weight-averaged sigma and depth: the layers every pixel of [`LayerModel::homogeneous`]
    /// gets.
    pub fn mean_layers(&self, average_over: &[bool]) -> [Vec<SplatLayer>; 3] {
        // Per channel, layer index -> (weight, weight * sigma, weight * depth) sums; runs of
        // pixels summed in parallel, the runs' sums added in order (same result every run).
        // Indexed by the layer index, not a map: the indices are few and small, and a map
        // entry per stored layer (tens of millions at full size) was most of the fit stage's
        // two calls (0.4 CPU-s). Same sums, added in the same order, as the map's.
        type Sums = [Vec<(f64, f64, f64)>; 3];
        const RUN: usize = 1 << 14;
        let runs: Vec<(Sums, usize)> = average_over
            .par_chunks(RUN)
            .enumerate()
            .map(|(r, flags)| {
                let mut sums: Sums = Default::default();
                let mut count = 0usize;
                for (i, _) in flags.iter().enumerate().filter(|m| *m.1) {
                    count += 1;
                    for (c, acc) in sums.iter_mut().enumerate() {
                        for l in self.layers(r * RUN + i, c) {
                            let e = sum_at(acc, l.index);
                            let w = f64::from(l.weight);
                            e.0 += w;
                            e.1 += w * f64::from(l.sigma_mm);
                            e.2 += w * f64::from(l.depth_mm);
                        }
                    }
                }
                (sums, count)
            })
            .collect();
        let mut acc: Sums = Default::default();
        let mut count = 0usize;
        for (sums, n) in runs {
            count += n;
            for (acc, sums) in acc.iter_mut().zip(sums) {
                for (index, (w, ws, wd)) in sums.into_iter().enumerate() {
                    // Indices below the run's largest that it never saw add 0 to 0: the
                    // map's absent entry and this zero agree at the filter below.
                    let e = sum_at(acc, index as u16);
                    e.0 += w;
                    e.1 += ws;
                    e.2 += wd;
                }
            }
        }
        std::array::from_fn(|c| {
            acc[c]
                .iter()
                .enumerate()
                .filter(|(_, v)| v.0 > 0.0)
                .map(|(index, &(w, ws, wd))| SplatLayer {
                    index: index as u16,
                    weight: (w / count.max(1) as f64) as f32,
                    sigma_mm: (ws / w) as f32,
                    depth_mm: (wd / w) as f32,
                })
                .collect()
        })
    }
}

impl From<&SplatLayer> for ShapeLayer {
    fn from(l: &SplatLayer) -> Self {
        ShapeLayer {
            index: l.index,
            weight: f64::from(l.weight),
            sigma_mm: l.sigma_mm,
            depth_mm: l.depth_mm,
        }
    }
}

/// One run's part of [`LayerModel::from_shapes`]: the layers its rows own and the shapes they
/// scale, each shape stored once (`stored`: key to start and length in `shapes`), rows indexing
/// both from the run's start.
struct RunBuilder<K> {
    own: Vec<SplatLayer>,
    shapes: Vec<ShapeLayer>,
    stored: std::collections::HashMap<K, (u32, u32)>,
    /// The last shape asked for: neighbouring pixels mostly share theirs (a tile's).
    last: Option<(K, (u32, u32))>,
}

impl<K: std::hash::Hash + Eq + Copy> RunBuilder<K> {
    fn new() -> Self {
        Self {
            own: Vec::new(),
            shapes: Vec::new(),
            stored: Default::default(),
            last: None,
        }
    }

    fn row<S: IntoIterator<Item = ShapeLayer>>(
        &mut self,
        source: RowSource<'_, K>,
        shape: impl Fn(K) -> S,
    ) -> Row {
        match source {
            RowSource::Empty => EMPTY_ROW,
            RowSource::Own(layers) => self.own_row(layers),
            RowSource::Shape { key, scale } => {
                let (start, len) = self.stored_shape(key, shape);
                match u16::try_from(len) {
                    Ok(0) => EMPTY_ROW,
                    Ok(len) => Row::Scaled { scale, start, len },
                    // Longer than a scaled row can say: written out as its own layers.
                    Err(_) => {
                        let (s, e) = (start as usize, (start + len) as usize);
                        let shapes = std::mem::take(&mut self.shapes);
                        let row = self.own_row(RowLayers::Scaled(&shapes[s..e], scale));
                        self.shapes = shapes;
                        row
                    }
                }
            }
        }
    }

    fn own_row(&mut self, layers: RowLayers<'_>) -> Row {
        let start = self.own.len() as u32;
        self.own.extend(layers);
        Row::own(start, layers.len() as u32)
    }

    /// Start and length of the shape of `key` in the run's shapes (stored on first use).
    fn stored_shape<S: IntoIterator<Item = ShapeLayer>>(
        &mut self,
        key: K,
        shape: impl Fn(K) -> S,
    ) -> (u32, u32) {
        if let Some((k, at)) = self.last
            && k == key
        {
            return at;
        }
        let shapes = &mut self.shapes;
        let at = *self.stored.entry(key).or_insert_with(|| {
            let start = shapes.len();
            shapes.extend(shape(key));
            (start as u32, (shapes.len() - start) as u32)
        });
        self.last = Some((key, at));
        at
    }
}

/// The sums of layer `index` in `sums` (grown with zeros to hold it).
fn sum_at(sums: &mut Vec<(f64, f64, f64)>, index: u16) -> &mut (f64, f64, f64) {
    let i = usize::from(index);
    if sums.len() <= i {
        sums.resize(i + 1, (0.0, 0.0, 0.0));
    }
    &mut sums[i]
}

/// Quality knobs of the renderer.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOptions {
    /// Gaussian kernels are cut at this many sigmas.
    pub truncate_sigmas: f64,
    /// Layers whose weight is below this fraction of the pixel's total are skipped.
    pub min_relative_weight: f32,
    /// Ratio between consecutive sigma bins (> 1; smaller is more exact and slower).
    pub sigma_bin_ratio: f64,
    /// Smallest sigma bin (pixels); narrower layers are blurred by this much.
    pub min_sigma_px: f64,
    /// Pyramid: a bin whose sigma is at least this many pixels times a power of two `f >= 2` is
    /// splatted, blurred and read back on the image downsampled by the largest such `f` (the
    /// blur there keeps at least this many coarse pixels of sigma, so the bilinear resampling
    /// barely shows). `f64::INFINITY` blurs every bin at full resolution (the reference path).
    pub coarse_sigma_px: f64,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            truncate_sigmas: 3.5,
            min_relative_weight: 1e-3,
            sigma_bin_ratio: 1.3,
            min_sigma_px: 0.3,
            coarse_sigma_px: 4.0,
        }
    }
}

impl RenderOptions {
    fn validate(&self) -> Result<(), RenderError> {
        if self.truncate_sigmas.is_nan() || self.truncate_sigmas < 1.0 {
            return Err(RenderError::BadOption("truncate_sigmas must be >= 1"));
        }
        if self.sigma_bin_ratio.is_nan() || self.sigma_bin_ratio <= 1.0 {
            return Err(RenderError::BadOption("sigma_bin_ratio must be > 1"));
        }
        if self.min_sigma_px.is_nan() || self.min_sigma_px <= 0.0 {
            return Err(RenderError::BadOption("min_sigma_px must be > 0"));
        }
        if self.coarse_sigma_px.is_nan() || self.coarse_sigma_px < 1.0 {
            return Err(RenderError::BadOption(
                "coarse_sigma_px must be >= 1 (or infinite)",
            ));
        }
        Ok(())
    }

    fn bin_position(&self, sigma_px: f64) -> f64 {
        (sigma_px.max(self.min_sigma_px) / self.min_sigma_px).ln() / self.sigma_bin_ratio.ln()
    }

    fn bin_sigma(&self, bin: usize) -> f64 {
        self.min_sigma_px * self.sigma_bin_ratio.powi(bin as i32)
    }

    /// Farthest, in pixels, a render carries the light of a source whose layers are at most
    /// `sigma_px` wide and shifted by at most `shift_px`: the truncated kernel of the bin above
    /// `sigma_px`, plus the bilinear splat and read-back on that bin's pyramid level.
    pub fn reach_px(&self, sigma_px: f64, shift_px: f64) -> f64 {
        let f = self.level_factor(sigma_px);
        self.truncate_sigmas * self.bin_above(sigma_px) + shift_px + 2.0 * f as f64 + 1.0
    }

    /// Downsampling factor of the coarsest pyramid level a layer of at most `sigma_px` uses:
    /// a crop of the image that starts at a multiple of it samples every level as the whole
    /// image does.
    pub fn level_factor(&self, sigma_px: f64) -> usize {
        1 << self.bin_level(self.bin_above(sigma_px))
    }

    /// Sigma of the widest bin a layer of `sigma_px` is splatted into.
    fn bin_above(&self, sigma_px: f64) -> f64 {
        self.bin_sigma(self.bin_position(sigma_px).floor() as usize + 1)
    }

    /// Downsampling factor `2^level` of the pyramid level a bin of `sigma_px` is blurred on.
    fn bin_level(&self, sigma_px: f64) -> u32 {
        let ratio = sigma_px / self.coarse_sigma_px;
        if !ratio.is_finite() || ratio < 2.0 {
            return 0;
        }
        // At most 2^12: far beyond any camera's size.
        (ratio.log2().floor() as u32).min(12)
    }
}

/// One sigma bin of one channel: the sources splatted on its pyramid level.
struct Bin {
    /// Index of the frame in a [`render_global_many`] batch (0 for [`render_global`]).
    frame: usize,
    channel: usize,
    sigma_px: f64,
    level: u32,
    /// Size of the level's grid ([`level_grid`]), kept so a splat need not divide.
    grid: (usize, usize),
    /// Coarse image (`grid.0 x grid.1`) of the level.
    image: Vec<f32>,
}

impl Bin {
    /// The empty bin `b` of `channel` in `frame` for a `w x h` image: its sigma, its pyramid
    /// level and that level's grid.
    fn empty(
        opts: &RenderOptions,
        b: usize,
        (w, h): (usize, usize),
        frame: usize,
        channel: usize,
    ) -> Self {
        let sigma_px = opts.bin_sigma(b);
        let level = opts.bin_level(sigma_px);
        let (gw, gh) = level_grid(w, h, level);
        Self {
            frame,
            channel,
            sigma_px,
            level,
            grid: (gw, gh),
            image: mlsss_core::resources::zeros_written(gw * gh),
        }
    }
}

/// Size of the grid of pyramid level `level` for a `w x h` image: coarse sample `j` sits on fine
/// pixel `j * 2^level`; one extra sample covers the last fine pixel's interpolation.
fn level_grid(w: usize, h: usize, level: u32) -> (usize, usize) {
    if level == 0 {
        return (w, h);
    }
    let f = 1usize << level;
    ((w - 1) / f + 2, (h - 1) / f + 2)
}

/// [`RenderOptions`]' bin arithmetic with what depends on the bin index alone tabulated: the
/// same numbers without a `powi`, `log2` and `floor` per layer and bin (which were most of a
/// splat's cost).
struct BinTable {
    min_sigma_px: f64,
    /// `ln(sigma_bin_ratio)`.
    ln_ratio: f64,
    /// `2^bin_level(bin_sigma(b))` of the first bins.
    factors: Vec<f64>,
    opts: RenderOptions,
}

impl BinTable {
    /// Bins tabulated; wider bins (never reached by a real model) are computed.
    const TABULATED: usize = 128;

    fn new(opts: &RenderOptions) -> Self {
        Self {
            min_sigma_px: opts.min_sigma_px,
            ln_ratio: opts.sigma_bin_ratio.ln(),
            factors: (0..Self::TABULATED)
                .map(|b| Self::factor_of(opts, b))
                .collect(),
            opts: opts.clone(),
        }
    }

    fn factor_of(opts: &RenderOptions, b: usize) -> f64 {
        f64::from(1u32 << opts.bin_level(opts.bin_sigma(b)))
    }

    /// [`RenderOptions::bin_position`].
    #[inline]
    fn bin_position(&self, sigma_px: f64) -> f64 {
        (sigma_px.max(self.min_sigma_px) / self.min_sigma_px).ln() / self.ln_ratio
    }

    /// Downsampling factor of bin `b`'s pyramid level.
    #[inline]
    fn level_factor(&self, b: usize) -> f64 {
        match self.factors.get(b) {
            Some(&f) => f,
            None => Self::factor_of(&self.opts, b),
        }
    }
}

/// Renders the subsurface (global) image, RGB per pixel, of the light whose per-pixel irradiance
/// is `irradiance` (0 where unlit or shadowed) and whose geometry gives `shift[i] = t_i + t_o`
/// (`None` where the light cannot enter).
pub fn render_global(
    surface: &Surface,
    irradiance: &[f32],
    shift: &[Option<Vector3<f64>>],
    model: &LayerModel,
    opts: &RenderOptions,
) -> Result<Vec<[f32; 3]>, RenderError> {
    let mut frames = render_global_many(surface, &[irradiance], shift, model, opts)?;
    Ok(frames.pop().unwrap_or_default())
}

/// Renders the global images of several irradiance images under the same geometry and model
/// (one frame per irradiance image), each exactly as it renders alone. Why:
/// most of a render is spent finding, per source and layer, where and into which sigma bins it
/// splats (footprint, shift, bin position); that depends on the geometry and the model only, so
/// it is found once per source for all the frames. Frames are splatted in batches of at most
/// `SPLAT_BATCH_BYTES` of bin images.
pub fn render_global_many(
    surface: &Surface,
    irradiances: &[&[f32]],
    shift: &[Option<Vector3<f64>>],
    model: &LayerModel,
    opts: &RenderOptions,
) -> Result<Vec<Vec<[f32; 3]>>, RenderError> {
    render_global_many_by(
        surface,
        irradiances,
        shift,
        model,
        opts,
        SPLAT_CHUNK_SOURCES,
    )
}

/// [`render_global_many`] finding the splats of `chunk` sources per pass (the result does not
/// depend on it; tests take small passes).
fn render_global_many_by(
    surface: &Surface,
    irradiances: &[&[f32]],
    shift: &[Option<Vector3<f64>>],
    model: &LayerModel,
    opts: &RenderOptions,
    chunk: usize,
) -> Result<Vec<Vec<[f32; 3]>>, RenderError> {
    opts.validate()?;
    let n = surface.len();
    for (what, got) in [
        ("shift", shift.len()),
        ("model", model.width * model.height),
    ]
    .into_iter()
    .chain(irradiances.iter().map(|e| ("irradiance", e.len())))
    {
        if got != n {
            return Err(RenderError::SizeMismatch { what, got, want: n });
        }
    }
    if n == 0 {
        return Ok(vec![Vec::new(); irradiances.len()]);
    }
    let (w, h) = (surface.width, surface.height);
    // Full-resolution bins per channel (from min_sigma_px up to the first pyramid level) are
    // most of a frame's bin memory.
    // (Without a pyramid, `coarse_sigma_px` is infinite: capped.)
    let full_bins = opts
        .bin_position(2.0 * opts.coarse_sigma_px)
        .ceil()
        .min(62.0) as usize
        + 2;
    let frame_bytes = n * 3 * full_bins * std::mem::size_of::<f32>();
    let batch = (SPLAT_BATCH_BYTES / frame_bytes.max(1)).max(1);
    let mut out = Vec::with_capacity(irradiances.len());
    for frames in irradiances.chunks(batch) {
        let mut bins = splat_frames(surface, frames, shift, model, opts, chunk);
        blur_bins(&mut bins, w, h, opts)?;
        for f in 0..frames.len() {
            // Per frame, the bins in the order `render_global` has them: channel by channel,
            // each channel's in its order of first use.
            let own: Vec<&Bin> = bins.iter().filter(|b| b.frame == f).collect();
            out.push(sum_bin_refs(&own, surface));
        }
    }
    Ok(out)
}

/// Most bytes of bin images [`render_global_many`] holds at once (frames are splatted in
/// batches that fit).
const SPLAT_BATCH_BYTES: usize = 768 << 20;

/// Blurs every bin on its own level; bins are independent jobs.
fn blur_bins(
    bins: &mut [Bin],
    w: usize,
    h: usize,
    opts: &RenderOptions,
) -> Result<(), RenderError> {
    bins.par_iter_mut().try_for_each(|bin| {
        let (gw, gh) = level_grid(w, h, bin.level);
        let f = f64::from(1u32 << bin.level);
        // The bilinear splat and read-back each widen the kernel by a tent of half-width f
        // (variance f^2/6 per axis): blur the rest.
        let sigma = if bin.level == 0 {
            bin.sigma_px
        } else {
            (bin.sigma_px * bin.sigma_px - f * f / 3.0).max(0.0).sqrt() / f
        };
        gaussian_blur(&mut bin.image, gw, gh, sigma, opts.truncate_sigmas)
    })?;
    Ok(())
}

/// Sums the blurred bins per channel and level, brings every level back to full resolution and
/// turns the deposited flux into radiance.
fn sum_bin_refs(bins: &[&Bin], surface: &Surface) -> Vec<[f32; 3]> {
    let (w, h) = (surface.width, surface.height);
    let n = surface.len();
    let mut out = vec![[0.0f32; 3]; n];
    let levels: std::collections::BTreeSet<u32> = bins.iter().map(|b| b.level).collect();
    for level in levels {
        let (gw, gh) = level_grid(w, h, level);
        let mut acc = vec![[0.0f32; 3]; gw * gh];
        for bin in bins.iter().filter(|b| b.level == level) {
            for (a, v) in acc.iter_mut().zip(&bin.image) {
                a[bin.channel] += v;
            }
        }
        add_upsampled(&mut out, w, h, &acc, gw, level);
    }
    // Deposited flux per receiving pixel -> radiance: divide by the receiver's area.
    out.par_iter_mut()
        .enumerate()
        .for_each(|(i, o)| match surface.footprint(i) {
            Some(fp) => {
                let inv = (1.0 / fp.area()) as f32;
                o.iter_mut().for_each(|v| *v *= inv);
            }
            None => *o = [0.0; 3],
        });
    out
}

/// Where one layer of one source lands: for each of its two sigma bins, the bin, its share of the
/// layer and the splat position on the bin's pyramid level.
struct LayerSplat {
    weight: f32,
    targets: [Option<(usize, f64, BilinearAt)>; 2],
}

/// The splats of source `i`'s layers of channel `c` (none where it has no shift or footprint),
/// and its area: all of a source's splatting work that does not depend on the irradiance.
fn layer_splats(
    surface: &Surface,
    shift: &[Option<Vector3<f64>>],
    model: &LayerModel,
    table: &BinTable,
    c: usize,
    i: usize,
    splats: &mut Vec<LayerSplat>,
) -> f64 {
    splats.clear();
    let layers = model.layers(i, c);
    if layers.is_empty() {
        return 0.0;
    }
    let (Some(t), Some(fp)) = (shift[i], surface.footprint(i)) else {
        return 0.0;
    };
    let w = surface.width;
    let area = fp.area();
    let pixel_mm = area.sqrt();
    let (x, y) = ((i % w) as f64, (i / w) as f64);
    let Some(map) = fp.pixel_map() else {
        return area;
    };
    let total: f32 = layers.iter().map(|l| l.weight).sum();
    for l in layers {
        if l.weight.is_nan() || l.weight <= table.opts.min_relative_weight * total {
            continue;
        }
        let d = map.pixels_for(&(t * f64::from(l.depth_mm)));
        let pos = table.bin_position(f64::from(l.sigma_mm) / pixel_mm);
        let b0 = floor(pos) as usize;
        let frac = pos - b0 as f64;
        let target = |b: usize, share: f64| {
            (share > 0.0).then(|| {
                let f = table.level_factor(b);
                (b, share, bilinear_at((x + d.x) / f, (y + d.y) / f))
            })
        };
        splats.push(LayerSplat {
            weight: l.weight,
            targets: [target(b0, 1.0 - frac), target(b0 + 1, frac)],
        });
    }
    area
}

/// Sources whose splats [`splat_frames`] finds in one pass before spending them: about 100
/// bytes per source, layer and channel are held (16 k sources of 4 layers: 20 MB).
const SPLAT_CHUNK_SOURCES: usize = 16 * 1024;

/// Parts each channel's sources of a pass are split into to find their splats in parallel.
const SPLAT_PARTS_PER_CHANNEL: usize = 4;

/// Forward-warps every lit source by each layer's shift into the images of its two sigma bins
/// (bilinear, on each bin's pyramid level), for several frames at once (`frames[f]` = frame
/// `f`'s irradiance). The bins come channel by channel, then frame by frame, each frame's in its
/// order of first use (the order the sums use, so the result does not depend on the threads):
/// exactly the bins a render of that frame alone makes (test
/// `many_frames_render_as_each_frame_alone`).
///
/// Why two phases per pass of `chunk` sources: a source's splats depend on the geometry and the
/// model only, so they are found once for every frame (in parallel over parts of the pass),
/// then each (channel, frame) pair spends them into its own bins in source order (in parallel
/// over the pairs). One job per channel, as before, left one of two cores idle for a third of
/// the splatting (3 jobs on 2 cores): the quick demo's evaluation spends 60 % of its CPU here.
fn splat_frames(
    surface: &Surface,
    frames: &[&[f32]],
    shift: &[Option<Vector3<f64>>],
    model: &LayerModel,
    opts: &RenderOptions,
    chunk: usize,
) -> Vec<Bin> {
    let (w, h) = (surface.width, surface.height);
    let table = BinTable::new(opts);
    let lit = |e: f32| !(e.is_nan() || e <= 0.0);
    let mut targets: Vec<FrameBins> = (0..3)
        .flat_map(|c| (0..frames.len()).map(move |f| FrameBins::new(c, f)))
        .collect();
    let n = surface.len();
    for first in (0..n).step_by(chunk.max(1)) {
        let sources = first..(first + chunk.max(1)).min(n);
        let parts: Vec<SourceSplats> = (0..3 * SPLAT_PARTS_PER_CHANNEL)
            .into_par_iter()
            .map(|j| {
                let (c, part) = (j / SPLAT_PARTS_PER_CHANNEL, j % SPLAT_PARTS_PER_CHANNEL);
                let range = part_of(&sources, part, SPLAT_PARTS_PER_CHANNEL);
                let any_lit = |i: usize| frames.iter().any(|e| lit(e[i]));
                SourceSplats::find(surface, shift, model, &table, c, range, any_lit)
            })
            .collect();
        targets.par_iter_mut().for_each(|target| {
            let irradiance = frames[target.frame];
            let own = &parts[target.channel * SPLAT_PARTS_PER_CHANNEL..][..SPLAT_PARTS_PER_CHANNEL];
            for part in own {
                for (i, area, splats) in part.sources() {
                    let e = irradiance[i];
                    if !lit(e) {
                        continue;
                    }
                    for l in splats {
                        let amount = f64::from(l.weight) * f64::from(e) * area;
                        for &(b, share, at) in l.targets.iter().flatten() {
                            target.splat(b, at, (amount * share) as f32, (w, h), opts);
                        }
                    }
                }
            }
        });
    }
    targets.into_iter().flat_map(|t| t.bins).collect()
}

/// Part `part` of `parts` nearly equal parts of `range`.
fn part_of(range: &std::ops::Range<usize>, part: usize, parts: usize) -> std::ops::Range<usize> {
    let len = range.end - range.start;
    range.start + len * part / parts..range.start + len * (part + 1) / parts
}

/// The splats of a run of sources of one channel (none for a source lit in no frame).
struct SourceSplats {
    sources: std::ops::Range<usize>,
    /// `splats[starts[j]..starts[j + 1]]` are source `sources.start + j`'s.
    starts: Vec<usize>,
    areas: Vec<f64>,
    splats: Vec<LayerSplat>,
}

impl SourceSplats {
    fn find(
        surface: &Surface,
        shift: &[Option<Vector3<f64>>],
        model: &LayerModel,
        table: &BinTable,
        c: usize,
        sources: std::ops::Range<usize>,
        any_lit: impl Fn(usize) -> bool,
    ) -> Self {
        let mut found = Self {
            starts: Vec::with_capacity(sources.len() + 1),
            areas: Vec::with_capacity(sources.len()),
            splats: Vec::new(),
            sources: sources.clone(),
        };
        let mut one = Vec::new();
        found.starts.push(0);
        for i in sources {
            let area = if any_lit(i) {
                layer_splats(surface, shift, model, table, c, i, &mut one)
            } else {
                one.clear();
                0.0
            };
            found.splats.append(&mut one);
            found.starts.push(found.splats.len());
            found.areas.push(area);
        }
        found
    }

    /// Each source with its area and splats, in source order.
    fn sources(&self) -> impl Iterator<Item = (usize, f64, &[LayerSplat])> {
        self.sources.clone().enumerate().map(|(j, i)| {
            let splats = &self.splats[self.starts[j]..self.starts[j + 1]];
            (i, self.areas[j], splats)
        })
    }
}

/// One channel's bins of one frame, in order of first use.
struct FrameBins {
    channel: usize,
    frame: usize,
    /// Position in `bins` of each sigma bin used so far.
    index: Vec<Option<usize>>,
    bins: Vec<Bin>,
}

impl FrameBins {
    fn new(channel: usize, frame: usize) -> Self {
        Self {
            channel,
            frame,
            index: Vec::new(),
            bins: Vec::new(),
        }
    }

    /// Adds `amount` at `at` in sigma bin `b` (made on first use) of a `w x h` image.
    #[inline]
    fn splat(
        &mut self,
        b: usize,
        at: BilinearAt,
        amount: f32,
        (w, h): (usize, usize),
        opts: &RenderOptions,
    ) {
        if self.index.len() <= b {
            self.index.resize(b + 1, None);
        }
        let bins = &mut self.bins;
        let (frame, channel) = (self.frame, self.channel);
        let k = *self.index[b].get_or_insert_with(|| {
            bins.push(Bin::empty(opts, b, (w, h), frame, channel));
            bins.len() - 1
        });
        let bin = &mut bins[k];
        let (gw, gh) = bin.grid;
        splat_at(&mut bin.image, gw, gh, at, amount);
    }
}

/// Adds the level-`level` flux image `coarse` (`gw` wide), bilinearly interpolated, to the flux
/// image `out` (`w x h`).
fn add_upsampled(
    out: &mut [[f32; 3]],
    w: usize,
    h: usize,
    coarse: &[[f32; 3]],
    gw: usize,
    level: u32,
) {
    if level == 0 {
        for (o, v) in out.iter_mut().zip(coarse) {
            for c in 0..3 {
                o[c] += v[c];
            }
        }
        return;
    }
    let f = 1usize << level;
    let inv = 1.0 / f as f32;
    // A coarse sample holds the flux of f x f fine pixels; interpolation spreads it over them.
    let per_pixel = inv * inv;
    out.par_chunks_mut(w)
        .take(h)
        .enumerate()
        .for_each(|(y, row)| {
            let (j, fy) = (y / f, (y % f) as f32 * inv);
            let (r0, r1) = (
                &coarse[j * gw..(j + 1) * gw],
                &coarse[(j + 1) * gw..(j + 2) * gw],
            );
            for (x, o) in row.iter_mut().enumerate() {
                let (k, fx) = (x / f, (x % f) as f32 * inv);
                for c in 0..3 {
                    let top = r0[k][c] + fx * (r0[k + 1][c] - r0[k][c]);
                    let bottom = r1[k][c] + fx * (r1[k + 1][c] - r1[k][c]);
                    o[c] += per_pixel * (top + fy * (bottom - top));
                }
            }
        });
}

/// The pixel below and left of `(x, y)` and the fractions towards the next ones.
#[derive(Debug, Clone, Copy)]
struct BilinearAt {
    x0: f64,
    y0: f64,
    fx: f32,
    fy: f32,
}

fn bilinear_at(x: f64, y: f64) -> BilinearAt {
    let (x0, y0) = (floor(x), floor(y));
    BilinearAt {
        x0,
        y0,
        fx: (x - x0) as f32,
        fy: (y - y0) as f32,
    }
}

/// Adds `amount` to the four pixels around a position found by [`bilinear_at`], bilinearly.
#[inline]
fn splat_at(img: &mut [f32], w: usize, h: usize, at: BilinearAt, amount: f32) {
    let BilinearAt { x0, y0, fx, fy } = at;
    for (dx, dy, share) in [
        (0, 0, (1.0 - fx) * (1.0 - fy)),
        (1, 0, fx * (1.0 - fy)),
        (0, 1, (1.0 - fx) * fy),
        (1, 1, fx * fy),
    ] {
        let (px, py) = (x0 as i64 + dx, y0 as i64 + dy);
        if px >= 0 && py >= 0 && (px as usize) < w && (py as usize) < h && share > 0.0 {
            img[py as usize * w + px as usize] += amount * share;
        }
    }
}

/// In-place separable Gaussian blur with zero borders (light leaving the image is lost), on one
/// thread (the renderer runs bins in parallel): weights normalised in `f64` and rounded to `f32`,
/// radius `ceil(truncate * sigma)`. A `w * h` mismatch is an error.
pub fn gaussian_blur(
    img: &mut [f32],
    w: usize,
    h: usize,
    sigma: f64,
    truncate: f64,
) -> Result<(), BlurError> {
    let kernel = GaussianKernel::new(sigma, truncate, Normalisation::Weights).to_f32();
    blur_2d(img, w, h, &kernel, Border::Zero)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The straightforward single-frame render the batched one is checked against: each
    /// source's splats found and spent at once, frame by frame.
    fn reference_render_global(
        surface: &Surface,
        irradiance: &[f32],
        shift: &[Option<Vector3<f64>>],
        model: &LayerModel,
        opts: &RenderOptions,
    ) -> Vec<[f32; 3]> {
        let mut bins = splat_sources(surface, irradiance, shift, model, opts);
        blur_bins(&mut bins, surface.width, surface.height, opts).expect("valid options");
        sum_bins(&bins, surface)
    }

    /// The global image from one frame's blurred bins.
    fn sum_bins(bins: &[Bin], surface: &Surface) -> Vec<[f32; 3]> {
        let refs: Vec<&Bin> = bins.iter().collect();
        sum_bin_refs(&refs, surface)
    }

    /// Forward-warps every lit source by each layer's shift into the images of its two sigma bins
    /// (bilinear, on each bin's pyramid level). Channels are splatted in parallel; the bins come out
    /// channel by channel, each channel's in the order of first use (the order the sums use, so the
    /// result does not depend on the threads).
    fn splat_sources(
        surface: &Surface,
        irradiance: &[f32],
        shift: &[Option<Vector3<f64>>],
        model: &LayerModel,
        opts: &RenderOptions,
    ) -> Vec<Bin> {
        (0..3)
            .into_par_iter()
            .map(|c| splat_channel(surface, irradiance, shift, model, opts, c))
            .collect::<Vec<_>>()
            .into_iter()
            .flatten()
            .collect()
    }

    /// [`splat_sources`] for channel `c`.
    fn splat_channel(
        surface: &Surface,
        irradiance: &[f32],
        shift: &[Option<Vector3<f64>>],
        model: &LayerModel,
        opts: &RenderOptions,
        c: usize,
    ) -> Vec<Bin> {
        let (w, h) = (surface.width, surface.height);
        // index[b]: position of bin b in `bins` (allocated on first use).
        let mut index: Vec<Option<usize>> = Vec::new();
        let mut bins: Vec<Bin> = Vec::new();
        for (i, &e) in irradiance.iter().enumerate() {
            if e.is_nan() || e <= 0.0 {
                continue;
            }
            let (Some(t), Some(fp)) = (shift[i], surface.footprint(i)) else {
                continue;
            };
            let area = fp.area();
            let pixel_mm = area.sqrt();
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            let layers = model.layers(i, c);
            let total: f32 = layers.iter().map(|l| l.weight).sum();
            for l in layers {
                if l.weight.is_nan() || l.weight <= opts.min_relative_weight * total {
                    continue;
                }
                let Some(d) = fp.pixels_for(&(t * f64::from(l.depth_mm))) else {
                    continue;
                };
                let amount = f64::from(l.weight) * f64::from(e) * area;
                let pos = opts.bin_position(f64::from(l.sigma_mm) / pixel_mm);
                let b0 = pos.floor() as usize;
                let frac = pos - b0 as f64;
                for (b, share) in [(b0, 1.0 - frac), (b0 + 1, frac)] {
                    if share <= 0.0 {
                        continue;
                    }
                    if index.len() <= b {
                        index.resize(b + 1, None);
                    }
                    let k = *index[b].get_or_insert_with(|| {
                        bins.push(Bin::empty(opts, b, (w, h), 0, c));
                        bins.len() - 1
                    });
                    let bin = &mut bins[k];
                    let f = f64::from(1u32 << bin.level);
                    let (gw, gh) = level_grid(w, h, bin.level);
                    splat_bilinear(
                        &mut bin.image,
                        gw,
                        gh,
                        (x + d.x) / f,
                        (y + d.y) / f,
                        (amount * share) as f32,
                    );
                }
            }
        }
        bins
    }

    /// The bilinear splat with the standard library's `floor` (the render's own is checked
    /// against it).
    fn splat_bilinear(img: &mut [f32], w: usize, h: usize, x: f64, y: f64, amount: f32) {
        let (x0, y0) = (x.floor(), y.floor());
        let at = BilinearAt {
            x0,
            y0,
            fx: (x - x0) as f32,
            fy: (y - y0) as f32,
        };
        splat_at(img, w, h, at, amount);
    }

    /// A flat patch z = 0 on a `pitch` mm grid, seen from far above.
    fn plane(w: usize, h: usize, pitch: f64) -> Surface {
        Surface::flat(w, h, pitch, Vector3::new(0.0, 0.0, 1e4))
    }

    fn normal_pdf(x: f64, sigma: f64) -> f64 {
        (-0.5 * (x / sigma).powi(2)).exp() / (sigma * (2.0 * std::f64::consts::PI).sqrt())
    }

    #[test]
    fn uniform_plane_lit_by_a_line_gives_the_shifted_1d_profile() {
        // Line of light along y at column 40 (one pixel = 0.1 mm wide), two layers:
        // expected L(x) = sum_l w_l E W g(x - x_line - z_l t; sigma_l) (1-D normal pdf in 1/mm).
        let (w, h, pitch) = (120, 60, 0.1);
        let surface = plane(w, h, pitch);
        let line = 40;
        let irradiance: Vec<f32> = (0..w * h)
            .map(|i| if i % w == line { 2.0 } else { 0.0 })
            .collect();
        let t = Vector3::new(0.6, 0.0, 0.0);
        let shift = vec![Some(t); w * h];
        let layers = [
            SplatLayer {
                index: 1,
                weight: 0.3,
                sigma_mm: 0.35,
                depth_mm: 0.2,
            },
            SplatLayer {
                index: 6,
                weight: 0.2,
                sigma_mm: 0.9,
                depth_mm: 1.2,
            },
        ];
        let model = LayerModel::from_fn(w, h, |_, _| layers.to_vec());
        let opts = RenderOptions {
            truncate_sigmas: 5.0,
            sigma_bin_ratio: 1.05,
            coarse_sigma_px: f64::INFINITY,
            ..Default::default()
        };
        let out = render_global(&surface, &irradiance, &shift, &model, &opts).unwrap();
        let row = 30;
        let mut worst = 0.0f64;
        let peak = 2.0 * 0.1 * (0.3 * normal_pdf(0.0, 0.35) + 0.2 * normal_pdf(0.0, 0.9));
        for x in 5..w - 5 {
            let s = (x as f64 - line as f64) * pitch;
            let want: f64 = layers
                .iter()
                .map(|l| {
                    let mu = f64::from(l.depth_mm) * t.x;
                    f64::from(l.weight) * 2.0 * pitch * normal_pdf(s - mu, f64::from(l.sigma_mm))
                })
                .sum();
            let got = f64::from(out[row * w + x][1]);
            worst = worst.max((got - want).abs() / peak);
        }
        // Discretisation of a 0.35 mm Gaussian on a 0.1 mm grid and sigma binning: < 2 % of the peak.
        assert!(worst < 0.02, "worst relative error {worst}");
    }

    #[test]
    fn flux_is_conserved_and_the_homogeneous_model_averages() {
        let (w, h) = (40, 40);
        let surface = plane(w, h, 0.2);
        let mut irradiance = vec![0.0f32; w * h];
        irradiance[20 * w + 20] = 1.0;
        let model = LayerModel::from_fn(w, h, |i, c| {
            vec![SplatLayer {
                index: 0,
                weight: 0.1 * (1 + c + i % 2) as f32,
                sigma_mm: 0.5,
                depth_mm: 0.0,
            }]
        });
        let shift = vec![Some(Vector3::zeros()); w * h];
        let out = render_global(
            &surface,
            &irradiance,
            &shift,
            &model,
            &RenderOptions::default(),
        )
        .unwrap();
        // Total re-emitted flux = w * E * dA, radiance integrates back over the area.
        let flux: f64 = out.iter().map(|p| f64::from(p[0]) * 0.04).sum();
        assert!((flux - 0.1 * 0.04).abs() < 1e-6, "{flux}");
        let homog = model.homogeneous(&vec![true; w * h], &vec![true; w * h]);
        assert!((homog.layers(5, 0).to_vec()[0].weight - 0.15).abs() < 1e-6);
        assert!((homog.layers(6, 2).to_vec()[0].weight - 0.35).abs() < 1e-6);
    }

    /// `mean_layers` equals a map of sums per layer index, added pixel by pixel in order (the
    /// rule it had been written as), bit for bit: sparse and repeated indices, pixels without
    /// layers, zero weights, averaged over a random subset, across several of its parallel runs.
    #[test]
    fn mean_layers_equal_a_map_of_sums_in_pixel_order() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(17);
        let (w, h) = (300, 130);
        let drawn: Vec<[Vec<SplatLayer>; 3]> = (0..w * h)
            .map(|_| {
                std::array::from_fn(|_| {
                    (0..rng.gen_range(0..4))
                        .map(|_| SplatLayer {
                            index: [0u16, 1, 2, 7, 40, 41, 300][rng.gen_range(0..7)],
                            weight: if rng.gen_bool(0.1) {
                                0.0
                            } else {
                                rng.gen_range(0.0..2.0)
                            },
                            sigma_mm: rng.gen_range(0.01..3.0),
                            depth_mm: rng.gen_range(0.0..1.5),
                        })
                        .collect()
                })
            })
            .collect();
        let model = LayerModel::from_fn(w, h, |i, c| drawn[i][c].clone());
        let over: Vec<bool> = (0..w * h).map(|_| rng.gen_bool(0.7)).collect();
        let mut sums: [std::collections::BTreeMap<u16, (f64, f64, f64)>; 3] = Default::default();
        let mut count = 0usize;
        for i in (0..w * h).filter(|&i| over[i]) {
            count += 1;
            for (c, acc) in sums.iter_mut().enumerate() {
                for l in model.layers(i, c) {
                    let e = acc.entry(l.index).or_insert((0.0, 0.0, 0.0));
                    let w = f64::from(l.weight);
                    e.0 += w;
                    e.1 += w * f64::from(l.sigma_mm);
                    e.2 += w * f64::from(l.depth_mm);
                }
            }
        }
        let want: [Vec<SplatLayer>; 3] = std::array::from_fn(|c| {
            sums[c]
                .iter()
                .filter(|(_, v)| v.0 > 0.0)
                .map(|(&index, &(w, ws, wd))| SplatLayer {
                    index,
                    weight: (w / count as f64) as f32,
                    sigma_mm: (ws / w) as f32,
                    depth_mm: (wd / w) as f32,
                })
                .collect()
        });
        let got = model.mean_layers(&over);
        assert_eq!(got[0].len(), 7);
        for c in 0..3 {
            let bits = |ls: &[SplatLayer]| -> Vec<(u16, u32, u32, u32)> {
                ls.iter()
                    .map(|l| {
                        let b = (
                            l.weight.to_bits(),
                            l.sigma_mm.to_bits(),
                            l.depth_mm.to_bits(),
                        );
                        (l.index, b.0, b.1, b.2)
                    })
                    .collect()
            };
            assert_eq!(bits(&got[c]), bits(&want[c]), "channel {c}");
        }
    }

    /// Largest absolute difference relative to the reference's peak, and the relative L2 error.
    fn difference(fast: &[[f32; 3]], reference: &[[f32; 3]]) -> (f64, f64) {
        let (mut peak, mut worst, mut num, mut den) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for (a, b) in fast.iter().zip(reference) {
            for c in 0..3 {
                let (a, b) = (f64::from(a[c]), f64::from(b[c]));
                peak = peak.max(b.abs());
                worst = worst.max((a - b).abs());
                num += (a - b) * (a - b);
                den += b * b;
            }
        }
        (worst / peak, (num / den).sqrt())
    }

    /// Property: on random scenes (sparse point sources, which show the pyramid's sub-pixel
    /// phase errors worst, and dense striped light), random per-pixel layers with sigmas from a
    /// fraction of a pixel to 30 pixels and random shifts, the pyramid agrees with the
    /// full-resolution reference within 0.5 % of the peak at every pixel and 1 % in RMS (measured:
    /// at most 0.12 % and 0.47 %; with `coarse_sigma_px = 2` the RMS reaches 1.4 %: the sub-cell
    /// position of a source is lost on a coarse level, which changes its variance by up to
    /// `f^2/4`, small against the blurred `(2 f c)^2` only when `c` is large enough).
    #[test]
    fn pyramid_matches_the_full_resolution_reference() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        for case in 0..4 {
            let (w, h, pitch) = (72 + 9 * case, 60 + 7 * case, 0.2);
            let surface = plane(w, h, pitch);
            let sparse = case % 2 == 0;
            let irradiance: Vec<f32> = (0..w * h)
                .map(|i| {
                    let lit = if sparse {
                        rng.gen_bool(0.004)
                    } else {
                        (i % w) % 9 < 2
                    };
                    if lit { rng.gen_range(0.2..1.0) } else { 0.0 }
                })
                .collect();
            // Drawn in pixel then channel order, as rows of the model.
            let rows: Vec<Vec<SplatLayer>> = (0..w * h * 3)
                .map(|_| {
                    (0..rng.gen_range(1..=3))
                        .map(|k| SplatLayer {
                            index: k,
                            weight: rng.gen_range(0.01..1.0),
                            // log-uniform over 0.05..6 mm = 0.25..30 px
                            sigma_mm: (0.05f32.ln() + rng.gen_range(0.0..1.0f32) * 120f32.ln())
                                .exp(),
                            depth_mm: rng.gen_range(0.0..1.5),
                        })
                        .collect()
                })
                .collect();
            let model = LayerModel::from_fn(w, h, |i, c| rows[i * 3 + c].clone());
            let t = Vector3::new(rng.gen_range(-0.8..0.8), rng.gen_range(-0.8..0.8), 0.0);
            let shift = vec![Some(t); w * h];
            let fast_opts = RenderOptions::default();
            let reference_opts = RenderOptions {
                coarse_sigma_px: f64::INFINITY,
                ..RenderOptions::default()
            };
            let fast = render_global(&surface, &irradiance, &shift, &model, &fast_opts).unwrap();
            let reference =
                render_global(&surface, &irradiance, &shift, &model, &reference_opts).unwrap();
            let (worst, rms) = difference(&fast, &reference);
            assert!(
                worst < 0.005 && rms < 0.01,
                "case {case}: worst {worst:.5} of the peak, rms {rms:.5}"
            );
        }
    }

    /// The batched renderer gives every frame exactly (bit for bit) what `render_global`
    /// gives it alone: frames lit in different places (a pixel unlit in one frame lit in
    /// another, NaN and negative irradiance among them), random per-pixel layers, shifts that
    /// vary per pixel and some pixels without a shift, on the pyramid and at full resolution,
    /// with a batch of one frame and of several.
    #[test]
    fn many_frames_render_as_each_frame_alone() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(29);
        let (w, h, pitch) = (53, 41, 0.2);
        let surface = plane(w, h, pitch);
        let frames: Vec<Vec<f32>> = (0..5)
            .map(|f| {
                (0..w * h)
                    .map(|i| match (i % w + f) % 7 {
                        0 => f32::NAN,
                        1 => -0.3,
                        2 | 3 => 0.0,
                        _ => rng.gen_range(0.1..1.0),
                    })
                    .collect()
            })
            .collect();
        let rows: Vec<Vec<SplatLayer>> = (0..w * h * 3)
            .map(|_| {
                (0..rng.gen_range(0..=3))
                    .map(|k| SplatLayer {
                        index: k,
                        weight: rng.gen_range(0.0..1.0),
                        sigma_mm: (0.05f32.ln() + rng.gen_range(0.0..1.0f32) * 120f32.ln()).exp(),
                        depth_mm: rng.gen_range(0.0..1.5),
                    })
                    .collect()
            })
            .collect();
        let model = LayerModel::from_fn(w, h, |i, c| rows[i * 3 + c].clone());
        let shift: Vec<Option<Vector3<f64>>> = (0..w * h)
            .map(|_| {
                rng.gen_bool(0.95)
                    .then(|| Vector3::new(rng.gen_range(-0.8..0.8), rng.gen_range(-0.8..0.8), 0.0))
            })
            .collect();
        for opts in [
            RenderOptions::default(),
            RenderOptions {
                coarse_sigma_px: f64::INFINITY,
                ..RenderOptions::default()
            },
        ] {
            let alone: Vec<Vec<[f32; 3]>> = frames
                .iter()
                .map(|e| reference_render_global(&surface, e, &shift, &model, &opts))
                .collect();
            assert!(alone.iter().flatten().flatten().any(|&v| v > 0.0));
            let refs: Vec<&[f32]> = frames.iter().map(Vec::as_slice).collect();
            let many = render_global_many(&surface, &refs, &shift, &model, &opts).unwrap();
            assert_eq!(many, alone);
            // Splats found in passes of a few sources (several passes, some parts empty).
            for chunk in [1, 3, 37, 500] {
                let passes = render_global_many_by(&surface, &refs, &shift, &model, &opts, chunk);
                assert_eq!(passes.unwrap(), alone, "passes of {chunk} sources");
            }
            for f in 0..frames.len() {
                let one = render_global_many(&surface, &refs[f..f + 1], &shift, &model, &opts);
                assert_eq!(one.unwrap()[0], alone[f], "frame {f} alone");
            }
        }
    }

    #[test]
    fn size_mismatch_is_an_error() {
        let surface = plane(4, 4, 1.0);
        let model = LayerModel::from_fn(4, 4, |_, _| Vec::new());
        let err = render_global(
            &surface,
            &[0.0; 3],
            &[None; 16],
            &model,
            &RenderOptions::default(),
        );
        assert!(matches!(
            err,
            Err(RenderError::SizeMismatch {
                what: "irradiance",
                ..
            })
        ));
    }

    /// `from_fn` over several runs of pixels (written in parallel into untouched memory): every
    /// row holds exactly `f`'s layers; a row for which `f` gives fewer layers on its second call
    /// than on its first keeps empty layers in the slots it did not fill.
    #[test]
    fn from_fn_rows_hold_their_layers_across_runs() {
        let layer = |k: usize| SplatLayer {
            index: (k % 11) as u16,
            weight: k as f32,
            sigma_mm: 0.5,
            depth_mm: 0.25,
        };
        let count = |k: usize| (k * 7 + k / 5) % 4;
        // 3 runs of 4096 pixels and a part run.
        let (w, h) = (130, 100);
        let model = LayerModel::from_fn(w, h, |i, c| {
            let k = i * 3 + c;
            (0..count(k)).map(move |j| layer(k * 4 + j))
        });
        for i in 0..w * h {
            for c in 0..3 {
                let k = i * 3 + c;
                let want: Vec<SplatLayer> = (0..count(k)).map(|j| layer(k * 4 + j)).collect();
                assert_eq!(model.layers(i, c).to_vec(), want, "pixel {i} channel {c}");
            }
        }
        // Pixel 4100 (second run), channel 1: two layers counted, one written.
        let calls = std::sync::atomic::AtomicUsize::new(0);
        let short = LayerModel::from_fn(w, h, |i, c| {
            let n = if (i, c) == (4100, 1) {
                2 - calls
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed)
                    .min(1)
            } else {
                0
            };
            (0..n).map(layer)
        });
        let empty = SplatLayer {
            index: 0,
            weight: 0.0,
            sigma_mm: 0.0,
            depth_mm: 0.0,
        };
        assert_eq!(short.layers(4100, 1).to_vec(), [layer(0), empty]);
        assert!(short.layers(4100, 0).is_empty() && short.layers(4101, 1).is_empty());
    }

    /// `from_shapes` against the same rows written out one by one (`from_fn`): rows of every
    /// source (empty, own layers, a shape by key with the row's scale, shapes of no layers) over
    /// three runs of pixels, each key's shape stored once per run, each scaled weight rounded
    /// once from the shape's `f64` weight; a band of rows cut from it holds the same rows.
    #[test]
    fn shared_shape_rows_equal_the_rows_written_out() {
        let shape = |key: u32| -> Vec<ShapeLayer> {
            (0..key % 5)
                .map(|j| ShapeLayer {
                    index: j as u16,
                    weight: 0.1 + f64::from(key) / 3.0 + f64::from(j),
                    sigma_mm: 0.5 + j as f32,
                    depth_mm: 0.01 * key as f32,
                })
                .collect()
        };
        let (w, h) = (130, 70);
        let owned: Vec<Vec<SplatLayer>> = (0..w * h * 3)
            .map(|k| {
                (0..k % 3)
                    .map(|j| SplatLayer {
                        index: 9,
                        weight: k as f32,
                        sigma_mm: 2.0,
                        depth_mm: j as f32,
                    })
                    .collect()
            })
            .collect();
        let key_and_scale = |k: usize| (((k / 7) % 13) as u32, 1.0 + k as f64 / 1e3);
        let model = LayerModel::from_shapes(
            w,
            h,
            |i, c| {
                let k = i * 3 + c;
                match k % 4 {
                    0 => RowSource::Empty,
                    1 => RowSource::Own(RowLayers::Own(&owned[k])),
                    _ => {
                        let (key, scale) = key_and_scale(k);
                        RowSource::Shape { key, scale }
                    }
                }
            },
            shape,
        );
        let want = LayerModel::from_fn(w, h, |i, c| {
            let k = i * 3 + c;
            let (key, scale) = key_and_scale(k);
            match k % 4 {
                0 => Vec::new(),
                1 => owned[k].clone(),
                _ => shape(key)
                    .iter()
                    .map(|s| SplatLayer {
                        index: s.index,
                        weight: (s.weight * scale) as f32,
                        sigma_mm: s.sigma_mm,
                        depth_mm: s.depth_mm,
                    })
                    .collect(),
            }
        });
        assert_eq!(model, want);
        assert_eq!(model.layer_count(), want.layer_count());
        assert!(model.all_layers().eq(want.all_layers()));
        assert!(model.row_lens().eq(want.row_lens()));
        let all_shapes: usize = (0..13).map(|key| shape(key).len()).sum();
        assert_eq!(
            model.shapes.len(),
            3 * all_shapes,
            "each run stores every shape once"
        );
        let band = model.rows(20..45);
        assert_eq!((band.width, band.height), (w, 25));
        for i in 0..w * 25 {
            for c in 0..3 {
                assert_eq!(band.layers(i, c), model.layers(20 * w + i, c));
            }
        }
    }

    /// A shape longer than a scaled row can index (`u16` layers) is written out as the row's own
    /// layers, scaled: same layers, nothing dropped.
    #[test]
    fn a_shape_too_long_to_share_is_written_out() {
        let long = usize::from(u16::MAX) + 2;
        let shape = |_: ()| {
            (0..long).map(|j| ShapeLayer {
                index: (j % 7) as u16,
                weight: 1.0 + j as f64,
                sigma_mm: 1.0,
                depth_mm: 0.0,
            })
        };
        let model = LayerModel::from_shapes(
            2,
            1,
            |i, _| match i {
                0 => RowSource::Shape {
                    key: (),
                    scale: 0.5,
                },
                _ => RowSource::Empty,
            },
            shape,
        );
        for c in 0..3 {
            let row = model.layers(0, c);
            assert!(matches!(row, RowLayers::Own(_)));
            assert_eq!(row.len(), long);
            assert!(row.iter().zip(shape(())).all(|(l, s)| l == s.scaled(0.5)));
            assert!(model.layers(1, c).is_empty());
        }
    }

    /// `fill_empty` against the copy it replaces: `from_fn` giving each empty row the filler's
    /// layers. Rows of 0..3 layers from a small LCG (so empty rows sit at the start, the end and
    /// in runs), filled where a pixel is "on the surface".
    #[test]
    fn fill_empty_equals_the_copying_fill() {
        let layer = |k: u32| SplatLayer {
            index: (k % 7) as u16,
            weight: k as f32 * 0.25,
            sigma_mm: 1.0 + k as f32,
            depth_mm: 0.1 * k as f32,
        };
        let mean: [Vec<SplatLayer>; 3] = [vec![layer(100)], vec![layer(200), layer(201)], vec![]];
        for seed in 0..20u32 {
            let (w, h) = (7, 5);
            let mut state = seed.wrapping_mul(2_654_435_761).wrapping_add(1);
            let mut next = || {
                state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                state >> 16
            };
            let counts: Vec<u32> = (0..w * h * 3).map(|_| next() % 4).collect();
            let on: Vec<bool> = (0..w * h).map(|_| next() % 3 != 0).collect();
            let rows = |i: usize, c: usize| {
                let k = i * 3 + c;
                (0..counts[k]).map(move |j| layer(k as u32 * 4 + j))
            };
            let mut model = LayerModel::from_fn(w, h, rows);
            let want = LayerModel::from_fn(w, h, |i, c| {
                let own: Vec<SplatLayer> = model.layers(i, c).to_vec();
                if own.is_empty() && on[i] {
                    mean[c].clone()
                } else {
                    own
                }
            });
            model.fill_empty(|i, c| on[i].then_some(mean[c].as_slice()));
            assert_eq!(model, want, "seed {seed}");
        }
    }
}
