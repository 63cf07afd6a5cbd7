use super::*;

#[test]
fn direct_part_rules_split_a_white_frame() {
    let direct = [[0.2f32, 0.3, 0.1]];
    let global = [[1.0f32, 1.0, 1.0]];
    let close = |a: [f32; 3], b: [f32; 3]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6);
    let (d, g) = DirectPart::Separation.split((0.25, 0.45), &direct, &global);
    assert_eq!((d[0], g[0]), (direct[0], global[0]));
    // None: all light is subsurface light.
    let (d, g) = DirectPart::None.split((0.25, 0.45), &direct, &global);
    assert!(
        close(d[0], [0.0; 3]) && close(g[0], [1.2, 1.3, 1.1]),
        "{d:?} {g:?}"
    );
    // Colourless: the smallest channel in every channel, the rest back to the global part.
    let (d, g) = DirectPart::Colourless.split((0.25, 0.45), &direct, &global);
    assert!(
        close(d[0], [0.1; 3]) && close(g[0], [1.1, 1.2, 1.0]),
        "{d:?} {g:?}"
    );
    // Auto: the separation calls 0.2 of 1.2 direct (below the range): none removed.
    let (d, g) = DirectPart::Auto.split((0.25, 0.45), &direct, &global);
    assert!(
        close(d[0], [0.0; 3]) && close(g[0], [1.2, 1.3, 1.1]),
        "{d:?} {g:?}"
    );
    // Whatever the rule, direct + global is the white frame.
    for rule in [
        DirectPart::Separation,
        DirectPart::None,
        DirectPart::Colourless,
        DirectPart::Auto,
    ] {
        let (d, g) = rule.split((0.25, 0.45), &direct, &global);
        let total = [0, 1, 2].map(|c| d[0][c] + g[0][c]);
        assert!(close(total, [1.2, 1.3, 1.1]), "{rule:?}");
    }
}

#[test]
fn auto_direct_removes_a_dark_pixels_direct_light_and_keeps_a_light_ones() {
    let range = (0.25, 0.45);
    // Dark skin: the separation calls 0.05 of 0.08 direct (fraction 0.625): all removed.
    let (d, g) = ([0.05f32; 3], [0.06f32, 0.025, 0.005]);
    assert_eq!(direct_fraction(d, g), Some(0.625));
    assert_eq!(auto_direct_weight(d, g, range), 1.0);
    // Light skin: 0.1 of 0.6 (fraction 1/6, about the separation's leak): none removed.
    let (d, g) = ([0.1f32; 3], [0.7f32, 0.5, 0.3]);
    assert_eq!(auto_direct_weight(d, g, range), 0.0);
    // Half way through the range: half.
    let (d, g) = ([0.35f32; 3], [0.65f32; 3]);
    assert!((auto_direct_weight(d, g, range) - 0.5).abs() < 1e-5);
    // No light or non-finite input: no direct part (all light stays subsurface light).
    assert_eq!(direct_fraction([0.0; 3], [0.0; 3]), None);
    assert_eq!(auto_direct_weight([f32::NAN; 3], g, range), 0.0);
}

#[test]
fn the_scanline_is_a_quarter_down_the_subject_across_its_columns() {
    // Subject on rows 2..=10 of a 12x12 image; on row 4 it spans columns 3..=7.
    let (w, h) = (12, 12);
    let mask: Vec<bool> = (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            (2..=10).contains(&y) && if y == 4 { (3..=7).contains(&x) } else { x == 5 }
        })
        .collect();
    let surface = Surface {
        width: w,
        height: h,
        points: vec![Vector3::zeros(); w * h],
        normals: vec![Vector3::z(); w * h],
        mask,
        camera_centre: Vector3::new(0.0, 0.0, 100.0),
    };
    assert_eq!(scanline(&surface), (4, (3, 7)));
}

#[test]
fn the_reference_slit_is_the_first_vertical_one() {
    let slit = |axis, offset| Pattern::Slit {
        axis,
        width: 2,
        period: 16,
        offset,
    };
    let slits = [slit(Axis::Y, 0), slit(Axis::X, 2), slit(Axis::X, 0)];
    assert_eq!(reference_slit(&slits), Some(2));
    assert_eq!(reference_slit(&slits[..2]), Some(0), "else the first");
    assert!(reference_slit(&[]).is_none());
}

#[test]
fn slit_frames_are_read_in_runs_of_one_axis() {
    let slit = |axis, offset| Pattern::Slit {
        axis,
        width: 3,
        period: 30,
        offset,
    };
    let frames: Vec<(u32, Pattern)> = [
        slit(Axis::X, 0),
        slit(Axis::X, 3),
        slit(Axis::Y, 0),
        slit(Axis::X, 6),
        slit(Axis::X, 9),
        slit(Axis::Y, 3),
    ]
    .into_iter()
    .enumerate()
    .map(|(j, p)| (j as u32 + 40, p))
    .collect();
    assert_eq!(same_axis_runs(&frames), vec![0..2, 2..3, 3..5, 5..6]);
    assert_eq!(same_axis_runs(&frames[..1]), vec![0..1]);
    assert!(same_axis_runs(&[]).is_empty());
}

/// The white parts read the separation's own images under its rule (no copies kept, a1deb73)
/// and a stored split under any other; none after their release.
#[test]
fn white_parts_are_the_separation_under_its_rule_and_the_split_otherwise() {
    let (direct, global) = (vec![[0.2f32, 0.3, 0.1]], vec![[1.0f32, 1.0, 1.0]]);
    let mut p = ProjectorInputs {
        k: 0,
        centre: Vector3::zeros(),
        falloff: Falloff::default(),
        black_level: 0.0,
        coords: vec![None],
        separation_direct: direct.clone(),
        separation_global: global.clone(),
        white_split: None,
        stray: vec![[0.0; 3]],
        blur_px: 0.0,
        noise: None,
        stack: SlitStack::default(),
        geometry: GeometryMap::default(),
    };
    assert_eq!(p.direct_white(), &direct[..]);
    assert_eq!(p.global_white(), &global[..]);
    // No direct part: the whole white frame is global light.
    p.white_split = Some(DirectPart::None.split((0.25, 0.45), &direct, &global));
    assert_eq!(p.direct_white(), &[[0.0f32; 3]][..]);
    assert_eq!(p.global_white(), &[[1.2f32, 1.3, 1.1]][..]);
    // Released, neither part is left, split or not.
    p.release_white_images();
    assert!(p.direct_white().is_empty() && p.global_white().is_empty() && p.stray.is_empty());
}
