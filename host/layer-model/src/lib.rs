//! The multi-layered subsurface scattering model (DESIGN section 5): slit radiance profiles, EM
//! fits of the layer model (free means as in the paper, layered means tied to depth as ours), and
//! the renderer of paper eqs. 3-5 with its baselines.

pub mod boxed_gaussian;
pub mod dipole;
pub mod em_free;
pub mod em_layered;
pub mod fit;
pub mod fit_options;
mod inline_floor;
pub mod layer_depth;
pub mod mixture;
pub mod model_file;
pub mod profiles;
pub mod relight;
pub mod render;
pub mod shading_regression;
pub mod slit_global;
pub mod spatial_prior;
pub mod surface;

#[cfg(test)]
mod chain_tests;
#[cfg(test)]
mod em_properties;
