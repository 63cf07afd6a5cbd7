#!/usr/bin/env python3
"""How fast a decoder of linear float frames could be, against the decoding target of issue 19
(5x the numpy port of OpenCV's GrayCodePattern logic): times that port on each real procam capture,
then the least any decoder must spend reading the same frames once, as the f32 stack ours decodes
and as the 8-bit stack the port decodes (a numpy max-reduction over the stacked frames: one pass,
memory-bound, one core). Prints per capture the port's best time, 1/5 of it (the target's budget)
and both reading floors.

    scripts/decode_bound.py [--procam DIR] [--repeats N]

Runs in the peers' venv (numpy, opencv-contrib-python-headless): e.g.
`PEERS_VENV=DIR scripts/peers.sh --only decode` makes one, then `DIR/bin/python
scripts/decode_bound.py`. Never a dependency of mlsss.
"""
import argparse
import glob
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import peers  # noqa: E402


def best_time(repeats, run):
    """Best wall seconds of `repeats` runs (peers.best_of's first figure)."""
    return peers.best_of(repeats, run)[0]


def main():
    root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--procam", default=os.path.join(root, "../shared/data/procam-calibration/sample_data"))
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    captures = sorted(glob.glob(os.path.join(args.procam, "capture_*")))
    if not captures:
        sys.exit(f"error: no capture_* folder under {args.procam}")
    print(f"{'capture':<10} {'frames':>6} {'numpy s':>9} {'budget s':>9} {'read f32 s':>11} "
          f"{'f32 / 2 s':>10} {'read u8 s':>10}  f32 MB")
    for c in captures:
        frames = peers.read_pngs(c)
        port = best_time(args.repeats, lambda: peers.opencv_decode(frames))
        as_f32 = frames.astype(np.float32).reshape(len(frames), -1)
        as_u8 = frames.reshape(len(frames), -1)
        read_f32 = best_time(args.repeats, lambda: as_f32.max(axis=0))
        read_u8 = best_time(args.repeats, lambda: as_u8.max(axis=0))
        print(f"{os.path.basename(c):<10} {len(frames):>6} {port:>9.4f} {port / 5:>9.4f} {read_f32:>11.4f} "
              f"{read_f32 / 2:>10.4f} {read_u8:>10.4f}  {as_f32.nbytes / 1e6:.0f}")
    print("budget = numpy / 5 (the target). A decoder of the f32 frames spends at least 'read f32' on one\n"
          "core and at best half of that on two ('f32 / 2', if two cores read twice as fast as one) before\n"
          "it decides a single bit")


if __name__ == "__main__":
    main()
