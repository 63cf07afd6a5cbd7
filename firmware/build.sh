#!/usr/bin/env bash
# Checks and builds the controller firmware (called by scripts/test.sh; also usable alone):
# formatting, lints (the core on the host, the boards on thumbv7em), host tests of the sequencer
# core (incl. the QEMU image test), release images of both boards, and their flash/RAM sizes.
set -euo pipefail
cd "$(dirname "$0")"

HOST_TARGET="$(rustc -vV | sed -n 's/^host: //p')"
BOARDS=(mlsss-fw-qemu mlsss-fw-nucleo)
IMAGES=target/thumbv7em-none-eabihf/release

step() { printf '\n==> firmware: %s\n' "$*" >&2; }

step "toolchain (thumbv7em-none-eabihf)"
rustup target list --installed | grep -qx thumbv7em-none-eabihf || rustup target add thumbv7em-none-eabihf

step "cargo fmt --check"
cargo fmt --all -- --check

step "clippy: sequencer core and its tests on the host"
cargo clippy -p mlsss-sequencer --all-targets --target "$HOST_TARGET" -- -D warnings

step "clippy: board binaries on thumbv7em-none-eabihf"
cargo clippy --workspace -- -D warnings

step "release images"
cargo build --release "${BOARDS[@]/#/--bin=}"

step "host tests of the sequencer core (the QEMU image test boots $IMAGES/mlsss-fw-qemu)"
cargo test -p mlsss-sequencer --target "$HOST_TARGET"

step "flash / RAM of the images"
# Any of these reads the ARM ELF: rustup's llvm-tools, a system LLVM, or GNU binutils (always
# there with the C toolchain Rust links with).
SIZE="$(rustc --print sysroot)/lib/rustlib/$HOST_TARGET/bin/llvm-size"
[ -x "$SIZE" ] || SIZE="$(command -v llvm-size || command -v arm-none-eabi-size || command -v size)"
printf '%-18s %10s %10s\n' image "flash (B)" "RAM (B)"
for bin in "${BOARDS[@]}"; do
    # Berkeley format: text data bss. Flash holds text + the initial values of data; RAM holds
    # data + bss (the stack is the rest of RAM and not counted).
    read -r text data bss _ < <("$SIZE" "$IMAGES/$bin" | tail -n 1)
    printf '%-18s %10d %10d\n' "$bin" $((text + data)) $((data + bss))
done
