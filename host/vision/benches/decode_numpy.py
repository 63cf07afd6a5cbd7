"""Straightforward numpy vectorised Gray-code decode, the peer of `benches/decode.rs`.

Reads the frames the Rust bench wrote (raw little-endian f32: header of three u32 = width, height,
frame count; then white, black, x pairs MSB first, y pairs MSB first), decodes them the textbook
way (lit mask from white - black, each bit = pattern > inverse, Gray to binary by prefix XOR), and
prints one JSON object with frames per second (decode only, best of N runs).

    python3 host/vision/benches/decode_numpy.py FRAMES.f32 [RUNS]
"""

import json
import sys
import time

import numpy as np


def decode(frames, bits_x, bits_y, min_amplitude=0.02):
    white, black = frames[0], frames[1]
    lit = (white - black) >= min_amplitude
    codes = []
    offset = 2
    for bits in (bits_x, bits_y):
        pairs = frames[offset:offset + 2 * bits]
        offset += 2 * bits
        bit_planes = pairs[0::2] > pairs[1::2]  # MSB first
        binary = np.logical_xor.accumulate(bit_planes, axis=0)  # Gray -> binary, MSB first
        weights = (1 << np.arange(bits - 1, -1, -1)).astype(np.int32)
        code = np.tensordot(weights, binary.astype(np.int32), axes=1)
        codes.append(np.where(lit, code, -1))
    return codes


def main():
    path = sys.argv[1]
    runs = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    header = np.fromfile(path, dtype="<u4", count=3)
    width, height, count = (int(v) for v in header)
    frames = np.fromfile(path, dtype="<f4", offset=12).reshape(count, height, width)
    code_frames = count - 2
    bits_x = bits_y = code_frames // 4
    best = float("inf")
    for _ in range(runs):
        start = time.perf_counter()
        u, v = decode(frames, bits_x, bits_y)
        best = min(best, time.perf_counter() - start)
    print(json.dumps({
        "numpy_seconds_per_projector": best,
        "numpy_frames_per_s": code_frames / best,
        "valid_fraction": float(np.mean((u >= 0) & (v >= 0))),
        "numpy": np.__version__,
    }))


if __name__ == "__main__":
    main()
