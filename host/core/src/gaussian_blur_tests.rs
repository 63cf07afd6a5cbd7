//! The shared blur against a naive reference, and bit for bit against the five blurs it replaced
//! (kept here verbatim as the definition of their callers' numbers).

use super::*;
use proptest::prelude::*;

/// Direct 2-D convolution in f64 with the continuous formula: out(x, y) =
/// sum_ij g(i) g(j) v(border(x + i), border(y + j)) / (sum g)^2.
fn naive_2d(
    data: &[f64],
    w: usize,
    h: usize,
    sigma: f64,
    truncate: f64,
    border: Border,
) -> Vec<f64> {
    let r = (truncate * sigma).ceil().max(1.0) as isize;
    let g = |k: isize| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp();
    let norm: f64 = (-r..=r).map(g).sum();
    let mut out = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0;
            for j in -r..=r {
                for i in -r..=r {
                    let (Some(xx), Some(yy)) = (
                        border.index(x as isize + i, w),
                        border.index(y as isize + j, h),
                    ) else {
                        continue;
                    };
                    acc += g(i) * g(j) * data[yy * w + xx];
                }
            }
            out[y * w + x] = acc / (norm * norm);
        }
    }
    out
}

fn bits32(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn bits64(v: &[f64]) -> Vec<u64> {
    v.iter().map(|x| x.to_bits()).collect()
}

// ---- The replaced blurs, verbatim but for their signatures. ----

/// virtual-booth subsurface_transport.rs `gaussian_filter`.
fn old_subsurface(data: &[[f64; 3]], side: usize, sigma: f64) -> Vec<[f64; 3]> {
    if sigma < 0.25 {
        return data.to_vec();
    }
    let radius = (3.5 * sigma).ceil() as isize;
    let kernel: Vec<f64> = (-radius..=radius)
        .map(|k| (-0.5 * (k as f64 / sigma).powi(2)).exp())
        .collect();
    let norm: f64 = kernel.iter().sum();
    let pass = |src: &[[f64; 3]], horizontal: bool| -> Vec<[f64; 3]> {
        let mut dst = vec![[0.0; 3]; src.len()];
        for y in 0..side {
            for x in 0..side {
                let mut acc = [0.0; 3];
                for (k, w) in kernel.iter().enumerate() {
                    let o = k as isize - radius;
                    let (sx, sy) = if horizontal {
                        (x as isize + o, y as isize)
                    } else {
                        (x as isize, y as isize + o)
                    };
                    if sx < 0 || sy < 0 || sx as usize >= side || sy as usize >= side {
                        continue;
                    }
                    let v = src[sy as usize * side + sx as usize];
                    for c in 0..3 {
                        acc[c] += w * v[c];
                    }
                }
                dst[y * side + x] = acc.map(|a| a / norm);
            }
        }
        dst
    };
    pass(&pass(data, true), false)
}

/// virtual-booth projector.rs `gaussian_blur`.
fn old_projector(data: &[f64], sigma: f64) -> Vec<f64> {
    let radius = (3.5 * sigma).ceil() as isize;
    let kernel: Vec<f64> = (-radius..=radius)
        .map(|k| (-0.5 * (k as f64 / sigma).powi(2)).exp())
        .collect();
    let norm: f64 = kernel.iter().sum();
    (0..data.len() as isize)
        .map(|i| {
            kernel
                .iter()
                .enumerate()
                .filter_map(|(j, w)| {
                    let idx = i + j as isize - radius;
                    (idx >= 0 && (idx as usize) < data.len()).then(|| w * data[idx as usize])
                })
                .sum::<f64>()
                / norm
        })
        .collect()
}

/// layer-model render.rs `kernel`.
fn old_render_kernel(sigma: f64, truncate: f64) -> Vec<f32> {
    if sigma <= 0.0 {
        return vec![1.0];
    }
    let r = (truncate * sigma).ceil().max(1.0) as i64;
    let raw: Vec<f64> = (-r..=r)
        .map(|k| (-0.5 * (k as f64 / sigma).powi(2)).exp())
        .collect();
    let sum: f64 = raw.iter().sum();
    raw.iter().map(|v| (v / sum) as f32).collect()
}

/// layer-model render.rs `gaussian_blur`.
fn old_render(img: &mut [f32], w: usize, h: usize, sigma: f64, truncate: f64) {
    let k = old_render_kernel(sigma, truncate);
    if k.len() == 1 {
        return;
    }
    let r = k.len() / 2;
    let mut line = vec![0.0f32; w + 2 * r];
    for row in img.chunks_mut(w) {
        line[r..r + w].copy_from_slice(row);
        for (x, o) in row.iter_mut().enumerate() {
            *o = line[x..x + k.len()]
                .iter()
                .zip(&k)
                .map(|(v, k)| v * k)
                .sum();
        }
    }
    let src = img.to_vec();
    for y in 0..h {
        let out = &mut img[y * w..(y + 1) * w];
        out.iter_mut().for_each(|v| *v = 0.0);
        let lo = y.saturating_sub(r);
        let hi = (y + r).min(h - 1);
        for yy in lo..=hi {
            let kv = k[yy + r - y];
            for (o, v) in out.iter_mut().zip(&src[yy * w..(yy + 1) * w]) {
                *o += kv * v;
            }
        }
    }
}

/// vision chessboard.rs `gaussian_blur` (on a bare buffer).
fn old_chessboard(data: &[f32], w: usize, h: usize, sigma: f32) -> Vec<f32> {
    let radius = (3.0 * sigma).ceil().max(1.0) as isize;
    let kernel: Vec<f32> = (-radius..=radius)
        .map(|i| (-(i * i) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let norm: f32 = kernel.iter().sum();
    let kernel: Vec<f32> = kernel.iter().map(|k| k / norm).collect();
    let (w, h) = (w as isize, h as isize);
    let mut tmp = vec![0.0f32; data.len()];
    for y in 0..h {
        let row = &data[(y * w) as usize..((y + 1) * w) as usize];
        for x in 0..w {
            let mut acc = 0.0;
            for (k, &kv) in kernel.iter().enumerate() {
                let xx = (x + k as isize - radius).clamp(0, w - 1);
                acc += kv * row[xx as usize];
            }
            tmp[(y * w + x) as usize] = acc;
        }
    }
    let mut out = vec![0.0f32; data.len()];
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0;
            for (k, &kv) in kernel.iter().enumerate() {
                let yy = (y + k as isize - radius).clamp(0, h - 1);
                acc += kv * tmp[(yy * w + x) as usize];
            }
            out[(y * w + x) as usize] = acc;
        }
    }
    out
}

/// vision separation.rs test helper `gauss_blur` (periodic).
fn old_separation(signal: &[f64], sigma: f64) -> Vec<f64> {
    if sigma <= 0.0 {
        return signal.to_vec();
    }
    let r = (4.0 * sigma).ceil() as i64;
    let weights: Vec<f64> = (-r..=r)
        .map(|k| (-(k as f64).powi(2) / (2.0 * sigma * sigma)).exp())
        .collect();
    let norm: f64 = weights.iter().sum();
    let n = signal.len() as i64;
    (0..n)
        .map(|i| {
            (-r..=r)
                .map(|k| signal[(i + k).rem_euclid(n) as usize] * weights[(k + r) as usize])
                .sum::<f64>()
                / norm
        })
        .collect()
}

/// vision geometry/synthetic.rs `gaussian_kernel`: quarter-pixel taps out to 3 sigma.
fn old_synthetic_kernel(sigma: f64) -> Vec<(f64, f32)> {
    if sigma <= 0.0 {
        return vec![(0.0, 1.0)];
    }
    let step = 0.25;
    let n = (3.0 * sigma / step).ceil() as i32;
    let taps: Vec<(f64, f64)> = (-n..=n)
        .map(|i| {
            let o = i as f64 * step;
            (o, (-0.5 * (o / sigma).powi(2)).exp())
        })
        .collect();
    let total: f64 = taps.iter().map(|t| t.1).sum();
    taps.into_iter()
        .map(|(o, w)| (o, (w / total) as f32))
        .collect()
}

// ---- Strategies. ----

/// Values with exact zeros, negatives and a wide spread of magnitudes.
fn value() -> impl Strategy<Value = f64> {
    prop_oneof![
        1 => Just(0.0),
        6 => -10.0..10.0f64,
        1 => -1e6..1e6f64,
    ]
}

fn image(max_side: usize) -> impl Strategy<Value = (usize, usize, Vec<f64>)> {
    (1..=max_side, 1..=max_side)
        .prop_flat_map(|(w, h)| (Just(w), Just(h), prop::collection::vec(value(), w * h)))
}

fn border() -> impl Strategy<Value = Border> {
    prop_oneof![Just(Border::Zero), Just(Border::Clamp), Just(Border::Wrap)]
}

proptest! {
    #[test]
    fn banded_blur_is_bit_identical_to_the_serial_one(
        (w, h, data) in image(48),
        sigma in 0.3..6.0f64,
        truncate in 1.0..4.0f64,
        border in border(),
        outputs in any::<bool>(),
        band_rows in 1..70usize,
    ) {
        let normalisation = if outputs { Normalisation::Outputs } else { Normalisation::Weights };
        let kernel = GaussianKernel::new(sigma, truncate, normalisation);
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        // Each output pixel is mapped with its index: a mix-up of pixels shows.
        let banded = |kernel: &GaussianKernel<f64>, data: &[f64]| {
            blur_2d_mapped_in_bands(w, h, kernel, border, |i| data[i], |i, v| (i, v), band_rows)
        };
        let mut serial = data.clone();
        blur_2d(&mut serial, w, h, &kernel, border).unwrap();
        let got = banded(&kernel, &data);
        prop_assert!(got.iter().enumerate().all(|(i, &(j, _))| i == j));
        prop_assert_eq!(bits(&got.iter().map(|p| p.1).collect::<Vec<_>>()), bits(&serial));
        // Multi-channel samples in f64 (the point normals' moments, the fusion's sums) and
        // f32 samples with f32 weights (the renderer's images).
        let tuples: Vec<[f64; 10]> = data.iter().map(|&v| std::array::from_fn(|k| v * k as f64 - 1.0)).collect();
        let mut serial = tuples.clone();
        blur_2d(&mut serial, w, h, &kernel, border).unwrap();
        let got = blur_2d_mapped_in_bands(w, h, &kernel, border, |i| tuples[i], |_, v| v, band_rows);
        prop_assert_eq!(bits(serial.as_flattened()), bits(got.as_flattened()));
        let kernel = kernel.to_f32();
        let floats: Vec<f32> = data.iter().map(|&v| v as f32).collect();
        let mut serial = floats.clone();
        blur_2d(&mut serial, w, h, &kernel, border).unwrap();
        let got = blur_2d_mapped_in_bands(w, h, &kernel, border, |i| floats[i], |_, v| v, band_rows);
        let bits32 = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        prop_assert_eq!(bits32(&got), bits32(&serial));
    }

    #[test]
    fn matches_the_naive_double_sum_under_every_border(
        (w, h, data) in image(12),
        sigma in 0.3..4.0f64,
        truncate in 1.0..4.0f64,
        border in border(),
        outputs in any::<bool>(),
    ) {
        let normalisation = if outputs { Normalisation::Outputs } else { Normalisation::Weights };
        let kernel = GaussianKernel::new(sigma, truncate, normalisation);
        let mut got = data.clone();
        blur_2d(&mut got, w, h, &kernel, border).unwrap();
        let want = naive_2d(&data, w, h, sigma, truncate, border);
        let scale = data.iter().fold(1.0f64, |m, v| m.max(v.abs()));
        for (g, n) in got.iter().zip(&want) {
            prop_assert!((g - n).abs() <= 1e-12 * scale, "{g} vs {n}");
        }
        // The 1-D blur of the first row against the naive single sum.
        let row = blur_1d(&data[..w], &kernel, border);
        let r = (truncate * sigma).ceil().max(1.0) as isize;
        let g = |k: isize| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp();
        let norm: f64 = (-r..=r).map(g).sum();
        for (x, got) in row.iter().enumerate() {
            let want: f64 = (-r..=r)
                .filter_map(|i| border.index(x as isize + i, w).map(|j| g(i) * data[j]))
                .sum::<f64>()
                / norm;
            prop_assert!((got - want).abs() <= 1e-12 * scale, "{got} vs {want}");
        }
    }

    #[test]
    fn identical_to_the_old_subsurface_filter((side, data) in (1..14usize).prop_flat_map(|s| {
        (Just(s), prop::collection::vec([value(), value(), value()], s * s))
    }), sigma in 0.25..3.0f64) {
        let want = old_subsurface(&data, side, sigma);
        let mut got = data.clone();
        let kernel = GaussianKernel::new(sigma, 3.5, Normalisation::Outputs);
        blur_2d(&mut got, side, side, &kernel, Border::Zero).unwrap();
        let flat = |v: &[[f64; 3]]| v.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
        prop_assert_eq!(flat(&got), flat(&want));
    }

    #[test]
    fn identical_to_the_old_projector_profile_blur(
        data in prop::collection::vec(0.0..1.0f64, 1..200),
        sigma in 0.01..20.0f64,
    ) {
        let kernel = GaussianKernel::new(sigma, 3.5, Normalisation::Outputs);
        prop_assert_eq!(
            bits64(&blur_1d(&data, &kernel, Border::Zero)),
            bits64(&old_projector(&data, sigma))
        );
    }

    #[test]
    fn identical_to_the_old_render_blur(
        (w, h, data) in image(40),
        sigma in 0.0..6.0f64,
        truncate in 1.0..5.0f64,
    ) {
        let data: Vec<f32> = data.iter().map(|&v| v as f32).collect();
        let mut want = data.clone();
        old_render(&mut want, w, h, sigma, truncate);
        let mut got = data;
        let kernel = GaussianKernel::new(sigma, truncate, Normalisation::Weights).to_f32();
        blur_2d(&mut got, w, h, &kernel, Border::Zero).unwrap();
        prop_assert_eq!(bits32(&got), bits32(&want));
    }

    #[test]
    fn identical_to_the_old_chessboard_blur(
        (w, h, data) in image(30),
        sigma in 0.1..4.0f32,
    ) {
        let data: Vec<f32> = data.iter().map(|&v| v as f32).collect();
        let want = old_chessboard(&data, w, h, sigma);
        let mut got = data;
        let kernel = GaussianKernel::new(sigma, 3.0, Normalisation::Weights);
        blur_2d(&mut got, w, h, &kernel, Border::Clamp).unwrap();
        prop_assert_eq!(bits32(&got), bits32(&want));
    }

    #[test]
    fn matches_the_old_periodic_blur(
        data in prop::collection::vec(0.0..1.0f64, 1..100),
        sigma in 0.0..30.0f64,
    ) {
        // The old helper wrote the weight as exp(-k^2 / (2 sigma^2)): equal to rounding.
        let kernel = GaussianKernel::new(sigma, 4.0, Normalisation::Outputs);
        let got = blur_1d(&data, &kernel, Border::Wrap);
        for (g, o) in got.iter().zip(old_separation(&data, sigma)) {
            prop_assert!((g - o).abs() <= 1e-14, "{g} vs {o}");
        }
    }

    #[test]
    fn identical_to_the_old_synthetic_kernel(sigma in 0.0..8.0f64) {
        // Quarter-pixel taps: the kernel of sigma / step taps, offsets scaled by the step.
        let step = 0.25;
        let kernel = GaussianKernel::new(sigma / step, 3.0, Normalisation::Weights).to_f32();
        let got: Vec<(f64, f32)> =
            kernel.taps().map(|(k, w)| (k as f64 * step, w)).collect();
        let want = old_synthetic_kernel(sigma);
        prop_assert_eq!(got.len(), want.len());
        for (g, o) in got.iter().zip(&want) {
            prop_assert_eq!((g.0.to_bits(), g.1.to_bits()), (o.0.to_bits(), o.1.to_bits()));
        }
    }
}

#[test]
fn borders_differ_as_documented_at_the_ends() {
    // A step 1 | 0 ...: zero loses mass at the left end, clamp replicates the 1, wrap reads the
    // far end.
    let data = [1.0f64, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 5.0];
    let kernel = GaussianKernel::new(1.0, 3.0, Normalisation::Weights);
    let zero = blur_1d(&data, &kernel, Border::Zero);
    let clamp = blur_1d(&data, &kernel, Border::Clamp);
    let wrap = blur_1d(&data, &kernel, Border::Wrap);
    assert!(zero[0] < clamp[0]);
    assert!(wrap[0] > clamp[0], "the 5 at the far end wraps in");
    // Mass: wrap keeps it exactly (to rounding), zero loses some.
    let total = |v: &[f64]| v.iter().sum::<f64>();
    assert!((total(&wrap) - 6.0).abs() < 1e-12);
    assert!(total(&zero) < 6.0 - 1e-3);
}

#[test]
fn identity_and_bad_shapes() {
    let kernel = GaussianKernel::<f64>::new(0.0, 3.0, Normalisation::Weights);
    assert!(kernel.is_identity());
    let data = [1.0, -2.0, 3.0];
    assert_eq!(blur_1d(&data, &kernel, Border::Zero), data);
    // The identity leaves every sample as it is, a negative zero too, as `blur_2d` does.
    let signed = [1.0, -0.0, 3.0, -4.0, 0.5, 6.0];
    let mapped = blur_2d_mapped(
        3,
        2,
        &kernel,
        Border::Zero,
        |i| signed[i],
        |_, v| v.to_bits(),
    );
    assert_eq!(mapped, signed.map(f64::to_bits));
    let none = blur_2d_mapped(0, 5, &kernel, Border::Clamp, |_| 1.0, |i, v: f64| (i, v));
    assert!(none.is_empty());
    let mut img = vec![0.0f64; 6];
    let k = GaussianKernel::new(1.0, 3.0, Normalisation::Weights);
    assert_eq!(
        blur_2d(&mut img, 4, 2, &k, Border::Zero),
        Err(BlurError::Shape {
            len: 6,
            width: 4,
            height: 2
        })
    );
    assert_eq!(blur_2d(&mut img, 3, 2, &k, Border::Zero), Ok(()));
    assert_eq!(
        blur_2d(&mut [] as &mut [f64], 0, 5, &k, Border::Clamp),
        Ok(())
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(12))]

    /// Rows longer than a pass's block of outputs (full-size camera rows): still the old
    /// render blur bit for bit, across the block seams.
    #[test]
    fn long_rows_identical_to_the_old_render_blur(
        (w, h, data) in (500..1400usize, 1..4usize).prop_flat_map(|(w, h)| {
            (Just(w), Just(h), prop::collection::vec(value(), w * h))
        }),
        sigma in 0.0..30.0f64,
    ) {
        let data: Vec<f32> = data.iter().map(|&v| v as f32).collect();
        let mut want = data.clone();
        old_render(&mut want, w, h, sigma, 3.5);
        let mut got = data;
        let kernel = GaussianKernel::new(sigma, 3.5, Normalisation::Weights).to_f32();
        blur_2d(&mut got, w, h, &kernel, Border::Zero).unwrap();
        prop_assert_eq!(bits32(&got), bits32(&want));
    }
}
