//! The workspace's dev profile (the one `scripts/test.sh` builds) lowers the optimisation only of
//! crates that run at build time: procedural macros and the crates only they use.
//!
//! Why (regression, fa4bba0): at opt-level 0 or 1 rustc shares a crate's generic instances with
//! its dependants, and our crates (opt-level 1) then call a dependency's unoptimised
//! `Range::next` and friends instead of inlining their own. With `moxcms` and `pxfm` (linked
//! into us through `image`) at opt-level 0, the dev-profile Monte Carlo ran 30x slower and the
//! integration tests took 556 s instead of 99 s. Procedural macros and build scripts are not
//! linked into our code, so they may be built unoptimised.

use std::collections::{BTreeSet, HashMap};
use std::path::Path;
use std::process::Command;

use mlsss_tests::run_json;
use serde_json::Value;

/// The packages named under `[profile.dev.package]` with an opt-level below 3.
fn unoptimised_dev_packages(manifest: &str) -> BTreeSet<String> {
    let table: toml::Table = manifest.parse().expect("the workspace Cargo.toml parses");
    let packages = table
        .get("profile")
        .and_then(|p| p.get("dev"))
        .and_then(|d| d.get("package"))
        .and_then(|p| p.as_table())
        .cloned()
        .unwrap_or_default();
    packages
        .iter()
        .filter(|(name, _)| name.as_str() != "*")
        .filter(|(_, settings)| {
            settings
                .get("opt-level")
                .and_then(|o| o.as_integer())
                .is_some_and(|level| level < 3)
        })
        .map(|(name, _)| name.clone())
        .collect()
}

/// The names of the packages linked into the workspace's code: reached from the workspace
/// members by normal and dev dependencies, not through build dependencies or procedural macros.
fn linked_packages(metadata: &Value) -> BTreeSet<String> {
    let packages: HashMap<&str, &Value> = metadata["packages"]
        .as_array()
        .expect("packages")
        .iter()
        .map(|p| (p["id"].as_str().expect("id"), p))
        .collect();
    let is_proc_macro = |id: &str| {
        let targets = packages[id]["targets"].as_array().into_iter().flatten();
        let mut kinds = targets.flat_map(|t| t["kind"].as_array().into_iter().flatten());
        kinds.any(|kind| kind == "proc-macro")
    };
    let nodes: HashMap<&str, &Value> = metadata["resolve"]["nodes"]
        .as_array()
        .expect("resolve nodes")
        .iter()
        .map(|n| (n["id"].as_str().expect("id"), n))
        .collect();
    let mut stack: Vec<&str> = metadata["workspace_members"]
        .as_array()
        .expect("workspace members")
        .iter()
        .filter_map(Value::as_str)
        .collect();
    let mut seen: BTreeSet<&str> = stack.iter().copied().collect();
    while let Some(id) = stack.pop() {
        for dep in nodes[id]["deps"].as_array().into_iter().flatten() {
            let dep_id = dep["pkg"].as_str().expect("pkg");
            let linked_kind = dep["dep_kinds"]
                .as_array()
                .into_iter()
                .flatten()
                .any(|k| k["kind"].as_str() != Some("build"));
            if linked_kind && !is_proc_macro(dep_id) && seen.insert(dep_id) {
                stack.push(dep_id);
            }
        }
    }
    seen.iter()
        .map(|id| packages[id]["name"].as_str().expect("name").to_owned())
        .collect()
}

/// The triple of the platform the tests run on (`rustc -vV`'s `host:` line).
fn host_triple() -> String {
    let rustc = std::env::var("RUSTC").unwrap_or_else(|_| "rustc".into());
    let out = Command::new(rustc)
        .arg("-vV")
        .output()
        .expect("run rustc -vV");
    assert!(out.status.success(), "rustc -vV failed");
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .find_map(|l| l.strip_prefix("host: "))
        .expect("rustc -vV names the host")
        .trim()
        .to_owned()
}

#[test]
fn the_dev_profile_leaves_only_build_time_crates_unoptimised() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let manifest = std::fs::read_to_string(root.join("Cargo.toml")).expect("read Cargo.toml");
    let unoptimised = unoptimised_dev_packages(&manifest);
    assert!(
        unoptimised.contains("syn"),
        "the check reads the profile table: {unoptimised:?}"
    );
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    // This machine's platform only (regression, 2026-11-30): offline, the whole graph needs every
    // platform's packages in the local registry (android-activity, ...), which a fresh machine's
    // build never downloads; on this platform's graph, what is linked here is what matters.
    let metadata = run_json(
        Command::new(cargo)
            .args(["metadata", "--format-version", "1", "--offline"])
            .args(["--filter-platform", &host_triple()])
            .current_dir(&root),
    );
    let linked = linked_packages(&metadata);
    // The traversal itself: `image` is linked into our code, `syn` only into macros.
    assert!(linked.contains("image") && linked.contains("png"));
    assert!(
        !linked.contains("syn"),
        "syn is reached only through macros"
    );
    let wrongly: Vec<&String> = unoptimised.intersection(&linked).collect();
    assert!(
        wrongly.is_empty(),
        "[profile.dev.package] lowers the opt-level of crates linked into our code: {wrongly:?}"
    );
}
