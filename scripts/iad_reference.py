#!/usr/bin/env python3
"""Exact (adding-doubling) reflectance and transmittance of slabs, the reference values of the
Monte Carlo validation tests in tests/tests/integration/mc_validation.rs.

    pip install iadpython==0.5.3
    python3 scripts/iad_reference.py        # prints the Rust table pasted into the test

Each case is a homogeneous slab (albedo a, optical thickness tau, HG anisotropy g, index n) under a
collimated normal beam from air, optionally between non-absorbing glass slides of index n_slide_above
/ n_slide_below (iadpython's n_above / n_below; a slide index equal to n means no slide). In the Monte
Carlo test a slide is a clear layer (mu_a = mu_s = 0) of index n_slide.

iadpython returns UR1 and UT1: total reflectance (specular included) and total transmittance
(unscattered included) for normal collimated incidence. The Monte Carlo `specular` is the Fresnel
reflection at the first surface (air -> slide, or air -> sample without slide), so the reference
diffuse reflectance is UR1 minus that.

The quadrature order is raised until two orders agree to 2e-5 absolute: iadpython 0.5.3 is not
monotone in quad_pts (for matched boundaries, orders >= 32 break down numerically), so each case is
computed at a list of orders and the first agreeing consecutive pair is used.
"""
import math

import iadpython

INF = float("inf")

# (name, a, tau, g, n, n_slide_above, n_slide_below)
CASES = [
    ("mcml_slab_matched", 0.9, 2.0, 0.75, 1.0, 1.0, 1.0),
    ("semi_infinite_matched_iso", 0.9, INF, 0.0, 1.0, 1.0, 1.0),
    ("thin_low_albedo_water", 0.5, 0.5, 0.0, 1.33, 1.33, 1.33),
    ("high_albedo_mismatched", 0.99, 1.0, 0.5, 1.4, 1.4, 1.4),
    ("backward_g_mismatched", 0.8, 2.0, -0.3, 1.2, 1.2, 1.2),
    ("glass_slides_forward", 0.95, 4.0, 0.9, 1.4, 1.5, 1.5),
    ("slide_above_only_iso", 0.95, 3.0, 0.0, 1.4, 1.5, 1.4),
    ("semi_infinite_skinlike", 0.98, INF, 0.8, 1.4, 1.4, 1.4),
    # The fat layer of MCML's 7-layer skin input alone (mu_a 0.3/cm, mu_s 150/cm, 0.59 cm): thick
    # and nearly conservative; MCML's own generator is biased here (benches/mcml_rng_bias.py).
    ("thick_fat_layer", 150 / 150.3, 150.3 * 0.59, 0.8, 1.44, 1.44, 1.44),
]

ORDERS = [12, 16, 20, 24, 28, 32, 40, 48]


def fresnel_normal(n1, n2):
    return ((n1 - n2) / (n1 + n2)) ** 2


def converged(a, tau, g, n, na, nb):
    previous = None
    for q in ORDERS:
        s = iadpython.Sample(a=a, b=tau, g=g, n=n, n_above=na, n_below=nb, quad_pts=q)
        ur1, ut1, _, _ = s.rt()
        ur1, ut1 = float(ur1), float(ut1)
        if previous and abs(previous[0] - ur1) < 2e-5 and abs(previous[1] - ut1) < 2e-5:
            return ur1, ut1, q
        previous = (ur1, ut1)
    raise RuntimeError(f"no convergence for {(a, tau, g, n, na, nb)}")


def main():
    print(f"// iadpython {iadpython.__version__}: (name, a, tau, g, n, n_slide_above, n_slide_below, specular, diffuse R, total T)")
    for name, a, tau, g, n, na, nb in CASES:
        ur1, ut1, q = converged(a, tau, g, n, na, nb)
        specular = fresnel_normal(1.0, na)
        tau_txt = "f64::INFINITY" if math.isinf(tau) else repr(tau)
        print(
            f'    Case {{ name: "{name}", albedo: {a}, tau: {tau_txt}, g: {g}, n: {n}, '
            f"n_slide_above: {na}, n_slide_below: {nb}, specular: {specular:.6f}, "
            f"diffuse_reflectance: {ur1 - specular:.6f}, total_transmittance: {ut1:.6f} }}, // quad_pts {q}"
        )


if __name__ == "__main__":
    main()
