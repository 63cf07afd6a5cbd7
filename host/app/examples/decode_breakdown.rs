//! Where the Gray-code decoder misses (issue 18) and how long it takes (issue 19).
//!
//! `decode_breakdown missed CAPTURE`: decodes every projector of a simulated capture with the
//! camera's noise model (as the decode stage does) and sorts the pixels lit in truth that are not
//! decoded by the decoder's reason (status of the first failing axis), by place (within 2 camera
//! pixels of a pixel the projector does not light: silhouette and shadow edges; else interior)
//! and by signal (the true direct white against the median of the lit pixels: below a quarter is
//! grazing or dark). Prints JSON.
//!
//! `decode_breakdown time DIR WIDTHxHEIGHT [REPEATS]`: decodes an OpenCV-ordered PNG sequence
//! REPEATS times and prints the best wall and the mean CPU seconds (all threads) of `decode`
//! alone, frames already loaded, and the best wall of each of the decoder's phases (and, with
//! `DECODE_OUT=DIR`, writes the decode there as the decode stage does).
//!
//! `decode_breakdown stage CAPTURE [REPEATS]`: the decode stage's work on a capture folder one
//! step at a time, every projector in turn: loading its frames, decoding them (REPEATS times,
//! with the decoder's own phases), writing the artefacts (into a temporary folder) and the
//! comparison with the truth. Prints the wall and CPU seconds (all threads) of each step summed
//! over the projectors, as JSON: where the stage's time goes.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

use anyhow::{Context, bail};
use mlsss::capture::{Capture, truth};
use mlsss::geometry::code_frames;
use mlsss::geometry::gray_code::{
    DecodeParams, DecodePhases, PixelStatus, ProjectorDecode, TruthComparison, decode, decode_timed,
};
use mlsss::imageio;
use mlsss::pipeline::decode_stage::load_coords;
use mlsss::pipeline::phase_clock::{PhaseClock, PhaseTimes};
use mlsss::resources::cpu_seconds;
use serde_json::json;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    match (args.get(1).map(String::as_str), args.get(2)) {
        (Some("missed"), Some(dir)) => missed(Path::new(dir)),
        (Some("time"), Some(dir)) => {
            let size = args.get(3).context("time needs WIDTHxHEIGHT")?;
            let (w, h) = size.split_once('x').context("size is WIDTHxHEIGHT")?;
            let repeats: usize = args.get(4).map_or(Ok(5), |r| r.parse())?;
            time(Path::new(dir), (w.parse()?, h.parse()?), repeats)
        }
        (Some("stage"), Some(dir)) => {
            let repeats: usize = args.get(3).map_or(Ok(1), |r| r.parse())?;
            stage(Path::new(dir), repeats)
        }
        _ => bail!(
            "usage: decode_breakdown missed CAPTURE | time DIR WxH [REPEATS] | stage CAPTURE \
             [REPEATS]"
        ),
    }
}

fn missed(dir: &Path) -> anyhow::Result<()> {
    let capture = Capture::open(dir)?;
    let truth_dir = dir.join("truth");
    let booth = &capture.manifest.booth;
    let mut out = Vec::new();
    for (k, proj) in booth.projectors.iter().enumerate() {
        let frames = code_frames::from_capture(&capture, k)?;
        let params = base_params()?.with_camera_noise(capture.manifest.frame_noise_of(k));
        let decoded = decode(&frames, (proj.width, proj.height), &params)?;
        let size = (decoded.width, decoded.height);
        let lit = load_coords(&truth::projector_coords(&truth_dir, k), size)?;
        let white = imageio::read_exr_rgb(&truth_dir.join(format!("proj{k}_direct_white.exr")))?;
        let signal: Vec<f32> = white.pixels().map(|p| p.0.iter().sum::<f32>()).collect();
        out.push(json!({
            "projector": k,
            "breakdown": breakdown(&decoded, &lit, &signal),
            "truth": TruthComparison::new(&decoded, &lit),
        }));
    }
    println!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}

/// Missed pixels (lit in truth, not decoded) counted by reason, place and signal, each as a
/// fraction of the pixels lit in truth.
fn breakdown(d: &ProjectorDecode, lit: &[Option<(f64, f64)>], signal: &[f32]) -> serde_json::Value {
    let (w, h) = (d.width as usize, d.height as usize);
    let mut lit_signal: Vec<f32> = (0..lit.len())
        .filter(|&i| lit[i].is_some())
        .map(|i| signal[i])
        .collect();
    let lit_count = lit_signal.len().max(1) as f64;
    let middle = lit_signal.len() / 2;
    let median = if lit_signal.is_empty() {
        0.0
    } else {
        *lit_signal.select_nth_unstable_by(middle, f32::total_cmp).1
    };
    let near_unlit = |i: usize| {
        let (x, y) = ((i % w) as isize, (i / w) as isize);
        (-2..=2).any(|dy| {
            (-2..=2).any(|dx| {
                let (nx, ny) = (x + dx, y + dy);
                nx < 0
                    || ny < 0
                    || nx >= w as isize
                    || ny >= h as isize
                    || lit[ny as usize * w + nx as usize].is_none()
            })
        })
    };
    let mut counts: BTreeMap<String, usize> = BTreeMap::new();
    for i in 0..lit.len() {
        if lit[i].is_none() || d.is_valid(i) {
            continue;
        }
        let status = [d.u.status[i], d.v.status[i]]
            .into_iter()
            .find(|s| !s.is_valid())
            .unwrap_or(PixelStatus::Decoded);
        let place = if near_unlit(i) { "edge" } else { "interior" };
        let level = if signal[i] < 0.25 * median {
            "dim"
        } else {
            "bright"
        };
        for key in [
            format!("status.{status:?}"),
            format!("place.{place}"),
            format!("signal.{level}"),
            format!("{place}.{level}.{status:?}"),
        ] {
            *counts.entry(key).or_default() += 1;
        }
        *counts.entry("missed".into()).or_default() += 1;
    }
    let fractions: BTreeMap<String, f64> = counts
        .into_iter()
        .map(|(k, v)| (k, v as f64 / lit_count))
        .collect();
    json!(fractions)
}

