//! Time limits on ONNX Runtime work. A valid ONNX graph can run for ever (a `Loop` of 2^62
//! iterations is a legal model), and nothing but ONNX Runtime itself can stop it: a run still
//! going when its component's [`Deadline`] passes is terminated by one process-wide watchdog
//! thread, which sets the run's terminate flag (`RunOptions::terminate`; ONNX Runtime checks
//! it before every node, inside `Loop` and `Scan` bodies too). The run then ends in
//! [`crate::Error::TimeLimit`].

use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock, PoisonError};
use std::time::{Duration, Instant};

use ort::session::RunOptions;

/// When ONNX Runtime work must stop: `limit` after the moment it was made.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Deadline {
    at: Instant,
    limit: Duration,
}

impl Deadline {
    /// `limit` from now. A limit beyond what the clock can represent (centuries) never passes.
    pub fn after(limit: Duration) -> Self {
        let now = Instant::now();
        let at = now
            .checked_add(limit)
            .unwrap_or_else(|| now + Duration::from_secs(u64::from(u32::MAX)));
        Self { at, limit }
    }

    /// The limit it was made with.
    pub fn limit(&self) -> Duration {
        self.limit
    }

    /// Whether it has passed.
    pub fn passed(&self) -> bool {
        Instant::now() >= self.at
    }
}

/// The `RunOptions` every run of one session is given, so that the watchdog can stop it.
pub(crate) struct RunHandle(Arc<RunOptions>);

impl RunHandle {
    pub(crate) fn new() -> ort::Result<Self> {
        Ok(Self(Arc::new(RunOptions::new()?)))
    }

    /// What to pass to `Session::run_with_options`.
    pub(crate) fn options(&self) -> &RunOptions {
        &self.0
    }
}

impl std::fmt::Debug for RunHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("RunHandle")
    }
}

/// A run being watched; dropping it (the run returned) stops the watch and clears any
/// terminate flag the watchdog set, so the next run of the session starts clean.
pub(crate) struct Watching {
    dog: &'static Watchdog,
    id: u64,
    run: Arc<RunOptions>,
}

impl Drop for Watching {
    fn drop(&mut self) {
        let mut state = self.dog.lock();
        state.watches.retain(|w| w.id != self.id);
        // Under the lock the watchdog cannot set the flag again once the watch is gone.
        let _ = self.run.unterminate();
    }
}

/// Watch one run of a session until `deadline`: `run` holds the `RunOptions` the run was given.
/// An error when the watchdog thread could not be started.
pub(crate) fn watch(deadline: Deadline, run: &RunHandle) -> std::io::Result<Watching> {
    let dog = watchdog()?;
    let mut state = dog.lock();
    state.next_id += 1;
    let id = state.next_id;
    state.watches.push(Watch {
        id,
        at: deadline.at,
        run: Arc::clone(&run.0),
    });
    drop(state);
    dog.changed.notify_one();
    Ok(Watching {
        dog,
        id,
        run: Arc::clone(&run.0),
    })
}

struct Watch {
    id: u64,
    at: Instant,
    run: Arc<RunOptions>,
}

#[derive(Default)]
struct State {
    next_id: u64,
    watches: Vec<Watch>,
}

#[derive(Default)]
struct Watchdog {
    state: Mutex<State>,
    changed: Condvar,
}

impl Watchdog {
    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Sleep until the earliest deadline (or a new watch), terminate every run whose deadline
    /// passed, for ever.
    fn serve(&self) {
        let mut state = self.lock();
        loop {
            let now = Instant::now();
            state.watches.retain(|w| {
                if w.at > now {
                    return true;
                }
                if let Err(e) = w.run.terminate() {
                    tracing::warn!(error = %e, "cannot stop an ONNX Runtime run at its time limit");
                }
                false
            });
            let next = state.watches.iter().map(|w| w.at).min();
            state = match next {
                Some(at) => {
                    self.changed
                        .wait_timeout(state, at.saturating_duration_since(now))
                        .unwrap_or_else(PoisonError::into_inner)
                        .0
                }
                None => self
                    .changed
                    .wait(state)
                    .unwrap_or_else(PoisonError::into_inner),
            };
        }
    }
}

/// The watchdog, its thread started at first use.
fn watchdog() -> std::io::Result<&'static Watchdog> {
    static DOG: OnceLock<&'static Watchdog> = OnceLock::new();
    static START: Mutex<()> = Mutex::new(());
    if let Some(dog) = DOG.get() {
        return Ok(dog);
    }
    let _starting = START.lock().unwrap_or_else(PoisonError::into_inner);
    if let Some(dog) = DOG.get() {
        return Ok(dog);
    }
    let dog: &'static Watchdog = Box::leak(Box::default());
    std::thread::Builder::new()
        .name("ort-watchdog".into())
        .spawn(|| dog.serve())?;
    Ok(DOG.get_or_init(|| dog))
}
