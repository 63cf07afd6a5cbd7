//! SIMD over photons: the MCML random walk run on `LANES` (16) photons at once, in f32.
//!
//! One photon's walk is a chain of dependent steps (each direction depends on the last), so a
//! scalar loop waits on square roots and divisions most of the time. Here every lane holds its own
//! photon and the common event, "move inside the layer, deposit, scatter", is computed for all
//! lanes with branch-free code that the compiler vectorises (state is stored lane-major, the maths
//! comes from `fast_math`, the random numbers from `lane_rng`). The rarer events, reaching a
//! boundary (Fresnel reflection, refraction, escape) and Russian roulette, are handled lane by lane
//! in scalar code; when a photon ends, its lane is refilled with the batch's next photon.
//!
//! Internal interfaces stay scalar on purpose: refracting or reflecting them inside the vector step
//! (Fresnel without division, the next layer's constants by a 16-entry permute) ran the 7-layer
//! skin 12 % slower with a branch around it (mispredicted about half the time) and no faster
//! without one (2026-11-25, seven_layer example, alternated runs): the step seems bound by its
//! instruction count, and the ~50 instructions the crossing adds to every step cost what the
//! scalar code spends on the ~0.7 crossings per step.
//!
//! The physics is exactly that of the scalar walk it replaces (see `transport`): the same step
//! sampling in optical depth, partial reflection at the outer surfaces, random reflection at
//! internal interfaces, the same roulette. The vector step only scales a lane's weight by the
//! albedo; what the lane lost in its current layer is the difference from its weight at the last
//! flush, added to the layer when the layer or the weight otherwise changes (`flush_deposit`), so
//! the hot loop never scatters into a per-layer array; the constants of a lane's layer are copied into the lane when it enters it, so
//! the hot loop never gathers either.
//!
//! The vector step (`lane_kernels.rs`) is compiled on portable array vectors (`simd`), on AVX2
//! registers (`simd_avx2`) and on AVX-512 registers (`simd_avx512`), and picked at run time. Fused
//! multiply-adds are exactly rounded on every one (FMA3, AVX-512, `f32::mul_add`), so all give
//! bit-identical results.
//!
//! The lanes hold f32 (16 per AVX-512 register, twice the photons per instruction of f64; see
//! `fast_math` for why f32 is enough). The scalar boundary code computes in f64 from the lanes'
//! f32 values and stores back f32; the tallies are f64.

use super::fresnel::{reflectance_with_cos_t, refracted_cos};
use super::lane_rng::{LaneRng, unit};
use super::simd::LANES;
use super::tally::BatchTally;
use super::transport::{
    Geometry, MAX_EVENTS_PER_PHOTON, ROULETTE_SURVIVAL, ROULETTE_THRESHOLD, tally_exit,
};

type Lane = [f32; LANES];

/// Independent groups of `LANES` photons a batch steps in turn. The scalar boundary code of one
/// group (branches, divisions, single-lane loads waiting on the vector results) then overlaps the
/// vector arithmetic of the other, and runs one vector step after its own group's (see
/// `run_batch_lanes`): 2 groups ran the 7-layer skin 19 % faster settled that way than settled
/// right after their own step. Once the step's chain of long-latency operations was shortened
/// (one division fewer in the scattering, the interface decision by table), 3 groups ran it 2.5 %
/// faster than 2 and 4 groups 1.3 % slower than 3 (2026-11-25, seven_layer, alternated runs).
pub(crate) const GROUPS: usize = 3;

