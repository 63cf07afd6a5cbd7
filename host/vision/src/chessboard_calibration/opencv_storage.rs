//! Import and export of calibrations as OpenCV `FileStorage` XML or YAML (DESIGN section 8), so
//! OpenCV users can bring and take calibrations.
//!
//! Written keys (all matrices `opencv-matrix` of doubles, scalars as numbers):
//! - `camera_size` (1x2: width, height), `camera_matrix` (3x3), `camera_distortion` (1x5),
//!   `camera_rms` when known;
//! - per projector k (from 0): `projector{k}_size`, `projector{k}_matrix`,
//!   `projector{k}_distortion`, `projector{k}_R` (3x3) and `projector{k}_T` (3x1, mm), the
//!   OpenCV `stereoCalibrate` pose camera -> projector (`x_proj = R x_cam + T`), and
//!   `projector{k}_rms` when known.
//!
//! Read: the keys above, or the single-projector layout of the widely used procam-calibration
//! scripts (`img_shape` (rows, cols), `cam_int`, `cam_dist`, `proj_int`, `proj_dist`, `rotation`
//! or its misspelling `roration`, `translation`), whose projector size is not stored and must be
//! given.
//!
//! Conventions: the world frame of an imported or exported calibration is the camera frame
//! (camera R = I, t = 0); a calibration whose camera is elsewhere is re-expressed in the camera
//! frame on export.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{Matrix3, Vector3};

use mlsss_core::calibration::{
    Calibration, DeviceCalibration, Extrinsics, Intrinsics, ProjectorCalibration,
};

/// Errors reading or writing OpenCV FileStorage files.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum OpenCvStorageError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    /// The text is not FileStorage XML/YAML as understood here.
    #[error("{path}: not an OpenCV FileStorage file: {reason}")]
    Syntax { path: String, reason: String },
    /// A required entry is missing or has the wrong shape.
    #[error("{path}: entry `{key}`: {reason}")]
    Entry {
        path: String,
        key: String,
        reason: String,
    },
    /// The file holds no projector size; it must be given (e.g. `--projector 1024x768`).
    #[error(
        "{path} does not store the projector's image size; give it (e.g. --projector 1024x768)"
    )]
    MissingProjectorSize { path: String },
    /// The extension is neither `.xml` nor `.yml`/`.yaml`.
    #[error("{path}: unknown FileStorage format; use a .xml, .yml or .yaml file name")]
    UnknownFormat { path: String },
}

/// One FileStorage entry: a matrix (row-major) or a scalar.
#[derive(Debug, Clone, PartialEq)]
enum Node {
    Matrix {
        rows: usize,
        cols: usize,
        data: Vec<f64>,
    },
    Scalar(f64),
}

/// File format, from the file name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Format {
    Xml,
    Yaml,
}

fn format_of(path: &Path) -> Result<Format, OpenCvStorageError> {
    match path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .as_deref()
    {
        Some("xml") => Ok(Format::Xml),
        Some("yml" | "yaml") => Ok(Format::Yaml),
        _ => Err(OpenCvStorageError::UnknownFormat {
            path: path.display().to_string(),
        }),
    }
}

/// Writes `calibration` as FileStorage XML or YAML (chosen by the extension of `path`).
pub fn write_opencv(calibration: &Calibration, path: &Path) -> Result<(), OpenCvStorageError> {
    let format = format_of(path)?;
    let entries = calibration_entries(calibration);
    let text = match format {
        Format::Xml => to_xml(&entries),
        Format::Yaml => to_yaml(&entries),
    };
    mlsss_core::atomic_file::write_bytes_atomically(path, text).map_err(|source| {
        OpenCvStorageError::Io {
            path: path.display().to_string(),
            source,
        }
    })
}

