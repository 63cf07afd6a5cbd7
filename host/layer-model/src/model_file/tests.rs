//! Tests of the model file: round trips, bad files, and renders of every baseline.

use super::*;
use mlsss_core::booth::Booth;
use mlsss_core::capture::Axis;

/// A small model of the plane z = 0 seen by the quick booth's calibration.
fn plane_model() -> SubsurfaceModel {
    plane_model_sized(24, 16)
}

fn plane_model_sized(w: usize, h: usize) -> SubsurfaceModel {
    let booth = Booth::builtin(true);
    let calibration = booth.calibration();
    let cam = booth.camera_calibration();
    // A patch of the camera image around its centre, scaled down to w x h.
    let points: Vec<Vector3<f64>> = (0..w * h)
        .map(|i| {
            let x = cam.width as f64 / 2.0 + ((i % w) as f64 - w as f64 / 2.0);
            let y = cam.height as f64 / 2.0 + ((i / w) as f64 - h as f64 / 2.0);
            let (o, d) = cam.ray(x, y);
            (o + d * (-o.z / d.z)).coords
        })
        .collect();
    let projectors: Vec<ProjectorLight> = calibration
        .projectors
        .iter()
        .map(|p| ProjectorLight {
            centre: p.device.extrinsics.centre().coords.into(),
            falloff: Falloff::Projector {
                axis: p
                    .device
                    .extrinsics
                    .device_to_world_dir(&Vector3::z())
                    .into(),
                scale: p.device.extrinsics.centre().coords.norm_squared(),
            },
            black_level: 0.01,
            blur_px: 0.5,
        })
        .collect();
    let layers = LayerModel::from_fn(w, h, |i, c| {
        vec![SplatLayer {
            index: 1,
            weight: 0.1 + 0.01 * c as f32 + 1e-4 * i as f32,
            sigma_mm: 0.5,
            depth_mm: 0.2,
        }]
    });
    SubsurfaceModel {
        header: ModelHeader {
            format_version: FORMAT_VERSION,
            width: w,
            height: h,
            em: EmVariant::Layered,
            components: 20,
            depth_spacing_mm: 0.2,
            eta: 1.4,
            view_ray: ViewRay::Refracted,
            training_projectors: vec![0, 1, 2],
            holdout: Some(3),
            projectors: projectors.clone(),
            camera_centre: cam.extrinsics.centre().coords.into(),
            patterns: booth.patterns.clone(),
            calibration,
            stats: FitStats::default(),
        },
        surface: Surface {
            width: w,
            height: h,
            points,
            // The camera looks along +z from z = -500: the skin faces -z.
            normals: vec![-Vector3::z(); w * h],
            mask: (0..w * h).map(|i| i % 7 != 3).collect(),
            camera_centre: cam.extrinsics.centre().coords,
        },
        albedo: (0..w * h)
            .map(|i| [0.3, 0.2, 0.1 + 1e-3 * i as f32])
            .collect(),
        white_albedo: vec![[0.5, 0.4, 0.3]; w * h],
        visibility: vec![vec![true; w * h]; projectors.len()],
        layers,
        dipole: None,
    }
}

/// A scanline rendered from the band of rows `rows_reaching` names is the whole model's
/// (how the fit stage draws Fig. 10 without rendering the whole image twice); a band half
/// as wide is not, so the reach is not padding.
#[test]
fn a_band_of_rows_renders_its_scanline_as_the_whole_model_does() {
    let (w, h, row) = (24, 140, 70);
    let mut model = plane_model_sized(w, h);
    model.layers = LayerModel::from_fn(w, h, |i, c| {
        [(0.05, 0.4, 0.0), (0.03, 2.5, 0.6)].map(|(weight, sigma_mm, depth_mm)| SplatLayer {
            index: 1,
            weight: weight + 0.01 * c as f32 + 1e-5 * i as f32,
            sigma_mm,
            depth_mm,
        })
    });
    model.header.view_ray = ViewRay::Refracted;
    let opts = RenderOptions::default();
    let band = model.rows_reaching(row..row + 1, |i| model.layers.extent(i), &opts);
    assert!(band.start > 0 && band.end < h, "{band:?}");
    let slit = Pattern::Slit {
        axis: Axis::Y,
        width: 2,
        period: 6,
        offset: 0,
    };
    let scanline = |m: &SubsurfaceModel, r: usize| -> Vec<[f32; 3]> {
        let g = render_pattern_alone(m, 1, &slit, Baseline::Mlsss, &opts)
            .unwrap()
            .global;
        g[r * w..(r + 1) * w].to_vec()
    };
    let whole = scanline(&model, row);
    let peak = whole.iter().flatten().fold(0.0f32, |a, &b| a.max(b));
    assert!(peak > 0.0);
    let gap = |part: &[[f32; 3]]| {
        whole
            .iter()
            .flatten()
            .zip(part.iter().flatten())
            .map(|(a, b)| (a - b).abs() / peak)
            .fold(0.0f32, f32::max)
    };
    let banded = scanline(&model.rows(band.clone()), row - band.start);
    assert!(gap(&banded) < 1e-5, "{}", gap(&banded));
    let half = band.len() / 4;
    let narrow = row - half..row + half;
    let short = scanline(&model.rows(narrow.clone()), row - narrow.start);
    assert!(gap(&short) > 1e-3, "{}", gap(&short));
}

