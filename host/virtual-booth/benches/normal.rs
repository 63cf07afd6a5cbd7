//! Standard normal deviates: the hand-written ziggurat against `rand_distr::StandardNormal`
//! (also a ziggurat), both on the Pcg64 stream the camera noise uses, interleaved so both see
//! the same machine load. `cargo bench -p mlsss-virtual-booth --bench normal`.

use std::hint::black_box;
use std::time::Instant;

use mlsss_virtual_booth::ziggurat;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use rand_pcg::Pcg64;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    const DRAWS: usize = 10_000_000;
    let (mut ours, mut theirs) = (Vec::new(), Vec::new());
    let (mut moments_ours, mut moments_theirs) = ([0.0f64; 3], [0.0f64; 3]);
    for round in 0..7u64 {
        let mut rng = Pcg64::seed_from_u64(round);
        let t = Instant::now();
        let mut m = [0.0f64; 3];
        for _ in 0..DRAWS {
            let x = ziggurat::standard_normal(&mut rng);
            m[0] += x;
            m[1] += x * x;
            m[2] += x * x * x * x;
        }
        ours.push(t.elapsed().as_secs_f64());
        black_box(m);
        moments_ours = m;
        let mut rng = Pcg64::seed_from_u64(round);
        let t = Instant::now();
        let mut m = [0.0f64; 3];
        for _ in 0..DRAWS {
            let x: f64 = rng.sample(StandardNormal);
            m[0] += x;
            m[1] += x * x;
            m[2] += x * x * x * x;
        }
        theirs.push(t.elapsed().as_secs_f64());
        black_box(m);
        moments_theirs = m;
    }
    let per = |s: f64| s / DRAWS as f64 * 1e9;
    let (a, b) = (median(ours), median(theirs));
    println!(
        "ziggurat (ours): {:.2} ns/draw; rand_distr StandardNormal: {:.2} ns/draw (ratio {:.3})",
        per(a),
        per(b),
        b / a
    );
    for (name, m) in [("ours", moments_ours), ("rand_distr", moments_theirs)] {
        let n = DRAWS as f64;
        println!(
            "{name}: mean {:+.5}, variance {:.5}, fourth moment {:.4} (normal: 0, 1, 3)",
            m[0] / n,
            m[1] / n,
            m[2] / n
        );
    }
}