/// Reads a FileStorage XML or YAML calibration. `projector_size` is used when the file does not
/// store the projectors' image size.
pub fn read_opencv(
    path: &Path,
    projector_size: Option<(u32, u32)>,
) -> Result<Calibration, OpenCvStorageError> {
    let format = format_of(path)?;
    let name = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| OpenCvStorageError::Io {
        path: name.clone(),
        source,
    })?;
    let nodes = match format {
        Format::Xml => parse_xml(&text),
        Format::Yaml => parse_yaml(&text),
    }
    .map_err(|reason| OpenCvStorageError::Syntax {
        path: name.clone(),
        reason,
    })?;
    calibration_from_nodes(&nodes, &name, projector_size)
}

fn matrix(rows: usize, cols: usize, data: Vec<f64>) -> Node {
    Node::Matrix { rows, cols, data }
}

fn k_node(k: &Intrinsics) -> Node {
    matrix(3, 3, vec![k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0])
}

/// The entries written for a calibration, in file order.
fn calibration_entries(calibration: &Calibration) -> Vec<(String, Node)> {
    let cam = &calibration.camera;
    // Re-express every device relative to the camera: T_dc = T_dw T_cw^-1.
    let (rc, tc) = (cam.extrinsics.r(), cam.extrinsics.t());
    let mut out = vec![
        (
            "camera_size".to_string(),
            matrix(1, 2, vec![cam.width as f64, cam.height as f64]),
        ),
        ("camera_matrix".into(), k_node(&cam.intrinsics)),
        (
            "camera_distortion".into(),
            matrix(1, 5, cam.intrinsics.distortion.to_vec()),
        ),
    ];
    if let Some(rms) = calibration.camera_rms_px {
        out.push(("camera_rms".into(), Node::Scalar(rms)));
    }
    for (k, p) in calibration.projectors.iter().enumerate() {
        let d = &p.device;
        let r = d.extrinsics.r() * rc.transpose();
        let t = d.extrinsics.t() - r * tc;
        out.push((
            format!("projector{k}_size"),
            matrix(1, 2, vec![d.width as f64, d.height as f64]),
        ));
        out.push((format!("projector{k}_matrix"), k_node(&d.intrinsics)));
        out.push((
            format!("projector{k}_distortion"),
            matrix(1, 5, d.intrinsics.distortion.to_vec()),
        ));
        out.push((
            format!("projector{k}_R"),
            matrix(3, 3, r.transpose().iter().copied().collect()),
        ));
        out.push((
            format!("projector{k}_T"),
            matrix(3, 1, t.iter().copied().collect()),
        ));
        if let Some(rms) = p.rms_px {
            out.push((format!("projector{k}_rms"), Node::Scalar(rms)));
        }
    }
    out
}

/// Numbers in the shortest form that reads back exactly.
fn number(v: f64) -> String {
    format!("{v:e}")
}

fn to_xml(entries: &[(String, Node)]) -> String {
    let mut s = String::from("<?xml version=\"1.0\"?>\n<opencv_storage>\n");
    for (key, node) in entries {
        match node {
            Node::Scalar(v) => {
                let _ = writeln!(s, "<{key}>{}</{key}>", number(*v));
            }
            Node::Matrix { rows, cols, data } => {
                let values: Vec<String> = data.iter().map(|v| number(*v)).collect();
                let _ = writeln!(
                    s,
                    "<{key} type_id=\"opencv-matrix\">\n  <rows>{rows}</rows>\n  <cols>{cols}</cols>\n  <dt>d</dt>\n  <data>\n    {}</data></{key}>",
                    values.join(" ")
                );
            }
        }
    }
    s.push_str("</opencv_storage>\n");
    s
}

fn to_yaml(entries: &[(String, Node)]) -> String {
    let mut s = String::from("%YAML:1.0\n---\n");
    for (key, node) in entries {
        match node {
            Node::Scalar(v) => {
                let _ = writeln!(s, "{key}: {}", number(*v));
            }
            Node::Matrix { rows, cols, data } => {
                let values: Vec<String> = data.iter().map(|v| number(*v)).collect();
                let _ = writeln!(
                    s,
                    "{key}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {} ]",
                    values.join(", ")
                );
            }
        }
    }
    s
}

