"""numpy peer of benches/photometry.rs: the same formulas on the same frame size, timed.

- Nayar separation with black level b: Ld = (max - min)/(1 - b), Lg = 2 (min - b max)/(1 - b^2),
  clamped at 0.
- 4-light least-squares photometric stereo: g = pinv(L) I per pixel (grey readings), n = g/|g|.
Prints one line per case: name, median seconds over the runs.
"""
import time

import numpy as np

W, H = 1379, 1029


def timed(fn, runs=10):
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def stripe_frames():
    x = np.arange(W, dtype=np.float32)[None, :]
    y = np.arange(H, dtype=np.float32)[:, None]
    direct = 0.3 + 0.1 * np.sin(x * 0.01)
    glob = 0.2 + 0.05 * np.cos(y * 0.013)
    b = 0.02
    frames = []
    for s in range(6):
        lit = ((x + 6 - s) % 6) < 3
        v = direct * np.where(lit, 1.0, b) + glob * (1 + b) / 2
        frames.append(np.stack([v, 0.8 * v, 0.6 * v], axis=-1).astype(np.float32))
    return np.stack(frames)


def separate(frames, b=0.02):
    lmax = frames.max(axis=0)
    lmin = frames.min(axis=0)
    d = (lmax - lmin) / (1 - b)
    g = 2 * (lmin - b * lmax) / (1 - b * b)
    return np.maximum(d, 0), np.maximum(g, 0)


def lights():
    l = np.array([[-0.45, 0.45, 0.77], [0.45, 0.45, 0.77], [-0.45, -0.45, 0.77], [0.45, -0.45, 0.77]])
    return l / np.linalg.norm(l, axis=1, keepdims=True)


def ps_frames(L):
    x = (np.arange(W) / W - 0.5)[None, :] * 1.2
    y = (np.arange(H) / H - 0.5)[:, None] * 1.2
    n = np.stack([np.broadcast_to(x, (H, W)), np.broadcast_to(y, (H, W)), np.ones((H, W))], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    shade = np.maximum(0, np.einsum("hwc,kc->khw", n, L)) * 0.6
    return np.stack([shade, 0.7 * shade, 0.5 * shade], -1).astype(np.float32)


def ps_least_squares(images, L):
    grey = images.mean(axis=-1).reshape(len(L), -1)  # k x pixels
    g = np.linalg.pinv(L) @ grey  # 3 x pixels
    albedo = np.linalg.norm(g, axis=0)
    n = g / np.maximum(albedo, 1e-12)
    return n, albedo


if __name__ == "__main__":
    frames = stripe_frames()
    print(f"numpy separation_nayar        {timed(lambda: separate(frames)):.4f} s")
    L = lights()
    images = ps_frames(L)
    print(f"numpy ps4_least_squares       {timed(lambda: ps_least_squares(images, L)):.4f} s")
