#!/usr/bin/env bash
# Runs every test of the project on a fresh machine: installs what is missing (the thumbv7em target,
# qemu-system-arm), then formatting, lints, host tests, firmware tests and cross-builds.
set -euo pipefail
cd "$(dirname "$0")/.."

step() { printf '\n==> %s\n' "$*" >&2; }

step "toolchain: thumbv7em-none-eabihf target, rustfmt, clippy"
if ! rustup target list --installed | grep -qx thumbv7em-none-eabihf; then
    rustup target add thumbv7em-none-eabihf
fi
rustup component list --installed | grep -q '^rustfmt' || rustup component add rustfmt
rustup component list --installed | grep -q '^clippy' || rustup component add clippy

# apt_install COMMAND PACKAGE...: installs the packages unless COMMAND is already there.
apt_install() {
    local command=$1
    shift
    command -v "$command" >/dev/null 2>&1 && return 0
    if [ "$(id -u)" = 0 ]; then
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq && apt-get install -y -qq "$@" >/dev/null
    elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
        sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
    else
        echo "error: $command is missing and this user cannot install it." >&2
        echo "       install it as root: apt-get install $*" >&2
        exit 1
    fi
}

step "qemu-system-arm (hardware-in-the-loop tests)"
apt_install qemu-system-arm qemu-system-arm

step "Xvfb and the X client libraries (projector window tests)"
# winit loads libX11/libXcursor/libXi/libxkbcommon at run time; Xvfb alone does not bring them.
apt_install Xvfb xvfb libx11-xcb1 libxcursor1 libxi6 libxkbcommon-x11-0

if [ "${CI:-}" = true ]; then
    # A clean build gains nothing from incremental state, which would take about half of target/
    # (1.6 of 2.8 GB): CI machines can be short of disk.
    export CARGO_INCREMENTAL=0
fi

step "cargo fmt --check"
cargo fmt --all -- --check

step "cargo clippy (host workspace)"
cargo clippy --workspace --all-targets -- -D warnings

step "cargo doc (host workspace, warnings are errors: broken or private intra-doc links)"
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --quiet

step "shared crate builds for the microcontroller"
cargo build -p mlsss-shared --target thumbv7em-none-eabihf --no-default-features

if [ -f firmware/Cargo.toml ]; then
    step "firmware: fmt, clippy, host tests of the sequencer core, board images"
    (cd firmware && ./build.sh)
fi

step "host tests (unit, integration, hardware-in-the-loop)"
# The integration tests run the `mlsss` binary; `cargo test` does not build it for another package.
# Building it together with the tests gives it the tests' feature set, so `cargo test` below
# reuses the library instead of compiling it a second time (`-p mlsss` alone would).
cargo build --workspace --bins --tests
cargo test --workspace -- --skip rig_hil
step "hardware-in-the-loop tests, alone"
# The emulated booth's clock waits (up to 1 s of virtual time) for the host's answers, so a loaded
# host no longer makes frames late (hardware/timing.md); they still run apart from the heavy tests.
# One at a time: two of them side by side (each a QEMU guest plus the host, and one an Xvfb) were
# enough to starve a host on a 2-core machine and fail the nominal run with one late frame.
# `--workspace` keeps the feature set of the run above, so nothing is compiled again.
cargo test --workspace --test integration -- rig_hil --test-threads=1