fn parse_numbers(text: &str) -> Result<Vec<f64>, String> {
    text.split(|c: char| c.is_whitespace() || c == ',')
        .filter(|t| !t.is_empty())
        .map(|t| {
            t.parse::<f64>()
                .map_err(|_| format!("`{t}` is not a number"))
        })
        .collect()
}

/// An XML element: its name, attributes, text (all text children, concatenated) and child
/// elements.
#[derive(Debug, Default)]
struct Element {
    name: String,
    attributes: Vec<(String, String)>,
    text: String,
    children: Vec<Element>,
}

impl Element {
    fn child(&self, name: &str) -> Option<&Element> {
        self.children.iter().find(|c| c.name == name)
    }

    fn attribute(&self, key: &str) -> Option<&str> {
        self.attributes
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
}

fn element_of(start: &quick_xml::events::BytesStart) -> Result<Element, String> {
    let name = String::from_utf8_lossy(start.name().as_ref()).into_owned();
    let attributes = start
        .attributes()
        .map(|a| {
            let a = a.map_err(|e| format!("<{name}>: {e}"))?;
            let key = String::from_utf8_lossy(a.key.as_ref()).into_owned();
            let value = a
                .unescape_value()
                .map_err(|e| format!("<{name}> {key}: {e}"))?
                .into_owned();
            Ok((key, value))
        })
        .collect::<Result<_, String>>()?;
    Ok(Element {
        name,
        attributes,
        ..Element::default()
    })
}

/// The document's root element (comments, processing instructions, the declaration and the
/// doctype are skipped; CDATA counts as text).
fn parse_xml_tree(text: &str) -> Result<Element, String> {
    use quick_xml::events::Event;
    let mut reader = quick_xml::Reader::from_str(text);
    // Open elements, innermost last; the bottom one collects the document's top-level elements.
    let mut stack = vec![Element::default()];
    loop {
        let event = reader
            .read_event()
            .map_err(|e| format!("at byte {}: {e}", reader.error_position()))?;
        match event {
            Event::Start(start) => stack.push(element_of(&start)?),
            Event::Empty(start) => {
                let element = element_of(&start)?;
                if let Some(parent) = stack.last_mut() {
                    parent.children.push(element);
                }
            }
            Event::End(_) => {
                // quick-xml checks that end tags match their start tags.
                let element = stack.pop().ok_or("unbalanced end tag")?;
                let parent = stack.last_mut().ok_or("unbalanced end tag")?;
                parent.children.push(element);
            }
            Event::Text(t) => {
                let t = t.unescape().map_err(|e| e.to_string())?;
                if let Some(open) = stack.last_mut() {
                    open.text.push_str(&t);
                }
            }
            Event::CData(t) => {
                if let Some(open) = stack.last_mut() {
                    open.text.push_str(&String::from_utf8_lossy(&t));
                }
            }
            Event::Comment(_) | Event::Decl(_) | Event::PI(_) | Event::DocType(_) => {}
            Event::Eof => break,
        }
    }
    let mut document = stack.pop().ok_or("unbalanced end tag")?;
    if !stack.is_empty() {
        return Err(format!("<{}> is not closed", document.name));
    }
    if document.children.len() != 1 {
        return Err(format!(
            "{} top-level elements, not one",
            document.children.len()
        ));
    }
    document
        .children
        .pop()
        .ok_or_else(|| "no root element".to_string())
}

/// The top-level entries of `<opencv_storage>`: matrices (`type_id="opencv-matrix"`) and numeric
/// scalars (other entries, such as strings or nested maps, are skipped).
fn parse_xml(text: &str) -> Result<HashMap<String, Node>, String> {
    let root = parse_xml_tree(text)?;
    if root.name != "opencv_storage" {
        return Err(format!("the root is <{}>, not <opencv_storage>", root.name));
    }
    let mut nodes = HashMap::new();
    for entry in &root.children {
        let name = &entry.name;
        if entry.attribute("type_id") == Some("opencv-matrix") {
            let field = |f: &str| {
                entry
                    .child(f)
                    .map(|c| c.text.as_str())
                    .ok_or_else(|| format!("<{name}> has no <{f}>"))
            };
            let rows = field("rows")?
                .trim()
                .parse()
                .map_err(|_| format!("<{name}> rows"))?;
            let cols = field("cols")?
                .trim()
                .parse()
                .map_err(|_| format!("<{name}> cols"))?;
            let data = parse_numbers(field("data")?)?;
            nodes.insert(name.clone(), Node::Matrix { rows, cols, data });
        } else if let Some(v) = entry
            .text
            .trim()
            .parse::<f64>()
            .ok()
            .filter(|_| entry.children.is_empty())
        {
            nodes.insert(name.clone(), Node::Scalar(v));
        }
    }
    Ok(nodes)
}

/// Top-level `key: value` scalars and `key: !!opencv-matrix` maps of FileStorage YAML.
fn parse_yaml(text: &str) -> Result<HashMap<String, Node>, String> {
    let mut nodes = HashMap::new();
    let lines: Vec<&str> = text.lines().collect();
    let mut i = 0;
    while i < lines.len() {
        let line = lines[i];
        i += 1;
        if line.starts_with('%') || line.starts_with("---") || line.trim().is_empty() {
            continue;
        }
        if line.starts_with(char::is_whitespace) {
            continue; // a field of something skipped
        }
        let Some((key, value)) = line.split_once(':') else {
            continue;
        };
        let (key, value) = (key.trim().to_string(), value.trim());
        if value.starts_with("!!opencv-matrix") {
            // Collect the indented block, then read rows/cols/data (data may span lines).
            let mut block = String::new();
            while i < lines.len() && lines[i].starts_with(char::is_whitespace) {
                block.push_str(lines[i]);
                block.push('\n');
                i += 1;
            }
            let field = |f: &str| {
                block
                    .lines()
                    .find_map(|l| l.trim().strip_prefix(&format!("{f}:")).map(str::trim))
                    .ok_or_else(|| format!("`{key}` has no {f}"))
            };
            let rows = field("rows")?
                .parse()
                .map_err(|_| format!("`{key}` rows"))?;
            let cols = field("cols")?
                .parse()
                .map_err(|_| format!("`{key}` cols"))?;
            let start = block
                .find('[')
                .ok_or_else(|| format!("`{key}` has no data list"))?;
            let end = block[start..]
                .find(']')
                .ok_or_else(|| format!("`{key}` data list is not closed"))?
                + start;
            let data = parse_numbers(&block[start + 1..end])?;
            nodes.insert(key, Node::Matrix { rows, cols, data });
        } else if let Ok(v) = value.parse::<f64>() {
            nodes.insert(key, Node::Scalar(v));
        }
    }
    Ok(nodes)
}

/// Looks up a matrix of the given shape.
fn get_matrix<'a>(
    nodes: &'a HashMap<String, Node>,
    path: &str,
    key: &str,
    shape: (usize, usize),
) -> Result<&'a [f64], OpenCvStorageError> {
    let entry = |reason: String| OpenCvStorageError::Entry {
        path: path.into(),
        key: key.into(),
        reason,
    };
    match nodes.get(key) {
        Some(Node::Matrix { rows, cols, data }) if data.len() == rows * cols => {
            if (*rows, *cols) == shape
                || (*rows * *cols == shape.0 * shape.1
                    && shape.0 * shape.1 <= 5
                    && (*rows == 1 || *cols == 1))
            {
                Ok(data)
            } else {
                Err(entry(format!(
                    "is {rows}x{cols}, expected {}x{}",
                    shape.0, shape.1
                )))
            }
        }
        Some(_) => Err(entry("is not a matrix with matching data".into())),
        None => Err(entry("missing".into())),
    }
}

