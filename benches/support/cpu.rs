//! This thread's CPU time, shared by the benches (the machine is shared: wall-clock figures include
//! the time other processes held the cores; this does not).

/// This thread's time on a CPU so far (ns), from `/proc/thread-self/schedstat`.
pub fn cpu_ns() -> Option<u64> {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}
