//! CPU time, as opposed to wall time: how much of a core a process or a group of threads
//! really got. On a machine with fewer cores than busy threads, a pass's wall time counts
//! the time its thread waited for a core; its CPU time does not. The bench's bound and the
//! workers' frame statistics use both to tell tracing from waiting for a core.
//!
//! Unix (`getrusage`) and Linux (`pthread_getcpuclockid`, thread clocks); elsewhere every
//! figure is zero, which the readers treat as "not measured".

use std::sync::{Arc, Mutex};

/// CPU time of the calling thread in nanoseconds (the simulator's calibration times passes,
/// rounds and bundles by it, so other processes on the machine do not inflate them); 0 where
/// unsupported or on error.
pub fn thread_cpu_ns() -> u64 {
    #[cfg(unix)]
    {
        clock_ns(libc::CLOCK_THREAD_CPUTIME_ID).unwrap_or(0)
    }
    #[cfg(not(unix))]
    {
        0
    }
}

/// What one reading of [`thread_cpu_ns`] adds to the interval it opens or closes: the median
/// of 1,001 back-to-back readings (the end of one system call and the start of the next). An
/// interval timed by two readings holds it once; where intervals are short and many (the
/// simulator's replayed coordinator reads the clock around each of half a million calls, a
/// fifth of its time in the clock), subtracting it leaves the work timed.
pub fn thread_clock_overhead_ns() -> u64 {
    let mut gaps: Vec<u64> = (0..1001)
        .map(|_| {
            let start = thread_cpu_ns();
            thread_cpu_ns().saturating_sub(start)
        })
        .collect();
    gaps.sort_unstable();
    gaps[gaps.len() / 2]
}

/// The time of CPU clock `clock` in nanoseconds, if it can be read.
#[cfg(unix)]
fn clock_ns(clock: libc::clockid_t) -> Option<u64> {
    // SAFETY: clock_gettime writes only into the timespec it is given.
    let mut ts: libc::timespec = unsafe { std::mem::zeroed() };
    if unsafe { libc::clock_gettime(clock, &mut ts) } != 0 {
        return None;
    }
    Some(ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64)
}

/// CPU seconds (user and system) the whole process has used since it started; 0 where
/// unsupported or on error.
pub fn process_cpu_seconds() -> f64 {
    #[cfg(unix)]
    {
        // SAFETY: getrusage writes only into the struct it is given.
        let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) } != 0 {
            return 0.0;
        }
        let secs = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 / 1e6;
        secs(usage.ru_utime) + secs(usage.ru_stime)
    }
    #[cfg(not(unix))]
    {
        0.0
    }
}

/// The CPU clocks of a set of threads (a tracing pool's), summed on demand: threads register
/// themselves when they start ([`ThreadClocks::register_current`]), and any thread may read
/// the total ([`ThreadClocks::seconds`]). Bounded by the threads registered, which the caller
/// bounds (a pool's size).
#[derive(Clone, Debug, Default)]
pub struct ThreadClocks {
    #[cfg(target_os = "linux")]
    clocks: Arc<Mutex<Vec<libc::clockid_t>>>,
    #[cfg(not(target_os = "linux"))]
    clocks: Arc<Mutex<Vec<()>>>,
}

impl ThreadClocks {
    /// No threads yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds the calling thread's CPU clock (call it on the thread, e.g. from a pool's start
    /// handler). A thread whose clock cannot be had is left out.
    pub fn register_current(&self) {
        #[cfg(target_os = "linux")]
        {
            let mut clock: libc::clockid_t = 0;
            // SAFETY: pthread_self is the calling thread; the call writes only `clock`.
            if unsafe { libc::pthread_getcpuclockid(libc::pthread_self(), &mut clock) } == 0 {
                self.clocks
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .push(clock);
            }
        }
    }

    /// How many threads are counted.
    pub fn threads(&self) -> usize {
        self.clocks.lock().unwrap_or_else(|p| p.into_inner()).len()
    }

    /// CPU seconds the registered threads have used since each started (a thread that has
    /// exited no longer counts: its clock cannot be read).
    pub fn seconds(&self) -> f64 {
        #[cfg(target_os = "linux")]
        {
            let clocks = self.clocks.lock().unwrap_or_else(|p| p.into_inner());
            clocks
                .iter()
                .map(|&c| clock_ns(c).map_or(0.0, |ns| ns as f64 / 1e9))
                .sum()
        }
        #[cfg(not(target_os = "linux"))]
        {
            0.0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Busy work, which the optimizer cannot drop, while `more` says so.
    fn spin_while(mut more: impl FnMut() -> bool) {
        let mut x = 0u64;
        while more() {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
            std::hint::black_box(x);
        }
    }

    /// Spins for `seconds` of wall time (less of this thread's CPU on a loaded machine).
    fn spin(seconds: f64) {
        let start = std::time::Instant::now();
        spin_while(|| start.elapsed().as_secs_f64() < seconds);
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn the_clocks_own_cost_is_a_small_part_of_what_it_times() {
        let overhead = thread_clock_overhead_ns();
        // A reading is a system call: some nanoseconds, never a millisecond.
        assert!((1..1_000_000).contains(&overhead), "{overhead} ns");
        // Against 10 ms of this thread's CPU (counted on its own clock, so a loaded machine
        // cannot shorten it), the readings' cost is under a hundredth.
        let start = thread_cpu_ns();
        spin_while(|| thread_cpu_ns() - start < 10_000_000);
        let timed = thread_cpu_ns() - start;
        assert!(overhead * 100 < timed, "{overhead} ns of {timed} ns");
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn registered_threads_count_their_own_cpu_and_sleeping_costs_none() {
        let clocks = ThreadClocks::new();
        let c = clocks.clone();
        let worker = std::thread::spawn(move || {
            c.register_current();
            let before = c.seconds();
            std::thread::sleep(std::time::Duration::from_millis(100));
            let slept = c.seconds() - before;
            spin(0.05);
            (slept, c.seconds() - before)
        });
        let (slept, total) = worker.join().unwrap();
        assert_eq!(clocks.threads(), 1);
        // Sleeping 100 ms uses (almost) no CPU; spinning 50 ms of wall uses some, at most
        // the wall time it spun plus the sleep.
        assert!(slept < 0.02, "slept {slept}");
        assert!(total > slept && total < 0.2, "total {total}");
        // The process's CPU covers at least that thread's.
        assert!(process_cpu_seconds() >= total);
    }
}
