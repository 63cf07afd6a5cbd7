//! Output paths that can never overwrite an input or each other: every command checks its
//! outputs against its inputs (files and folders) before it writes anything.

use std::path::Path;

use anyhow::bail;
use mlsss::pipeline::absolute_clean;

/// A path a command reads or writes, with the flag (or argument name) that gave it.
pub type NamedPath<'a> = (&'a str, &'a Path);

/// Refuses outputs that are an input, lie inside an input folder, or coincide with another
/// output; the error names both flags and the paths.
pub fn refuse_overlaps(inputs: &[NamedPath], outputs: &[NamedPath]) -> anyhow::Result<()> {
    for (i, (out_flag, out)) in outputs.iter().enumerate() {
        let out_full = absolute_clean(out);
        for (in_flag, input) in inputs {
            let in_full = absolute_clean(input);
            if out_full == in_full {
                bail!(
                    "{out_flag} {} is also the input {in_flag}: writing it would destroy the \
                     input; choose another {out_flag}",
                    out.display()
                );
            }
            if input.is_dir() && out_full.starts_with(&in_full) {
                bail!(
                    "{out_flag} {} is inside the input {in_flag} {}: writing there would change \
                     the input; choose an {out_flag} outside it",
                    out.display(),
                    input.display()
                );
            }
        }
        for (other_flag, other) in &outputs[..i] {
            if absolute_clean(other) == out_full {
                bail!(
                    "{other_flag} and {out_flag} are both {}: one output would overwrite the \
                     other; give them different paths",
                    out.display()
                );
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refuses_an_output_equal_to_an_input_inside_an_input_folder_or_twice() {
        let dir = tempfile::tempdir().unwrap();
        let model = dir.path().join("model.mlsss");
        std::fs::write(&model, b"m").unwrap();
        let pose = dir.path().join("pose00");
        std::fs::create_dir(&pose).unwrap();
        let in_pose = pose.join("capture.json");
        let fresh = dir.path().join("new.exr");
        let inputs = [("MODEL", model.as_path()), ("CAPTURE", pose.as_path())];
        let check = |outs: &[NamedPath]| refuse_overlaps(&inputs, outs);
        assert!(check(&[("--out", &fresh)]).is_ok());
        let err = check(&[("--out", &model)]).unwrap_err().to_string();
        assert!(err.contains("also the input MODEL"), "{err}");
        // Another spelling of the same file is the same file.
        let dotted = dir.path().join(".").join("model.mlsss");
        assert!(check(&[("--out", &dotted)]).is_err());
        let err = check(&[("--out", &in_pose)]).unwrap_err().to_string();
        assert!(err.contains("inside the input CAPTURE"), "{err}");
        let err = check(&[("--out", &fresh), ("PNG", &fresh)])
            .unwrap_err()
            .to_string();
        assert!(err.contains("both"), "{err}");
    }
}
