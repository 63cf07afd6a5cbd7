//! The scene as the camera sees it: every camera pixel is traced (with `ss x ss` sub-samples) to
//! the subject, giving the surface samples, their footprint areas and their materials. Everything
//! else (projector illumination, reflection, subsurface transport) works on this buffer.
//!
//! Conventions
//! - Camera pixel (x, y), centres at integer coordinates; sub-sample (i, j) of pixel (x, y) is at
//!   `(x - 0.5 + (i + 0.5) / ss, y - 0.5 + (j + 0.5) / ss)`.
//! - Buffers are row-major by pixel; sub-samples of a pixel are contiguous (`pixel * ss^2 + j * ss + i`).
//! - The pixel-centre sample defines the truth maps (mask, depth, points, normals, projector
//!   coordinates); sub-samples integrate radiometry over the pixel.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use super::camera::CameraModel;
use super::material_maps::MaterialMaps;
use super::subjects::{Hit, Subject};

/// A point on the subject's surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceSample {
    pub point: Point3<f64>,
    /// Outward unit normal.
    pub normal: Vector3<f64>,
    /// Unit vector from the point to the camera centre.
    pub to_camera: Vector3<f64>,
    /// Surface area this sample stands for, mm^2.
    pub area_mm2: f64,
}

/// What the camera sees.
#[derive(Debug, Clone)]
pub struct GeometryBuffer {
    pub width: u32,
    pub height: u32,
    /// Sub-samples per pixel along each axis.
    pub ss: u32,
    /// Pixel-centre hit of every pixel.
    pub centre: Vec<Option<Hit>>,
    /// Sub-samples, `ss^2` per pixel.
    pub subs: Vec<Option<SurfaceSample>>,
    /// Material weights `[melanin, blood, stubble]` per pixel (mean over its sub-samples); zero
    /// until [`GeometryBuffer::assign_materials`].
    pub materials: Vec<[f32; 3]>,
    /// Diffuse albedo per sub-sample (printed targets; 0 for skin).
    pub albedo: Vec<f32>,
    /// Fraction of the pixel's sub-samples that hit the subject.
    pub coverage: Vec<f32>,
}

/// Obliquity below which the footprint stops growing (keeps silhouette samples finite).
const MIN_VIEW_COSINE: f64 = 0.15;

/// The world ray directions of every camera pixel's centre and sub-samples (every ray starts at
/// the camera's centre), for tracing several subjects before the same camera: the calibration
/// poses. Undistorting the pixels was a tenth of a pose's CPU time.
pub struct CameraRays {
    ss: u32,
    origin: Point3<f64>,
    /// Per pixel: its centre's direction, then its sub-samples' in sub-sample order.
    directions: Vec<Vector3<f64>>,
}

impl CameraRays {
    /// The rays of `camera`'s pixels with `ss x ss` sub-samples each.
    pub fn new(camera: &CameraModel, ss: u32) -> Self {
        let (w, h) = (camera.calib.width, camera.calib.height);
        let directions = (0..w * h)
            .into_par_iter()
            .flat_map_iter(|i| {
                let (x, y) = (i % w, i / w);
                std::iter::once(camera.calib.ray(x as f64, y as f64).1).chain((0..ss * ss).map(
                    move |s| {
                        let (sx, sy) = sub_sample_position(x, y, s % ss, s / ss, ss);
                        camera.calib.ray(sx, sy).1
                    },
                ))
            })
            .collect();
        Self {
            ss,
            origin: camera.calib.extrinsics.centre(),
            directions,
        }
    }
}

/// Camera coordinates of sub-sample (i, j) of pixel (x, y) (see the module conventions).
fn sub_sample_position(x: u32, y: u32, i: u32, j: u32, ss: u32) -> (f64, f64) {
    (
        x as f64 - 0.5 + (i as f64 + 0.5) / ss as f64,
        y as f64 - 0.5 + (j as f64 + 0.5) / ss as f64,
    )
}

impl GeometryBuffer {
    /// Traces every pixel of `camera` against `subject`.
    pub fn trace(camera: &CameraModel, subject: &Subject, ss: u32) -> Self {
        Self::trace_by(camera, subject, ss, |_, _, [sx, sy]| {
            camera.calib.ray(sx, sy)
        })
    }

    /// [`Self::trace`] along the precomputed `rays` of `camera`.
    pub fn trace_rays(camera: &CameraModel, subject: &Subject, rays: &CameraRays) -> Self {
        let per_pixel = 1 + (rays.ss * rays.ss) as usize;
        Self::trace_by(camera, subject, rays.ss, |pixel, sample, _| {
            (rays.origin, rays.directions[pixel * per_pixel + sample])
        })
    }

