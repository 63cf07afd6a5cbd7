//! The virtual booth: renders captures of a described booth and subject, with noise, and writes
//! the ground truth beside them (DESIGN section 6). It is the reference every accuracy figure is
//! measured against, so it is built from physics that knows nothing of the MLSSS model:
//!
//! - geometry by ray casting (`subjects`, `head`, `scene`), shadows by rays to the projectors;
//! - projectors as pinholes with response curve, black level and defocus (`projector`);
//! - surface reflection as a rough dielectric specular lobe with Fresnel (`surface_reflection`);
//! - light below the surface from Monte Carlo exit responses of layered skin (`skin_optics`,
//!   `material_maps`, `subsurface`), blended by the material maps and interpolated over the angle
//!   of incidence;
//! - a camera with distortion, shot and read noise, saturation and 12-bit codes (`camera`).

pub mod camera;
pub mod head;
pub mod material_maps;
pub mod projector;
pub mod scene;
pub mod skin_optics;
pub mod subjects;
pub mod subsurface;
pub mod surface_reflection;
