//! Resource use of the running process, for reports.

/// Peak resident memory of this process in MiB (`VmHWM` of `/proc/self/status`); `None` where
/// the platform does not expose it.
pub fn peak_memory_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    parse_vm_hwm_kib(&status).map(|kib| kib as f64 / 1024.0)
}

/// The `VmHWM:` line of a `/proc/<pid>/status` text, in KiB.
fn parse_vm_hwm_kib(status: &str) -> Option<u64> {
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let mut fields = line.split_whitespace().skip(1);
    let value: u64 = fields.next()?.parse().ok()?;
    match fields.next() {
        Some("kB") | None => Some(value),
        Some(_) => None,
    }
}

/// CPU time (user + system, all threads, exited ones included) this process has used, in
/// seconds, from `/proc/self/stat` (resolution one clock tick, 10 ms); `None` where the platform
/// does not expose it. The one CPU-time probe of the workspace: reports and benches take
/// differences of two readings.
pub fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    parse_stat_cpu_ticks(&stat).map(|ticks| ticks as f64 / USER_HZ)
}

/// Clock ticks per second of `/proc/<pid>/stat` times (`USER_HZ`, 100 on every Linux ABI).
const USER_HZ: f64 = 100.0;

/// `utime + stime` (fields 14 and 15) of a `/proc/<pid>/stat` line, in clock ticks. The command
/// name (field 2, in parentheses) may hold spaces, so fields are counted after its `)`.
fn parse_stat_cpu_ticks(stat: &str) -> Option<u64> {
    let rest = &stat[stat.rfind(')')? + 1..];
    let mut fields = rest.split_whitespace().skip(11);
    let utime: u64 = fields.next()?.parse().ok()?;
    let stime: u64 = fields.next()?.parse().ok()?;
    Some(utime + stime)
}

/// Hands the memory the allocator holds free back to the system. Why: glibc keeps what freed
/// allocations of up to 32 MB leave in its per-thread arenas (a full-size image is 17 MB), so
/// the memory of a finished phase would add to the next phase's peak. A few milliseconds; a
/// no-op where the allocator is not glibc's. The buffers kept for reading frames go first.
pub fn release_free_memory() {
    crate::capture::folder::release_frame_buffers();
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `malloc_trim` takes no pointers and only returns free pages of the allocator's
    // own arenas to the system; it is thread-safe.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Makes glibc's allocator keep the memory of freed buffers of up to 32 MiB for the next
/// allocations (`mallopt`: mmap threshold 32 MiB, trim threshold 1 GiB) instead of mapping the
/// first ones afresh and giving back what its arenas free beyond twice the threshold it adapts to.
/// Why: the simulator allocates and frees buffers of 1-30 MB per frame (noise-free components,
/// noisy values, PNG data); each fresh mapping is page-faulted and zeroed page by page, 23 % of
/// the CPU time of simulating the quick calibration poses. With these settings (as
/// `GLIBC_TUNABLES`) the quick demo's system time fell from 3.4-4.7 s to 2.6-2.9 s, its peak
/// resident memory unchanged (1.07-1.09 GB). [`release_free_memory`] still hands the free memory
/// back between phases. Call once, first thing in `main`; a no-op where the allocator is not
/// glibc's.
pub fn keep_freed_memory_for_reuse() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `mallopt` takes no pointers and only changes the allocator's thresholds; a value it
    // refuses leaves the setting as it was (the result is ignored: the settings only save time).
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
    }
}

/// The glibc tunable that, set to 1, makes its allocator ask for transparent huge pages on what
/// it maps: its arenas' heaps as they grow and its blocks of 2 MiB or more
/// (`madvise(MADV_HUGEPAGE)`).
const HUGE_PAGE_MALLOC_TUNABLE: &str = "glibc.malloc.hugetlb";

/// The `GLIBC_TUNABLES` value to start the program again with so that glibc's allocator backs
/// its memory with transparent huge pages, or `None` when that would change nothing or is not
/// wanted: the kernel's THP mode (`thp_enabled`, the text of
/// `/sys/kernel/mm/transparent_hugepage/enabled`, the selected mode in brackets) is not
/// `madvise` (under `always` every mapping gets them anyway, under `never` none can), or the
/// value the program was started with (`current`) already sets `glibc.malloc.hugetlb`, whatever
/// to (the user's choice stands: `glibc.malloc.hugetlb=0` turns this off). Other tunables in
/// `current` are kept.
///
/// Why: glibc reads its tunables once, at start-up (`mallopt` has no setting for this one), and
/// without it the pipeline's buffers are faulted in and zeroed 4 KiB at a time. The full-size
/// `mlsss process --until fit` (2-core VM, three pairs alternated with and without it):
/// page faults 1.17-1.27 -> 0.25-0.39 million, system time 8.7-12.0 -> 6.7 s, CPU time 47.9-51.5
/// -> 45.3-48.5 s, wall 28.4-32.5 -> 26.6-28.3 s, peak memory 1.75-1.85 -> 1.77 GiB. Per
/// block it is not the same: advising every block of 4 MiB or more from a wrapper around the
/// system allocator saved no CPU time and, on the layer model's 465 MB, raised the peak to
/// 2.2 GB (2026-11-29 session notes).
pub fn tunables_for_huge_page_malloc(current: Option<&str>, thp_enabled: &str) -> Option<String> {
    if !thp_enabled.contains("[madvise]") {
        return None;
    }
    let current = current.unwrap_or("");
    let sets_hugetlb = current
        .split(':')
        .any(|setting| setting.split('=').next() == Some(HUGE_PAGE_MALLOC_TUNABLE));
    if sets_hugetlb {
        return None;
    }
    Some(if current.is_empty() {
        format!("{HUGE_PAGE_MALLOC_TUNABLE}=1")
    } else {
        format!("{current}:{HUGE_PAGE_MALLOC_TUNABLE}=1")
    })
}

