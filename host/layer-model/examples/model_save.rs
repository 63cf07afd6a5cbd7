//! Times saving a model file: `cargo run --release -p mlsss-layer-model --example model_save --
//! MODEL OUT [ROUNDS]` loads MODEL, saves it to OUT ROUNDS times (3 by default) and prints each
//! save's wall-clock and CPU seconds (all threads), then whether OUT's bytes equal MODEL's.

use std::time::Instant;

use mlsss_core::resources::cpu_seconds;
use mlsss_layer_model::model_file::SubsurfaceModel;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let [_, model, out, rest @ ..] = args.as_slice() else {
        return Err("usage: model_save MODEL OUT [ROUNDS]".into());
    };
    let rounds: usize = rest.first().map_or(Ok(3), |r| r.parse())?;
    let loaded = SubsurfaceModel::load(model.as_ref())?;
    for round in 0..rounds {
        let (t, c) = (Instant::now(), cpu_seconds());
        loaded.save(out.as_ref())?;
        let cpu = cpu_seconds().zip(c).map_or(f64::NAN, |(b, a)| b - a);
        println!(
            "save {round}: {:.3} s wall, {cpu:.2} CPU-s",
            t.elapsed().as_secs_f64()
        );
    }
    let same = std::fs::read(model)? == std::fs::read(out)?;
    println!("bytes equal to {model}: {same}");
    Ok(())
}
