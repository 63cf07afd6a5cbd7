// The lane-vector code of the photon step, compiled once per instruction set: included by
// `photon_lanes` into modules where `F64s` and `U64s` are the array vectors of `simd` or the AVX2
// vectors of `simd_avx2`. Everything here is written against that common API.

/// The constants of every lane's current layer, as vectors.
pub(crate) struct LayerVectors {
    z_top: F64s,
    z_bottom: F64s,
    inv_mu_t: F64s,
    absorb_fraction: F64s,
    hg_one_plus_g2: F64s,
    hg_one_minus_g2: F64s,
    hg_one_minus_g: F64s,
    hg_two_g: F64s,
    hg_inv_two_g: F64s,
}

impl LayerVectors {
    #[inline(always)]
    fn load(lanes: &Lanes) -> Self {
        Self {
            z_top: F64s::load(lanes.z_top),
            z_bottom: F64s::load(lanes.z_bottom),
            inv_mu_t: F64s::load(lanes.inv_mu_t),
            absorb_fraction: F64s::load(lanes.absorb_fraction),
            hg_one_plus_g2: F64s::load(lanes.hg_one_plus_g2),
            hg_one_minus_g2: F64s::load(lanes.hg_one_minus_g2),
            hg_one_minus_g: F64s::load(lanes.hg_one_minus_g),
            hg_two_g: F64s::load(lanes.hg_two_g),
            hg_inv_two_g: F64s::load(lanes.hg_inv_two_g),
        }
    }
}

/// 64 random bits for every lane: one xoshiro256++ step of each lane's stream.
#[inline(always)]
pub(crate) fn next_bits(rng: &mut LaneRng) -> U64s {
    // Explicit loads: `array::map` with a fn item would go through a shim without AVX2.
    let s0 = U64s::load(rng.s[0]);
    let s1 = U64s::load(rng.s[1]);
    let s2 = U64s::load(rng.s[2]);
    let s3 = U64s::load(rng.s[3]);
    let result = s0.wrapping_add(s3).rotate_left(23).wrapping_add(s0);
    let t = s1 << 17;
    let s2 = s2 ^ s0;
    let s3 = s3 ^ s1;
    let s1 = s1 ^ s2;
    let s0 = s0 ^ s3;
    let s2 = s2 ^ t;
    let s3 = s3.rotate_left(45);
    rng.s = [s0.store(), s1.store(), s2.store(), s3.store()];
    result
}

/// Uniform in [0, 1) from the top 52 bits of every lane (see `lane_rng::unit`).
#[inline(always)]
pub(crate) fn units(bits: U64s) -> F64s {
    ((bits >> 12) | U64s::splat(0x3ff0_0000_0000_0000)).as_f64_bits() - F64s::splat(1.0)
}

/// Uniform in (0, 1] from the top 52 bits of every lane, safe for `ln`.
#[inline(always)]
pub(crate) fn units_open(bits: U64s) -> F64s {
    F64s::splat(2.0) - ((bits >> 12) | U64s::splat(0x3ff0_0000_0000_0000)).as_f64_bits()
}