/// The sections of format 2 as the module doc spells them, written one after the other with a
/// linear palette search: the reference the parallel, per-part save must decompress to.
fn reference_sections(model: &SubsurfaceModel) -> Vec<u8> {
    let mut buf = Vec::new();
    let f32s = |buf: &mut Vec<u8>, vs: &[f32]| {
        vs.iter()
            .for_each(|v| buf.extend_from_slice(&v.to_le_bytes()))
    };
    let header = serde_json::to_vec(&model.header).unwrap();
    buf.extend_from_slice(&(header.len() as u32).to_le_bytes());
    buf.extend_from_slice(&header);
    for vs in [&model.surface.points, &model.surface.normals] {
        for v in vs {
            f32s(&mut buf, &[v.x as f32, v.y as f32, v.z as f32]);
        }
    }
    buf.extend(model.surface.mask.iter().map(|&m| m as u8));
    for a in model.albedo.iter().chain(&model.white_albedo) {
        f32s(&mut buf, a);
    }
    for v in &model.visibility {
        buf.extend(v.iter().map(|&m| m as u8));
    }
    let section = |buf: &mut Vec<u8>, m: &LayerModel| {
        for len in m.row_lens() {
            buf.extend_from_slice(&(len as u16).to_le_bytes());
        }
        let layers: Vec<SplatLayer> = m.all_layers().collect();
        let mut palette: Vec<(u16, f32, f32)> = Vec::new();
        let mut ids = Vec::new();
        for l in &layers {
            let key = (l.index, l.sigma_mm, l.depth_mm);
            let id = match palette.iter().position(|p| *p == key) {
                Some(id) => id,
                None => {
                    palette.push(key);
                    palette.len() - 1
                }
            };
            ids.push(id as u32);
        }
        buf.extend_from_slice(&(palette.len() as u32).to_le_bytes());
        for (index, sigma, depth) in &palette {
            buf.extend_from_slice(&index.to_le_bytes());
            f32s(buf, &[*sigma, *depth]);
        }
        buf.extend_from_slice(&(layers.len() as u32).to_le_bytes());
        let width = if palette.len() <= 256 {
            1
        } else if palette.len() <= 65536 {
            2
        } else {
            4
        };
        buf.push(width as u8);
        for id in ids {
            buf.extend_from_slice(&id.to_le_bytes()[..width]);
        }
        for plane in 0..4 {
            buf.extend(layers.iter().map(|l| l.weight.to_le_bytes()[plane]));
        }
    };
    section(&mut buf, &model.layers);
    buf.push(model.dipole.is_some() as u8);
    if let Some(d) = &model.dipole {
        section(&mut buf, d);
    }
    buf
}

/// The saved file is the magic, the version and gzip members that decompress to the sections
/// the module doc specifies (written serially by the reference), for a layer model with 1-byte
/// palette ids and a dipole with 2-byte ids and empty rows.
#[test]
fn the_saved_file_decompresses_to_the_documented_sections() {
    use std::io::Read;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.mlsss");
    let mut model = plane_model_sized(40, 30);
    model.dipole = Some(LayerModel::from_fn(40, 30, |i, c| {
        (0..(i + c) % 3)
            .map(|k| SplatLayer {
                index: k as u16,
                weight: 1e-3 * (i * 3 + c) as f32,
                sigma_mm: 0.1 + 1e-3 * (i % 300) as f32,
                depth_mm: 0.05 * k as f32,
            })
            .collect::<Vec<_>>()
    }));
    model.save(&path).unwrap();
    let file = std::fs::read(&path).unwrap();
    assert_eq!(&file[..8], MAGIC);
    assert_eq!(file[8..12], FORMAT_VERSION.to_le_bytes());
    let mut sections = Vec::new();
    flate2::read::MultiGzDecoder::new(&file[12..])
        .read_to_end(&mut sections)
        .unwrap();
    let reference = reference_sections(&model);
    assert_eq!(sections.len(), reference.len());
    assert!(sections == reference);
}

