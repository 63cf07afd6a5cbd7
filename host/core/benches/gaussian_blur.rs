//! The renderer's blur (f32, zero border, weights normalised up front) through the shared
//! `gaussian_blur` module against the renderer's former hand-written one, interleaved so both
//! see the same machine load. `cargo bench -p mlsss-core --bench gaussian_blur`.

use std::hint::black_box;
use std::time::Instant;

use mlsss_core::gaussian_blur::{Border, GaussianKernel, Normalisation, blur_2d};

/// layer-model render.rs `gaussian_blur` before it moved to mlsss-core (the baseline).
fn old_render(img: &mut [f32], w: usize, h: usize, sigma: f64, truncate: f64) {
    let k: Vec<f32> = {
        let r = (truncate * sigma).ceil().max(1.0) as i64;
        let raw: Vec<f64> = (-r..=r)
            .map(|k| (-0.5 * (k as f64 / sigma).powi(2)).exp())
            .collect();
        let sum: f64 = raw.iter().sum();
        raw.iter().map(|v| (v / sum) as f32).collect()
    };
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

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    // Bin images of the renderer: a level-0 bin of a quick-demo crop and a coarse level's.
    for &(w, h, sigma) in &[
        (640usize, 480usize, 2.5f64),
        (640, 480, 6.0),
        (160, 120, 3.0),
    ] {
        let truncate = 3.5;
        let image: Vec<f32> = (0..w * h)
            .map(|i| ((i * 2654435761) % 1000) as f32 * 1e-3)
            .collect();
        let reps = if w * h > 100_000 { 30 } else { 300 };
        let (mut old, mut new) = (Vec::new(), Vec::new());
        for _ in 0..reps {
            let mut a = image.clone();
            let t = Instant::now();
            old_render(black_box(&mut a), w, h, sigma, truncate);
            old.push(t.elapsed().as_secs_f64());
            let mut b = image.clone();
            let t = Instant::now();
            let kernel = GaussianKernel::new(sigma, truncate, Normalisation::Weights).to_f32();
            blur_2d(black_box(&mut b), w, h, &kernel, Border::Zero).expect("w x h image");
            new.push(t.elapsed().as_secs_f64());
            assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()));
        }
        let (old, new) = (median(old), median(new));
        println!(
            "{w}x{h} sigma {sigma}: old {:.3} ms, shared {:.3} ms (ratio {:.3})",
            old * 1e3,
            new * 1e3,
            new / old
        );
    }
}