/// The photons in flight, lane-major.
///
/// Laid out in declaration order on a 64-byte boundary, so that every `Lane` (16 f32, one
/// AVX-512 register, two AVX2 ones) fills whole cache lines. Why: with Rust's default layout the
/// struct is 8-aligned and its vectors straddle two cache lines wherever the stack happens to put
/// it; the same kernel took 1.52 CPU-s for 400k photons of the 7-layer skin in the `mlsss`
/// binary and 1.42-1.48 in the `seven_layer` example, and 1.44 and 1.39-1.41 once aligned
/// (2026-11-28, AMD EPYC with AVX-512, alternated runs, tallies bit-identical).
#[repr(C, align(64))]
pub(crate) struct Lanes {
    x: Lane,
    y: Lane,
    z: Lane,
    ux: Lane,
    uy: Lane,
    uz: Lane,
    weight: Lane,
    /// Optical depth left of the current step; 0 means "sample a new step".
    optical_left: Lane,
    /// Constants of each lane's current layer.
    z_top: Lane,
    z_bottom: Lane,
    inv_mu_t: Lane,
    albedo: Lane,
    hg_g: Lane,
    hg_one_minus_g: Lane,
    hg_two_g: Lane,
    /// 2 (1 - g)^2.
    hg_scale: Lane,
    /// The lane's weight when its deposit was last flushed: what it lost since, to absorption in
    /// its current layer, is this minus its weight now (see `flush_deposit`).
    weight_at_flush: Lane,
    /// Bit `lane` set for a lane holding a photon, clear for an idle one (at the end of a batch).
    active: u32,
    /// Interaction events of all lanes, all photons together: a popcount per step, so the step
    /// keeps no per-lane counter.
    interactions: u64,
    /// Vector steps this group has made (wrapping) and the count when each lane's photon was
    /// launched: their difference is the photon's events, without a per-lane increment per step.
    steps: u32,
    launched_at: [u32; LANES],
    layer: [usize; LANES],
    /// Per-photon exits, summed into the batch moments when the photon ends.
    reflected: [f64; LANES],
    transmitted: [f64; LANES],
    /// Per-photon absorption, `absorbed[lane * layers + layer]`.
    absorbed: Vec<f64>,
    rng: LaneRng,
    /// The 32 random bits of each lane's last scattering draw. A lane whose step stopped at a
    /// boundary did not scatter, so its bits are fresh: the reflect-or-refract choice there takes
    /// them instead of stepping the lane's stream in scalar code (whose single-lane writes the
    /// next vector step would have to wait for).
    scatter_bits: [u32; LANES],
    /// The 32 random bits of each lane's last azimuth draw (drawn with the step's other two).
    azimuth_bits: [u32; LANES],
}

impl Lanes {
    fn new(layers: usize, rng: LaneRng) -> Self {
        let zero = [0.0; LANES];
        Self {
            x: zero,
            y: zero,
            z: zero,
            ux: zero,
            uy: zero,
            uz: zero,
            weight: zero,
            optical_left: zero,
            z_top: zero,
            z_bottom: zero,
            inv_mu_t: zero,
            albedo: zero,
            hg_g: zero,
            hg_one_minus_g: zero,
            hg_two_g: zero,
            hg_scale: zero,
            weight_at_flush: zero,
            active: 0,
            interactions: 0,
            steps: 0,
            launched_at: [0; LANES],
            layer: [0; LANES],
            reflected: [0.0; LANES],
            transmitted: [0.0; LANES],
            absorbed: vec![0.0; LANES * layers],
            rng,
            scatter_bits: [0; LANES],
            azimuth_bits: [0; LANES],
        }
    }

    /// Copies the constants of layer `index` into `lane`.
    fn enter_layer(&mut self, geo: &Geometry, lane: usize, index: usize) {
        let layer = &geo.layers[index];
        self.layer[lane] = index;
        self.z_top[lane] = layer.z_top as f32;
        self.z_bottom[lane] = layer.z_bottom as f32;
        self.inv_mu_t[lane] = layer.inv_mu_t as f32;
        self.albedo[lane] = layer.albedo as f32;
        self.hg_g[lane] = layer.hg.g as f32;
        self.hg_one_minus_g[lane] = layer.hg.one_minus_g as f32;
        self.hg_two_g[lane] = layer.hg.two_g as f32;
        self.hg_scale[lane] = layer.hg.scale as f32;
    }

    /// Adds the weight `lane` lost since the last flush to its current layer's absorption. Called
    /// before anything but absorption changes the weight or the layer (boundaries, roulette) and
    /// when the photon ends, so the vector step only scales the weight by the albedo. The
    /// difference of two f32 is exact in f64: the deposits sum exactly to the weight lost.
    #[inline(always)]
    fn flush_deposit(&mut self, lane: usize, layers: usize) {
        let lost = f64::from(self.weight_at_flush[lane]) - f64::from(self.weight[lane]);
        self.absorbed[lane * layers + self.layer[lane]] += lost;
        self.weight_at_flush[lane] = self.weight[lane];
    }
}