/// A layer model whose rows share shapes (as the spatial prior's and the dipole's) saves the
/// sections of its layers written out, the same file as its written-out twin's, and loads back
/// equal to it.
#[test]
fn shared_shapes_save_as_their_layers_written_out() {
    use crate::render::{RowSource, ShapeLayer};
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (40, 30);
    let shape = |(tile, c): (usize, usize)| {
        (0..1 + (tile + c) % 3).map(move |k| ShapeLayer {
            index: k as u16,
            weight: 0.1 + 0.05 * k as f64 + 1e-3 * tile as f64,
            sigma_mm: 0.2 + 0.1 * (tile % 5) as f32,
            depth_mm: 0.05 * k as f32,
        })
    };
    let own = |i: usize, c: usize| -> Vec<SplatLayer> {
        (0..(i + c) % 3)
            .map(|k| SplatLayer {
                index: 7 + k as u16,
                weight: 1e-3 * (i * 3 + c) as f32,
                sigma_mm: 0.3,
                depth_mm: 0.0,
            })
            .collect()
    };
    let owned: Vec<Vec<SplatLayer>> = (0..w * h * 3).map(|k| own(k / 3, k % 3)).collect();
    let source = |i: usize, c: usize| match i % 5 {
        0 => RowSource::Own(crate::render::RowLayers::Own(&owned[i * 3 + c])),
        1 => RowSource::Empty,
        _ => RowSource::Shape {
            key: ((i / w / 6) * 7 + (i % w) / 6, c),
            scale: 0.5 + 1e-3 * i as f64,
        },
    };
    let mut shared = plane_model_sized(w, h);
    shared.layers = LayerModel::from_shapes(w, h, source, shape);
    let mut written_out = plane_model_sized(w, h);
    written_out.layers = LayerModel::from_fn(w, h, |i, c| shared.layers.layers(i, c).to_vec());
    let (a, b) = (
        dir.path().join("shared.mlsss"),
        dir.path().join("out.mlsss"),
    );
    shared.save(&a).unwrap();
    written_out.save(&b).unwrap();
    assert!(std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap());
    let loaded = SubsurfaceModel::load(&a).unwrap();
    assert_eq!(loaded.layers, shared.layers);
    assert!(shared.layers.row_lens().any(|n| n > 1));
}

#[test]
fn a_model_survives_the_file_bit_for_bit_and_bad_files_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.mlsss");
    let mut model = plane_model();
    model.surface.points = model
        .surface
        .points
        .iter()
        .map(|p| p.map(|v| f64::from(v as f32)))
        .collect();
    // A second layer model with a palette of more than 256 entries (2-byte ids) and rows of
    // 0 to 2 layers.
    model.dipole = Some(LayerModel::from_fn(
        model.header.width,
        model.header.height,
        |i, c| {
            (0..(i + c) % 3)
                .map(|k| SplatLayer {
                    index: k as u16,
                    weight: 1e-3 * (i * 3 + c) as f32,
                    sigma_mm: 0.1 + 1e-3 * i as f32,
                    depth_mm: 0.0,
                })
                .collect::<Vec<_>>()
        },
    ));
    // Format 1 files are still read, bit for bit.
    model.save_as(&path, 1).unwrap();
    let old = SubsurfaceModel::load(&path).unwrap();
    assert_eq!(
        (old.layers, old.dipole),
        (model.layers.clone(), model.dipole.clone())
    );
    model.save(&path).unwrap();
    let back = SubsurfaceModel::load(&path).unwrap();
    // Binary sections are exact; the JSON header's floats may differ in the last digit.
    assert_eq!(back.surface, model.surface);
    assert_eq!(back.layers, model.layers);
    assert_eq!(back.dipole, model.dipole);
    assert_eq!(back.albedo, model.albedo);
    assert_eq!(back.white_albedo, model.white_albedo);
    assert_eq!(back.visibility, model.visibility);
    assert_eq!(back.header.patterns, model.header.patterns);
    assert_eq!(back.header.holdout, Some(3));
    let (a, b) = (&back.header.projectors[2], &model.header.projectors[2]);
    assert!((a.centre[0] - b.centre[0]).abs() < 1e-9 && a.black_level == b.black_level);

    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    assert!(SubsurfaceModel::load(&path).is_err());
    std::fs::write(&path, b"MLSSSMDL\x09\0\0\0").unwrap();
    let err = SubsurfaceModel::load(&path).unwrap_err().to_string();
    assert!(err.contains("version 9"), "{err}");
    std::fs::write(&path, b"not a model at all").unwrap();
    assert!(matches!(
        SubsurfaceModel::load(&path),
        Err(ModelFileError::NotAModel { .. })
    ));
}

