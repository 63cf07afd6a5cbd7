#!/usr/bin/env python3
"""MCML's own random generator against adding-doubling: the evidence behind `mcml_race.py`'s
choice of reference (it judges agreement against MCML with xoshiro256+ in place of `ran3`).

    python3 host/monte-carlo/benches/mcml_rng_bias.py PATH/TO/gpumcml/cpumcml \
        [--mcml-photons 2000000] [--ours-photons 5000000] [--runs 2] [--mlsss target/release/mlsss]

Needs iadpython 0.5.3 (`pip install iadpython==0.5.3`, as `scripts/iad_reference.py`). The medium is
the fat layer of MCML's 7-layer skin input alone, in air (n 1.44, mu_a 0.3/cm, mu_s 150/cm, g 0.8,
0.59 cm: optical thickness 88.7, albedo 0.998), a slab adding-doubling solves exactly. Each of the
`--runs` rounds runs MCML as published and MCML with xoshiro256+ side by side (one core each; the
published one seeds itself from the clock, so rounds are a few seconds apart at least), then ours
on every core; it prints the diffuse reflectance, transmittance and absorption of each program
pooled over the rounds, against adding-doubling in units of the program's standard error (MCML
prints none: its per-photon variance is taken equal to ours). Adding-doubling's own uncertainty
is the change from 40 to 48 quadrature points (below 1e-5 here).

Measured 2026-12-02 with the defaults (2 runs, 2M MCML and 5M of our photons each; seeds from
598472999): MCML as published R_d -0.17 %, T +0.79 %, A +0.21 % (z -5.78, +4.93, +4.91); MCML with
xoshiro256+ -0.00 %, -0.29 %, +0.03 % (z -0.09, -1.78, +0.71); ours +0.00 %, -0.06 %, +0.00 % (z
+0.13, -0.60, +0.02). A first run by hand the same day (other seeds) gave the same picture: MCML
as published -0.19 %, +0.86 %, +0.25 % (z -6.7, +5.4, +4.0), ours within 1.2 standard errors.
"""

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import mcml_race  # noqa: E402  (the MCML builds and its output parser)

# n, mu_a (1/cm), mu_s (1/cm), g, d (cm): the last layer of MCML's 7-layer skin input.
FAT_CM = (1.44, 0.3, 150.0, 0.8, 0.59)


def adding_doubling() -> tuple[dict, float]:
    """(R_d, T, A) of the slab by iadpython at 48 quadrature points, and the largest change of
    the three from 40 points."""
    import iadpython

    n, mua, mus, g, d = FAT_CM
    specular = ((n - 1) / (n + 1)) ** 2
    values = []
    for q in (40, 48):
        ur1, ut1, _, _ = iadpython.Sample(a=mus / (mua + mus), b=(mua + mus) * d, g=g, n=n,
                                          n_above=n, n_below=n, quad_pts=q).rt()
        ur1, ut1 = float(ur1), float(ut1)
        values.append({"diffuse_reflectance": ur1 - specular, "total_transmittance": ut1,
                       "absorbed": 1 - ur1 - ut1})
    change = max(abs(values[1][k] - values[0][k]) for k in values[1])
    return values[1], change


def layers_toml() -> str:
    n, mua, mus, g, d = FAT_CM
    return (f"n_above = 1.0\nn_below = 1.0\n\n[[layer]]\nname = \"subcutaneous fat\"\n"
            f"thickness_mm = {d * 10}\nmu_a = {mua / 10}\nmu_s = {mus / 10}\ng = {g}\nn = {n}\n")


