//! Scheduling priority of a session's real-time threads (the generator and the feature thread),
//! as real-time audio software asks for it (JACK and PipeWire through rtkit; systemd's
//! `LimitNICE=`): on a shared machine the latency left once the steps are at their floor is
//! other processes preempting these threads, not work. On Linux the nice value is per thread:
//! `setpriority(PRIO_PROCESS, gettid(), n)` changes the calling thread only, and threads it
//! starts afterwards inherit it.

use std::sync::atomic::{AtomicBool, Ordering};

/// One warning per process, however many threads and sessions are refused.
static WARNED: AtomicBool = AtomicBool::new(false);

/// Give the calling thread the nice value `nice` (0: leave it as it is). Never fails: when the
/// system refuses (raising priority needs CAP_SYS_NICE or an RLIMIT_NICE allowing it), one
/// warning says how to allow it and the thread keeps its priority. Returns the thread's nice
/// value afterwards.
pub fn raise_current_thread(nice: i32) -> i32 {
    let tid = Some(rustix::thread::gettid());
    if nice != 0
        && let Err(e) = rustix::process::setpriority_process(tid, nice)
        && !WARNED.swap(true, Ordering::Relaxed)
    {
        tracing::warn!(
            nice,
            error = %e,
            "cannot raise the live threads' priority; run choreod with CAP_SYS_NICE \
             (setcap cap_sys_nice+ep, or AmbientCapabilities=CAP_SYS_NICE) or allow it with \
             LimitNICE={nice} in the systemd unit (ulimit -e {})",
            20 - nice
        );
    }
    rustix::process::getpriority_process(tid).unwrap_or(0)
}

/// How much more favourable than the session's threads the output threads (the player and the
/// viewer's server) run: they do microseconds of work per frame but must wake on time, while
/// the generator and ONNX Runtime's workers keep both cores busy at the session's own value.
const OUTPUT_BOOST: i32 = 10;

/// Give the calling output thread `nice - OUTPUT_BOOST` (at least -20) when the session raises
/// its threads (`nice < 0`), else `nice`; where the system refuses the boost, the session's own
/// value (warning as [`raise_current_thread`] does when that is refused too).
pub fn raise_output_thread(nice: i32) -> i32 {
    if nice < 0 {
        let boosted = (nice - OUTPUT_BOOST).max(-20);
        let tid = Some(rustix::thread::gettid());
        if rustix::process::setpriority_process(tid, boosted).is_ok() {
            return boosted;
        }
    }
    raise_current_thread(nice)
}
