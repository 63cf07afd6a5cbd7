//! Noise-free rendering of the camera image under one projector: per sub-sample illumination
//! (projector coordinates, irradiance, shadows), the direct component (surface reflection) and
//! the global component (subsurface transport), in linear camera values.
//!
//! Conventions
//! - Camera values: linear, 1 = saturation, before noise and quantisation (`camera::GAIN`).
//! - Direct light is colourless (specular reflection of white light, or a grey print); global
//!   light has three channels.
//! - A sub-sample is lit when it faces the projector, projects inside its image and the segment to
//!   the projector centre is free (shadow rays are traced per sub-sample only near shadow edges).

use mlsss_core::capture::Pattern;
use nalgebra::Vector3;
use rayon::prelude::*;

use super::camera::{CameraModel, GAIN};
use super::complement_frames::{self, Recipe};
use super::projector::{EmissionField, Illumination, ProjectorModel};
use super::scene::{GeometryBuffer, SurfaceSample};
use super::skin_optics::SKIN_INDEX;
use super::subjects::Subject;
use super::subsurface_transport::{EntrySample, SubsurfaceKernel, SubsurfaceOperator};
use super::surface_reflection::{DiffuseExit, SKIN_ROUGHNESS, lambert_brdf, specular_brdf};

/// Everything fixed for a capture: booth devices, subject and what the camera sees.
pub struct Scene {
    pub camera: CameraModel,
    pub projectors: Vec<ProjectorModel>,
    pub subject: Subject,
    pub geometry: GeometryBuffer,
}

/// Noise-free camera values of one frame.
#[derive(Debug, Clone)]
pub struct FrameRadiance {
    /// Direct (surface) component, one value per pixel.
    pub direct: Vec<f32>,
    /// Global (subsurface) component, RGB per pixel; `None` where the subject carries no light
    /// under its surface (not skin: a chessboard), so the frame holds, derives and sums no
    /// zeros for it.
    pub global: Option<Vec<[f32; 3]>>,
}

impl FrameRadiance {
    /// A black frame of `pixels` pixels.
    pub fn black(pixels: usize) -> Self {
        Self {
            direct: vec![0.0; pixels],
            global: None,
        }
    }

    /// The global component of pixel `i` (zero without one).
    pub fn global_at(&self, i: usize) -> [f32; 3] {
        self.global.as_ref().map_or([0.0; 3], |g| g[i])
    }

    /// Direct + global, RGB, of every pixel.
    pub fn totals(&self) -> Vec<[f32; 3]> {
        match &self.global {
            Some(global) => self
                .direct
                .iter()
                .zip(global)
                .map(|(&d, g)| g.map(|g| d + g))
                .collect(),
            None => self.direct.iter().map(|&d| [d; 3]).collect(),
        }
    }
}

/// One projector's light transport into the scene: precomputed illumination geometry and
/// (skin subjects) subsurface transport, from which its frames are rendered.
pub struct ProjectorTransport<'a> {
    pub k: usize,
    scene: &'a Scene,
    sub_uv: Vec<[f64; 2]>,
    /// Irradiance per unit emitted level (0 when unlit).
    sub_irradiance: Vec<f32>,
    /// Camera value per unit irradiance reflected at the surface.
    sub_reflect: Vec<f32>,
    /// Truth: (u, v, lit) of each pixel centre.
    pub coords: Vec<[f32; 3]>,
    /// Camera value per unit exitance at each pixel.
    exit_factor: Vec<f32>,
    operator: Option<SubsurfaceOperator<'a>>,
}

