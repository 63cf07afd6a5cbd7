//! The booth's metering step, simulated: before the scan, each projector shows white once at the
//! nominal exposure, the camera takes a frame (with its noise), and the exposure of that
//! projector's scan frames is chosen from it (`mlsss_core::capture::exposure::meter`).
//!
//! The white it meters is the projector's noise-free white of the scan itself (rendered once,
//! for its frame and for the other projectors' stray light): exposure only scales the frames
//! when they are finished, after rendering, so metering needs no render of its own.

use super::frame_render::Scene;
use mlsss_core::booth::TimingSpec;
use mlsss_core::capture::exposure::{MeteringTarget, ProjectorExposure, meter};
use mlsss_mc::NormalStream;

/// Noise stream of projector 0's metering frame, the next ones after it (apart from every scan
/// frame's stream).
const METERING_NOISE_STREAM: u64 = 0x3e7e_0000;

/// The metered exposure of projector `k` of `scene`, from its noise-free white at the nominal
/// exposure (RGB per pixel): the camera's noisy frame of it (a noise stream of its own, apart
/// from every scan frame's) is what the booth meters.
pub fn meter_projector(
    scene: &Scene,
    k: usize,
    white: &[[f32; 3]],
    timing: &TimingSpec,
    seed: u64,
) -> ProjectorExposure {
    let mut noisy: Vec<f32> = white.iter().flatten().copied().collect();
    let mut normals = NormalStream::new(seed, METERING_NOISE_STREAM + k as u64);
    scene.camera.add_noise(&mut noisy, &mut normals);
    let brightest_channel: Vec<f32> = noisy
        .chunks_exact(3)
        .map(|p| p[0].max(p[1]).max(p[2]).min(1.0))
        .collect();
    meter(
        k as u8,
        &brightest_channel,
        timing,
        &MeteringTarget::default(),
    )
}
