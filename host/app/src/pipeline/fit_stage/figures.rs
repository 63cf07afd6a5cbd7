//! The fit stage's figures: the paper's Fig. 10 (measured against modelled slit light along a
//! forehead scanline) and per-pixel profile plots, with the model's profile of one pixel they draw.

use super::*;

/// The model's profile of one pixel: `E sum_l w_l (g_l * box_W)(s)`, comb images included.
pub(super) fn model_profile(
    layers: &[SplatLayer],
    irradiance: f64,
    profile: &Profile,
    s: f64,
) -> f64 {
    let w = profile.slit_width;
    let period = profile.period.unwrap_or(f64::INFINITY);
    let images: &[f64] = if period.is_finite() {
        &[-1.0, 0.0, 1.0]
    } else {
        &[0.0]
    };
    layers
        .iter()
        .map(|l| {
            let sigma = f64::from(l.sigma_mm).max(1e-6) * std::f64::consts::SQRT_2;
            let mu = f64::from(l.depth_mm) * profile.shift_per_depth;
            let mass: f64 = images
                .iter()
                .map(|k| {
                    // The slit's own image has no offset (0 x an infinite period is NaN).
                    let d = s - mu - if *k == 0.0 { 0.0 } else { k * period };
                    0.5 * (mlsss_core::special::erf((d + w / 2.0) / sigma)
                        - mlsss_core::special::erf((d - w / 2.0) / sigma))
                })
                .sum();
            f64::from(l.weight) * irradiance * mass
        })
        .sum()
}

/// The scanline of the profiles stage that both figures sample: its row and the subject's
/// columns between the record's scanline columns.
struct Scanline {
    row: usize,
    width: usize,
    columns: Vec<usize>,
}

impl Scanline {
    fn new(inputs: &ProfileInputs, record: &ProfilesRecord) -> Self {
        let surface = &inputs.surface;
        let w = surface.width;
        let (row, (c0, c1)) = (record.scanline_row, record.scanline_columns);
        let columns: Vec<usize> = (c0..=c1.max(c0))
            .filter(|&x| x < w && surface.mask[row * w + x])
            .collect();
        Self {
            row,
            width: w,
            columns,
        }
    }

    /// The R channel of `img` (row `r` of it) at the scanline's columns.
    fn red_along_row(&self, img: &[[f32; 3]], r: usize) -> Vec<(f64, f64)> {
        self.columns
            .iter()
            .map(|&x| (x as f64, f64::from(img[r * self.width + x][0])))
            .collect()
    }

    /// The R channel of a full-size image at the scanline.
    fn red_along(&self, img: &[[f32; 3]]) -> Vec<(f64, f64)> {
        self.red_along_row(img, self.row)
    }
}

/// What the figures take from the slit profiles, taken as soon as the layers are fitted so the
/// profiles can be freed before the model is assembled, rendered and saved.
pub(super) struct PreparedFigures {
    /// The projector Fig. 10 shows (the held-out one, else the first training projector).
    projector: usize,
    /// Its slit's measured global light (`None` when it cannot be extracted).
    measured_slit: Option<Vec<[f32; 3]>>,
    profiles_plot: LinePlot,
}

/// Fig. 10's projector (the held-out one, else the first training projector) and its measured
/// slit light: taken before the EM, so the projectors' images it is extracted from can be freed
/// for the rest of the fit.
pub(super) fn fig10_measured(
    ctx: &StageContext,
    inputs: &ProfileInputs,
    holdout: Option<usize>,
    training: &[usize],
) -> Result<Fig10Measured, FitStageError> {
    let projector = holdout.unwrap_or(training[0]);
    let slit = fig10_slit(&ctx.capture.manifest.booth.patterns);
    Ok(Fig10Measured {
        projector,
        slit: measured_global(ctx, inputs, projector, &slit)?,
    })
}

/// Fig. 10's projector and its measured slit light (`None` when it cannot be extracted).
pub(super) struct Fig10Measured {
    projector: usize,
    slit: Option<Vec<[f32; 3]>>,
}

/// The figures' data from the profiles: Fig. 10's measured slit ([`fig10_measured`]) and the
/// pixel profiles' plot (drawn from `layers`, the model's layers).
pub(super) fn prepare_figures(
    inputs: &ProfileInputs,
    record: &ProfilesRecord,
    layers: &LayerModel,
    fig10: Fig10Measured,
    training: &[usize],
    profiles: (&[SlitSweep], &[GeometryMap]),
) -> PreparedFigures {
    let scanline = Scanline::new(inputs, record);
    let (sweeps, geometries) = profiles;
    PreparedFigures {
        projector: fig10.projector,
        measured_slit: fig10.slit,
        profiles_plot: pixel_profiles_plot(layers, training, sweeps, geometries, &scanline),
    }
}