    /// [`Self::trace`] with the ray of each pixel (index), sample (0: the centre, `1 + j ss + i`:
    /// sub-sample (i, j)) at camera coordinates from `ray`.
    fn trace_by(
        camera: &CameraModel,
        subject: &Subject,
        ss: u32,
        ray: impl Fn(usize, usize, [f64; 2]) -> (Point3<f64>, Vector3<f64>) + Sync,
    ) -> Self {
        let (w, h) = (camera.calib.width, camera.calib.height);
        let spp = (ss * ss) as usize;
        let intr = &camera.calib.intrinsics;
        let eye = camera.calib.extrinsics.centre();
        let rows: Vec<_> = (0..h)
            .into_par_iter()
            .map(|y| {
                let mut centre = Vec::with_capacity(w as usize);
                let mut subs = Vec::with_capacity(w as usize * spp);
                let mut albedo = Vec::with_capacity(w as usize * spp);
                let mut coverage = Vec::with_capacity(w as usize);
                for x in 0..w {
                    let pixel = (y * w + x) as usize;
                    let (o, d) = ray(pixel, 0, [x as f64, y as f64]);
                    centre.push(subject.intersect(&o, &d, 1e-6, 1e5));
                    let mut hits = 0usize;
                    for j in 0..ss {
                        for i in 0..ss {
                            let (sx, sy) = sub_sample_position(x, y, i, j, ss);
                            let (o, d) = ray(pixel, (1 + j * ss + i) as usize, [sx, sy]);
                            let hit = subject.intersect(&o, &d, 1e-6, 1e5);
                            let sample = hit.map(|hit| {
                                // Solid angle of a sub-pixel: cos^3(off-axis) / (fx fy ss^2).
                                let d_cam = camera.calib.extrinsics.r() * d;
                                let solid_angle =
                                    d_cam.z.powi(3) / (intr.fx * intr.fy) / (ss * ss) as f64;
                                let to_camera = (eye - hit.point).normalize();
                                let cos_view = hit.normal.dot(&to_camera).max(MIN_VIEW_COSINE);
                                SurfaceSample {
                                    point: hit.point,
                                    normal: hit.normal,
                                    to_camera,
                                    area_mm2: solid_angle * hit.t * hit.t / cos_view,
                                }
                            });
                            let a = match (&sample, subject) {
                                (Some(s), Subject::Chessboard(board)) => board.albedo(&s.point),
                                _ => 0.0,
                            };
                            hits += usize::from(sample.is_some());
                            subs.push(sample);
                            albedo.push(a as f32);
                        }
                    }
                    coverage.push(hits as f32 / spp as f32);
                }
                (centre, subs, albedo, coverage)
            })
            .collect();
        let mut buf = Self {
            width: w,
            height: h,
            ss,
            centre: Vec::with_capacity((w * h) as usize),
            subs: Vec::with_capacity((w * h) as usize * spp),
            materials: vec![[0.0; 3]; (w * h) as usize],
            albedo: Vec::with_capacity((w * h) as usize * spp),
            coverage: Vec::with_capacity((w * h) as usize),
        };
        for (c, s, a, cov) in rows {
            buf.centre.extend(c);
            buf.subs.extend(s);
            buf.albedo.extend(a);
            buf.coverage.extend(cov);
        }
        buf
    }

    /// Fills the per-pixel material weights from the maps (mean over the sub-samples).
    pub fn assign_materials(&mut self, maps: &MaterialMaps) {
        let spp = self.spp();
        let subs = &self.subs;
        self.materials
            .par_iter_mut()
            .enumerate()
            .for_each(|(i, out)| {
                let mut sum = [0.0f64; 3];
                let mut n = 0usize;
                for s in subs[i * spp..(i + 1) * spp].iter().flatten() {
                    let m = maps.weights(s.point.x, s.point.y);
                    for c in 0..3 {
                        sum[c] += m[c];
                    }
                    n += 1;
                }
                *out = sum.map(|v| (v / n.max(1) as f64) as f32);
            });
    }

    /// Number of pixels.
    pub fn pixels(&self) -> usize {
        (self.width * self.height) as usize
    }

    /// Sub-samples per pixel.
    pub fn spp(&self) -> usize {
        (self.ss * self.ss) as usize
    }

    /// Sub-samples of pixel `i`.
    pub fn subs_of(&self, i: usize) -> &[Option<SurfaceSample>] {
        let spp = self.spp();
        &self.subs[i * spp..(i + 1) * spp]
    }

    /// Total surface area seen by pixel `i`, mm^2.
    pub fn pixel_area(&self, i: usize) -> f64 {
        self.subs_of(i).iter().flatten().map(|s| s.area_mm2).sum()
    }

    /// Area-weighted mean point and normal of pixel `i`'s sub-samples.
    pub fn pixel_surface(&self, i: usize) -> Option<(Point3<f64>, Vector3<f64>, f64)> {
        let mut area = 0.0;
        let mut p = Vector3::zeros();
        let mut n = Vector3::zeros();
        for s in self.subs_of(i).iter().flatten() {
            area += s.area_mm2;
            p += s.point.coords * s.area_mm2;
            n += s.normal * s.area_mm2;
        }
        (area > 0.0).then(|| (Point3::from(p / area), n.normalize(), area))
    }

    /// Extent `[x_min, x_max, y_min, y_max]` (world mm) of the surface points seen.
    pub fn extent(&self) -> Option<[f64; 4]> {
        let mut e = [
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        for hit in self.centre.iter().flatten() {
            e[0] = e[0].min(hit.point.x);
            e[1] = e[1].max(hit.point.x);
            e[2] = e[2].min(hit.point.y);
            e[3] = e[3].max(hit.point.y);
        }
        e[0].is_finite().then_some(e)
    }

    /// Mean footprint side of a pixel on the subject, mm (the scale of the subsurface grid).
    pub fn mean_pixel_size_mm(&self) -> f64 {
        let (mut sum, mut n) = (0.0, 0usize);
        for i in 0..self.pixels() {
            let a = self.pixel_area(i);
            if self.coverage[i] >= 1.0 {
                sum += a.sqrt();
                n += 1;
            }
        }
        if n == 0 { 1.0 } else { sum / n as f64 }
    }
}