fn intrinsics_from(k: &[f64], dist: &[f64]) -> Intrinsics {
    let mut distortion = [0.0; 5];
    for (d, v) in distortion.iter_mut().zip(dist) {
        *d = *v;
    }
    Intrinsics {
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
        distortion,
    }
}

/// Distortion with 4, 5 (or more: only the first 5 are kept) coefficients.
fn get_distortion<'a>(
    nodes: &'a HashMap<String, Node>,
    path: &str,
    key: &str,
) -> Result<&'a [f64], OpenCvStorageError> {
    match nodes.get(key) {
        Some(Node::Matrix { data, .. }) if data.len() >= 4 => Ok(data),
        _ => Err(OpenCvStorageError::Entry {
            path: path.into(),
            key: key.into(),
            reason: "missing, or fewer than 4 coefficients".into(),
        }),
    }
}

fn scalar(nodes: &HashMap<String, Node>, key: &str) -> Option<f64> {
    match nodes.get(key) {
        Some(Node::Scalar(v)) => Some(*v),
        _ => None,
    }
}

fn calibration_from_nodes(
    nodes: &HashMap<String, Node>,
    path: &str,
    projector_size: Option<(u32, u32)>,
) -> Result<Calibration, OpenCvStorageError> {
    if nodes.contains_key("camera_matrix") {
        return from_our_layout(nodes, path);
    }
    // The procam-calibration layout: one projector, its size not stored.
    let shape = get_matrix(nodes, path, "img_shape", (2, 1))?;
    let (pw, ph) = projector_size
        .ok_or_else(|| OpenCvStorageError::MissingProjectorSize { path: path.into() })?;
    let camera = DeviceCalibration {
        width: shape[1] as u32,
        height: shape[0] as u32,
        intrinsics: intrinsics_from(
            get_matrix(nodes, path, "cam_int", (3, 3))?,
            get_distortion(nodes, path, "cam_dist")?,
        ),
        extrinsics: Extrinsics::identity(),
    };
    let rotation_key = if nodes.contains_key("rotation") {
        "rotation"
    } else {
        "roration"
    };
    let r = get_matrix(nodes, path, rotation_key, (3, 3))?;
    let t = get_matrix(nodes, path, "translation", (3, 1))?;
    let projector = DeviceCalibration {
        width: pw,
        height: ph,
        intrinsics: intrinsics_from(
            get_matrix(nodes, path, "proj_int", (3, 3))?,
            get_distortion(nodes, path, "proj_dist")?,
        ),
        extrinsics: Extrinsics::from_rt(&Matrix3::from_row_slice(r), &Vector3::from_row_slice(t)),
    };
    Ok(Calibration {
        camera,
        camera_rms_px: None,
        projectors: vec![ProjectorCalibration {
            device: projector,
            response: None,
            // The file's `rms` is the stereo RMS of both devices, not the projector's own.
            rms_px: None,
        }],
    })
}

