// The lane-vector code of the photon step, compiled once per instruction set: included by
// `photon_lanes` into modules where `F32s` and `U32s` are the array vectors of `simd`, the AVX2
// vectors of `simd_avx2` or the AVX-512 ones of `simd_avx512`. Everything here is written against
// that common API, in f32: 16 photons per AVX-512 register.

/// Old directions with ux^2 + uy^2 below this are treated as vertical by `spin` (within 1e-6 rad;
/// MCML's COSZERO is 1e-12 on uz, the same order on the sine).
const NEAR_VERTICAL_SIN_SQ: f32 = 1e-12;

/// The Henyey-Greenstein constants of every lane's current layer, as vectors.
pub(crate) struct PhaseFunctionVectors {
    hg_g: F32s,
    hg_one_minus_g: F32s,
    hg_two_g: F32s,
    hg_scale: F32s,
}

impl PhaseFunctionVectors {
    #[inline(always)]
    pub(crate) fn load(lanes: &Lanes) -> Self {
        Self {
            hg_g: F32s::load(lanes.hg_g),
            hg_one_minus_g: F32s::load(lanes.hg_one_minus_g),
            hg_two_g: F32s::load(lanes.hg_two_g),
            hg_scale: F32s::load(lanes.hg_scale),
        }
    }
}

/// 32 random bits for every lane: one xoshiro128++ step of each lane's stream.
#[inline(always)]
pub(crate) fn next_bits(rng: &mut LaneRng) -> U32s {
    let [bits] = next_bits_n(rng);
    bits
}

/// The next `N` draws of every lane's stream (`next_bits` `N` times), with the state loaded and
/// stored once: each load or store of the state is eight AVX2 instructions.
#[inline(always)]
pub(crate) fn next_bits_n<const N: usize>(rng: &mut LaneRng) -> [U32s; N] {
    // Explicit loads: `array::map` with a fn item would go through a shim without AVX2.
    let mut s0 = U32s::load(rng.s[0]);
    let mut s1 = U32s::load(rng.s[1]);
    let mut s2 = U32s::load(rng.s[2]);
    let mut s3 = U32s::load(rng.s[3]);
    // A loop, not `array::from_fn`: its closure is called out of line, without AVX2 (10x slower).
    let mut draws = [U32s::splat(0); N];
    for draw in &mut draws {
        *draw = s0.wrapping_add(s3).rotate_left(7).wrapping_add(s0);
        let t = s1 << 9;
        s2 = s2 ^ s0;
        s3 = s3 ^ s1;
        s1 = s1 ^ s2;
        s0 = s0 ^ s3;
        s2 = s2 ^ t;
        s3 = s3.rotate_left(11);
    }
    rng.s = [s0.store(), s1.store(), s2.store(), s3.store()];
    draws
}

/// Uniform in [0, 1) on a 2^-23 grid from the top 23 bits of every lane (exponent trick).
#[inline(always)]
pub(crate) fn units(bits: U32s) -> F32s {
    ((bits >> 9) | U32s::splat(0x3f80_0000)).as_f32_bits() - F32s::splat(1.0)
}

/// Uniform in (0, 1] from the top 31 bits of every lane, down to 2^-32: safe for `ln`, and the
/// sampled optical depth -ln(u) reaches 22 (a 23-bit grid would stop at 16).
#[inline(always)]
pub(crate) fn units_open(bits: U32s) -> F32s {
    (bits >> 1).signed_to_f32().mul_add(
        F32s::splat(fast_math::TWO_POW_M31),
        F32s::splat(fast_math::TWO_POW_M32),
    )
}