/// Buffers at least this large are advised onto huge pages (numpy's threshold, 4 MiB).
const HUGE_PAGE_ADVICE_BYTES: usize = 4 << 20;

/// An empty vector with room for `capacity` values, whose memory the kernel is asked to back with
/// transparent huge pages before anything touches it (`madvise(MADV_HUGEPAGE)`, what numpy does
/// for every array of 4 MiB or more). Why: a fresh full-size output is tens of MB; on 4 KiB pages
/// filling 68 MB took 35 ms of CPU, mostly page faults, against 8 ms on 2 MiB pages (measured on
/// the 2-core host with THP in `madvise` mode). Fill it with `extend`/rayon's `par_extend`, which
/// write in place. A no-op off Linux, for small buffers, or where the kernel declines.
pub fn vec_on_huge_pages<T>(capacity: usize) -> Vec<T> {
    let buffer: Vec<T> = Vec::with_capacity(capacity);
    advise_huge_pages(
        buffer.as_ptr() as usize,
        capacity.saturating_mul(std::mem::size_of::<T>()),
    );
    buffer
}

/// `len` zeros on huge pages ([`vec_on_huge_pages`]): the allocation comes zeroed and untouched
/// from the system (`calloc`), so the advice takes effect at the first write.
pub fn zeros_on_huge_pages(len: usize) -> Vec<f32> {
    let buffer = vec![0.0f32; len];
    advise_huge_pages(buffer.as_ptr() as usize, len.saturating_mul(4));
    buffer
}

/// `len` zeros whose pages were written (on every core) rather than only mapped. Why: sums added
/// into a fresh zeroed allocation (`vec![0.0; len]`, untouched pages from the system) read the
/// kernel's shared zero page first, and the first write then takes a second fault, copies the
/// page and flushes the other cores' TLBs (an inter-processor interrupt, costly on a VM), page
/// by page. Measured where it is used: the virtual booth's subsurface sums, and the renderer's
/// sigma bins (`mlsss eval` of a quick demo in a fresh process, 6 alternated pairs on the 2-core
/// VM: write-protect faults 11 % of its CPU -> none, CPU 5.79 -> 5.36 s, wall 3.42 -> 3.19 s).
/// perf shows `do_wp_page` under the summing code again if a compiler ever drops the writes.
pub fn zeros_written(len: usize) -> Vec<f32> {
    use rayon::prelude::*;
    let mut zeros = vec![0.0f32; len];
    zeros
        .par_chunks_mut(1 << 16)
        .for_each(|chunk| chunk.fill(0.0));
    zeros
}