/// Which lanes need scalar work after a vector step, as bit masks.
pub(crate) struct StepOutcome {
    /// The step reached a boundary of the lane's layer (nothing was moved yet).
    at_boundary: u32,
    /// The lane's weight fell below the roulette threshold.
    light: u32,
}

impl StepOutcome {
    const NONE: Self = Self {
        at_boundary: 0,
        light: 0,
    };
}

/// Moves `lane` to the boundary its step reached and applies Fresnel there. Returns false when the
/// photon ends (all its weight left, or it was lost).
#[inline(always)]
fn cross_boundary(geo: &Geometry, lanes: &mut Lanes, lane: usize, tally: &mut BatchTally) -> bool {
    if lanes.steps.wrapping_sub(lanes.launched_at[lane]) >= MAX_EVENTS_PER_PHOTON {
        // Trapped by total internal reflection in a clear layer: drop it.
        return false;
    }
    let layer = &geo.layers[lanes.layer[lane]];
    let going_down = lanes.uz[lane] > 0.0;
    // The lane's own (f32) boundaries, the ones its vector step compared against.
    let boundary = if going_down {
        lanes.z_bottom[lane]
    } else {
        lanes.z_top[lane]
    };
    // In f32, the lanes' precision: the vector step decided the hit in f32 too.
    let to_boundary = (boundary - lanes.z[lane]).abs() / lanes.uz[lane].abs();
    if !to_boundary.is_finite() {
        // Travelling parallel to the layers in a clear layer: never comes back.
        return false;
    }
    lanes.x[lane] = to_boundary.mul_add(lanes.ux[lane], lanes.x[lane]);
    lanes.y[lane] = to_boundary.mul_add(lanes.uy[lane], lanes.y[lane]);
    lanes.z[lane] = boundary;
    if layer.mu_t > 0.0 {
        let left = (-to_boundary).mul_add(layer.mu_t as f32, lanes.optical_left[lane]);
        lanes.optical_left[lane] = left.max(0.0);
    }
    let last = lanes.layer[lane] + 1 == geo.layers.len();
    let outer = (going_down && last) || (!going_down && lanes.layer[lane] == 0);
    if outer {
        escape_partially(geo, lanes, lane, going_down, tally)
    } else {
        cross_internal(geo, lanes, lane, going_down);
        true
    }
}

/// At the top or bottom surface: the Fresnel-transmitted part of the weight leaves and is tallied,
/// the direction is mirrored and the reflected weight goes on. Returns false when nothing is left.
fn escape_partially(
    geo: &Geometry,
    lanes: &mut Lanes,
    lane: usize,
    going_down: bool,
    tally: &mut BatchTally,
) -> bool {
    let layer = &geo.layers[lanes.layer[lane]];
    let n_out = if going_down { layer.n_down } else { layer.n_up };
    let cos_i = f64::from(lanes.uz[lane]).abs();
    let reflectance = match refracted_cos(layer.n, n_out, cos_i) {
        None => 1.0,
        Some(cos_t) => reflectance_with_cos_t(layer.n, n_out, cos_i, cos_t),
    };
    lanes.flush_deposit(lane, geo.layers.len());
    let weight = f64::from(lanes.weight[lane]);
    let escaping = weight * (1.0 - reflectance);
    if going_down {
        lanes.transmitted[lane] += escaping;
    } else if escaping > 0.0 {
        lanes.reflected[lane] += escaping;
        let at = [f64::from(lanes.x[lane]), f64::from(lanes.y[lane])];
        tally_exit(geo, &at, escaping, tally);
    }
    lanes.uz[lane] = -lanes.uz[lane];
    lanes.weight[lane] = (weight * reflectance) as f32;
    lanes.weight_at_flush[lane] = lanes.weight[lane];
    lanes.weight[lane] > 0.0
}