def mcml_tallies(work: Path) -> dict:
    out = mcml_race.parse_mco(work / "race.mco", layers=1)
    return {"diffuse_reflectance": out["diffuse_reflectance"],
            "total_transmittance": out["total_transmittance"], "absorbed": out["absorbed"][0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cpumcml", type=Path, help="the cpumcml/ folder of ominux/gpumcml")
    ap.add_argument("--mcml-photons", type=int, default=2_000_000)
    ap.add_argument("--ours-photons", type=int, default=5_000_000)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--seed", type=int, default=None, help="first seed of ours and of the xoshiro build")
    ap.add_argument("--mlsss", type=Path, default=mcml_race.REPO / "target/release/mlsss")
    args = ap.parse_args()
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(4), "little") % 10**9
    exact, ad_change = adding_doubling()
    keys = ("diffuse_reflectance", "total_transmittance", "absorbed")
    runs = {"MCML as published": [], "MCML with xoshiro256+": [], "ours": []}
    ours_se = []
    with tempfile.TemporaryDirectory(prefix="mcml-rng-") as tmp:
        published, xoshiro = Path(tmp) / "mcml", Path(tmp) / "mcml-xoshiro"
        builds = [(mcml_race.build_mcml(args.cpumcml, published), published),
                  (mcml_race.build_mcml(args.cpumcml, xoshiro, xoshiro=True), xoshiro)]
        for _, work in builds:
            (work / "race.mci").write_text(mcml_race.mci_text(args.mcml_photons, [FAT_CM]))
        layers = Path(tmp) / "fat.toml"
        layers.write_text(layers_toml())
        for r in range(args.runs):
            env = dict(os.environ, MCML_SEED=str(seed + r))
            side_by_side = [subprocess.Popen([str(exe), "race.mci"], cwd=work, env=env,
                                             stdout=subprocess.DEVNULL) for exe, work in builds]
            if any(p.wait() != 0 for p in side_by_side):
                sys.exit("MCML failed")
            runs["MCML as published"].append(mcml_tallies(published))
            runs["MCML with xoshiro256+"].append(mcml_tallies(xoshiro))
            out = subprocess.run([str(args.mlsss), "mc", "layers", "--file", str(layers), "--photons",
                                  str(args.ours_photons), "--seed", str(seed + r), "--json"],
                                 check=True, capture_output=True, text=True).stdout
            ours = json.loads(out)
            runs["ours"].append({"diffuse_reflectance": ours["diffuse_reflectance"],
                                 "total_transmittance": ours["total_transmittance"],
                                 "absorbed": ours["absorbed"][0]})
            ours_se.append({"diffuse_reflectance": ours["diffuse_reflectance_se"],
                            "total_transmittance": ours["total_transmittance_se"],
                            "absorbed": ours["absorbed_se"][0]})
            print(f"round {r + 1} of {args.runs} done", file=sys.stderr)

    print(f"fat slab alone (n {FAT_CM[0]}, mu_a {FAT_CM[1]}/cm, mu_s {FAT_CM[2]}/cm, g {FAT_CM[3]}, "
          f"{FAT_CM[4]} cm) in air, {args.runs} run(s) each: MCML {args.mcml_photons} photons, "
          f"ours {args.ours_photons} (seeds from {seed})")
    print(f"adding-doubling (iadpython, 48 points; change from 40: {ad_change:.1e}): "
          + ", ".join(f"{k} {exact[k]:.6f}" for k in keys))
    print(f"{'program':<24} {'quantity':<20} {'value':>10} {'rel':>8} {'z':>6}")
    # The standard error of our pooled mean; another program's is it scaled to its photons.
    se_ours = {k: math.sqrt(sum(s[k] ** 2 for s in ours_se)) / len(ours_se) for k in keys}
    for program, values in runs.items():
        photons = args.ours_photons if program == "ours" else args.mcml_photons
        for k in keys:
            mean = sum(v[k] for v in values) / len(values)
            se = se_ours[k] * math.sqrt(args.ours_photons / photons)
            z = (mean - exact[k]) / math.sqrt(se * se + ad_change * ad_change)
            print(f"{program:<24} {k:<20} {mean:>10.6f} {100 * (mean - exact[k]) / exact[k]:>+7.2f}% {z:>+6.2f}")


if __name__ == "__main__":
    main()
