//! Per-projector VSYNC counting and refresh-period measurement.
//!
//! The projectors are not genlocked (e.g. 60.00, 59.94, 60.02 Hz), so every slot is timed on the
//! lit projector's own VSYNC edges and each projector's period is measured from its edges.
//! Conventions: edge timestamps in microseconds of the controller clock; periods in nanoseconds
//! (a microsecond is too coarse to tell 59.94 from 59.97 Hz over one period).

/// An interval longer than this many halves of the period means edges were missed.
const GAP_HALF_PERIODS: u64 = 3;

/// Counts and times the VSYNC edges of one projector.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VsyncTracker {
    /// Edges seen since the last reset.
    count: u32,
    /// Time of the latest edge.
    last_us: Option<u64>,
    /// Start of the current gap-free run of edges: (time, count at that edge).
    anchor: Option<(u64, u32)>,
    /// Period assumed until two edges were seen, nanoseconds.
    nominal_ns: u32,
    /// Intervals that were too long (edges missing).
    gaps: u32,
}

impl VsyncTracker {
    /// A tracker with no edges yet, assuming `nominal_us` until it has measured the period.
    pub const fn new(nominal_us: u32) -> Self {
        Self {
            count: 0,
            last_us: None,
            anchor: None,
            nominal_ns: nominal_us.saturating_mul(1000),
            gaps: 0,
        }
    }

    /// Forgets every edge (when a run is armed) and sets the assumed period.
    pub fn reset(&mut self, nominal_us: u32) {
        *self = Self::new(nominal_us);
    }

    /// Records an edge at `t_us`; returns the new edge count.
    pub fn on_edge(&mut self, t_us: u64) -> u32 {
        if let Some(last) = self.last_us {
            let interval_ns = t_us.saturating_sub(last) * 1000;
            if interval_ns * 2 > GAP_HALF_PERIODS * u64::from(self.period_ns()) {
                // Edges are missing: restart the measurement after the gap so it does not bias
                // the period.
                self.gaps = self.gaps.saturating_add(1);
                self.anchor = None;
            }
        }
        self.count = self.count.wrapping_add(1);
        self.last_us = Some(t_us);
        if self.anchor.is_none() {
            self.anchor = Some((t_us, self.count));
        }
        self.count
    }

    /// Edges seen since the last reset.
    pub fn count(&self) -> u32 {
        self.count
    }

    /// Time of the latest edge.
    pub fn last_us(&self) -> Option<u64> {
        self.last_us
    }

    /// Times edges went missing.
    pub fn gaps(&self) -> u32 {
        self.gaps
    }

    /// Mean refresh period in nanoseconds over the current gap-free run of edges (first to last
    /// edge, so timestamp jitter does not accumulate), or the nominal one before two edges.
    pub fn period_ns(&self) -> u32 {
        match (self.anchor, self.last_us) {
            (Some((t0, n0)), Some(t1)) if self.count > n0 => {
                let intervals = u64::from(self.count - n0);
                let ns = (t1 - t0) * 1000 / intervals;
                u32::try_from(ns).unwrap_or(u32::MAX)
            }
            _ => self.nominal_ns,
        }
    }

    /// [`Self::period_ns`] rounded to microseconds.
    pub fn period_us(&self) -> u64 {
        (u64::from(self.period_ns()) + 500) / 1000
    }

    /// `periods` refresh periods in microseconds, from the measured period in nanoseconds.
    pub fn span_us(&self, periods: u32) -> u64 {
        (u64::from(self.period_ns()) * u64::from(periods) + 500) / 1000
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn measures_a_59_94_hz_period_to_the_nanosecond_level() {
        // 59.94 Hz: 16 683.35 us. Edges timestamped to the microsecond (floor), as a board does.
        let mut v = VsyncTracker::new(16_667);
        assert_eq!(v.period_ns(), 16_667_000);
        for k in 0..121u64 {
            let t_ns = 1_000_000_000 + k * 16_683_350;
            v.on_edge(t_ns / 1000);
        }
        let p = v.period_ns();
        assert!((16_683_300..=16_683_400).contains(&p), "period {p} ns");
        assert_eq!(v.count(), 121);
        assert_eq!(v.gaps(), 0);
        assert_eq!(v.span_us(12), 200_200);
    }

    #[test]
    fn a_missing_edge_is_a_gap_and_does_not_bias_the_period() {
        let mut v = VsyncTracker::new(16_667);
        let mut t = 0;
        for _ in 0..10 {
            t += 16_667;
            v.on_edge(t);
        }
        t += 2 * 16_667; // one edge lost
        v.on_edge(t);
        for _ in 0..3 {
            t += 16_667;
            v.on_edge(t);
        }
        assert_eq!(v.gaps(), 1);
        assert_eq!(v.count(), 14);
        assert_eq!(v.period_ns(), 16_667_000);
    }
}
