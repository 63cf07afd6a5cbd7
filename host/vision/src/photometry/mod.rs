//! Photometry: projector response calibration, direct/global separation and photometric stereo
//! (DESIGN section 4, stages 4 and 5).

pub mod dichromatic;
pub mod image_set;
pub mod kernel_leak;
pub mod lobe_direct;
pub mod mat_file;
pub mod normal_fusion;
pub mod photometric_stereo;
pub mod ps_scene;
pub mod response;
pub mod separation;
pub mod slit_leak;
pub mod specular_ps;
#[cfg(test)]
mod test_scenes;
pub mod transmission_ps;