/// The decoder's defaults, with the fields of the JSON object in `DECODE_PARAMS` (if set) replaced.
fn base_params() -> anyhow::Result<DecodeParams> {
    let mut value = serde_json::to_value(DecodeParams::default())?;
    if let Ok(text) = std::env::var("DECODE_PARAMS") {
        let extra: serde_json::Value = serde_json::from_str(&text)?;
        for (k, v) in extra
            .as_object()
            .context("DECODE_PARAMS is a JSON object")?
        {
            value[k] = v.clone();
        }
    }
    Ok(serde_json::from_value(value)?)
}

fn time(dir: &Path, size: (u32, u32), repeats: usize) -> anyhow::Result<()> {
    let frames = code_frames::from_opencv_dir(dir, size)?;
    let params = DecodeParams::for_8_bit();
    let mut best = f64::INFINITY;
    let cpu_start = cpu_seconds().unwrap_or(f64::NAN);
    let mut valid = 0;
    let mut phases = [f64::INFINITY; 3];
    for _ in 0..repeats.max(1) {
        let start = Instant::now();
        let (decoded, times) = decode_timed(&frames, size, &params)?;
        best = best.min(start.elapsed().as_secs_f64());
        for (best, t) in phases
            .iter_mut()
            .zip([times.bits_s, times.repair_s, times.check_s])
        {
            *best = best.min(t);
        }
        valid = decoded.summary().valid;
        if let Ok(out) = std::env::var("DECODE_OUT") {
            mlsss::pipeline::decode_stage::write_decode(Path::new(&out), 0, &decoded)?;
        }
    }
    let cpu = (cpu_seconds().unwrap_or(f64::NAN) - cpu_start) / repeats.max(1) as f64;
    println!(
        "{}",
        json!({
            "best_wall_s": best,
            "mean_cpu_s": cpu,
            "best_phases_wall_s": {"bits": phases[0], "repair": phases[1], "check": phases[2]},
            "valid_pixels": valid,
        })
    );
    Ok(())
}

/// Wall and CPU seconds of `phase` in `times`, per repeat.
fn phase_json(times: &PhaseTimes, phase: &str, repeats: usize) -> serde_json::Value {
    let n = repeats.max(1) as f64;
    let per_repeat = |map: &BTreeMap<String, f64>| map.get(phase).map_or(f64::NAN, |s| s / n);
    json!({"wall_s": per_repeat(&times.phase_s), "cpu_s": per_repeat(&times.phase_cpu_s)})
}

fn stage(dir: &Path, repeats: usize) -> anyhow::Result<()> {
    let capture = Capture::open(dir)?;
    let truth_dir = dir.join("truth");
    let out = std::env::temp_dir().join(format!("decode-breakdown-{}", std::process::id()));
    let booth = &capture.manifest.booth;
    let mut phases = DecodePhases::default();
    let repeats = repeats.max(1);
    // As the stage does: each projector's frames are read into the previous one's buffers.
    let mut spare = None;
    let mut clock = PhaseClock::start();
    for (k, proj) in booth.projectors.iter().enumerate() {
        let frames = code_frames::from_capture_reusing(&capture, k, spare.take())?;
        clock.lap("load");
        let params = base_params()?.with_camera_noise(capture.manifest.frame_noise_of(k));
        let mut decoded = None;
        for _ in 0..repeats {
            let (d, p) = decode_timed(&frames, (proj.width, proj.height), &params)?;
            phases.bits_s += p.bits_s;
            phases.repair_s += p.repair_s;
            phases.check_s += p.check_s;
            decoded = Some(d);
        }
        clock.lap("decode");
        let decoded = decoded.context("no decode")?;
        spare = Some(frames);
        mlsss::pipeline::decode_stage::write_decode(&out, k, &decoded)?;
        clock.lap("write");
        let size = (decoded.width, decoded.height);
        let lit = load_coords(&truth::projector_coords(&truth_dir, k), size)?;
        std::hint::black_box(TruthComparison::new(&decoded, &lit));
        clock.lap("truth");
    }
    std::fs::remove_dir_all(&out).ok();
    let times = clock.finish();
    let n = repeats as f64;
    println!(
        "{}",
        serde_json::to_string_pretty(&json!({
            "load": phase_json(&times, "load", 1),
            "decode": phase_json(&times, "decode", repeats),
            "decode_phases_wall_s": {
                "bits": phases.bits_s / n,
                "repair": phases.repair_s / n,
                "check": phases.check_s / n,
            },
            "write": phase_json(&times, "write", 1),
            "truth": phase_json(&times, "truth", 1),
        }))?
    );
    Ok(())
}