/// At an interface between two layers: reflect or refract at random with the Fresnel probability.
#[inline(always)]
fn cross_internal(geo: &Geometry, lanes: &mut Lanes, lane: usize, going_down: bool) {
    let index = lanes.layer[lane];
    let layer = &geo.layers[index];
    let next = if going_down { index + 1 } else { index - 1 };
    let n_next = if going_down { layer.n_down } else { layer.n_up };
    let cos_i = f64::from(lanes.uz[lane]).abs();
    let interface = &geo.interfaces[index][usize::from(going_down)];
    let bound = interface.at(cos_i);
    let refracts = if layer.n == n_next {
        Some(cos_i)
    } else if bound < 1.0 {
        // Not totally reflected: the same bits as below, most often settled by the bound alone.
        let u = unit(lanes.scatter_bits[lane]);
        let cos_t = interface.refracted_cos(cos_i);
        (u >= bound || u >= reflectance_with_cos_t(layer.n, n_next, cos_i, cos_t)).then_some(cos_t)
    } else {
        refracted_cos(layer.n, n_next, cos_i).filter(|&cos_t| {
            unit(lanes.scatter_bits[lane]) >= reflectance_with_cos_t(layer.n, n_next, cos_i, cos_t)
        })
    };
    match refracts {
        Some(cos_t) => {
            let ratio = layer.n / n_next;
            lanes.ux[lane] = (f64::from(lanes.ux[lane]) * ratio) as f32;
            lanes.uy[lane] = (f64::from(lanes.uy[lane]) * ratio) as f32;
            let cos_t = cos_t as f32;
            lanes.uz[lane] = if going_down { cos_t } else { -cos_t };
            lanes.flush_deposit(lane, geo.layers.len());
            lanes.enter_layer(geo, lane, next);
        }
        None => lanes.uz[lane] = -lanes.uz[lane],
    }
}

/// Russian roulette: survives with probability `ROULETTE_SURVIVAL` with its weight scaled up.
fn survives_roulette(lanes: &mut Lanes, lane: usize, layers: usize) -> bool {
    if unit(lanes.rng.next_bits_of(lane)) < ROULETTE_SURVIVAL {
        lanes.flush_deposit(lane, layers);
        lanes.weight[lane] = (f64::from(lanes.weight[lane]) / ROULETTE_SURVIVAL) as f32;
        lanes.weight_at_flush[lane] = lanes.weight[lane];
        true
    } else {
        false
    }
}

/// Adds the photon in `lane` to the batch moments and clears its accumulators.
fn finish_photon(lanes: &mut Lanes, lane: usize, layers: usize, tally: &mut BatchTally) {
    lanes.flush_deposit(lane, layers);
    tally.reflect.add(lanes.reflected[lane]);
    tally.transmit.add(lanes.transmitted[lane]);
    let absorbed = &mut lanes.absorbed[lane * layers..(lane + 1) * layers];
    for (moments, a) in tally.absorbed.iter_mut().zip(absorbed.iter_mut()) {
        moments.add(*a);
        *a = 0.0;
    }
    lanes.reflected[lane] = 0.0;
    lanes.transmitted[lane] = 0.0;
}

/// Puts the batch's next photon into `lane`, or marks it idle when none is left.
fn launch(geo: &Geometry, lanes: &mut Lanes, lane: usize, left: &mut u64, tally: &mut BatchTally) {
    let entering = (1.0 - geo.specular) as f32;
    while *left > 0 {
        *left -= 1;
        if entering <= 0.0 {
            // Totally reflected at the entry: the photon contributes zero to every tally.
            finish_photon(lanes, lane, geo.layers.len(), tally);
            continue;
        }
        lanes.x[lane] = 0.0;
        lanes.y[lane] = 0.0;
        lanes.z[lane] = 0.0;
        [lanes.ux[lane], lanes.uy[lane], lanes.uz[lane]] = geo.entry_dir.map(|u| u as f32);
        lanes.weight[lane] = entering;
        lanes.weight_at_flush[lane] = entering;
        lanes.optical_left[lane] = 0.0;
        lanes.launched_at[lane] = lanes.steps;
        lanes.active |= 1 << lane;
        lanes.enter_layer(geo, lane, 0);
        return;
    }
    lanes.active &= !(1 << lane);
}

