//! The booth's metering step, simulated: before the scan, each projector shows white once at the
//! nominal exposure, the camera takes a frame (with its noise), and the exposure of that
//! projector's scan frames is chosen from it (`mlsss_core::capture::exposure::meter`).
//!
//! The noise-free whites are returned too: the scan needs every white for the other projectors'
//! stray light, and rendering them here saves rendering them again.

use rand::SeedableRng;
use rand_pcg::Pcg64;

use super::frame_render::{ProjectorTransport, Scene};
use super::subsurface_transport::SubsurfaceKernel;
use mlsss_core::booth::TimingSpec;
use mlsss_core::capture::Pattern;
use mlsss_core::capture::exposure::{MeteringTarget, ProjectorExposure, meter};

/// Seed offset of the metering frames' noise (apart from every scan frame's stream).
const METERING_NOISE_STREAM: u64 = 0x3e7e_0000;

/// Each projector's metered exposure and its noise-free white at the nominal exposure (RGB).
pub struct Metering {
    pub exposure: Vec<ProjectorExposure>,
    pub whites: Vec<Vec<[f32; 3]>>,
}

/// Meters every projector of `scene` (`kernel`: the subject's subsurface transport).
pub fn meter_projectors(
    scene: &Scene,
    kernel: Option<&SubsurfaceKernel>,
    timing: &TimingSpec,
    seed: u64,
) -> Metering {
    let target = MeteringTarget::default();
    let mut exposure = Vec::new();
    let mut whites = Vec::new();
    for k in 0..scene.projectors.len() {
        let view = ProjectorTransport::new(scene, k, kernel);
        let white: Vec<[f32; 3]> = view
            .render(&[scene.projectors[k].emission(&Pattern::White)])
            .first()
            .map(|f| (0..f.direct.len()).map(|i| f.total(i)).collect())
            .unwrap_or_default();
        let mut noisy: Vec<f32> = white.iter().flatten().copied().collect();
        let mut rng = Pcg64::seed_from_u64(seed ^ (METERING_NOISE_STREAM + k as u64));
        scene.camera.add_noise(&mut noisy, &mut rng);
        let brightest_channel: Vec<f32> = noisy
            .chunks_exact(3)
            .map(|p| p[0].max(p[1]).max(p[2]).min(1.0))
            .collect();
        exposure.push(meter(k as u8, &brightest_channel, timing, &target));
        whites.push(white);
    }
    Metering { exposure, whites }
}