impl<'a> ProjectorTransport<'a> {
    /// Prepares projector `k`; `kernel` is the subsurface transport (skin subjects only).
    pub fn new(scene: &'a Scene, k: usize, kernel: Option<&'a SubsurfaceKernel>) -> Self {
        let geo = &scene.geometry;
        let proj = &scene.projectors[k];
        let (w, h) = (geo.width as usize, geo.height as usize);
        let spp = geo.spp();
        // Shadows at pixel centres first; sub-samples are traced only where these disagree.
        let centre_shadow = centre_shadows(scene, proj);
        let per_pixel: Vec<PixelLight> = (0..w * h)
            .into_par_iter()
            .map(|i| pixel_light(scene, proj, &centre_shadow, i))
            .collect();
        let mut view = Self {
            k,
            scene,
            sub_uv: Vec::with_capacity(w * h * spp),
            sub_irradiance: Vec::with_capacity(w * h * spp),
            sub_reflect: Vec::with_capacity(w * h * spp),
            coords: Vec::with_capacity(w * h),
            exit_factor: vec![0.0; w * h],
            operator: None,
        };
        for pixel in per_pixel {
            view.sub_uv.extend(pixel.uv);
            view.sub_irradiance.extend(pixel.irradiance);
            view.sub_reflect.extend(pixel.reflect);
            view.coords.push(pixel.coords);
        }
        if let (true, Some(kernel)) = (scene.subject.is_skin(), kernel) {
            let entries = subsurface_entries(geo, proj);
            view.exit_factor = exit_factors(scene, &entries);
            view.operator = Some(SubsurfaceOperator::new(kernel, w, h, &entries));
        }
        view
    }

    /// Renders a batch of emitted light fields (one per frame).
    pub fn render(&self, emissions: &[EmissionField]) -> Vec<FrameRadiance> {
        let geo = &self.scene.geometry;
        let (n, spp, frames) = (geo.pixels(), geo.spp(), emissions.len());
        let mut direct = vec![0.0f32; n * frames];
        // Pixel `i`'s direct light into `d` and, for the subsurface operator, the flux entering
        // the skin into `phi` (none without an operator: not skin).
        let light = |i: usize, d: &mut [f32], mut phi: Option<&mut [f32]>| {
            // Written before they are read: a fresh zeroed allocation read first maps the
            // shared zero page, and the first write then copies it and flushes the other
            // core's TLB, page by page (a fifth of a calibration pose's CPU time).
            d.fill(0.0);
            if let Some(phi) = phi.as_deref_mut() {
                phi.fill(0.0);
            }
            let Some(first) = emissions.first() else {
                return;
            };
            for s in i * spp..(i + 1) * spp {
                let irr = self.sub_irradiance[s];
                if irr <= 0.0 {
                    continue;
                }
                let [u, v] = self.sub_uv[s];
                // Located once, read for every frame (all fields share one layout).
                let position = first.position(u, v);
                let refl = self.sub_reflect[s] / spp as f32;
                let area = geo.subs[s].map_or(0.0, |x| x.area_mm2) as f32;
                for (f, emission) in emissions.iter().enumerate() {
                    let e = irr * emission.at_position(&position);
                    d[f] += refl * e;
                    if let Some(phi) = phi.as_deref_mut() {
                        phi[f] += area * e;
                    }
                }
            }
        };
        let Some(operator) = &self.operator else {
            direct
                .par_chunks_mut(frames)
                .enumerate()
                .for_each(|(i, d)| light(i, d, None));
            return frames_from_pixel_major(&direct, None, n, frames);
        };
        let mut flux = vec![0.0f32; n * frames];
        direct
            .par_chunks_mut(frames)
            .zip(flux.par_chunks_mut(frames))
            .enumerate()
            .for_each(|(i, (d, phi))| light(i, d, Some(phi)));
        let exitance = operator.apply(&flux, frames);
        // Not needed past the operator: freed before the frames are built (batch peak memory).
        drop(flux);
        frames_from_pixel_major(&direct, Some((&exitance, &self.exit_factor)), n, frames)
    }