/// Natural logarithm of positive normal f32 (bound in `fast_math`).
#[inline(always)]
pub(crate) fn ln(x: F32s) -> F32s {
    // Shift the exponent so that the mantissa lands in [sqrt(1/2), sqrt(2)): ln(1 + f) then has
    // |f| < 0.42 and Cephes' polynomial applies (no division, unlike fdlibm's reduction).
    const SQRT_HALF: u32 = 0x3f35_04f3;
    let shifted = x
        .to_bits()
        .wrapping_add(U32s::splat(0x3f80_0000 - SQRT_HALF));
    // k as f32 without an integer conversion: 2^23 + e has e in its low mantissa bits.
    let k = (U32s::splat(0x4b00_0000) | (shifted >> 23)).as_f32_bits()
        - F32s::splat(8_388_608.0 + 127.0);
    let m = ((shifted & U32s::splat(0x007f_ffff)).wrapping_add(U32s::splat(SQRT_HALF)))
        .as_f32_bits();
    let c = F32s::splat;
    let f = m - c(1.0);
    let z = f * f;
    // Estrin's scheme: a tree of depth 4 instead of Horner's chain of 8 (the step's latency).
    // Element by element, not `LN_POLY.map(c)`: `array::map` calls out of line into code
    // compiled without AVX, which then calls `_mm256_set1_ps` out of line too (22 % of the
    // AVX2 step's samples, perf).
    let p = &fast_math::LN_POLY;
    let (a0, a1, a2, a3, a4) = (c(p[0]), c(p[1]), c(p[2]), c(p[3]), c(p[4]));
    let (a5, a6, a7, a8) = (c(p[5]), c(p[6]), c(p[7]), c(p[8]));
    let z2 = z * z;
    let low = f.mul_add(a1, a0) + z * f.mul_add(a3, a2);
    let high = f.mul_add(a5, a4) + z * f.mul_add(a7, a6);
    let p = z2.mul_add(high, low) + (z2 * z2) * a8;
    let y = (f * z).mul_add(p, k.mul_add(c(fast_math::LN2_LO), c(-0.5) * z));
    k.mul_add(c(fast_math::LN2_HI), f + y)
}

/// (sin a, cos a) for |a| <= pi/4 (Cephes' single-precision kernel polynomials).
#[inline(always)]
pub(crate) fn sin_cos_quarter(a: F32s) -> (F32s, F32s) {
    let c = F32s::splat;
    let z = a * a;
    let [s1, s2, s3] = fast_math::SIN_POLY;
    let [c1, c2, c3] = fast_math::COS_POLY;
    let sin = (z * a).mul_add(z.mul_add(z.mul_add(c(s1), c(s2)), c(s3)), a);
    let cos = (z * z).mul_add(
        z.mul_add(z.mul_add(c(c1), c(c2)), c(c3)),
        z.mul_add(c(-0.5), c(1.0)),
    );
    (sin, cos)
}

/// One event for every lane: lanes whose step ends inside their layer move, deposit and scatter;
/// lanes whose step reaches a boundary keep their state and the sampled depth for the scalar code.
///
/// Written in phases, each loading the lane vectors it needs and storing what it changed before
/// the next begins (`keep_stores_whole` between them, so that no load moves up). With every
/// vector loaded up front, the step's values outnumbered AVX2's 16 registers (two per 16-lane
/// vector): 104 of its instructions moved spills to the stack and back, 59 now (callgrind,
/// 7-layer skin). Side by side, one thread each, tallies bit-identical: the `seven_layer`
/// example about 10 % faster (18 pairs, 13 faster), `mlsss mc layers` about 4 % (16 pairs, 9
/// faster; this VM's noise is of that order). The step's three random draws are made together
/// at its start, the xoshiro state loaded and stored once instead of three times (16 AVX2
/// instructions each way): spill instructions 59 -> 22 per step, 1.227e9 -> 1.135e9
/// instructions for 20 000 photons (callgrind), the `seven_layer` example 10 % faster (12
/// pairs, 9 faster), `mlsss mc layers` 17 % less CPU (10 pairs, all faster), tallies
/// bit-identical.
#[inline(always)]
pub(crate) fn interact(lanes: &mut Lanes) -> StepOutcome {
    let zero = F32s::splat(0.0);
    // The step's three draws at once (the state loaded and stored once, not three times); the
    // scattering's two wait in memory for their phase.
    let [step_bits, scatter_bits, azimuth_bits] = next_bits_n(&mut lanes.rng);
    lanes.scatter_bits = scatter_bits.store();
    lanes.azimuth_bits = azimuth_bits.store();
    // Where the step ends: in the layer, or at its boundary (then nothing moves).
    let sampled = -ln(units_open(step_bits));
    let optical_left = F32s::load(lanes.optical_left);
    let z = F32s::load(lanes.z);
    let uz = F32s::load(lanes.uz);
    let tau = optical_left.eq(zero).select(sampled, optical_left);
    let going_down = uz.gt(zero);
    let depth_to_boundary = going_down.select(
        F32s::load(lanes.z_bottom) - z,
        z - F32s::load(lanes.z_top),
    );
    let step = tau * F32s::load(lanes.inv_mu_t);
    // A NaN (infinite step along a clear layer) compares false, so it counts as a boundary hit.
    let inside = (step * uz.abs()).lt(depth_to_boundary);
    let inside_bits = inside.bitmask();
    keep_stores_whole();
    lanes.optical_left = inside.select(zero, tau).store();
    lanes.z = inside.select(step.mul_add(uz, z), z).store();

    // The move and the deposit.
    let x = F32s::load(lanes.x);
    let ux = F32s::load(lanes.ux);
    let y = F32s::load(lanes.y);
    let uy = F32s::load(lanes.uy);
    let weight = F32s::load(lanes.weight);
    let moved_x = inside.select(step.mul_add(ux, x), x);
    let moved_y = inside.select(step.mul_add(uy, y), y);
    let weight = inside.select(weight * F32s::load(lanes.albedo), weight);
    let light = weight.lt(F32s::splat(ROULETTE_THRESHOLD as f32));
    keep_stores_whole();
    lanes.x = moved_x.store();
    lanes.y = moved_y.store();
    lanes.weight = weight.store();

    // The scattering.
    let (cos_p, sin_p) = azimuth(U32s::load(lanes.azimuth_bits));
    let polar = henyey_greenstein(
        &PhaseFunctionVectors::load(lanes),
        units(U32s::load(lanes.scatter_bits)),
    );
    // Loaded again, not kept in registers through the move and the random draws above.
    let (ux, uy, uz) = (
        F32s::load(lanes.ux),
        F32s::load(lanes.uy),
        F32s::load(lanes.uz),
    );
    let [nx, ny, nz] = spin([ux, uy, uz], polar, cos_p, sin_p);
    let ux = inside.select(nx, ux);
    let uy = inside.select(ny, uy);
    let uz = inside.select(nz, uz);
    keep_stores_whole();
    lanes.ux = ux.store();
    lanes.uy = uy.store();
    lanes.uz = uz.store();

    let active = lanes.active;
    lanes.interactions += u64::from((inside_bits & active).count_ones());
    lanes.steps = lanes.steps.wrapping_add(1);
    StepOutcome {
        at_boundary: !inside_bits & active,
        light: light.bitmask() & active,
    }
}

