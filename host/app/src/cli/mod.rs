//! One file per subcommand. Each file defines `Args` (clap) and `run(args) -> anyhow::Result<()>`.
//! Commands that measure something take `--json` and print exactly one JSON object on stdout;
//! progress and logs go to stderr.

pub mod bench;
pub mod booth;
pub mod calibrate;
pub mod decode;
pub mod demo;
pub mod eval;
pub mod mc;
pub mod monte_carlo_args;
pub mod normals;
pub mod number_arg;
pub mod output_paths;
pub mod process;
pub mod ps_scene;
pub mod render;
pub mod response;
pub mod rig;
pub mod simulate;
pub mod size_arg;
pub mod stage_bar;