/// Scalar work for one lane after a vector step; ends and replaces its photon when it dies.
#[inline(always)]
fn settle_lane(
    geo: &Geometry,
    lanes: &mut Lanes,
    lane: usize,
    at_boundary: bool,
    left: &mut u64,
    tally: &mut BatchTally,
) {
    let mut alive = !at_boundary || cross_boundary(geo, lanes, lane, tally);
    if alive && f64::from(lanes.weight[lane]) < ROULETTE_THRESHOLD {
        alive = survives_roulette(lanes, lane, geo.layers.len());
    }
    if !alive {
        finish_photon(lanes, lane, geo.layers.len(), tally);
        launch(geo, lanes, lane, left, tally);
    }
}

/// The vector step on the portable array vectors (any CPU).
pub(crate) mod portable {
    use super::{Lanes, StepOutcome};
    use crate::fast_math;
    use crate::lane_rng::LaneRng;
    use crate::simd::{F32s, U32s};
    use crate::transport::ROULETTE_THRESHOLD;
    include!("lane_kernels.rs");
}

/// The vector step on AVX2 registers.
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2 {
    use super::{Lanes, StepOutcome};
    use crate::fast_math;
    use crate::lane_rng::LaneRng;
    use crate::simd_avx2::{F32s, U32s};
    use crate::transport::ROULETTE_THRESHOLD;
    include!("lane_kernels.rs");
}

/// The vector step on AVX-512 registers.
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx512 {
    use super::{Lanes, StepOutcome};
    use crate::fast_math;
    use crate::lane_rng::LaneRng;
    use crate::simd_avx512::{F32s, U32s};
    use crate::transport::ROULETTE_THRESHOLD;
    include!("lane_kernels.rs");
}

/// Runs `photons` photons with the streams of (seed, batch), `step` advancing all lanes of a group
/// by one event.
#[inline(always)]
fn run_batch_lanes(
    geo: &Geometry,
    seed: u64,
    batch: u64,
    photons: u64,
    step: impl Fn(&mut Lanes) -> StepOutcome,
) -> BatchTally {
    let layers = geo.layers.len();
    let mut tally = BatchTally::new(layers, geo.grid.as_ref(), geo.radial.as_ref());
    let mut groups: [Lanes; GROUPS] = std::array::from_fn(|g| {
        Lanes::new(
            layers,
            LaneRng::for_batch(seed, batch * GROUPS as u64 + g as u64),
        )
    });
    let mut left = photons;
    for lanes in &mut groups {
        for lane in 0..LANES {
            launch(geo, lanes, lane, &mut left, &mut tally);
        }
    }
    let busy = |lanes: &Lanes| lanes.active != 0;
    // Each group's scalar work runs after the NEXT group's vector step, not right after its own:
    // the scalar code reads single lanes of the vectors its step just stored and writes single
    // lanes its next step loads as vectors, and a load that overlaps a store still in flight but
    // is not contained in it waits until the store retires. A vector step in between hides that.
    let mut outcomes: [StepOutcome; GROUPS] = std::array::from_fn(|_| StepOutcome::NONE);
    loop {
        let mut stepped = false;
        for g in 0..GROUPS {
            if busy(&groups[g]) {
                outcomes[g] = step(&mut groups[g]);
                stepped = true;
            }
            let before = (g + GROUPS - 1) % GROUPS;
            let outcome = std::mem::replace(&mut outcomes[before], StepOutcome::NONE);
            let lanes = &mut groups[before];
            let mut pending = outcome.at_boundary | outcome.light;
            while pending != 0 {
                let lane = pending.trailing_zeros() as usize;
                pending &= pending - 1;
                let at_boundary = outcome.at_boundary & (1 << lane) != 0;
                settle_lane(geo, lanes, lane, at_boundary, &mut left, &mut tally);
            }
        }
        if !stepped && outcomes.iter().all(|o| o.at_boundary | o.light == 0) {
            break;
        }
    }
    for lanes in &groups {
        tally.interactions += lanes.interactions;
    }
    tally
}

