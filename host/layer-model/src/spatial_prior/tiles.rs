//! The tile grid of the fit and the prior's borrowed inputs over it: each tile's fitted shape,
//! its validation pixel, and the mixture shape of its neighbourhood.

use rayon::prelude::*;

use super::shapes::{Shape, merged_mixture, normalised};
use super::{Neighbourhood, PriorOptions};
use crate::fit::tile_pixel;
use crate::profiles::{GeometryMap, SlitSweep};
use crate::render::LayerModel;
use crate::surface::Surface;

/// The tile grid of a fit with `block x block` tiles.
#[derive(Debug, Clone, Copy)]
pub(super) struct Tiles {
    width: usize,
    height: usize,
    block: usize,
    across: usize,
    down: usize,
}

impl Tiles {
    pub(super) fn new(width: usize, height: usize, block: usize) -> Self {
        let block = block.max(1);
        Self {
            width,
            height,
            block,
            across: width.div_ceil(block),
            down: height.div_ceil(block),
        }
    }

    pub(super) fn count(&self) -> usize {
        self.across * self.down
    }

    pub(super) fn of_pixel(&self, i: usize) -> usize {
        (i / self.width / self.block) * self.across + (i % self.width) / self.block
    }
}

/// Everything the prior needs, borrowed.
pub(super) struct Inputs<'a> {
    pub(super) model: &'a LayerModel,
    pub(super) surface: &'a Surface,
    pub(super) geometries: &'a [GeometryMap],
    pub(super) sweeps: &'a [SlitSweep<'a>],
    pub(super) tiles: Tiles,
    pub(super) depth_spacing: f64,
    pub(super) opts: &'a PriorOptions,
}

impl Inputs<'_> {
    pub(super) fn lit(&self, i: usize) -> bool {
        self.surface.mask[i] && self.geometries.iter().any(|g| g.get(i).is_some())
    }

    /// The pixel the fit used for tile `t`.
    pub(super) fn fitted_pixel(&self, t: usize) -> Option<usize> {
        let tl = &self.tiles;
        tile_pixel(
            t % tl.across,
            t / tl.across,
            tl.block,
            tl.width,
            tl.height,
            &|i| self.lit(i),
        )
    }

    /// Shape of every tile and channel (from the fitted pixel's layers).
    pub(super) fn tile_shapes(&self) -> Vec<[Option<Shape>; 3]> {
        (0..self.tiles.count())
            .into_par_iter()
            .map(|t| {
                let mut out: [Option<Shape>; 3] = Default::default();
                if let Some(i) = self.fitted_pixel(t) {
                    for (c, o) in out.iter_mut().enumerate() {
                        *o = normalised(self.model.layers(i, c));
                    }
                }
                out
            })
            .collect()
    }

    /// A pixel of tile `t` no fit used, and the tile to leave out of its mixtures (the tile the
    /// validation pixel was fitted in, when that is not `t`).
    pub(super) fn validation_pixel(&self, t: usize) -> Option<(usize, Option<usize>)> {
        let tl = &self.tiles;
        let fitted = self.fitted_pixel(t)?;
        if tl.block == 1 {
            let x = fitted % tl.width;
            let right = fitted + 1;
            return (x + 1 < tl.width && self.lit(right)).then_some((right, Some(right)));
        }
        let (x0, y0) = ((t % tl.across) * tl.block, (t / tl.across) * tl.block);
        let (x1, y1) = (
            (x0 + tl.block).min(tl.width),
            (y0 + tl.block).min(tl.height),
        );
        (y0..y1)
            .rev()
            .flat_map(|y| (x0..x1).rev().map(move |x| y * tl.width + x))
            .find(|&i| i != fitted && self.lit(i))
            .map(|i| (i, None))
    }

    /// Tiles within Chebyshev radius `r` of tile `t` (itself included).
    pub(super) fn window(&self, t: usize, r: usize) -> impl Iterator<Item = usize> + '_ {
        let tl = self.tiles;
        let (tx, ty) = (t % tl.across, t / tl.across);
        let (x0, x1) = (tx.saturating_sub(r), (tx + r).min(tl.across - 1));
        let (y0, y1) = (ty.saturating_sub(r), (ty + r).min(tl.down - 1));
        (y0..=y1).flat_map(move |y| (x0..=x1).map(move |x| y * tl.across + x))
    }
}

/// The mixture shape of tile `t` over `hood`, leaving out tile `exclude`.
pub(super) fn hood_shape(
    inputs: &Inputs,
    shapes: &[[Option<Shape>; 3]],
    global: &[Option<Shape>; 3],
    t: usize,
    c: usize,
    hood: Neighbourhood,
    exclude: Option<usize>,
) -> Option<Shape> {
    match hood {
        Neighbourhood::Global => global[c].clone(),
        Neighbourhood::Radius(r) => merged_mixture(
            inputs
                .window(t, r)
                .filter(|&s| Some(s) != exclude)
                .filter_map(|s| shapes[s][c].as_ref()),
            inputs.opts.sigma_bin_ratio,
        ),
    }
}
