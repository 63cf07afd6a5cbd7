#!/usr/bin/env bash
# Every processing stage against its peer in one run (see scripts/peers.py for what is compared):
# builds the release binary and the two examples, makes a venv with the Python peers from PyPI
# (never a dependency of mlsss), runs the comparisons and prints ours, peer, ratio and accuracy.
#
#   scripts/peers.sh [peers.py options, e.g. --repeats 5 --only ps --json]
#
# PEERS_VENV (default target/peers-venv) is where the venv goes; the real procam data is expected
# at ../shared/data/procam-calibration/sample_data (override with --procam).
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release -q -p mlsss --bin mlsss --example em_crosscheck --example peer_images
VENV="${PEERS_VENV:-target/peers-venv}"
if [ ! -x "$VENV/bin/python" ]; then
    python3 -m venv "$VENV"
    "$VENV/bin/pip" install -q numpy scipy scikit-learn opencv-contrib-python-headless OpenEXR
fi
exec "$VENV/bin/python" scripts/peers.py "$@"