/// The batch loop with the AVX2 vector step.
///
/// # Safety
/// The CPU must support AVX2 and FMA (the `simd_avx2` intrinsics are only sound under this
/// function).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,popcnt,bmi1")]
unsafe fn run_batch_avx2(geo: &Geometry, seed: u64, batch: u64, photons: u64) -> BatchTally {
    // A closure, not the fn item: closures inherit this function's target features, so the
    // intrinsics inline into it (the fn item's `Fn::call` shim would not have AVX2).
    #[allow(clippy::redundant_closure)]
    run_batch_lanes(geo, seed, batch, photons, |lanes| avx2::interact(lanes))
}

/// The batch loop with the AVX-512 vector step (one 512-bit register per lane vector).
///
/// # Safety
/// The CPU must support AVX-512 F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,popcnt,bmi1")]
unsafe fn run_batch_avx512(geo: &Geometry, seed: u64, batch: u64, photons: u64) -> BatchTally {
    #[allow(clippy::redundant_closure)]
    run_batch_lanes(geo, seed, batch, photons, |lanes| avx512::interact(lanes))
}

/// Instruction sets the vector step can use, best first.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Isa {
    Avx512,
    Avx2,
    Portable,
}

impl Isa {
    /// The best one this CPU runs.
    pub(crate) fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            let bits = std::arch::is_x86_feature_detected!("popcnt")
                && std::arch::is_x86_feature_detected!("bmi1");
            if bits && std::arch::is_x86_feature_detected!("avx512f") {
                return Self::Avx512;
            }
            if bits
                && std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
            {
                return Self::Avx2;
            }
        }
        Self::Portable
    }

    /// Name for reports.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Self::Avx512 => "avx512",
            Self::Avx2 => "avx2",
            Self::Portable => "portable",
        }
    }
}

/// Runs one batch with the given instruction set, which must be `Isa::detect()` or one listed
/// after it.
pub(crate) fn run_batch(
    isa: Isa,
    geo: &Geometry,
    seed: u64,
    batch: u64,
    photons: u64,
) -> BatchTally {
    match isa {
        // SAFETY: `Isa::detect` found AVX-512 F on this CPU.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => unsafe { run_batch_avx512(geo, seed, batch, photons) },
        // SAFETY: `Isa::detect` found AVX2 and FMA on this CPU.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => unsafe { run_batch_avx2(geo, seed, batch, photons) },
        _ => run_batch_lanes(geo, seed, batch, photons, portable::interact),
    }
}

#[cfg(test)]
mod tests {
    use super::portable::{
        PhaseFunctionVectors, PolarAngle, azimuth, henyey_greenstein, next_bits, spin,
    };
    use super::*;

    /// Every lane vector starts a cache line (the layout [`Lanes`] documents; regression test
    /// for the split loads that cost the `mlsss` binary 5 % of the Monte Carlo).
    #[test]
    fn every_lane_vector_fills_whole_cache_lines() {
        assert_eq!(std::mem::align_of::<Lanes>(), 64);
        assert_eq!(std::mem::size_of::<Lane>(), 64);
        let offsets = [
            std::mem::offset_of!(Lanes, x),
            std::mem::offset_of!(Lanes, y),
            std::mem::offset_of!(Lanes, z),
            std::mem::offset_of!(Lanes, ux),
            std::mem::offset_of!(Lanes, uy),
            std::mem::offset_of!(Lanes, uz),
            std::mem::offset_of!(Lanes, weight),
            std::mem::offset_of!(Lanes, optical_left),
            std::mem::offset_of!(Lanes, z_top),
            std::mem::offset_of!(Lanes, z_bottom),
            std::mem::offset_of!(Lanes, inv_mu_t),
            std::mem::offset_of!(Lanes, albedo),
            std::mem::offset_of!(Lanes, hg_g),
            std::mem::offset_of!(Lanes, hg_one_minus_g),
            std::mem::offset_of!(Lanes, hg_two_g),
            std::mem::offset_of!(Lanes, hg_scale),
            std::mem::offset_of!(Lanes, weight_at_flush),
        ];
        for offset in offsets {
            assert_eq!(offset % 64, 0, "a lane vector at offset {offset}");
        }
    }
    use crate::simd::F32s;