/// Keeps the write-back of the lane state below as whole-vector stores.
///
/// Each stored vector is `inside.select(new, old)` with `old` loaded from the same place, and
/// LLVM folds such a store into a masked store (`vmaskmovps` on AVX2) when nothing between
/// the load and the store may write memory. On AMD Zen 3 a 256-bit `vmaskmovps` store is
/// microcoded: with the step's 14 of them the AVX2 walk ran 0.57-0.73e5 photons per CPU-s,
/// with blends and plain stores 0.96-1.27e5 (7-layer skin, `seven_layer` example, one thread
/// each, side by side, 12 and 14 rounds, tallies bit-identical). An out-of-line call in `ln`
/// used to hide the pattern (at 0.68-0.84e5). An empty `asm!` that may write memory is such a
/// thing, and emits no instruction. No load moves across it either, which keeps each phase of
/// `interact` loading its own vectors (fewer spills, see there).
#[inline(always)]
fn keep_stores_whole() {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: an empty instruction with no operands.
    unsafe {
        std::arch::asm!("", options(nostack, preserves_flags));
    }
}

/// A polar scattering angle as the fraction 1 - cos theta = `numerator` / `denominator`, both
/// positive, numerator <= 2 denominator: `spin` divides once for this and for its own ratio.
pub(crate) struct PolarAngle {
    pub(crate) numerator: F32s,
    pub(crate) denominator: F32s,
}

/// Henyey-Greenstein scattering by inverse CDF for uniforms `xi` in [0, 1): 1 - cos theta as a
/// `PolarAngle`.
///
/// The textbook inverse, cos = (1 + g^2 - t^2) / 2g with t = (1 - g^2) / (1 - g + 2 g xi), is
/// rearranged (t - (1 - g) = 2 g (1 - g) (1 - xi) / d, t + (1 - g) = 2 (1 - g) (1 + g xi) / d) to
/// 1 - cos = 2 (1 - g)^2 (1 - xi) (1 + g xi) / d^2, d = 1 - g + 2 g xi: the same function with no
/// 1 / g (isotropic layers need no special case) and no cancellation, so forward scattering (cos
/// near 1, the common case at g = 0.9) keeps f32's relative precision in 1 - cos and sin theta.
/// Every factor is positive; the clamp only catches rounding above 2 at xi = 0.
#[inline(always)]
pub(crate) fn henyey_greenstein(phase: &PhaseFunctionVectors, xi: F32s) -> PolarAngle {
    let c = F32s::splat;
    let d = phase.hg_two_g.mul_add(xi, phase.hg_one_minus_g);
    let denominator = d * d;
    let numerator = phase.hg_scale * ((c(1.0) - xi) * phase.hg_g.mul_add(xi, c(1.0)));
    PolarAngle {
        numerator: numerator.min(c(2.0) * denominator),
        denominator,
    }
}

