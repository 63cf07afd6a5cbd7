//! `mlsss` starts itself again with glibc's allocator on transparent huge pages (`main.rs`,
//! `resources::tunables_for_huge_page_malloc`): the restart must be invisible but for speed.

use mlsss_tests::mlsss;

/// The program's output and exit status, started plainly (where this machine's kernel waits to
/// be asked for huge pages, it restarts itself) or with the restart turned off.
fn run(args: &[&str], restart: bool) -> std::process::Output {
    let mut command = mlsss();
    command
        .args(args)
        .env_remove("MLSSS_RESTARTED_FOR_HUGE_PAGES");
    if restart {
        command.env_remove("GLIBC_TUNABLES");
    } else {
        command.env("GLIBC_TUNABLES", "glibc.malloc.hugetlb=0");
    }
    command.output().unwrap()
}

#[test]
fn restarting_for_huge_pages_keeps_arguments_output_and_exit_status() {
    // A success and two failures (their outputs differ).
    for (args, succeeds) in [
        (&["booth", "--json"][..], true),
        (&["booth", "--file", "/nonexistent/booth.toml"][..], false),
        (&["mc", "slab", "--no-such-flag"][..], false),
    ] {
        let (restarted, plain) = (run(args, true), run(args, false));
        assert_eq!(restarted.status.success(), succeeds, "{args:?}");
        assert_eq!(restarted.status.code(), plain.status.code(), "{args:?}");
        assert_eq!(restarted.stdout, plain.stdout, "{args:?}");
        assert_eq!(restarted.stderr, plain.stderr, "{args:?}");
    }
}