/// The slit Fig. 10 shows: vertical lines at offset 0.
fn fig10_slit(spec: &mlsss_core::booth::PatternSpec) -> Pattern {
    Pattern::Slit {
        axis: Axis::X,
        width: spec.slit_width_px,
        period: spec.slit_period_px,
        offset: 0,
    }
}

/// Draws `fig10` and `pixel_profiles` (SVG and PNG) and writes their data to `fig10.json`.
pub(super) fn write_figures(
    ctx: &StageContext,
    inputs: &ProfileInputs,
    record: &ProfilesRecord,
    model: &SubsurfaceModel,
    prepared: &PreparedFigures,
) -> Result<(), FitStageError> {
    let scanline = Scanline::new(inputs, record);
    let fig10 = fig10_plot(ctx, inputs, model, prepared, &scanline)?;
    fig10.write(&ctx.dir().join("fig10"))?;
    let profiles_plot = &prepared.profiles_plot;
    profiles_plot.write(&ctx.dir().join("pixel_profiles"))?;
    let data = json!({
        "fig10": series_json(&fig10),
        "pixel_profiles": series_json(profiles_plot),
    });
    let path = ctx.dir().join("fig10.json");
    mlsss_core::atomic_file::write_bytes_atomically(&path, data.to_string())
        .map_err(|source| FitStageError::Io { path, source })
}

/// Fig. 10: the held-out projector's slit (first training projector without holdout) along the
/// scanline: measured and (simulated capture) true global light against the model's and the
/// homogeneous model's.
fn fig10_plot(
    ctx: &StageContext,
    inputs: &ProfileInputs,
    model: &SubsurfaceModel,
    prepared: &PreparedFigures,
    scanline: &Scanline,
) -> Result<LinePlot, FitStageError> {
    let surface = &inputs.surface;
    let row = scanline.row;
    let size = (surface.width as u32, surface.height as u32);
    let k = prepared.projector;
    let slit = fig10_slit(&model.header.patterns);
    let mut series = Vec::new();
    if let Some(m) = &prepared.measured_slit {
        series.push(Series {
            label: "measured (R)".into(),
            colour: [200, 30, 30],
            mark: Mark::Dots,
            points: scanline.red_along(m),
        });
    }
    if let Some(t) = ctx.truth_dir()
        && let Some(p) = inputs.projectors.get(k)
        && let Some(truth) = true_slit_global(&t, k, &slit, p.black_level, size)?
    {
        series.push(Series {
            label: "true (R)".into(),
            colour: [40, 40, 40],
            mark: Mark::Dashed,
            points: scanline.red_along(&truth),
        });
    }
    series.extend(rendered_slit_series(model, k, &slit, scanline)?);
    Ok(LinePlot {
        title: format!(
            "Fig. 10: projector {k}{}, {}, row {row}",
            if model.header.holdout == Some(k) {
                " (held out)"
            } else {
                ""
            },
            slit.label()
        ),
        x_label: "camera column (px)".into(),
        y_label: "radiance (camera units)".into(),
        series,
    })
}

/// The model's and the homogeneous model's global light of projector `k`'s `slit` along the
/// scanline, as the `MLSSS (R)` and `homogeneous (R)` series.
fn rendered_slit_series(
    model: &SubsurfaceModel,
    k: usize,
    slit: &Pattern,
    scanline: &Scanline,
) -> Result<Vec<Series>, FitStageError> {
    let (row, w) = (scanline.row, scanline.width);
    let opts = RenderOptions::default();
    // The measured and true curves are the slit's light alone (without the black level's).
    // Rendered from the band of rows whose light reaches the scanline: the same curve as from
    // the whole image, for a fraction of the work.
    let mean = model.homogeneous_layers();
    let mean_extent = extent(mean.iter().flatten().copied());
    let band = model.rows_reaching(
        row..row + 1,
        |i| {
            let own = model.layers.extent(i);
            let mean = if model.surface.mask[i] {
                mean_extent
            } else {
                (0.0, 0.0)
            };
            (own.0.max(mean.0), own.1.max(mean.1))
        },
        &opts,
    );
    let r = row - band.start;
    let mut crop = model.rows_without_dipole(band);
    // The curves are the R channel alone: the G and B layers go before rendering. Channels
    // render independently, so R is the same bit for bit, for a third of the splats and blurs
    // (the two renders were most of the figures' 0.8-1.0 s at full size).
    crop.layers = red_layers_only(&crop.layers);
    let red_mean = [mean[0].clone(), Vec::new(), Vec::new()];
    let homogeneous = LayerModel::uniform(w, crop.header.height, &red_mean, &crop.surface.mask);
    let ours_alone = render_pattern_alone(&crop, k, slit, Baseline::Mlsss, &opts)?.global;
    crop.layers = homogeneous;
    let homogeneous_alone = render_pattern_alone(&crop, k, slit, Baseline::Mlsss, &opts)?.global;
    Ok([
        ("MLSSS (R)", [30, 90, 200], &ours_alone),
        ("homogeneous (R)", [60, 170, 60], &homogeneous_alone),
    ]
    .into_iter()
    .map(|(label, colour, alone)| Series {
        label: label.into(),
        colour,
        mark: Mark::Line,
        points: scanline.red_along_row(alone, r),
    })
    .collect())
}