/// Natural logarithm of positive normal numbers, to about 1 ulp.
#[inline(always)]
pub(crate) fn ln(x: F64s) -> F64s {
    // Shift the exponent so that the mantissa lands in [sqrt(1/2), sqrt(2)): ln(1 + f) then has
    // |f| < 0.42 and the series converges fast (musl's reduction, on the whole 64-bit word).
    const SQRT_HALF_HIGH: u64 = 0x3fe6_a09e_0000_0000;
    let shifted = x
        .to_bits()
        .wrapping_add(U64s::splat(0x3ff0_0000_0000_0000 - SQRT_HALF_HIGH));
    let biased_exponent = shifted >> 52;
    // k as f64 without an integer conversion (which does not vectorise before AVX-512):
    // 2^52 + e has e in its low mantissa bits.
    let k = (U64s::splat(0x4330_0000_0000_0000) | biased_exponent).as_f64_bits()
        - F64s::splat(4_503_599_627_370_496.0 + 1023.0);
    let m = ((shifted & U64s::splat(0x000f_ffff_ffff_ffff))
        .wrapping_add(U64s::splat(SQRT_HALF_HIGH)))
    .as_f64_bits();
    let c = F64s::splat;
    let f = m - c(1.0);
    let half_f_sq = c(0.5) * f * f;
    let s = f / (c(2.0) + f);
    let z = s * s;
    let w = z * z;
    let odd = w * (c(fast_math::LG2) + w * (c(fast_math::LG4) + w * c(fast_math::LG6)));
    let even = z
        * (c(fast_math::LG1)
            + w * (c(fast_math::LG3) + w * (c(fast_math::LG5) + w * c(fast_math::LG7))));
    let r = even + odd;
    s * (half_f_sq + r) + k * c(fast_math::LN2_LO) - half_f_sq + f + k * c(fast_math::LN2_HI)
}

/// (sin a, cos a) for |a| <= pi/4 (fdlibm's kernel polynomials).
#[inline(always)]
pub(crate) fn sin_cos_quarter(a: F64s) -> (F64s, F64s) {
    let c = F64s::splat;
    let z = a * a;
    let sin_poly = c(fast_math::S1)
        + z * (c(fast_math::S2)
            + z * (c(fast_math::S3)
                + z * (c(fast_math::S4) + z * (c(fast_math::S5) + z * c(fast_math::S6)))));
    let cos_poly = c(fast_math::C1)
        + z * (c(fast_math::C2)
            + z * (c(fast_math::C3)
                + z * (c(fast_math::C4) + z * (c(fast_math::C5) + z * c(fast_math::C6)))));
    let sin = a + a * z * sin_poly;
    let cos = c(1.0) - c(0.5) * z + z * z * cos_poly;
    (sin, cos)
}

/// One event for every lane: lanes whose step ends inside their layer move, deposit and scatter;
/// lanes whose step reaches a boundary keep their state and the sampled depth for the scalar code.
#[inline(always)]
pub(crate) fn interact(lanes: &mut Lanes) -> StepOutcome {
    let x = F64s::load(lanes.x);
    let y = F64s::load(lanes.y);
    let z = F64s::load(lanes.z);
    let ux = F64s::load(lanes.ux);
    let uy = F64s::load(lanes.uy);
    let uz = F64s::load(lanes.uz);
    let weight = F64s::load(lanes.weight);
    let optical_left = F64s::load(lanes.optical_left);
    let deposit_sum = F64s::load(lanes.deposit);
    let layer = LayerVectors::load(lanes);
    let zero = F64s::splat(0.0);
    let sampled = -ln(units_open(next_bits(&mut lanes.rng)));
    let xi = units(next_bits(&mut lanes.rng));
    let (cos_p, sin_p) = azimuth(next_bits(&mut lanes.rng));

    let resume = optical_left.eq(zero);
    let tau = resume.select(sampled, optical_left);
    let going_down = uz.gt(zero);
    let depth_to_boundary = going_down.select(layer.z_bottom - z, z - layer.z_top);
    let step = tau * layer.inv_mu_t;
    // A NaN (infinite step along a clear layer) compares false, so it counts as a boundary hit.
    let inside = (step * uz.abs()).lt(depth_to_boundary);

    let deposit = weight * layer.absorb_fraction;
    let cos_t = henyey_greenstein_cos(&layer, xi);
    let [nx, ny, nz] = spin([ux, uy, uz], cos_t, cos_p, sin_p);
    let x = inside.select(x + step * ux, x);
    let y = inside.select(y + step * uy, y);
    let z = inside.select(z + step * uz, z);
    let ux = inside.select(nx, ux);
    let uy = inside.select(ny, uy);
    let uz = inside.select(nz, uz);
    let weight = inside.select(weight - deposit, weight);
    let deposit_sum = deposit_sum + inside.select(deposit, zero);
    let optical_left = inside.select(zero, tau);

    let active = U64s::load(lanes.active);
    let counted = (inside & active).store();
    for (total, lane_counted) in lanes.interactions.iter_mut().zip(counted) {
        *total += lane_counted & 1;
    }
    for events in &mut lanes.events {
        *events = events.wrapping_add(1);
    }
    let light = weight.lt(F64s::splat(ROULETTE_THRESHOLD));
    lanes.x = x.store();
    lanes.y = y.store();
    lanes.z = z.store();
    lanes.ux = ux.store();
    lanes.uy = uy.store();
    lanes.uz = uz.store();
    lanes.weight = weight.store();
    lanes.optical_left = optical_left.store();
    lanes.deposit = deposit_sum.store();
    StepOutcome {
        at_boundary: (!inside & active).bitmask(),
        light: (light & active).bitmask(),
    }
}

