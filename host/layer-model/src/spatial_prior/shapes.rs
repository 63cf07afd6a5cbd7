//! Layer shapes (weights relative to their sum): merging the shapes of several tiles into one
//! mixture, dropping the layers the renderer skips, and the likelihood of profiles under a shape.

use std::collections::BTreeMap;

use crate::em_layered::{self, Layer, LayeredParams};
use crate::mixture::{EmError, Profile};
use crate::render::{RenderOptions, RowLayers, SplatLayer};

/// A layer shape: weights sum to 1.
pub(super) type Shape = Vec<SplatLayer>;

/// The pixel's layers scaled to unit total weight; `None` without weight.
pub(super) fn normalised(layers: RowLayers<'_>) -> Option<Shape> {
    let total: f32 = layers.iter().map(|l| l.weight).sum();
    (total > 0.0 && total.is_finite()).then(|| {
        layers
            .iter()
            .map(|l| SplatLayer {
                weight: l.weight / total,
                ..l
            })
            .collect()
    })
}

/// Sigma bins per layer index in the merged layers' `index` code (`index * SIGMA_BINS + bin`).
pub(super) const SIGMA_BINS: u16 = 64;

/// The merged layers' identity: depth index (or rank) and sigma bin, so that layers averaged
/// across pixels by index (the homogeneous baseline) share depth and width.
fn layer_code(index: u16, bin: i32) -> u16 {
    let bin = (bin + i32::from(SIGMA_BINS / 2)).clamp(0, i32::from(SIGMA_BINS) - 1) as u16;
    index.saturating_mul(SIGMA_BINS).saturating_add(bin)
}

/// The layer index layers are merged under: one family for every depth. Layers of one sigma
/// bin at different depths merge into one at their weight-averaged depth, which keeps the first
/// moment of the shifted light (linear in depth) for every light direction; the spread of
/// shifts lost, `(z_max - z_min) |t_i|` (0.3 mm x 0.64 on the quick demo), matters only where
/// sigma is as small, below the camera pixel. Keeping the depths apart multiplies the layer
/// count by the depth indices as soon as `D > 0` (quick demo: model 76 -> 183 MB, held-out
/// render time x2.4; `subsurface::layer_depth`).
fn depth_key(_l: &SplatLayer) -> u16 {
    0
}

/// Equal-weight mixture of `shapes`, components of one family ([`depth_key`]) merged within log-sigma bins
/// (weight summed, variance moment-matched, depth weight-averaged); the merged layers' `index`
/// is [`layer_code`].
pub(super) fn merged_mixture<'a>(
    shapes: impl Iterator<Item = &'a Shape>,
    bin_ratio: f64,
) -> Option<Shape> {
    // (layer index, sigma bin) -> (weight, weight * sigma^2, weight * depth)
    let mut bins: BTreeMap<(u16, i32), (f64, f64, f64)> = BTreeMap::new();
    let mut count = 0usize;
    let log_ratio = bin_ratio.ln();
    for shape in shapes {
        count += 1;
        for l in shape {
            let sigma = f64::from(l.sigma_mm).max(1e-6);
            let bin = (sigma.ln() / log_ratio).round() as i32;
            let e = bins.entry((depth_key(l), bin)).or_insert((0.0, 0.0, 0.0));
            let w = f64::from(l.weight);
            e.0 += w;
            e.1 += w * sigma * sigma;
            e.2 += w * f64::from(l.depth_mm);
        }
    }
    if count == 0 {
        return None;
    }
    let out: Shape = bins
        .iter()
        .filter(|(_, e)| e.0 > 0.0)
        .map(|(&(index, bin), &(w, wss, wd))| SplatLayer {
            index: layer_code(index, bin),
            weight: (w / count as f64) as f32,
            sigma_mm: (wss / w).sqrt() as f32,
            depth_mm: (wd / w) as f32,
        })
        .collect();
    (!out.is_empty()).then_some(out)
}

/// `shape` without the layers whose weight is at most the renderer's default
/// `min_relative_weight` of the total, which it skips: merged shapes carry many such (the
/// full-size subject's global shape: 9-14 of 25-29 layers per channel), and storing them made
/// the model ~1.8x larger and every pass over it slower for no change in a default render. The
/// rest keep their weights (the renderer does not renormalise either), so default renders are
/// unchanged: dropping layers only raises the others' share of the smaller total.
pub(super) fn without_faint(mut shape: Shape) -> Shape {
    let floor = RenderOptions::default().min_relative_weight;
    let total: f32 = shape.iter().map(|l| l.weight).sum();
    shape.retain(|l| l.weight > floor * total);
    shape
}

/// Log-likelihood (per unit weight, averaged over profiles) of `profiles` under `shape`, each
/// layer at its own depth in units of `depth_spacing` (depth ignored when the spacing is 0, as
/// the layered fit's means are then all 0).
pub(super) fn shape_log_likelihood(
    profiles: &[Profile],
    shape: &Shape,
    depth_spacing: f64,
    wrap_images: usize,
) -> Result<f64, EmError> {
    let params = LayeredParams {
        layers: shape
            .iter()
            .map(|l| Layer {
                depth_index: if depth_spacing > 0.0 {
                    (f64::from(l.depth_mm) / depth_spacing).round().max(0.0) as usize
                } else {
                    0
                },
                weight: f64::from(l.weight),
                sigma: f64::from(l.sigma_mm),
            })
            .collect(),
        depth_spacing,
    };
    em_layered::log_likelihood(profiles, &params, wrap_images)
}