/// `layers` with every pixel's G and B layers dropped.
fn red_layers_only(layers: &LayerModel) -> LayerModel {
    LayerModel::from_fn(layers.width, layers.height, |i, c| {
        let red = (c == 0).then(|| layers.layers(i, 0));
        red.into_iter().flatten()
    })
}

/// A few scanline pixels' profiles (R, first training projector, along x): samples against the
/// fitted model's profile.
fn pixel_profiles_plot(
    model_layers: &LayerModel,
    training: &[usize],
    sweeps: &[SlitSweep],
    geometries: &[GeometryMap],
    scanline: &Scanline,
) -> LinePlot {
    let (row, w, columns) = (scanline.row, scanline.width, &scanline.columns);
    let mut profile_series = Vec::new();
    let picks: Vec<usize> = [1usize, 2, 3]
        .iter()
        .filter_map(|q| columns.get(columns.len() * q / 4).map(|&x| row * w + x))
        .collect();
    let colours = [[200, 30, 30], [30, 90, 200], [60, 160, 60]];
    for (n, &i) in picks.iter().enumerate() {
        let (Some(geo), Some(sweep)) = (geometries[0].get(i).copied(), sweeps.first()) else {
            continue;
        };
        let Some(profile) = sweep.profile(i, 0, 0, &geo) else {
            continue;
        };
        let colour = colours[n % colours.len()];
        let pixel = format!("pixel ({}, {row})", i % w);
        profile_series.push(Series {
            label: format!("{pixel} samples"),
            colour,
            mark: Mark::Dots,
            points: profile.samples.iter().map(|s| (s.s, s.y)).collect(),
        });
        let half = profile.period.unwrap_or(10.0) / 2.0;
        let layers = model_layers.layers(i, 0).to_vec();
        profile_series.push(Series {
            label: format!("{pixel} model"),
            colour,
            mark: Mark::Line,
            points: (0..=200)
                .map(|j| {
                    let s = -half + 2.0 * half * f64::from(j) / 200.0;
                    (s, model_profile(&layers, geo.irradiance, &profile, s))
                })
                .collect(),
        });
    }
    LinePlot {
        title: format!("Profiles (R, projector {}, x): samples, model", training[0]),
        x_label: "signed distance to the slit centre on the surface (mm)".into(),
        y_label: "global radiance (camera units)".into(),
        series: profile_series,
    }
}

fn series_json(plot: &LinePlot) -> Value {
    json!({
        "title": plot.title,
        "x_label": plot.x_label,
        "y_label": plot.y_label,
        "series": plot.series.iter().map(|s| json!({
            "label": s.label,
            "points": s.points,
        })).collect::<Vec<_>>(),
    })
}

/// Measured global light of projector `k`'s `slit`, extracted from its frame as the profiles
/// stage does (`subsurface::slit_global`), from the separation of that projector's own white
/// frame (separation ran on every projector): the whole frame, where the fit holds the slits
/// at the pixels with profiles only (or, held out, not at all).
fn measured_global(
    ctx: &StageContext,
    inputs: &ProfileInputs,
    k: usize,
    slit: &Pattern,
) -> Result<Option<Vec<[f32; 3]>>, FitStageError> {
    let Some(p) = inputs.projectors.get(k) else {
        return Ok(None);
    };
    let Some(frame) = ctx.capture.manifest.plan.find(k as u8, slit) else {
        return Ok(None);
    };
    let pixels = ctx
        .capture
        .read_frame_pixels(frame.index)
        .map_err(ProfilesStageError::from)?;
    let white = mlsss_layer_model::slit_global::WhiteSeparation {
        direct: p.direct_white(),
        global: p.global_white(),
        stray: &p.stray,
        black_level: p.black_level,
        blur_px: p.blur_px,
    };
    Ok(mlsss_layer_model::slit_global::slit_global(&pixels, slit, &p.coords, &white).ok())
}