/// Henyey-Greenstein scattering cosine by inverse CDF for uniforms `xi` in [0, 1).
#[inline(always)]
fn henyey_greenstein_cos(layer: &LayerVectors, xi: F64s) -> F64s {
    let c = F64s::splat;
    let t = layer.hg_one_minus_g2 / (layer.hg_one_minus_g + layer.hg_two_g * xi);
    let anisotropic = ((layer.hg_one_plus_g2 - t * t) * layer.hg_inv_two_g)
        .max(c(-1.0))
        .min(c(1.0));
    let isotropic = layer.hg_inv_two_g.eq(c(0.0));
    isotropic.select(c(2.0) * xi - c(1.0), anisotropic)
}

/// (cos phi, sin phi) of a uniform azimuth: a uniform angle in [-pi/4, pi/4) from the top 52 bits,
/// turned by a uniform multiple of 90 degrees from the lowest two bits.
#[inline(always)]
pub(crate) fn azimuth(bits: U64s) -> (F64s, F64s) {
    let a = (units(bits) - F64s::splat(0.5)) * F64s::splat(std::f64::consts::FRAC_PI_2);
    let (s, c) = sin_cos_quarter(a);
    let zero = U64s::splat(0);
    let quarter_turn = !((bits & U64s::splat(1)).eq_u64(zero));
    let half_turn = !((bits & U64s::splat(2)).eq_u64(zero));
    let (c, s) = (quarter_turn.select(-s, c), quarter_turn.select(c, s));
    (half_turn.select(-c, c), half_turn.select(-s, s))
}

/// Turns directions by polar cosine `cos_t` and azimuth (cos_p, sin_p) about themselves (MCML's
/// formulas, with sin(theta) / sqrt(1 - uz^2) taken as one square root).
#[inline(always)]
pub(crate) fn spin(dir: [F64s; 3], cos_t: F64s, cos_p: F64s, sin_p: F64s) -> [F64s; 3] {
    let c = F64s::splat;
    let sin_t_sq = (c(1.0) - cos_t * cos_t).max(c(0.0));
    let [ux, uy, uz] = dir;
    let one_minus_uz2 = c(1.0) - uz * uz;
    let vertical = one_minus_uz2.lt(c(NEAR_VERTICAL));
    // Both branches are computed (the lanes disagree); the unused one may divide by ~0 harmlessly.
    let k = (sin_t_sq / one_minus_uz2).sqrt();
    let sin_t = sin_t_sq.sqrt();
    let signed_cos_t = uz.lt(c(0.0)).select(-cos_t, cos_t);
    [
        vertical.select(
            sin_t * cos_p,
            k * (ux * uz * cos_p - uy * sin_p) + ux * cos_t,
        ),
        vertical.select(
            sin_t * sin_p,
            k * (uy * uz * cos_p + ux * sin_p) + uy * cos_t,
        ),
        vertical.select(signed_cos_t, -k * cos_p * one_minus_uz2 + uz * cos_t),
    ]
}
