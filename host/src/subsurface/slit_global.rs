//! The global (subsurface) light of a slit frame, the input of the profiles.
//!
//! A slit frame of projector K holds: the direct reflection where the slit lands, the subsurface
//! light of the slit, and flat offsets from the projector's black level `b` (its "dark" pixels
//! still emit `b`) and from the other projectors' black level (stray). With the separation of the
//! white frame (`Ld`, `Lg` under level 1) and the projector's response `b + (1 - b) level`:
//!
//! `global_slit = frame - Ld (b + (1 - b) lit) - b Lg - stray`
//!
//! where `lit` is 1 when the pixel's projector coordinate falls inside a lit slit. Negative values
//! (noise) are kept: the EM clamps them at 0 itself.

use crate::capture::Pattern;

/// Inputs for one projector, per camera pixel (RGB).
#[derive(Debug, Clone, Copy)]
pub struct WhiteSeparation<'a> {
    pub direct: &'a [[f32; 3]],
    pub global: &'a [[f32; 3]],
    /// Light of the other projectors' black level present in every frame (zeros if unknown).
    pub stray: &'a [[f32; 3]],
    /// Projector black level (fraction of white).
    pub black_level: f32,
}

/// Global component of one slit frame. `coords[i]` is the projector coordinate of pixel `i`.
pub fn slit_global(
    frame: &[[f32; 3]],
    pattern: &Pattern,
    coords: &[Option<(f32, f32)>],
    white: &WhiteSeparation,
) -> Vec<[f32; 3]> {
    let b = white.black_level;
    frame
        .iter()
        .enumerate()
        .map(|(i, f)| {
            let lit = coords[i].map_or(0.0, |(u, v)| {
                pattern.value(u.round().max(0.0) as u32, v.round().max(0.0) as u32)
            });
            let level = b + (1.0 - b) * lit;
            let mut out = [0.0f32; 3];
            for (c, o) in out.iter_mut().enumerate() {
                *o = f[c] - white.direct[i][c] * level - b * white.global[i][c] - white.stray[i][c];
            }
            out
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::Axis;

    #[test]
    fn removes_direct_on_the_slit_and_the_flat_offsets() {
        // Four pixels at projector columns 0, 3, 6, 9; slit on columns 3..5.
        let coords: Vec<Option<(f32, f32)>> = (0..4).map(|k| Some((3.0 * k as f32, 0.0))).collect();
        let pattern = Pattern::Slit {
            axis: Axis::X,
            width: 3,
            period: 30,
            offset: 3,
        };
        let (b, ld, lg, stray, profile) =
            (0.02f32, 0.3f32, 0.5f32, 0.01f32, [0.05, 0.4, 0.1, 0.02]);
        let frame: Vec<[f32; 3]> = (0..4)
            .map(|k| {
                let lit = if k == 1 { 1.0 } else { 0.0 };
                let v = ld * (b + (1.0 - b) * lit) + b * lg + stray + profile[k];
                [v, v, v]
            })
            .collect();
        let white = WhiteSeparation {
            direct: &[[ld; 3]; 4],
            global: &[[lg; 3]; 4],
            stray: &[[stray; 3]; 4],
            black_level: b,
        };
        let g = slit_global(&frame, &pattern, &coords, &white);
        for k in 0..4 {
            assert!((g[k][1] - profile[k]).abs() < 1e-6, "{k}: {:?}", g[k]);
        }
    }
}
