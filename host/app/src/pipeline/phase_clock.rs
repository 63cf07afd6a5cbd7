//! Wall and CPU seconds of a stage's phases, for its report (`<stage>.phase_s`,
//! `<stage>.phase_cpu_s`): the pipeline times whole stages, this says where inside one the time
//! goes, so a benchmark can race the variants of a phase without a profiler.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use mlsss_core::resources::{cpu_seconds, thread_cpu_seconds};

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

/// Whose CPU time a clock reads. Why: a stage's head start runs on threads of its own beside
/// the stages before it ([`super::Stage::head_start`]), so the process's clock mixes the two;
/// the head start's threads' clocks tell them apart.
#[derive(Debug, Clone, Default)]
pub enum CpuSource {
    /// The whole process.
    #[default]
    Process,
    /// The threads listed (kernel thread ids): a head start's pool.
    Threads(ThreadList),
    /// The process less the threads listed: what runs beside a head start.
    ProcessLess(ThreadList),
}

/// Kernel ids of a thread pool's threads, filled as its threads start.
pub type ThreadList = Arc<Mutex<Vec<u32>>>;

impl CpuSource {
    /// CPU seconds (user + system) used so far by this source; `None` where the platform does
    /// not tell. Only differences of two readings mean anything, and only while the listed
    /// threads live (an exited thread's time leaves `Threads` and enters `ProcessLess`).
    pub fn seconds(&self) -> Option<f64> {
        match self {
            Self::Process => cpu_seconds(),
            Self::Threads(list) => threads_seconds(list),
            Self::ProcessLess(list) => Some(cpu_seconds()? - threads_seconds(list).unwrap_or(0.0)),
        }
    }
}

/// Sum of the listed threads' CPU seconds.
fn threads_seconds(list: &ThreadList) -> Option<f64> {
    let tids = list.lock().ok()?;
    tids.iter().map(|&tid| thread_cpu_seconds(tid)).sum()
}

/// Laps of a stopwatch: each [`PhaseClock::lap`] books the time since the previous one.
pub struct PhaseClock {
    wall: Instant,
    cpu: Option<f64>,
    source: CpuSource,
    times: PhaseTimes,
}

impl PhaseClock {
    /// A clock on the process's CPU time.
    pub fn start() -> Self {
        Self::start_on(CpuSource::Process)
    }

    /// A clock on `source`'s CPU time (a stage's context says which: `StageContext::cpu`).
    pub fn start_on(source: CpuSource) -> Self {
        Self {
            wall: Instant::now(),
            cpu: source.seconds(),
            source,
            times: PhaseTimes::default(),
        }
    }

    /// Books the time since the last lap (or the start) to `phase`, adding to what it has.
    pub fn lap(&mut self, phase: &str) {
        let (wall, cpu) = (Instant::now(), self.source.seconds());
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

impl PhaseTimes {
    /// Adds `other`'s times to these, phase by phase (a stage's head start and its rest).
    pub fn add(&mut self, other: &PhaseTimes) {
        for (mine, theirs) in [
            (&mut self.phase_s, &other.phase_s),
            (&mut self.phase_cpu_s, &other.phase_cpu_s),
        ] {
            for (phase, s) in theirs {
                *mine.entry(phase.clone()).or_default() += s;
            }
        }
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
    fn added_times_sum_phase_by_phase() {
        let times = |pairs: &[(&str, f64)]| PhaseTimes {
            phase_s: pairs.iter().map(|&(k, v)| (k.to_owned(), v)).collect(),
            phase_cpu_s: pairs
                .iter()
                .map(|&(k, v)| (k.to_owned(), 2.0 * v))
                .collect(),
        };
        let mut a = times(&[("read", 1.0), ("write", 0.5)]);
        a.add(&times(&[("write", 0.25), ("lobe", 2.0)]));
        assert_eq!(a, times(&[("read", 1.0), ("write", 0.75), ("lobe", 2.0)]));
    }

    /// A pool's threads' clocks count the pool's work; the process less them does not.
    #[test]
    fn a_pools_threads_clock_its_work_apart_from_the_rest() {
        if mlsss_core::resources::current_thread_id().is_none() {
            return;
        }
        let threads = ThreadList::default();
        let listed = threads.clone();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .start_handler(move |_| {
                let tid = mlsss_core::resources::current_thread_id().unwrap();
                listed.lock().unwrap().push(tid);
            })
            .build()
            .unwrap();
        let (pool_clock, rest) = (
            CpuSource::Threads(threads.clone()),
            CpuSource::ProcessLess(threads),
        );
        let burn = |seconds: f64| {
            let start = Instant::now();
            let mut x = 0u64;
            while start.elapsed().as_secs_f64() < seconds {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
                std::hint::black_box(x);
            }
        };
        pool.install(|| ());
        let p0 = pool_clock.seconds().unwrap();
        pool.install(|| burn(0.3));
        let p1 = pool_clock.seconds().unwrap();
        burn(0.2);
        let p2 = pool_clock.seconds().unwrap();
        // A wall-clock burn on a busy machine may get less CPU: bounded from above; the idle
        // pool stays within two ticks. (The rest's clock also counts the other tests running
        // in this process: only its relation to the process's is checked.)
        assert!(p1 - p0 > 0.05 && p1 - p0 < 0.35, "pool {}", p1 - p0);
        assert!((p2 - p1).abs() < 0.03, "pool while idle {}", p2 - p1);
        let rest_seconds = rest.seconds().unwrap();
        let process = CpuSource::Process.seconds().unwrap();
        assert!(
            rest_seconds <= process - p1 + 0.03,
            "{rest_seconds} {process} {p1}"
        );
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
