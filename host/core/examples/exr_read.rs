//! Times reading EXR files: `cargo run --release -p mlsss-core --example exr_read -- FILE...`
//! reads each file 5 times as RGB and prints the CPU seconds (all threads) per read.

use mlsss_core::imageio::read_exr_rgb;
use mlsss_core::resources::cpu_seconds;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    for path in std::env::args().skip(1) {
        let (t, c) = (std::time::Instant::now(), cpu_seconds());
        for _ in 0..5 {
            read_exr_rgb(path.as_ref())?;
        }
        let cpu = cpu_seconds().zip(c).map_or(f64::NAN, |(b, a)| b - a);
        println!(
            "{path}: {:.3} CPU-s, {:.3} s wall per read",
            cpu / 5.0,
            t.elapsed().as_secs_f64() / 5.0
        );
    }
    Ok(())
}