/// Advises the whole pages inside `[start, start + bytes)` onto huge pages.
fn advise_huge_pages(start: usize, bytes: usize) {
    #[cfg(target_os = "linux")]
    {
        if bytes < HUGE_PAGE_ADVICE_BYTES {
            return;
        }
        const PAGE: usize = 4096;
        let first = start.div_ceil(PAGE) * PAGE;
        let end = (start + bytes) / PAGE * PAGE;
        if end > first {
            // SAFETY: the range holds only whole pages inside one live allocation of the caller;
            // MADV_HUGEPAGE changes how the kernel backs them, never their contents, and a
            // refusal (kernel without THP) leaves them as they were, so the result is ignored.
            unsafe {
                libc::madvise(first as *mut libc::c_void, end - first, libc::MADV_HUGEPAGE);
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (start, bytes, HUGE_PAGE_ADVICE_BYTES);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Written zeros are zeros, every chunk of them (the last one partial), and as many as asked.
    #[test]
    fn written_zeros_are_as_many_zeros_as_asked() {
        for len in [0, 1, (1 << 16) - 1, 3 * (1 << 16) + 5] {
            let zeros = zeros_written(len);
            assert_eq!(zeros.len(), len);
            assert!(zeros.iter().all(|&v| v == 0.0));
        }
    }

    /// The advice changes nothing visible: the buffers hold and keep what is written.
    #[test]
    fn huge_page_buffers_behave_as_ordinary_vectors() {
        let mut values: Vec<u64> = vec_on_huge_pages(1 << 20);
        assert!(values.is_empty() && values.capacity() >= 1 << 20);
        values.extend(0..1 << 20);
        assert_eq!((values[12_345], values.len()), (12_345, 1 << 20));
        let zeros = zeros_on_huge_pages(3 << 20);
        assert_eq!(zeros.len(), 3 << 20);
        assert!(zeros.iter().all(|&z| z == 0.0));
        let small: Vec<u8> = vec_on_huge_pages(10);
        assert!(small.capacity() >= 10);
    }

    #[test]
    fn huge_page_malloc_is_added_only_where_the_kernel_waits_to_be_asked() {
        let madvise = "always [madvise] never\n";
        assert_eq!(
            tunables_for_huge_page_malloc(None, madvise).as_deref(),
            Some("glibc.malloc.hugetlb=1")
        );
        assert_eq!(
            tunables_for_huge_page_malloc(Some(""), madvise).as_deref(),
            Some("glibc.malloc.hugetlb=1")
        );
        // Other tunables are kept, this one appended.
        assert_eq!(
            tunables_for_huge_page_malloc(Some("glibc.malloc.arena_max=2"), madvise).as_deref(),
            Some("glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1")
        );
        // Already set (by us before a restart, or by the user, to any value): left alone.
        for set in [
            "glibc.malloc.hugetlb=1",
            "glibc.malloc.hugetlb=0",
            "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=2",
        ] {
            assert_eq!(
                tunables_for_huge_page_malloc(Some(set), madvise),
                None,
                "{set}"
            );
        }
        // A tunable whose name only starts like it is another tunable.
        assert_eq!(
            tunables_for_huge_page_malloc(Some("glibc.malloc.hugetlbx=1"), madvise).as_deref(),
            Some("glibc.malloc.hugetlbx=1:glibc.malloc.hugetlb=1")
        );
        // THP for every mapping, for none, or no THP at all: nothing to ask for.
        for mode in ["[always] madvise never", "always madvise [never]", ""] {
            assert_eq!(tunables_for_huge_page_malloc(None, mode), None, "{mode}");
        }
    }

    #[test]
    fn parses_user_and_system_time_after_the_command_name() {
        // Fields 3.. of a real line; the command name holds a space and a parenthesis.
        let stat = "4242 (ml (sss) x) R 1 4242 4242 0 -1 4194304 900 0 0 0 1234 56 0 0 20 0 3 0";
        assert_eq!(parse_stat_cpu_ticks(stat), Some(1290));
        assert_eq!(parse_stat_cpu_ticks("4242 (x) R 1"), None);
    }

    /// On-CPU time of the calling thread, nanoseconds, from the scheduler's own account
    /// (`/proc/thread-self/schedstat`, first field): a measure independent of the probe.
    fn thread_cpu_nanos() -> Option<u64> {
        let text = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
        text.split_whitespace().next()?.parse().ok()
    }

    #[test]
    fn cpu_time_rises_by_what_an_exited_thread_burnt() {
        if !cfg!(target_os = "linux") {
            assert_eq!(cpu_seconds(), None);
            return;
        }
        let before = cpu_seconds().expect("linux has /proc/self/stat");
        // A thread burns 0.3 s of CPU as counted by the scheduler, then exits.
        let burnt = std::thread::spawn(|| {
            let start = thread_cpu_nanos()?;
            let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
            let mut x = 0u64;
            loop {
                for i in 0..1_000_000u64 {
                    x = x.wrapping_mul(6364136223846793005).wrapping_add(i);
                }
                std::hint::black_box(x);
                let spent = thread_cpu_nanos()? - start;
                if spent >= 300_000_000 || std::time::Instant::now() > deadline {
                    return Some(spent as f64 * 1e-9);
                }
            }
        })
        .join()
        .expect("the burner does not panic")
        .expect("linux has /proc/thread-self/schedstat");
        assert!(burnt >= 0.3, "burnt only {burnt} s in a minute");
        let after = cpu_seconds().expect("linux has /proc/self/stat");
        // The probe counts in 10 ms ticks, sampled: allow two ticks and a tenth of slack.
        let rise = after - before;
        assert!(
            rise >= 0.9 * burnt - 0.02,
            "burnt {burnt} s, probe rose {rise} s"
        );
    }

    #[test]
    fn parses_the_high_water_mark_line() {
        let status = "Name:\tmlsss\nVmPeak:\t  900 kB\nVmHWM:\t   20480 kB\nVmRSS:\t 100 kB\n";
        assert_eq!(parse_vm_hwm_kib(status), Some(20480));
        assert_eq!(parse_vm_hwm_kib("VmRSS: 1 kB\n"), None);
        assert_eq!(parse_vm_hwm_kib("VmHWM: 12 MB\n"), None);
        if cfg!(target_os = "linux") {
            let mb = peak_memory_mb().expect("linux has /proc/self/status");
            assert!(mb > 1.0 && mb < 1e6, "{mb}");
        }
    }
}