    /// The AVX2 and portable vector steps must agree to the bit (same IEEE operations in the same
    /// order), on a medium that exercises every path: internal Fresnel interfaces, partial escape
    /// at both surfaces, roulette and the exit grid.
    #[test]
    fn every_instruction_set_gives_bit_identical_tallies() {
        use crate::{GridSpec, Layer, McConfig, Medium};
        let medium = Medium {
            layers: vec![
                Layer::from_albedo(0.9, 0.5, 0.7, 1.5),
                Layer::from_albedo(0.99, 2.0, 0.0, 1.33),
            ],
            n_above: 1.0,
            n_below: 1.2,
        };
        let cfg = McConfig {
            incidence_deg: 40.0,
            grid: Some(GridSpec {
                cell_mm: 0.3,
                cells: 11,
            }),
            ..McConfig::new(3000, 11)
        };
        let geo = Geometry::new(&medium, &cfg);
        let portable = run_batch(Isa::Portable, &geo, cfg.seed, 5, cfg.photons);
        assert!(portable.interactions > 3000, "photons did interact");
        let best = Isa::detect();
        let others = [Isa::Avx512, Isa::Avx2, Isa::Portable];
        // Every set at or below the best this CPU has (the enum lists them best first).
        for isa in others.into_iter().skip_while(|&isa| isa != best) {
            let tally = run_batch(isa, &geo, cfg.seed, 5, cfg.photons);
            assert_eq!(portable.reflect, tally.reflect, "{isa:?}");
            assert_eq!(portable.transmit, tally.transmit, "{isa:?}");
            assert_eq!(portable.absorbed, tally.absorbed, "{isa:?}");
            assert_eq!(portable.grid, tally.grid, "{isa:?}");
            assert_eq!(portable.interactions, tally.interactions, "{isa:?}");
        }
    }

    /// The batch loop settles each group one vector step late, so its end (groups running dry at
    /// different times, outcomes still pending) must still finish every photon exactly once.
    /// Truth: in a purely absorbing slab between matched indices each photon's weight 1 is either
    /// absorbed whole at its first interaction or transmitted whole, so absorption plus
    /// transmission summed over the photons is the photon count exactly. Batches from 1 photon to
    /// a few more than the lanes in flight, on every instruction set this CPU runs.
    #[test]
    fn every_photon_of_a_batch_ends_exactly_once() {
        use crate::{Layer, McConfig, Medium};
        let slab = Layer {
            thickness_mm: 0.8,
            mu_a: 1.0,
            mu_s: 0.0,
            g: 0.0,
            n: 1.0,
        };
        let medium = Medium::slab(slab, 1.0, 1.0);
        let cfg = McConfig::new(1, 4);
        let geo = Geometry::new(&medium, &cfg);
        let in_flight = (GROUPS * LANES) as u64;
        let best = Isa::detect();
        let sets = [Isa::Avx512, Isa::Avx2, Isa::Portable];
        for isa in sets.into_iter().skip_while(|&isa| isa != best) {
            for photons in [
                1,
                2,
                LANES as u64 - 1,
                in_flight,
                in_flight + 1,
                3 * in_flight + 5,
            ] {
                let tally = run_batch(isa, &geo, cfg.seed, 0, photons);
                let n = photons as f64;
                let ended =
                    (tally.transmit.mean_se(photons).0 + tally.absorbed[0].mean_se(photons).0) * n;
                assert!(
                    (ended - n).abs() < 1e-9,
                    "{isa:?}, {photons} photons: {ended} ended"
                );
                // exp(-0.8) of them cross unabsorbed: the split is random, the sum is not.
                assert!(tally.absorbed[0].mean_se(photons).0 > 0.0 || photons < 3);
            }
        }
    }

