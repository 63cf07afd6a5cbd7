//! `mlsss calibrate`: camera and projector calibration from chessboard poses, or conversion of an
//! OpenCV FileStorage calibration into our JSON.

use std::path::{Path, PathBuf};

use super::size_arg::parse_size;
use anyhow::{Context, bail};
use indicatif::{ProgressBar, ProgressStyle};
use mlsss::capture::Capture;
use mlsss::chessboard_calibration::opencv_storage::{read_opencv, write_opencv};
use mlsss::chessboard_calibration::pose_measurement::PoseLayout;
use mlsss::chessboard_calibration::procam::{
    BoardSpec, ProcamOptions, ProcamResult, distortion_term_names,
};
use mlsss::pose_calibration::calibrate_poses;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Layout {
    /// Our capture folders (capture.json of kind `calibration`), all projectors of the booth.
    Capture,
    /// OpenCV-ordered Gray-code sequences of one projector: code frames, then white, then black.
    Opencv,
}

#[derive(Debug, clap::Args)]
pub struct Args {
    /// One folder per chessboard pose.
    #[arg(required_unless_present = "from_opencv")]
    captures: Vec<PathBuf>,
    /// Inner corners of the chessboard, COLSxROWS (e.g. 9x7). Default: the board a simulated
    /// capture records in its capture.json (real captures do not record it).
    #[arg(long, value_parser = parse_size, requires = "square")]
    board: Option<(u32, u32)>,
    /// Side of a chessboard square in millimetres (default: as --board).
    #[arg(long, requires = "board", value_parser = super::number_arg::positive_finite)]
    square: Option<f64>,
    /// Layout of the pose folders.
    #[arg(long, value_enum, default_value_t = Layout::Capture)]
    layout: Layout,
    /// Projector size WxH: required by `--layout opencv` (and by `--from-opencv` when the file
    /// does not store it).
    #[arg(long, value_parser = parse_size)]
    projector: Option<(u32, u32)>,
    /// Do not estimate the sixth-order radial coefficient k3 (keeps it 0; advisable with few poses).
    #[arg(long)]
    fix_k3: bool,
    /// Estimate every allowed distortion term of every device instead of, per device, the fewest
    /// that the corners support (chosen by the Bayesian information criterion; with a narrow
    /// field of view the high-order terms cannot be measured and only trade against the focal
    /// length and principal point).
    #[arg(long)]
    all_distortion_terms: bool,
    /// Convert this OpenCV FileStorage calibration (.xml/.yml) into our JSON instead of calibrating.
    #[arg(long, conflicts_with_all = ["captures", "board", "square"])]
    from_opencv: Option<PathBuf>,
    /// Output calibration JSON.
    #[arg(long)]
    out: PathBuf,
    /// OpenCV FileStorage copy of the result (.xml or .yml); default: --out with extension .xml.
    #[arg(long)]
    opencv_out: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

/// The chessboard from `--board` and `--square`, or else from the first simulated capture.
fn board_of(args: &Args) -> anyhow::Result<(u32, u32, f64)> {
    if let (Some((cols, rows)), Some(square)) = (args.board, args.square) {
        return Ok((cols, rows, square));
    }
    let recorded = match (args.layout, args.captures.first()) {
        (Layout::Capture, Some(first)) => {
            // A pose that cannot be read is that error, not a missing --board.
            let capture = Capture::open(first)
                .with_context(|| format!("reading the pose {}", first.display()))?;
            BoardSpec::from_manifest(&capture.manifest)
                .map(|b| (b.cols as u32, b.rows as u32, b.square_mm))
        }
        _ => None,
    };
    recorded.context(
        "--board and --square are required: the captures do not record their chessboard \
         (only simulated ones do); e.g. --board 9x7 --square 9",
    )
}

pub fn run(args: Args) -> anyhow::Result<()> {
    refuse_overwriting_inputs(&args)?;
    if let Some(missing) = args.captures.iter().find(|c| !c.is_dir()) {
        bail!(
            "pose folder {} does not exist (or is not a folder): give the calibration captures' \
             folders, e.g. out/calibration-poses/pose00",
            missing.display()
        );
    }
    if let Some(path) = &args.from_opencv {
        return convert(path, &args);
    }
    let (cols, rows, square) = board_of(&args)?;
    if !(square > 0.0 && square.is_finite()) {
        bail!("--square must be a positive length in millimetres, got {square}");
    }
    if cols < 3 || rows < 3 {
        bail!("--board needs at least 3x3 inner corners, got {cols}x{rows}");
    }
    let layout = match args.layout {
        Layout::Capture => PoseLayout::Capture,
        Layout::Opencv => PoseLayout::OpenCv {
            projector: args
                .projector
                .context("--layout opencv needs --projector WxH (e.g. --projector 1024x768)")?,
        },
    };
    let progress = ProgressBar::new(args.captures.len() as u64).with_style(
        ProgressStyle::with_template("{msg} {bar:30} {pos}/{len} poses")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    progress.set_message("measuring");
    let mut options = ProcamOptions::default();
    if args.fix_k3 {
        options.distortion[4] = false;
    }
    options.select_distortion = !args.all_distortion_terms;
    let board = BoardSpec {
        cols: cols as usize,
        rows: rows as usize,
        square_mm: square,
    };
    let calibrated = calibrate_poses(&args.captures, layout, &board, &options, &|| {
        progress.inc(1)
    });
    progress.finish_and_clear();
    let calibrated = calibrated?;
    for (name, reason) in &calibrated.board_not_found {
        eprintln!("skipping pose {name}: chessboard not found: {reason}");
    }
    let result = calibrated.result;
    for pose in result.poses.iter().filter(|p| p.used) {
        for reason in &pose.projector_reasons {
            eprintln!("pose {}: {reason}", pose.name);
        }
    }
    for pose in result.poses.iter().filter(|p| !p.used) {
        if let Some(reason) = &pose.reason {
            eprintln!("pose {} not used: {reason}", pose.name);
        }
    }
    save(&result.calibration, &args)?;
    print_result(&result, &args);
    Ok(())
}

/// Refuses outputs that are an input (a pose folder or a file in it, the OpenCV file converted)
/// or each other (`--out c.xml` would be overwritten by the OpenCV export beside it).
fn refuse_overwriting_inputs(args: &Args) -> anyhow::Result<()> {
    let mut inputs: Vec<(&str, &Path)> = args
        .captures
        .iter()
        .map(|c| ("pose", c.as_path()))
        .collect();
    if let Some(path) = &args.from_opencv {
        inputs.push(("--from-opencv", path));
    }
    let xml = opencv_path(args);
    let mut outputs: Vec<(&str, &Path)> = vec![("--out", &args.out)];
    if args.from_opencv.is_none() {
        outputs.push(("the OpenCV export (--opencv-out)", &xml));
    }
    super::output_paths::refuse_overlaps(&inputs, &outputs)
}

fn opencv_path(args: &Args) -> PathBuf {
    args.opencv_out
        .clone()
        .unwrap_or_else(|| args.out.with_extension("xml"))
}

fn save(calibration: &mlsss::calibration::Calibration, args: &Args) -> anyhow::Result<()> {
    calibration
        .save(&args.out)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let xml = opencv_path(args);
    write_opencv(calibration, &xml).with_context(|| format!("writing {}", xml.display()))?;
    Ok(())
}

fn convert(path: &Path, args: &Args) -> anyhow::Result<()> {
    let calibration = read_opencv(path, args.projector)?;
    calibration
        .save(&args.out)
        .with_context(|| format!("writing {}", args.out.display()))?;
    if args.json {
        println!(
            "{}",
            serde_json::json!({
                "source": path.display().to_string(),
                "out": args.out.display().to_string(),
                "projectors": calibration.projectors.len(),
                "camera": intrinsics_json(&calibration.camera.intrinsics),
            })
        );
    } else {
        println!(
            "converted {} -> {} (camera + {} projector(s))",
            path.display(),
            args.out.display(),
            calibration.projectors.len()
        );
    }
    Ok(())
}

fn intrinsics_json(k: &mlsss::calibration::Intrinsics) -> serde_json::Value {
    serde_json::json!({
        "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy, "distortion": k.distortion,
    })
}

/// Per device, the names of the estimated distortion terms (camera first).
fn distortion_terms_json(terms: &[[bool; 5]]) -> serde_json::Value {
    serde_json::json!(
        terms
            .iter()
            .map(|t| distortion_term_names(t))
            .collect::<Vec<_>>()
    )
}

fn print_result(result: &ProcamResult, args: &Args) {
    let cal = &result.calibration;
    let poses_used = result.poses.iter().filter(|p| p.used).count();
    if args.json {
        let projectors: Vec<serde_json::Value> = cal
            .projectors
            .iter()
            .zip(&result.projector_rms_px)
            .map(|(p, rms)| {
                let mut v = intrinsics_json(&p.device.intrinsics);
                v["rms_px"] = serde_json::json!(rms);
                v["position_mm"] =
                    serde_json::json!(p.device.extrinsics.centre().coords.as_slice());
                v
            })
            .collect();
        let mut value = serde_json::json!({
            "camera_rms_px": result.camera_rms_px,
            "projector_rms_px": result.projector_rms_px.first(),
            "stereo_rms_px": result.stereo_rms_px,
            "camera": intrinsics_json(&cal.camera.intrinsics),
            "projector": projectors.first(),
            "projectors": projectors,
            "poses_used": poses_used,
            "poses_total": result.poses.len(),
            "separate_fits": result.separate,
            "poses": result.poses,
            "distortion_terms": distortion_terms_json(&result.distortion_terms),
            "out": args.out.display().to_string(),
            "opencv_out": opencv_path(args).display().to_string(),
        });
        if cal.projectors.len() > 1 {
            value["projector_rms_px_all"] = serde_json::json!(result.projector_rms_px);
        }
        println!("{value}");
    } else {
        let k = &cal.camera.intrinsics;
        println!(
            "{poses_used}/{} poses used; camera fx {:.2} fy {:.2} cx {:.2} cy {:.2}, RMS {:.3} px",
            result.poses.len(),
            k.fx,
            k.fy,
            k.cx,
            k.cy,
            result.camera_rms_px
        );
        for (i, (p, rms)) in cal
            .projectors
            .iter()
            .zip(&result.projector_rms_px)
            .enumerate()
        {
            let k = &p.device.intrinsics;
            println!(
                "projector {i}: fx {:.2} fy {:.2} cx {:.2} cy {:.2}, RMS {rms:.3} px",
                k.fx, k.fy, k.cx, k.cy
            );
        }
        println!(
            "stereo RMS {:.3} px; wrote {} and {}",
            result.stereo_rms_px,
            args.out.display(),
            opencv_path(args).display()
        );
    }
}
