//! `mlsss`: the command-line program. A thin layer over the `mlsss` library: argument parsing,
//! progress and error reporting; all work happens in the library. One file per subcommand in `cli/`.

mod cli;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// Measure and render the multi-layered subsurface scattering of skin (MLSSS) from a booth of
/// four projectors and one camera.
#[derive(Debug, Parser)]
#[command(name = "mlsss", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Inspect a booth description: parse and validate it, summarise the frame plan.
    Booth(cli::booth::Args),
    /// Booth controller: find it, run a capture, measure its timing (real board or QEMU).
    Rig(cli::rig::Args),
    /// Render a capture in the virtual booth (Monte Carlo skin, noise) with ground truth.
    Simulate(cli::simulate::Args),
    /// Calibrate the camera and projectors from chessboard poses (or convert an OpenCV calibration).
    Calibrate(cli::calibrate::Args),
    /// Photometric stereo on an image set under distant lights (normals, albedo, errors).
    Normals(cli::normals::Args),
    /// Render a photometric-stereo test set with known normals, shadows and highlights.
    PsScene(cli::ps_scene::Args),
    /// Projector response (gamma, black level) from calibration captures, into the calibration.
    Response(cli::response::Args),
    /// Monte Carlo light transport in layered media (MCML physics): slab, layers file, benchmark.
    Mc(cli::mc::Args),
    /// Decode Gray-code frames to projector coordinates per camera pixel (capture or OpenCV order).
    Decode(cli::decode::Args),
    /// Run the processing pipeline on a capture up to a stage (decode ... fit) and report.
    Process(cli::process::Args),
    /// Render a projector's pattern on the measured face from a fitted model file (EXR + PNG).
    Render(cli::render::Args),
    /// Simulate, calibrate, process with a projector held out, relight it, evaluate: the main job.
    Demo(cli::demo::Args),
    /// Relight a held-out projector from a fitted model and compare with its frames (and truth).
    Eval(cli::eval::Args),
    /// Runtime against held-out error over the quality knobs: CSV table and Pareto-front plot.
    Bench(cli::bench::Args),
}

/// Lets every flag of every subcommand take a negative number (`--g -0.3`), which clap would
/// otherwise read as an unknown flag.
fn allow_negative_numbers(command: clap::Command) -> clap::Command {
    command
        .allow_negative_numbers(true)
        .mut_subcommands(allow_negative_numbers)
}

/// The error and its causes, one line each. Errors that already print their source in their
/// own message (`{path}: {source}`) would otherwise show each cause two or more times: a cause
/// whose text the line above already ends with is left out.
fn error_lines(err: &anyhow::Error) -> Vec<String> {
    let mut lines: Vec<String> = Vec::new();
    for cause in err.chain() {
        let text = cause.to_string();
        let already_said = lines
            .last()
            .is_some_and(|above| above.ends_with(&text) || above.contains(&format!("{text}: ")));
        if !already_said && !text.is_empty() {
            lines.push(text);
        }
    }
    lines
}

/// Starts the program again, once, with glibc's allocator on transparent huge pages where the
/// kernel gives them only on request ([`mlsss_core::resources::tunables_for_huge_page_malloc`]
/// says when, and why). glibc reads `GLIBC_TUNABLES` only at start-up, so a fresh start of the
/// same executable with the same arguments is the only way in; it keeps the process (its id,
/// standard streams and exit status). Does nothing where that does not apply, and carries on as
/// started if the restart fails.
fn restart_with_huge_page_malloc() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        use std::os::unix::process::CommandExt;
        /// Set in the restarted process: never restart twice, whatever glibc makes of the
        /// tunables.
        const RESTARTED: &str = "MLSSS_RESTARTED_FOR_HUGE_PAGES";
        if std::env::var_os(RESTARTED).is_some() {
            return;
        }
        let current = match std::env::var_os("GLIBC_TUNABLES") {
            None => None,
            Some(value) => match value.into_string() {
                Ok(text) => Some(text),
                Err(_) => return,
            },
        };
        let Ok(thp) = std::fs::read_to_string("/sys/kernel/mm/transparent_hugepage/enabled") else {
            return;
        };
        let Some(tunables) =
            mlsss_core::resources::tunables_for_huge_page_malloc(current.as_deref(), &thp)
        else {
            return;
        };
        let Ok(executable) = std::env::current_exe() else {
            return;
        };
        let mut args = std::env::args_os();
        let mut command = std::process::Command::new(executable);
        if let Some(name) = args.next() {
            command.arg0(name);
        }
        // `exec` returns only when it failed.
        let _failed = command
            .args(args)
            .env("GLIBC_TUNABLES", tunables)
            .env(RESTARTED, "1")
            .exec();
    }
}

fn main() -> ExitCode {
    use clap::{CommandFactory, FromArgMatches};
    restart_with_huge_page_malloc();
    mlsss_core::resources::keep_freed_memory_for_reuse();
    let matches = allow_negative_numbers(Cli::command()).get_matches();
    let cli = match Cli::from_arg_matches(&matches) {
        Ok(cli) => cli,
        Err(err) => err.exit(),
    };
    let result = match cli.command {
        Command::Booth(args) => cli::booth::run(args),
        Command::Rig(args) => cli::rig::run(args),
        Command::Simulate(args) => cli::simulate::run(args),
        Command::Calibrate(args) => cli::calibrate::run(args),
        Command::Normals(args) => cli::normals::run(args),
        Command::PsScene(args) => cli::ps_scene::run(args),
        Command::Response(args) => cli::response::run(args),
        Command::Mc(args) => cli::mc::run(args),
        Command::Decode(args) => cli::decode::run(args),
        Command::Process(args) => cli::process::run(args),
        Command::Render(args) => cli::render::run(args),
        Command::Demo(args) => cli::demo::run(args),
        Command::Eval(args) => cli::eval::run(args),
        Command::Bench(args) => cli::bench::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            let mut lines = error_lines(&err).into_iter();
            eprintln!("error: {}", lines.next().unwrap_or_default());
            for cause in lines {
                eprintln!("  caused by: {cause}");
            }
            ExitCode::FAILURE
        }
    }
}
