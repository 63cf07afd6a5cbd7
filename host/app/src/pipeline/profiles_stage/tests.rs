use super::*;

#[test]
fn direct_part_rules_split_a_white_frame() {
    let direct = [[0.2f32, 0.3, 0.1]];
    let global = [[1.0f32, 1.0, 1.0]];
    let close = |a: [f32; 3], b: [f32; 3]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6);
    let (d, g) = DirectPart::Separation.split(&direct, &global);
    assert_eq!((d[0], g[0]), (direct[0], global[0]));
    // None: all light is subsurface light.
    let (d, g) = DirectPart::None.split(&direct, &global);
    assert!(
        close(d[0], [0.0; 3]) && close(g[0], [1.2, 1.3, 1.1]),
        "{d:?} {g:?}"
    );
    // Colourless: the smallest channel in every channel, the rest back to the global part.
    let (d, g) = DirectPart::Colourless.split(&direct, &global);
    assert!(
        close(d[0], [0.1; 3]) && close(g[0], [1.1, 1.2, 1.0]),
        "{d:?} {g:?}"
    );
    // Whatever the rule, direct + global is the white frame.
    for rule in [
        DirectPart::Separation,
        DirectPart::None,
        DirectPart::Colourless,
    ] {
        let (d, g) = rule.split(&direct, &global);
        let total = [0, 1, 2].map(|c| d[0][c] + g[0][c]);
        assert!(close(total, [1.2, 1.3, 1.1]), "{rule:?}");
    }
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
    let slits: Vec<SlitGlobal> = vec![
        (slit(Axis::Y, 0), vec![[1.0; 3]]),
        (slit(Axis::X, 2), vec![[2.0; 3]]),
        (slit(Axis::X, 0), vec![[3.0; 3]]),
    ];
    assert_eq!(reference_slit(&slits).map(|s| s.0), Some(slit(Axis::X, 0)));
    assert_eq!(
        reference_slit(&slits[..2]).map(|s| s.0),
        Some(slit(Axis::Y, 0)),
        "else the first"
    );
    assert!(reference_slit(&[]).is_none());
}