fn from_our_layout(
    nodes: &HashMap<String, Node>,
    path: &str,
) -> Result<Calibration, OpenCvStorageError> {
    let size = |key: &str| -> Result<(u32, u32), OpenCvStorageError> {
        let s = get_matrix(nodes, path, key, (1, 2))?;
        Ok((s[0] as u32, s[1] as u32))
    };
    let (cw, ch) = size("camera_size")?;
    let camera = DeviceCalibration {
        width: cw,
        height: ch,
        intrinsics: intrinsics_from(
            get_matrix(nodes, path, "camera_matrix", (3, 3))?,
            get_distortion(nodes, path, "camera_distortion")?,
        ),
        extrinsics: Extrinsics::identity(),
    };
    let mut projectors = Vec::new();
    for k in 0.. {
        let prefix = format!("projector{k}");
        if !nodes.contains_key(&format!("{prefix}_matrix")) {
            break;
        }
        let (pw, ph) = size(&format!("{prefix}_size"))?;
        let r = get_matrix(nodes, path, &format!("{prefix}_R"), (3, 3))?;
        let t = get_matrix(nodes, path, &format!("{prefix}_T"), (3, 1))?;
        projectors.push(ProjectorCalibration {
            device: DeviceCalibration {
                width: pw,
                height: ph,
                intrinsics: intrinsics_from(
                    get_matrix(nodes, path, &format!("{prefix}_matrix"), (3, 3))?,
                    get_distortion(nodes, path, &format!("{prefix}_distortion"))?,
                ),
                extrinsics: Extrinsics::from_rt(
                    &Matrix3::from_row_slice(r),
                    &Vector3::from_row_slice(t),
                ),
            },
            response: None,
            rms_px: scalar(nodes, &format!("{prefix}_rms")),
        });
    }
    Ok(Calibration {
        camera,
        camera_rms_px: scalar(nodes, "camera_rms"),
        projectors,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Calibration {
        Calibration {
            camera: DeviceCalibration {
                width: 1280,
                height: 1024,
                intrinsics: Intrinsics {
                    fx: 3452.1,
                    fy: 3449.9,
                    cx: 587.2,
                    cy: 521.4,
                    distortion: [-0.22, -0.87, -7.3e-4, -1.7e-3, 3.125],
                },
                extrinsics: Extrinsics::identity(),
            },
            camera_rms_px: Some(0.31),
            projectors: vec![ProjectorCalibration {
                device: DeviceCalibration {
                    width: 1024,
                    height: 768,
                    intrinsics: Intrinsics {
                        fx: 3953.7,
                        fy: 3893.3,
                        cx: 737.2,
                        cy: 1357.8,
                        distortion: [-0.017, -0.44, -9.4e-3, -2.1e-2, 1.7],
                    },
                    extrinsics: Extrinsics::from_rt(
                        &nalgebra::Rotation3::from_euler_angles(0.08, 0.001, -0.009).into_inner(),
                        &Vector3::new(85.7, -630.5, -100.8),
                    ),
                },
                response: None,
                rms_px: Some(0.35),
            }],
        }
    }

    #[test]
    fn xml_and_yaml_round_trip_exactly() {
        let dir = tempfile::tempdir().unwrap();
        for name in ["c.xml", "c.yml"] {
            let path = dir.path().join(name);
            write_opencv(&sample(), &path).unwrap();
            let back = read_opencv(&path, None).unwrap();
            assert_eq!(back, sample(), "{name}");
        }
        assert!(matches!(
            write_opencv(&sample(), &dir.path().join("c.json")),
            Err(OpenCvStorageError::UnknownFormat { .. })
        ));
    }

    #[test]
    fn reads_the_procam_calibration_layout_of_the_real_data() {
        // Independent truth: the numbers printed in the real file of shared/data.
        let path = [
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data"),
            std::path::PathBuf::from("/work/shared/data"),
        ]
        .into_iter()
        .map(|d| d.join("procam-calibration/sample_data/calibration_result.xml"))
        .find(|p| p.is_file())
        .expect("the real data (shared/data beside the repository) is needed by this test");
        let text = std::fs::read_to_string(&path).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let copy = dir.path().join("calibration_result.xml");
        std::fs::write(&copy, text).unwrap();
        assert!(matches!(
            read_opencv(&copy, None),
            Err(OpenCvStorageError::MissingProjectorSize { .. })
        ));
        let c = read_opencv(&copy, Some((1024, 768))).unwrap();
        assert_eq!((c.camera.width, c.camera.height), (1280, 1024));
        assert!((c.camera.intrinsics.fx - 3452.392906872991).abs() < 1e-9);
        assert!((c.camera.intrinsics.cy - 521.4460256551882).abs() < 1e-9);
        assert!((c.camera.intrinsics.distortion[4] - 3.1254596570907323).abs() < 1e-12);
        let p = &c.projectors[0].device;
        assert!((p.intrinsics.fy - 3893.2555903450616).abs() < 1e-9);
        assert!((p.extrinsics.translation[1] + 630.4571881956325).abs() < 1e-9);
        assert!((p.extrinsics.rotation[1][2] - 0.07874092016164905).abs() < 1e-12);
    }

    /// What OpenCV itself writes and the old hand parser broke on: comments (also holding
    /// tags), attributes on the matrix and its fields, and a declaration with an encoding.
    #[test]
    fn xml_comments_and_attributes_are_understood() {
        let xml = r#"<?xml version="1.0" encoding="UTF-8"?>
<!-- written by hand; <camera_matrix> here is not an entry -->
<opencv_storage>
<!-- <camera_size type_id="opencv-matrix"><rows>1</rows><cols>2</cols><dt>d</dt><data>1 1</data></camera_size> -->
<camera_size type_id="opencv-matrix">
  <rows>1</rows>
  <cols>2</cols>
  <dt>d</dt>
  <data>1280 1024</data></camera_size>
<camera_matrix type_id="opencv-matrix" note='from "calib"'>
  <rows>3</rows><!-- three rows -->
  <cols>3</cols>
  <dt>d</dt>
  <data encoding="ascii">
    3452.5 0. 587.25 <!-- first row --> 0. 3449.75 521.5 0. 0. 1.</data></camera_matrix>
<camera_distortion type_id="opencv-matrix"><rows>1</rows><cols>5</cols><dt>d</dt>
  <data>-0.25 -0.875 0 0 3.125</data></camera_distortion>
<camera_rms>0.5</camera_rms>
<calibration_time>"Mon Jan  1 2024"</calibration_time>
<empty_entry/>
</opencv_storage>
"#;
        let nodes = parse_xml(xml).unwrap();
        assert_eq!(nodes["camera_size"], matrix(1, 2, vec![1280.0, 1024.0]));
        assert_eq!(
            nodes["camera_matrix"],
            matrix(
                3,
                3,
                vec![3452.5, 0.0, 587.25, 0.0, 3449.75, 521.5, 0.0, 0.0, 1.0]
            )
        );
        assert_eq!(nodes["camera_rms"], Node::Scalar(0.5));
        assert!(!nodes.contains_key("calibration_time"));
        assert_eq!(nodes.len(), 4);
        // And as a whole file: a camera-only calibration.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("commented.xml");
        std::fs::write(&path, xml).unwrap();
        let c = read_opencv(&path, None).unwrap();
        assert_eq!((c.camera.width, c.camera.height), (1280, 1024));
        assert_eq!(c.camera.intrinsics.fx, 3452.5);
        assert_eq!(c.camera.intrinsics.distortion[4], 3.125);
        assert_eq!(c.camera_rms_px, Some(0.5));
        assert!(c.projectors.is_empty());
    }

    #[test]
    fn broken_xml_is_a_syntax_error() {
        for bad in [
            "<opencv_storage><camera_rms>1</opencv_storage>",
            "<opencv_storage><a>1</a>",
            "<other><a>1</a></other>",
            "<opencv_storage/><opencv_storage/>",
            "<opencv_storage><m type_id=\"opencv-matrix\"><rows>x</rows></m></opencv_storage>",
        ] {
            assert!(parse_xml(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn malformed_files_name_the_problem() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.xml");
        std::fs::write(&path, "<?xml version=\"1.0\"?>\n<opencv_storage>\n<camera_matrix type_id=\"opencv-matrix\"><rows>3</rows><cols>3</cols><dt>d</dt><data>1 0 2 0 1 2</data></camera_matrix></opencv_storage>").unwrap();
        let err = read_opencv(&path, None).unwrap_err().to_string();
        assert!(err.contains("camera_size"), "{err}");
        std::fs::write(&path, "no xml here").unwrap();
        assert!(matches!(
            read_opencv(&path, None),
            Err(OpenCvStorageError::Syntax { .. })
        ));
    }
}
