//! Fits free-means mixtures to the profiles given as JSON on stdin and prints our components,
//! final log-likelihood and time per profile as JSON on stdout. Driven by
//! `scripts/em_vs_sklearn.py` (and `scripts/peers.sh`), which runs scikit-learn's
//! GaussianMixture on the same data in the same run and compares.
//!
//! Input: `{"components": K, "profiles": [{"s": [...], "y": [...], "width": W, "period": T}]}`.

use std::io::Read;
use std::time::Instant;

use mlsss::layer_model::em_free::fit_free;
use mlsss::layer_model::mixture::{EmConfig, Profile, Sample};
use serde::Deserialize;

#[derive(Deserialize)]
struct Input {
    components: usize,
    profiles: Vec<InProfile>,
}

#[derive(Deserialize)]
struct InProfile {
    s: Vec<f64>,
    y: Vec<f64>,
    width: f64,
    period: Option<f64>,
}

fn main() -> anyhow::Result<()> {
    let mut text = String::new();
    std::io::stdin().read_to_string(&mut text)?;
    let input: Input = serde_json::from_str(&text)?;
    let cfg = EmConfig {
        components: input.components,
        bic: false,
        tolerance: 1e-9,
        max_iterations: 500,
        ..EmConfig::default()
    };
    let profiles: Vec<Profile> = input
        .profiles
        .iter()
        .map(|p| Profile {
            noise: None,
            samples: p
                .s
                .iter()
                .zip(&p.y)
                .map(|(&s, &y)| Sample { s, y })
                .collect(),
            slit_width: p.width,
            period: p.period,
            shift_per_depth: 0.0,
        })
        .collect();
    let mut out = Vec::new();
    let start = Instant::now();
    for profile in &profiles {
        let t = Instant::now();
        let fit = fit_free(profile, &cfg, None)?;
        out.push(serde_json::json!({
            "weights": fit.components.iter().map(|c| c.weight).collect::<Vec<_>>(),
            "means": fit.components.iter().map(|c| c.mean).collect::<Vec<_>>(),
            "sigmas": fit.components.iter().map(|c| c.sigma).collect::<Vec<_>>(),
            "log_likelihood": fit.log_likelihood,
            "iterations": fit.trace.iterations(),
            "seconds": t.elapsed().as_secs_f64(),
        }));
    }
    let json = serde_json::json!({
        "fits": out,
        "total_seconds": start.elapsed().as_secs_f64(),
    });
    println!("{json}");
    Ok(())
}
