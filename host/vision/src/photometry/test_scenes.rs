//! Scenes shared by the photometric-stereo solvers' tests: distant lights in a ring around the
//! view axis and the normals of a sphere cap seen from above.

use nalgebra::Vector3;

use super::photometric_stereo::{DirectionalLights, LightSample};

/// Four white lights `tilt_deg` off the view axis (+z), a quarter turn apart from `phase_rad`,
/// about as the booth's projectors stand.
pub fn ring_of_four_lights(tilt_deg: f64, phase_rad: f64) -> DirectionalLights {
    let tilt = tilt_deg.to_radians();
    let lights = (0..4)
        .map(|k| {
            let phi = std::f64::consts::FRAC_PI_2 * k as f64 + phase_rad;
            LightSample {
                direction: Vector3::new(tilt.sin() * phi.cos(), tilt.sin() * phi.sin(), tilt.cos()),
                irradiance: [1.0; 3],
            }
        })
        .collect();
    DirectionalLights {
        lights,
        view: Vector3::z(),
    }
}

/// Normals of a sphere cap seen from above on a `size` x `size` grid (row-major), up to
/// `max_deg` from the view axis along each image axis.
pub fn sphere_cap_normals(size: u32, max_deg: f64) -> Vec<Vector3<f64>> {
    let r = max_deg.to_radians().sin();
    (0..size * size)
        .map(|i| {
            let (x, y) = (i % size, i / size);
            let u = ((x as f64 + 0.5) / size as f64 * 2.0 - 1.0) * r;
            let v = ((y as f64 + 0.5) / size as f64 * 2.0 - 1.0) * r;
            Vector3::new(u, v, (1.0 - u * u - v * v).sqrt())
        })
        .collect()
}
