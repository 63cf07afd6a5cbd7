use super::*;

fn layer(weight: f32, sigma_mm: f32, depth_mm: f32) -> SplatLayer {
    SplatLayer {
        index: 0,
        weight,
        sigma_mm,
        depth_mm,
    }
}

fn single_slit(width: f64, shift_per_depth: f64) -> Profile {
    Profile {
        noise: None,
        samples: Vec::new(),
        slit_width: width,
        period: None,
        shift_per_depth,
    }
}

#[test]
fn a_pixel_profile_is_the_layer_gaussian_integrated_over_the_slit() {
    // A slit as wide as two standard deviations, centred on the layer: the layer's light
    // within one sigma of its mean, 68.27 % of it (the normal distribution's 1-sigma mass).
    let one_sigma_mass = 0.682_689_492_137_086;
    let profile = single_slit(1.0, 0.0);
    let layers = [layer(2.0, 0.5, 0.0)];
    let at_centre = model_profile(&layers, 3.0, &profile, 0.0);
    assert!(
        (at_centre - 2.0 * 3.0 * one_sigma_mass).abs() < 1e-9,
        "{at_centre}"
    );
    // Symmetric about the slit, and far from it nothing.
    let (left, right) = (
        model_profile(&layers, 3.0, &profile, -0.7),
        model_profile(&layers, 3.0, &profile, 0.7),
    );
    assert!((left - right).abs() < 1e-12);
    assert!(model_profile(&layers, 3.0, &profile, 6.0) < 1e-12);
    // A layer 1 mm deep with 0.4 mm of shift per mm of depth peaks 0.4 mm forward.
    let shifted = single_slit(1.0, 0.4);
    let deep = [layer(2.0, 0.5, 1.0)];
    let peak = model_profile(&deep, 3.0, &shifted, 0.4);
    assert!((peak - at_centre).abs() < 1e-12, "{peak} vs {at_centre}");
    // A comb adds the neighbouring slits' light: one period away it is the same again.
    let comb = Profile {
        period: Some(4.0),
        ..single_slit(1.0, 0.0)
    };
    let c0 = model_profile(&layers, 3.0, &comb, 0.0);
    let c1 = model_profile(&layers, 3.0, &comb, 4.0);
    assert!(
        (c0 - at_centre).abs() < 1e-9 && (c1 - c0).abs() < 1e-9,
        "{c0} {c1}"
    );
}

#[test]
fn relative_rmse_is_over_the_mask_and_all_channels() {
    let a = [[1.0, 1.0, 1.0], [9.0, 9.0, 9.0]];
    let t = [[2.0, 2.0, 2.0], [0.0, 0.0, 0.0]];
    // sqrt(3 * 1^2 / (3 * 2^2)) = 0.5; the second pixel is masked out.
    assert!((rel_rmse(&a, &t, &[true, false]).unwrap() - 0.5).abs() < 1e-12);
    assert_eq!(rel_rmse(&a, &t, &[false, false]), None, "no truth light");
}

#[test]
fn unfitted_surface_pixels_get_the_mean_layers_and_only_they() {
    // Pixel 0 fitted, pixel 1 on the surface without a fit, pixel 2 off the surface.
    let model = LayerModel::from_fn(3, 1, |i, _| {
        (i == 0).then(|| layer(0.5, 1.0, 0.2)).into_iter()
    });
    let fitted = model.fitted();
    assert_eq!(fitted, [true, false, false]);
    let mut filled = model.clone();
    let count = fill_unfitted(&mut filled, &fitted, &[true, true, false]);
    assert_eq!(count, 1);
    for c in 0..3 {
        assert_eq!(filled.layers(0, c), model.layers(0, c));
        assert_eq!(filled.layers(1, c).to_vec(), model.mean_layers(&fitted)[c]);
        assert!(!filled.layers(1, c).is_empty());
        assert!(filled.layers(2, c).is_empty());
    }
}

#[test]
fn out_of_range_parameters_are_refused() {
    let ok = FitParams::default();
    check_params(&ok, 4).unwrap();
    let holdout = FitParams {
        holdout: Some(4),
        ..FitParams::default()
    };
    assert!(matches!(
        check_params(&holdout, 4),
        Err(FitStageError::BadHoldout {
            holdout: 4,
            count: 4
        })
    ));
    for bad in [
        FitParams {
            components: 0,
            ..FitParams::default()
        },
        FitParams {
            block: 0,
            ..FitParams::default()
        },
        FitParams {
            max_iterations: 0,
            ..FitParams::default()
        },
        // `process --tolerance NaN` ran without end (issue 21).
        FitParams {
            tolerance: f64::NAN,
            ..FitParams::default()
        },
        FitParams {
            tolerance: 0.0,
            ..FitParams::default()
        },
        // `--depth-spacing=-0.1` fitted a negative layer spacing (issue 21).
        FitParams {
            depth_spacing_mm: Some(-0.1),
            ..FitParams::default()
        },
        FitParams {
            depth_spacing_mm: Some(f64::INFINITY),
            ..FitParams::default()
        },
    ] {
        assert!(matches!(
            check_params(&bad, 4),
            Err(FitStageError::BadParameter(_))
        ));
    }
}