#[test]
fn renders_white_and_slits_with_every_baseline() {
    let model = plane_model();
    let opts = RenderOptions::default();
    let white = render_projector(&model, 0, &Pattern::White, Baseline::Mlsss, &opts).unwrap();
    let direct = render_projector(&model, 0, &Pattern::White, Baseline::Direct, &opts).unwrap();
    assert!(direct.global.iter().all(|g| *g == [0.0; 3]));
    // Direct only re-emits the white albedo locally: ratio to the model's direct part.
    let j = 5 * 24 + 5;
    assert!((direct.direct[j][0] / white.direct[j][0] - 0.5 / 0.3).abs() < 1e-4);
    let i = 8 * 24 + 12;
    assert!(model.surface.mask[i]);
    assert!(white.global[i][0] > 0.0 && white.direct[i][0] > 0.0);
    // Under white light with a uniform model, global / direct = weight / albedo, up to the
    // small per-pixel weight ramp and the border.
    let ratio = white.global[i][0] / white.direct[i][0];
    assert!((ratio - 0.1 / 0.3).abs() < 0.05, "{ratio}");
    let homog = render_projector(&model, 0, &Pattern::White, Baseline::Homogeneous, &opts).unwrap();
    assert!((homog.global[i][0] - white.global[i][0]).abs() < 0.02 * white.global[i][0]);
    // A slit through the patch's centre pixel.
    let u = model.projector_coords(1).unwrap()[i].unwrap().0.round() as u32;
    let slit = Pattern::Slit {
        axis: Axis::X,
        width: 3,
        period: 30,
        offset: (u + 29) % 30,
    };
    let s = render_projector(&model, 1, &slit, Baseline::Mlsss, &opts).unwrap();
    let (lo, hi) = s
        .total()
        .iter()
        .zip(&model.surface.mask)
        .filter(|(_, m)| **m)
        .fold((f32::MAX, 0.0f32), |(lo, hi), (v, _)| {
            (lo.min(v[0]), hi.max(v[0]))
        });
    assert!(hi > 3.0 * lo, "slits must show: {lo} .. {hi}");
    assert!(matches!(
        render_projector(&model, 0, &Pattern::White, Baseline::Dipole, &opts),
        Err(ModelFileError::NoDipole)
    ));
    assert!(matches!(
        render_projector(&model, 9, &Pattern::White, Baseline::Mlsss, &opts),
        Err(ModelFileError::NoSuchProjector { .. })
    ));
}

/// The rows without the dipole are the rows with it, less the dipole (whose rows are cut as
/// the rest), clamped to the image alike.
#[test]
fn rows_without_the_dipole_are_the_rows_less_the_dipole() {
    let mut model = plane_model_sized(24, 16);
    model.dipole = Some(LayerModel::from_fn(24, 16, |i, c| {
        (0..(i + c) % 3)
            .map(|k| SplatLayer {
                index: k as u16,
                weight: 1e-3 * (i * 3 + c) as f32,
                sigma_mm: 0.2,
                depth_mm: 0.0,
            })
            .collect::<Vec<_>>()
    }));
    for rows in [0..16, 3..9, 10..40, 20..30] {
        let with = model.rows(rows.clone());
        let dipole = with.dipole.clone().unwrap();
        assert_eq!((dipole.width, dipole.height), (24, with.header.height));
        let whole = model.dipole.as_ref().unwrap();
        let first = rows.start.min(16) * 24;
        for i in 0..24 * with.header.height {
            assert_eq!(dipole.layers(i, 1), whole.layers(first + i, 1));
        }
        let without = model.rows_without_dipole(rows);
        assert_eq!(without.dipole, None);
        assert_eq!(
            SubsurfaceModel {
                dipole: None,
                ..with
            },
            without
        );
    }
}
