//! The controller's monotonic microsecond clock and the 32 -> 64-bit counter extension.
//!
//! Conventions: times are microseconds since boot as `u64` (a 1 MHz 64-bit counter wraps after
//! 584 000 years, so the core never handles wrap-around itself). Hardware counters are 32-bit;
//! [`CounterExtender`] turns their readings into the 64-bit count.

/// A monotonic microsecond clock with a timer compare.
///
/// The board implements it on a hardware timer; host tests implement it with a simulated time
/// they advance by hand.
pub trait MonotonicClock {
    /// Microseconds since boot; never decreases.
    fn now_us(&mut self) -> u64;

    /// Arms the timer compare: the board must poll the controller again no later than `at_us`
    /// (a board that busy-polls may ignore it; one that sleeps wakes on the compare interrupt).
    fn set_alarm(&mut self, at_us: u64);

    /// Waits until the clock reads at least `at_us` and returns that reading (the instant the
    /// caller's next action happens). Called only for short waits (at most
    /// [`crate::controller::TRIGGER_SPIN_US`]) right before a trigger edge, so a board may spin.
    fn wait_until(&mut self, at_us: u64) -> u64;
}

/// Extends readings of a free-running 32-bit up-counter to 64 bits.
///
/// Correct as long as [`CounterExtender::extend`] is called at least once per counter period
/// (71 minutes for a 1 MHz counter, 171 s at 25 MHz); the boards read their clock continuously.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CounterExtender {
    last_raw: u32,
    total: u64,
}

impl CounterExtender {
    /// An extender whose first reading counts from 0.
    pub const fn new() -> Self {
        Self {
            last_raw: 0,
            total: 0,
        }
    }

    /// The 64-bit count for a new raw reading of the up-counter.
    pub fn extend(&mut self, raw: u32) -> u64 {
        // Wrapping difference: a counter that wrapped once since the last reading still gives
        // the right (small) delta.
        let delta = raw.wrapping_sub(self.last_raw);
        self.last_raw = raw;
        self.total += u64::from(delta);
        self.total
    }

    /// The 64-bit count for a reading of a 32-bit *down*-counter (CMSDK timers count down).
    pub fn extend_down(&mut self, raw_down: u32) -> u64 {
        self.extend(!raw_down)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_across_a_wrap_of_the_raw_counter() {
        let mut e = CounterExtender::new();
        assert_eq!(e.extend(10), 10);
        assert_eq!(e.extend(u32::MAX - 5), u64::from(u32::MAX) - 5);
        // The raw counter wraps: 0xFFFF_FFFA -> 4 is 10 ticks later.
        assert_eq!(e.extend(4), u64::from(u32::MAX) + 5);
        assert_eq!(e.extend(4), u64::from(u32::MAX) + 5);
    }

    #[test]
    fn down_counter_readings_increase() {
        let mut e = CounterExtender::new();
        let a = e.extend_down(u32::MAX); // !MAX = 0
        let b = e.extend_down(u32::MAX - 100);
        let c = e.extend_down(3); // ... then close to wrapping
        let d = e.extend_down(u32::MAX - 1); // wrapped: 4 + 1 ticks later
        assert_eq!(a, 0);
        assert_eq!(b, 100);
        assert_eq!(c, u64::from(u32::MAX) - 3);
        assert_eq!(d, c + 5);
    }
}