    /// The sampled scattering cosines follow Henyey-Greenstein: on a fine midpoint grid of the
    /// uniform, the mean cosine is g and the mean squared cosine (1 + 2 g^2) / 3 (the phase
    /// function's first two Legendre moments are g and g^2), isotropic and backward layers
    /// included; the fraction lies in [0, 2].
    #[test]
    fn scattering_cosines_have_the_henyey_greenstein_moments() {
        use crate::{Layer, McConfig, Medium};
        for g in [0.0, 0.5, 0.9, 0.95, -0.6] {
            let medium = Medium::slab(Layer::from_albedo(0.9, 1.0, g, 1.4), 1.0, 1.0);
            let geo = Geometry::new(&medium, &McConfig::new(1, 1));
            let mut lanes = Lanes::new(1, LaneRng::for_batch(1, 0));
            for lane in 0..LANES {
                lanes.enter_layer(&geo, lane, 0);
            }
            let layer = PhaseFunctionVectors::load(&lanes);
            let cells = 1 << 16;
            let (mut mean, mut mean_sq) = (0.0f64, 0.0f64);
            for first in (0..cells).step_by(LANES) {
                let xi = F32s(std::array::from_fn(|i| {
                    ((first + i) as f32 + 0.5) / cells as f32
                }));
                let polar = henyey_greenstein(&layer, xi);
                for (n, d) in polar.numerator.0.into_iter().zip(polar.denominator.0) {
                    assert!(n >= 0.0 && d > 0.0 && n <= 2.0 * d, "g {g}: {n} / {d}");
                    let cos = 1.0 - f64::from(n) / f64::from(d);
                    mean += cos;
                    mean_sq += cos * cos;
                }
            }
            let (mean, mean_sq) = (mean / cells as f64, mean_sq / cells as f64);
            assert!((mean - g).abs() < 2e-4, "g {g}: mean cosine {mean}");
            let want = (1.0 + 2.0 * g * g) / 3.0;
            assert!(
                (mean_sq - want).abs() < 2e-4,
                "g {g}: <cos^2> {mean_sq} vs {want}"
            );
        }
    }

    #[test]
    fn azimuth_is_a_unit_vector_in_every_quadrant() {
        let mut rng = LaneRng::for_batch(3, 0);
        let mut quadrants = [0usize; 4];
        for _ in 0..250 {
            let (c, s) = azimuth(next_bits(&mut rng));
            for (c, s) in c.0.into_iter().zip(s.0) {
                assert!((c * c + s * s - 1.0).abs() < 3e-7);
                let turn = s.atan2(c).rem_euclid(std::f32::consts::TAU);
                quadrants[((turn / std::f32::consts::FRAC_PI_2) as usize).min(3)] += 1;
            }
        }
        // 1000 expected per quadrant, binomial sd ~27.
        assert!(
            quadrants.iter().all(|&n| (850..1150).contains(&n)),
            "{quadrants:?}"
        );
    }

    /// The spin turns a direction by the asked polar angle and keeps it a unit vector, also for
    /// the near-vertical directions where 1 - uz^2 has no f32 precision left.
    #[test]
    fn spin_keeps_directions_unit_and_sets_the_polar_angle() {
        let v = F32s::splat;
        let cos_t = 0.3f32;
        let sin_t_sq = 1.0 - cos_t * cos_t;
        // 1 - cos theta = 0.7 / 1 and = 1.4 / 2: the spin must read the fraction, not its parts.
        let polar = |scale: f32| PolarAngle {
            numerator: v((1.0 - cos_t) * scale),
            denominator: v(scale),
        };
        let (s, c) = (0.5f32.sin(), 0.5f32.cos());
        let tilt = 3e-4f32; // uz rounds to within 1 ulp of 1: 1 - uz^2 is ~1e-7 with 50 % error
        for dir in [[0.6f32, 0.0, 0.8], [tilt, 0.0, (1.0 - tilt * tilt).sqrt()]] {
            for scale in [1.0, 2.0] {
                let out = spin([v(dir[0]), v(dir[1]), v(dir[2])], polar(scale), v(c), v(s));
                let out = out.map(|d| f64::from(d.0[0]));
                let dot: f64 = out.iter().zip(dir).map(|(o, d)| o * f64::from(d)).sum();
                let norm_sq: f64 = out.iter().map(|v| v * v).sum();
                assert!((norm_sq - 1.0).abs() < 1e-6, "{dir:?}: |u|^2 = {norm_sq}");
                assert!(
                    (dot - f64::from(cos_t)).abs() < 1e-6,
                    "{dir:?}: cos = {dot}"
                );
            }
        }
        let vertical = spin([v(0.0), v(0.0), v(-1.0)], polar(2.0), v(c), v(s));
        assert!((vertical[2].0[5] + cos_t).abs() < 1e-7);
        assert!((vertical[0].0[5] - sin_t_sq.sqrt() * c).abs() < 1e-7);
    }
}
