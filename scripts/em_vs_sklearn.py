#!/usr/bin/env python3
"""Cross-check of our EM (free means, box-convolved) against scikit-learn's GaussianMixture.

Profiles are drawn from known mixtures, sampled as the booth samples them (the slit shifted by its
own width over one period, so the samples' boxes tile the period), with multiplicative noise.
scikit-learn gets the same data expanded to samples: each reading becomes round(y * COUNTS)
points spread uniformly over its slit box. Both fits are scored with the same objective: the
weighted log-likelihood of the binned readings (our model's likelihood, exact for tiling boxes).
Also reported: recovery error against the generating mixture and time per profile.

Usage: python3 scripts/em_vs_sklearn.py [--profiles N] [--components K] [--release | --example-binary PATH]
(`scripts/peers.sh` runs it with the other peer comparisons.)
Needs: numpy, scipy, scikit-learn (pip install scikit-learn). Not a runtime dependency of mlsss.
"""
import argparse, json, subprocess, sys, time
import numpy as np
from scipy.special import ndtr
from sklearn.mixture import GaussianMixture

W, T, COUNTS = 0.25, 7.5, 400


def binned_ll(s, y, w, mu, sd):
    """sum_j y_j ln f(s_j) / sum_j y_j, f = mixture through the box, with +-T images."""
    y = np.clip(y, 0, None)
    f = np.zeros_like(s)
    for wi, mi, si in zip(w, mu, sd):
        for off in (-T, 0.0, T):
            f += wi * (ndtr((s - off + W / 2 - mi) / si) - ndtr((s - off - W / 2 - mi) / si)) / W
    return float(np.sum(y * np.log(np.maximum(f, 1e-300))) / np.sum(y))


def make_profiles(n, components, seed=7):
    """`n` profiles drawn from random `components`-mixtures, and their generating mixtures."""
    rng = np.random.default_rng(seed)
    s = -T / 2 + (np.arange(int(T / W)) + 0.5) * W
    profiles, truths = [], []
    for _ in range(n):
        w = rng.dirichlet(np.ones(components) * 3)
        mu = np.sort(rng.uniform(-0.8, 1.2, components))
        sd = rng.uniform(0.15, 1.0, components)
        y = np.exp(binned_ll_density(s, w, mu, sd)) * (1 + 0.02 * rng.standard_normal(s.size))
        profiles.append({"s": s.tolist(), "y": np.clip(y, 0, None).tolist(), "width": W, "period": T})
        truths.append((w, mu, sd))
    return profiles, truths


def compare(n, components, ours_cmd):
    """Our EM (`ours_cmd`: the em_crosscheck example) and scikit-learn on the same profiles."""
    profiles, truths = make_profiles(n, components)
    ours = json.loads(subprocess.run(ours_cmd, input=json.dumps({"components": components, "profiles": profiles}),
                                     capture_output=True, text=True, check=True).stdout)
    rows = []
    sk_time = 0.0
    for p, fit, truth in zip(profiles, ours["fits"], truths):
        sv, yv = np.array(p["s"]), np.array(p["y"])
        counts = np.round(yv / yv.max() * COUNTS).astype(int)
        pts = np.concatenate([sj + W * (np.arange(c) + 0.5) / max(c, 1) - W / 2 for sj, c in zip(sv, counts)])
        t0 = time.perf_counter()
        gm = GaussianMixture(components, n_init=1, random_state=0, tol=1e-6, max_iter=500).fit(pts[:, None])
        sk_time += time.perf_counter() - t0
        sk = (gm.weights_, gm.means_[:, 0], np.sqrt(gm.covariances_[:, 0, 0]))
        ll_sk = binned_ll(sv, yv, *sk)
        ll_ours = binned_ll(sv, yv, fit["weights"], fit["means"], fit["sigmas"])
        ll_truth = binned_ll(sv, yv, *truth)
        rows.append((ll_ours, ll_sk, ll_truth))
    r = np.array(rows)
    return {
        "profiles": n,
        "components": components,
        "samples_per_profile": len(profiles[0]["s"]),
        "ours_minus_sklearn_ll": {"min": float((r[:, 0] - r[:, 1]).min()), "mean": float((r[:, 0] - r[:, 1]).mean())},
        "ours_at_least_as_good_fraction": float(np.mean(r[:, 0] >= r[:, 1] - 1e-9)),
        "ours_minus_truth_ll_mean": float((r[:, 0] - r[:, 2]).mean()),
        "seconds_per_profile": {"ours": ours["total_seconds"] / n, "sklearn": sk_time / n},
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--profiles", type=int, default=40)
    ap.add_argument("--components", type=int, default=3)
    ap.add_argument("--release", action="store_true")
    ap.add_argument("--example-binary", help="a built em_crosscheck example (default: cargo run it)")
    a = ap.parse_args()
    if a.example_binary:
        cmd = [a.example_binary]
    else:
        cmd = ["cargo", "run", "-q", "-p", "mlsss", "--example", "em_crosscheck"]
        if a.release:
            cmd.insert(2, "--release")
    report = compare(a.profiles, a.components, cmd)
    report["ours_build"] = "prebuilt" if a.example_binary else ("release" if a.release else "dev")
    print(json.dumps(report, indent=1))


def binned_ll_density(s, w, mu, sd):
    f = np.zeros_like(s)
    for wi, mi, si in zip(w, mu, sd):
        for off in (-T, 0.0, T):
            f += wi * (ndtr((s - off + W / 2 - mi) / si) - ndtr((s - off - W / 2 - mi) / si)) / W
    return np.log(np.maximum(f, 1e-300))


if __name__ == "__main__":
    sys.exit(main())
