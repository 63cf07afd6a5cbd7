//! Wall and CPU seconds of a stage's phases, for its report (`<stage>.phase_s`,
//! `<stage>.phase_cpu_s`): the pipeline times whole stages, this says where inside one the time
//! goes, so a benchmark can race the variants of a phase without a profiler.

use std::collections::BTreeMap;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use mlsss_core::resources::cpu_seconds;

/// Phase name -> seconds, in the order the names sort. Reports written before the stages
/// timed their phases have none (empty maps).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PhaseTimes {
    /// Wall seconds per phase.
    pub phase_s: BTreeMap<String, f64>,
    /// CPU seconds (all threads) per phase; empty where the platform gives no CPU time.
    pub phase_cpu_s: BTreeMap<String, f64>,
}

/// Laps of a stopwatch: each [`PhaseClock::lap`] books the time since the previous one.
pub struct PhaseClock {
    wall: Instant,
    cpu: Option<f64>,
    times: PhaseTimes,
}

impl PhaseClock {
    pub fn start() -> Self {
        Self {
            wall: Instant::now(),
            cpu: cpu_seconds(),
            times: PhaseTimes::default(),
        }
    }

    /// Books the time since the last lap (or the start) to `phase`, adding to what it has.
    pub fn lap(&mut self, phase: &str) {
        let (wall, cpu) = (Instant::now(), cpu_seconds());
        *self.times.phase_s.entry(phase.into()).or_default() +=
            wall.duration_since(self.wall).as_secs_f64();
        if let (Some(before), Some(now)) = (self.cpu, cpu) {
            *self.times.phase_cpu_s.entry(phase.into()).or_default() += now - before;
        }
        (self.wall, self.cpu) = (wall, cpu);
    }

    pub fn finish(self) -> PhaseTimes {
        self.times
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_report_without_phases_reads_as_empty_times() {
        // Regression: flattened into the stage reports, the maps were required, so a report
        // without them (older runs, hand-written fixtures) failed to parse.
        #[derive(Deserialize)]
        struct Report {
            #[serde(flatten)]
            timing: PhaseTimes,
        }
        let report: Report = serde_json::from_str("{}").unwrap();
        assert_eq!(report.timing, PhaseTimes::default());
    }

    #[test]
    fn laps_add_up_per_phase_and_to_the_elapsed_time() {
        let started = Instant::now();
        let mut clock = PhaseClock::start();
        std::thread::sleep(std::time::Duration::from_millis(20));
        clock.lap("a");
        std::thread::sleep(std::time::Duration::from_millis(10));
        clock.lap("b");
        std::thread::sleep(std::time::Duration::from_millis(10));
        clock.lap("a");
        let elapsed = started.elapsed().as_secs_f64();
        let times = clock.finish();
        assert_eq!(times.phase_s.len(), 2);
        assert!(times.phase_s["a"] >= 0.030 && times.phase_s["b"] >= 0.010);
        let total: f64 = times.phase_s.values().sum();
        assert!(total <= elapsed, "{total} > {elapsed}");
    }
}