/// (cos phi, sin phi) of a uniform azimuth: a uniform angle in [-pi/4, pi/4) from the top 23 bits,
/// turned by a uniform multiple of 90 degrees from the lowest two bits.
#[inline(always)]
pub(crate) fn azimuth(bits: U32s) -> (F32s, F32s) {
    let a = (units(bits) - F32s::splat(0.5)) * F32s::splat(std::f32::consts::FRAC_PI_2);
    let (s, c) = sin_cos_quarter(a);
    let zero = U32s::splat(0);
    let quarter_turn = !((bits & U32s::splat(1)).eq_u32(zero));
    let half_turn = !((bits & U32s::splat(2)).eq_u32(zero));
    let (c, s) = (quarter_turn.select(-s, c), quarter_turn.select(c, s));
    (half_turn.select(-c, c), half_turn.select(-s, s))
}

/// Two independent standard normal deviates for every lane, by Box-Muller (1958):
/// r = sqrt(-2 ln u) with u uniform in (0, 1] from one draw of the lane's stream, and
/// (r cos phi, r sin phi) with phi the uniform `azimuth` of the next draw. Error bound and
/// range in `gaussian`.
#[inline(always)]
pub(crate) fn normal_pair(rng: &mut LaneRng) -> (F32s, F32s) {
    let r = (F32s::splat(-2.0) * ln(units_open(next_bits(rng)))).sqrt();
    let (cos_p, sin_p) = azimuth(next_bits(rng));
    (r * cos_p, r * sin_p)
}

/// Turns directions by a polar angle and azimuth (cos_p, sin_p) about themselves (MCML's
/// formulas). The sine of the old polar angle is taken from ux^2 + uy^2, not 1 - uz^2: in f32 the
/// latter loses the small sines of near-vertical directions, and the new direction would then not
/// be a unit vector.
///
/// With 1 - cos theta = N / D and s = sin^2(old), both 1 - cos theta = N s q and the factor
/// k = sin(theta) / sin(old) = sqrt(N (2D - N) / (D^2 s)) = q sqrt(N (2D - N) s) come from the one
/// division q = 1 / (D s), and the square root does not wait for it: the scattering's chain of
/// long-latency operations (the photon step's critical path) is one division and one square root
/// deep instead of two divisions and a root.
#[inline(always)]
pub(crate) fn spin(dir: [F32s; 3], polar: PolarAngle, cos_p: F32s, sin_p: F32s) -> [F32s; 3] {
    let c = F32s::splat;
    let [ux, uy, uz] = dir;
    let PolarAngle {
        numerator: n,
        denominator: d,
    } = polar;
    let sin_old_sq = ux.mul_add(ux, uy * uy);
    let vertical = sin_old_sq.lt(c(NEAR_VERTICAL_SIN_SQ));
    // Vertical lanes take s = 1, so that k is sin(theta) there.
    let s = vertical.select(c(1.0), sin_old_sq);
    let q = c(1.0) / (d * s);
    let k = q * (n * d.mul_add(c(2.0), -n) * s).sqrt();
    let cos_t = c(1.0) - n * s * q;
    let signed_cos_t = uz.lt(c(0.0)).select(-cos_t, cos_t);
    [
        vertical.select(
            k * cos_p,
            k.mul_add((ux * uz).mul_add(cos_p, -(uy * sin_p)), ux * cos_t),
        ),
        vertical.select(
            k * sin_p,
            k.mul_add((uy * uz).mul_add(cos_p, ux * sin_p), uy * cos_t),
        ),
        vertical.select(
            signed_cos_t,
            (-k * cos_p).mul_add(sin_old_sq, uz * cos_t),
        ),
    ]
}