    /// Renders a batch of patterns, deriving each complement frame from the batch's white and
    /// its rendered partner instead of rendering it (`complement_frames`): the Gray-code
    /// inverses and half the high-frequency shifts cost no subsurface sums.
    pub fn render_patterns(&self, patterns: &[Pattern]) -> Vec<FrameRadiance> {
        let proj = self.projector();
        let recipes = complement_frames::recipes(patterns);
        let emissions: Vec<EmissionField> = patterns
            .iter()
            .zip(&recipes)
            .filter(|(_, r)| **r == Recipe::Render)
            .map(|(p, _)| proj.emission(p))
            .collect();
        let mut rendered = self.render(&emissions).into_iter();
        let white_plus_black = (1.0 + proj.response(0.0) / proj.response(1.0)) as f32;
        let mut frames: Vec<Option<FrameRadiance>> = recipes
            .iter()
            .map(|r| match r {
                Recipe::Render => rendered.next(),
                Recipe::Complement { .. } => None,
            })
            .collect();
        for (i, r) in recipes.iter().enumerate() {
            if let Recipe::Complement { of, white } = *r {
                frames[i] = match (&frames[white], &frames[of]) {
                    (Some(w), Some(f)) => Some(complement_frames::derive(w, f, white_plus_black)),
                    _ => None,
                };
            }
        }
        let pixels = self.scene.geometry.pixels();
        frames
            .into_iter()
            .map(|f| f.unwrap_or_else(|| FrameRadiance::black(pixels)))
            .collect()
    }

    /// The projector this view belongs to.
    pub fn projector(&self) -> &ProjectorModel {
        &self.scene.projectors[self.k]
    }
}

/// The `frames` frames of `n` pixels from a batch's pixel-major sums: `direct[i * frames + f]`
/// and, for the global part, `exitance[(i * 3 + c) * frames + f]` times the pixel's camera value
/// per unit exitance `exit_factor[i]` (the frames have no global part without them).
///
/// Transposed a block of [`TRANSPOSE_BLOCK`] pixels at a time, every frame's part of the block in
/// turn: the block's sums stay in the core's cache while each frame reads them. Frame by frame
/// over the whole image instead, every read of one frame's value pulled a cache line of which
/// that frame used 4 bytes (the transposition was 13 % of a calibration pose's CPU time, perf).
fn frames_from_pixel_major(
    direct: &[f32],
    global: Option<(&[f32], &[f32])>,
    n: usize,
    frames: usize,
) -> Vec<FrameRadiance> {
    let mut out: Vec<FrameRadiance> = (0..frames)
        .map(|_| FrameRadiance {
            direct: vec![0.0; n],
            global: global.map(|_| vec![[0.0; 3]; n]),
        })
        .collect();
    // Per block of pixels, that block's part of every frame.
    let mut blocks: Vec<Vec<FramePart>> = (0..n.div_ceil(TRANSPOSE_BLOCK))
        .map(|_| Vec::with_capacity(frames))
        .collect();
    for frame in &mut out {
        let mut global_parts = frame.global.as_mut().map(|g| g.chunks_mut(TRANSPOSE_BLOCK));
        let parts = frame
            .direct
            .chunks_mut(TRANSPOSE_BLOCK)
            .map(|d| (d, global_parts.as_mut().and_then(Iterator::next)));
        for (block, part) in blocks.iter_mut().zip(parts) {
            block.push(part);
        }
    }
    blocks.into_par_iter().enumerate().for_each(|(b, parts)| {
        let first = b * TRANSPOSE_BLOCK;
        for (f, (d, g)) in parts.into_iter().enumerate() {
            for (j, value) in d.iter_mut().enumerate() {
                *value = direct[(first + j) * frames + f];
            }
            let (Some(g), Some((exitance, exit_factor))) = (g, global) else {
                continue;
            };
            for (j, value) in g.iter_mut().enumerate() {
                let i = first + j;
                let k = exit_factor[i];
                *value = [0, 1, 2].map(|c| k * exitance[(i * 3 + c) * frames + f]);
            }
        }
    });
    out
}

/// One frame's direct and (with a subsurface operator) global values over one block of pixels.
type FramePart<'a> = (&'a mut [f32], Option<&'a mut [[f32; 3]]>);

