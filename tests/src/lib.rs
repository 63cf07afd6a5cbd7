//! Helpers shared by the integration tests.

use std::path::PathBuf;
use std::process::Command;

/// Path of the `mlsss` binary built beside the test executable (`cargo test --workspace` builds it;
/// `CARGO_BIN_EXE_*` is only set for binaries of the test's own package).
pub fn mlsss_bin() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/integration-<hash> -> target/<profile>/mlsss
    let profile_dir = exe
        .parent()
        .and_then(|deps| deps.parent())
        .expect("test executable lives in target/<profile>/deps");
    let bin = profile_dir.join(format!("mlsss{}", std::env::consts::EXE_SUFFIX));
    assert!(
        bin.exists(),
        "{} not found: run the tests with `cargo test --workspace` so the binary is built",
        bin.display()
    );
    bin
}

/// A `Command` running `mlsss`.
pub fn mlsss() -> Command {
    Command::new(mlsss_bin())
}
