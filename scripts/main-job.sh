#!/usr/bin/env bash
# The main job until `mlsss demo` exists: simulate a --quick capture of a head in the virtual booth
# (Monte Carlo skin, ground truth), then decode it, triangulate it, separate direct/global light and
# solve photometric stereo, printing the report (errors against the truth, timings) as JSON.
# Everything goes to out/main-job/ (replaced on every run).
set -euo pipefail
cd "$(dirname "$0")/.."
out=out/main-job
rm -rf "$out"
mkdir -p "$out"
cargo build --release -p mlsss --bin mlsss
mlsss=target/release/mlsss
"$mlsss" simulate --quick --subject head --seed 1 --out "$out/capture"
"$mlsss" process "$out/capture" --calib truth --until normals --out "$out/processed" --json
echo "report: $out/processed/report.json; frames and truth: $out/capture" >&2