/// Pixels per block of [`frames_from_pixel_major`]: a block's sums of a
/// 40-frame batch take 256 x 40 x 16 bytes, 160 KB, within a core's L2 cache.
const TRANSPOSE_BLOCK: usize = 256;

/// Illumination of one pixel's sub-samples (in sub-sample order) and its centre's truth.
struct PixelLight {
    uv: Vec<[f64; 2]>,
    irradiance: Vec<f32>,
    reflect: Vec<f32>,
    coords: [f32; 3],
}

/// Whether each pixel centre is shadowed from the projector (false where the camera misses).
fn centre_shadows(scene: &Scene, proj: &ProjectorModel) -> Vec<bool> {
    scene
        .geometry
        .centre
        .par_iter()
        .map(|hit| {
            hit.is_some_and(|hit| {
                scene
                    .subject
                    .shadowed(&hit.point, &hit.normal, &proj.centre)
            })
        })
        .collect()
}

/// The shared shadow state of pixel `i` when it and its 8 neighbours' centres agree (its
/// sub-samples then need no shadow rays); `None` near a shadow edge.
fn uniform_shadow(centre_shadow: &[bool], w: usize, h: usize, i: usize) -> Option<bool> {
    let (x, y) = (i % w, i / w);
    let s = centre_shadow[i];
    for ny in y.saturating_sub(1)..(y + 2).min(h) {
        for nx in x.saturating_sub(1)..(x + 2).min(w) {
            if centre_shadow[ny * w + nx] != s {
                return None;
            }
        }
    }
    Some(s)
}

/// Sub-sample illumination and centre truth of pixel `i`.
fn pixel_light(
    scene: &Scene,
    proj: &ProjectorModel,
    centre_shadow: &[bool],
    i: usize,
) -> PixelLight {
    let geo = &scene.geometry;
    let (w, h) = (geo.width as usize, geo.height as usize);
    let spp = geo.spp();
    let known = uniform_shadow(centre_shadow, w, h, i);
    let mut light = PixelLight {
        uv: Vec::with_capacity(spp),
        irradiance: Vec::with_capacity(spp),
        reflect: Vec::with_capacity(spp),
        coords: [0.0; 3],
    };
    for (s, sample) in geo.subs_of(i).iter().enumerate() {
        match sample.and_then(|sample| sub_sample_light(scene, proj, &sample, i * spp + s, known)) {
            Some((ill, brdf)) => {
                light.uv.push([ill.u, ill.v]);
                light.irradiance.push(ill.irradiance_per_level as f32);
                light.reflect.push((GAIN * brdf) as f32);
            }
            None => {
                light.uv.push([0.0; 2]);
                light.irradiance.push(0.0);
                light.reflect.push(0.0);
            }
        }
    }
    light.coords = centre_coords(geo, proj, centre_shadow, i);
    light
}

/// Illumination and BRDF of a sub-sample, or `None` when it is unlit (faces away, projects
/// outside the image, or is shadowed); `sub` is its index among all sub-samples. `known` is the pixel's uniform shadow state, if any; a
/// shadow ray is traced only without it.
fn sub_sample_light(
    scene: &Scene,
    proj: &ProjectorModel,
    sample: &SurfaceSample,
    sub: usize,
    known: Option<bool>,
) -> Option<(Illumination, f64)> {
    let ill = proj.illuminate(&sample.point, &sample.normal)?;
    if ill.irradiance_per_level <= 0.0 || !proj.in_image(ill.u, ill.v) {
        return None;
    }
    let shadowed = known.unwrap_or_else(|| {
        scene
            .subject
            .shadowed(&sample.point, &sample.normal, &proj.centre)
    });
    // Skin reflects specularly at its surface (the rest is subsurface); prints are Lambertian.
    let brdf = if scene.subject.is_skin() {
        specular_brdf(
            &sample.normal,
            &ill.to_light,
            &sample.to_camera,
            SKIN_INDEX,
            SKIN_ROUGHNESS,
        )
    } else {
        lambert_brdf(scene.geometry.albedo[sub] as f64)
    };
    (!shadowed).then_some((ill, brdf))
}

