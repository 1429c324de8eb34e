//! How the daemon tells its own deaths from other people's: a fatal signal (SIGSEGV, SIGBUS,
//! SIGILL, SIGFPE, SIGABRT — a crash in a decoder or model, an allocation that failed) writes
//! its name into the spool's running marker before the process dies. A `kill -9` from outside
//! (an operator's restart, a supervisor, the OOM killer) runs no code and leaves the marker
//! empty: the next start then charges no job with the death (see `Spool::recover`).

use std::fs::File;
use std::os::fd::IntoRawFd;
use std::sync::OnceLock;
use std::sync::atomic::{AtomicI32, Ordering};

/// The signals that mean "this process crashed", with the text written for each.
const FATAL: [(libc::c_int, &[u8]); 5] = [
    (libc::SIGSEGV, b"SIGSEGV\n"),
    (libc::SIGBUS, b"SIGBUS\n"),
    (libc::SIGILL, b"SIGILL\n"),
    (libc::SIGFPE, b"SIGFPE\n"),
    (libc::SIGABRT, b"SIGABRT\n"),
];

/// The marker's descriptor, for the handler (which may only make async-signal-safe calls).
static MARKER: AtomicI32 = AtomicI32::new(-1);
/// The handlers that were in place before ours (Rust's stack-overflow reporter for SIGSEGV and
/// SIGBUS), called after the marker is written.
static PREVIOUS: OnceLock<Vec<(libc::c_int, libc::sigaction)>> = OnceLock::new();

/// From now on, a fatal signal writes its name into `marker` (opened for appending) before the
/// process dies as it would have. Once per process; later calls change nothing.
pub fn record_fatal_signals(marker: File) {
    if PREVIOUS.get().is_some() {
        return;
    }
    // The descriptor lives as long as the process: the handler may run at any moment.
    MARKER.store(marker.into_raw_fd(), Ordering::SeqCst);
    let mut previous = Vec::with_capacity(FATAL.len());
    for (signal, _) in FATAL {
        // SAFETY: a zeroed `sigaction` is a valid "default action, empty mask"; `sigaction`
        // only reads `action` and writes `old`, both valid for the call. The handler makes
        // only async-signal-safe calls (write, sigaction) and reads statics; until `PREVIOUS`
        // is set below it falls back to the default action.
        #[allow(unsafe_code)] // FFI: installing a signal handler has no safe interface.
        unsafe {
            let mut action: libc::sigaction = std::mem::zeroed();
            action.sa_sigaction = on_fatal_signal as *const () as libc::sighandler_t;
            // On the alternate stack, so that a stack overflow can still be recorded.
            action.sa_flags = libc::SA_SIGINFO | libc::SA_ONSTACK;
            libc::sigemptyset(&mut action.sa_mask);
            let mut old: libc::sigaction = std::mem::zeroed();
            if libc::sigaction(signal, &action, &mut old) == 0 {
                previous.push((signal, old));
            }
        }
    }
    let _ = PREVIOUS.set(previous);
}

/// Write the signal's name into the marker, then let the previous handler (or the default
/// action) end the process: a fault re-executes and dies, `abort` raises again.
#[allow(unsafe_code)] // A signal handler: raw FFI by nature.
extern "C" fn on_fatal_signal(
    signal: libc::c_int,
    info: *mut libc::siginfo_t,
    context: *mut libc::c_void,
) {
    let fd = MARKER.load(Ordering::SeqCst);
    if let Some((_, text)) = FATAL.iter().find(|(s, _)| *s == signal)
        && fd >= 0
    {
        // SAFETY: write(2) is async-signal-safe; `text` is a static byte string.
        unsafe {
            libc::write(fd, text.as_ptr().cast(), text.len());
        }
    }
    let previous = PREVIOUS
        .get()
        .and_then(|p| p.iter().find(|(s, _)| *s == signal))
        .map(|(_, action)| *action);
    // SAFETY: the previous action was read from the kernel for this signal: a handler with the
    // signature its flags declare, or SIG_DFL / SIG_IGN, which sigaction(2) reinstates.
    unsafe {
        match previous {
            Some(old) if old.sa_sigaction != libc::SIG_DFL && old.sa_sigaction != libc::SIG_IGN => {
                if old.sa_flags & libc::SA_SIGINFO != 0 {
                    let handler: extern "C" fn(
                        libc::c_int,
                        *mut libc::siginfo_t,
                        *mut libc::c_void,
                    ) = std::mem::transmute(old.sa_sigaction);
                    handler(signal, info, context);
                } else {
                    let handler: extern "C" fn(libc::c_int) = std::mem::transmute(old.sa_sigaction);
                    handler(signal);
                }
            }
            _ => {
                let mut default: libc::sigaction = std::mem::zeroed();
                default.sa_sigaction = libc::SIG_DFL;
                libc::sigaction(signal, &default, std::ptr::null_mut());
            }
        }
    }
}