/// Truth `(u, v, lit)` of pixel `i`'s centre; zero where the camera misses or the projector
/// cannot reach it.
fn centre_coords(
    geo: &GeometryBuffer,
    proj: &ProjectorModel,
    centre_shadow: &[bool],
    i: usize,
) -> [f32; 3] {
    match &geo.centre[i] {
        Some(hit) => match proj.illuminate(&hit.point, &hit.normal) {
            Some(ill) => {
                let lit = ill.irradiance_per_level > 0.0
                    && proj.in_image(ill.u, ill.v)
                    && !centre_shadow[i];
                [ill.u as f32, ill.v as f32, if lit { 1.0 } else { 0.0 }]
            }
            None => [0.0; 3],
        },
        None => [0.0; 3],
    }
}

/// Where light enters the skin at each pixel (one entry per pixel surface patch), with the
/// direction to the projector and the pixel's material mix `[base, melanin, blood, stubble]`.
fn subsurface_entries(geo: &GeometryBuffer, proj: &ProjectorModel) -> Vec<Option<EntrySample>> {
    (0..geo.pixels())
        .into_par_iter()
        .map(|i| {
            let (point, normal, area) = geo.pixel_surface(i)?;
            let to_light = (proj.centre - point).normalize();
            let m = geo.materials[i];
            Some(EntrySample {
                point,
                normal,
                to_light,
                area_mm2: area,
                materials: [1.0 - m[0] - m[1] - m[2], m[0], m[1], m[2]],
            })
        })
        .collect()
}

/// Camera value per unit subsurface exitance at each pixel: the Fresnel-weighted fraction
/// leaving towards the camera, scaled by how much of the pixel the subject covers.
fn exit_factors(scene: &Scene, entries: &[Option<EntrySample>]) -> Vec<f32> {
    let geo = &scene.geometry;
    let exit = DiffuseExit::new(SKIN_INDEX);
    let eye = scene.camera.calib.extrinsics.centre();
    entries
        .iter()
        .enumerate()
        .map(|(i, e)| {
            e.map_or(0.0, |e| {
                let to_camera: Vector3<f64> = (eye - e.point).normalize();
                (GAIN * geo.coverage[i] as f64 * exit.factor(e.normal.dot(&to_camera))) as f32
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The blocked transposition gives every frame's values as reading the sums frame by frame
    /// does (the layout before it), bit for bit, over a partial last block, with and without
    /// the global part (and without one, the frames have none).
    #[test]
    fn blocked_transposition_equals_reading_frame_by_frame() {
        let (n, frames) = (2 * TRANSPOSE_BLOCK + 37, 5);
        let value = |k: usize| ((k * 7919 % 1009) as f32).sqrt() - 13.0;
        let direct: Vec<f32> = (0..n * frames).map(value).collect();
        let exitance: Vec<f32> = (0..n * 3 * frames).map(|k| value(k + 5)).collect();
        let exit_factor: Vec<f32> = (0..n).map(|i| 0.5 + value(i) / 64.0).collect();
        for global in [None, Some((exitance.as_slice(), exit_factor.as_slice()))] {
            let got = frames_from_pixel_major(&direct, global, n, frames);
            assert_eq!(got.len(), frames);
            for (f, frame) in got.iter().enumerate() {
                // Without the sums of a subsurface operator a frame holds no global part.
                assert_eq!(frame.global.as_ref().map(Vec::len), global.map(|_| n));
                for i in 0..n {
                    assert_eq!(frame.direct[i].to_bits(), direct[i * frames + f].to_bits());
                    let want = global.map_or([0.0; 3], |(ex, k)| {
                        [0, 1, 2].map(|c| k[i] * ex[(i * 3 + c) * frames + f])
                    });
                    assert_eq!(frame.global_at(i).map(f32::to_bits), want.map(f32::to_bits));
                }
            }
        }
    }
}
