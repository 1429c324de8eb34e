//! The player: sends frames to the viewer's WebSocket and as VMC bundles at the motion's frame
//! period, on a schedule tied to the audio rather than to when a window happens to finish.
//!
//! Windows arrive a hop of frames at a time, a generation time after their audio. Frame `k`
//! leaves at `offset + k · period`, where the offset puts the last frame of a window
//! [`PlayoutClock::delay`] after the audio it was made from was heard: a window's first frame
//! then leaves `latency budget − latency` after the window arrives, so any window within the
//! budget is on time and the budget absorbs the generator's jitter. A frame that would leave more
//! than half a period late is dropped (a skip, counted and logged), never sent in a burst; when
//! the audio clock moves (a device lost and reconnected, clock drift) by more than
//! [`RESYNC_S`] the schedule is re-timed once, also logged.

use std::net::UdpSocket;
use std::sync::Arc;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use choreo_datasets::RigidPose;
use ndarray::Axis;
use tokio::sync::broadcast;

use super::{viewer, vmc};

/// Audio-clock moves smaller than this keep the schedule: larger than the jitter of when the
/// capture delivers a block (tens of ms), far smaller than a lost device (the 2 s stall
/// timeout).
pub const RESYNC_S: f64 = 0.2;
/// Late frames are reported at most this often.
const LATE_LOG_INTERVAL: Duration = Duration::from_secs(5);

/// What the generator hands the player.
#[derive(Debug)]
pub enum ToPlayer {
    /// New frames `first..first + n` of the session; `heard_at`: when the newest audio their
    /// window used arrived.
    Frames {
        first: usize,
        pose: RigidPose,
        heard_at: Instant,
    },
    /// A state the viewer shows instead of frames (e.g. "waiting for audio").
    Status(&'static str),
}

/// The frame schedule: `due(k) = offset + k · period` in seconds on the player's clock.
#[derive(Debug, Clone)]
pub struct PlayoutClock {
    period: f64,
    /// Seconds from hearing a window's newest audio to sending its last frame.
    delay: f64,
    offset: Option<f64>,
    /// When the last frame was actually sent.
    last_sent: Option<f64>,
}

/// What to do with one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Slot {
    /// Send it at this time (seconds on the player's clock; now or later).
    At(f64),
    /// Too late (or would crowd the frame before): skip it.
    Late,
}

impl PlayoutClock {
    /// A schedule at `fps` whose windows of `hop_frames` frames are made within
    /// `latency_budget` of their audio.
    pub fn new(fps: f64, hop_frames: usize, latency_budget: Duration) -> Self {
        let period = 1.0 / fps;
        Self {
            period,
            delay: hop_frames.saturating_sub(1) as f64 * period + latency_budget.as_secs_f64(),
            offset: None,
            last_sent: None,
        }
    }

    /// Seconds from hearing audio to sending the frame made from it.
    pub fn delay(&self) -> f64 {
        self.delay
    }

    /// A window whose last frame is `last` was made from audio heard at `heard` (seconds). The
    /// first window sets the schedule; later ones move it only when the audio clock moved by
    /// more than [`RESYNC_S`]. Returns the move (seconds) when it re-timed.
    pub fn window(&mut self, last: usize, heard: f64) -> Option<f64> {
        let estimate = heard + self.delay - last as f64 * self.period;
        match self.offset {
            Some(o) if (estimate - o).abs() <= RESYNC_S => None,
            Some(o) => {
                self.offset = Some(estimate);
                Some(estimate - o)
            }
            None => {
                self.offset = Some(estimate);
                None
            }
        }
    }

    /// When frame `k` leaves, `now` being the current time (seconds): at its due time, but never
    /// sooner than half a period after the previous frame was actually sent. A frame that could
    /// then only leave more than half a period past due is late: sending it would make a burst
    /// (the schedule moved earlier, or the player lost its core for a moment).
    pub fn slot(&self, k: usize, now: f64) -> Slot {
        let Some(offset) = self.offset else {
            return Slot::Late;
        };
        let due = offset + k as f64 * self.period;
        let half = self.period / 2.0;
        let earliest = self.last_sent.map_or(now, |sent| now.max(sent + half));
        let at = due.max(earliest);
        if at - due > half {
            Slot::Late
        } else {
            Slot::At(at)
        }
    }

    /// A frame was sent at `at` (seconds).
    pub fn sent(&mut self, at: f64) {
        self.last_sent = Some(at);
    }
}

/// What the player did, for `--stats`.
#[derive(Debug, Default, Clone, Copy)]
pub struct PlayStats {
    /// Frames not sent because they were late.
    pub late_frames: usize,
    /// Times the schedule was re-timed to the audio clock.
    pub resyncs: usize,
}

/// Send what arrives on `rx` on `clock`'s schedule until the sender is dropped.
pub fn play(
    rx: mpsc::Receiver<ToPlayer>,
    mut clock: PlayoutClock,
    fps: f64,
    frames_tx: Option<&broadcast::Sender<Arc<str>>>,
    osc: Option<&UdpSocket>,
) -> PlayStats {
    let epoch = Instant::now();
    let secs = |t: Instant| {
        t.saturating_duration_since(epoch).as_secs_f64()
            - epoch.saturating_duration_since(t).as_secs_f64()
    };
    let mut encoder = vmc::VmcEncoder::new();
    let mut wire = viewer::WireEncoder::default();
    let mut stats = PlayStats::default();
    let mut late_unreported = 0usize;
    let mut last_late_log: Option<Instant> = None;
    while let Ok(message) = rx.recv() {
        let (first, pose, heard_at) = match message {
            ToPlayer::Status(status) => {
                if let Some(tx) = frames_tx
                    && let Some(text) = viewer::WireEncoder::status(status)
                {
                    let _ = tx.send(text);
                }
                continue;
            }
            ToPlayer::Frames {
                first,
                pose,
                heard_at,
            } => (first, pose, heard_at),
        };
        let n = pose.joints.len_of(Axis(0));
        if n == 0 {
            continue;
        }
        if let Some(shift) = clock.window(first + n - 1, secs(heard_at)) {
            stats.resyncs += 1;
            tracing::warn!(
                shift_ms = (shift * 1000.0).round(),
                "live output re-timed to the audio (the input's clock moved)"
            );
        }
        for i in 0..n {
            let index = first + i;
            let at = match clock.slot(index, secs(Instant::now())) {
                Slot::At(at) => at,
                Slot::Late => {
                    stats.late_frames += 1;
                    late_unreported += 1;
                    continue;
                }
            };
            std::thread::sleep(Duration::from_secs_f64(
                (at - secs(Instant::now())).max(0.0),
            ));
            let time = index as f64 / fps;
            if let Some(tx) = frames_tx {
                for text in wire.frame(&pose, i, index, time) {
                    // No receiver (no page open) is fine.
                    let _ = tx.send(text);
                }
            }
            if let Some(socket) = osc {
                // UDP: a missing receiver is normal (ECONNREFUSED); nothing to do about it.
                let _ = socket.send(&encoder.bundle(&pose, i, time as f32));
            }
            clock.sent(secs(Instant::now()));
        }
        if late_unreported > 0 && last_late_log.is_none_or(|t| t.elapsed() >= LATE_LOG_INTERVAL) {
            tracing::warn!(
                skipped_frames = late_unreported,
                budget_ms = (clock.delay() * 1000.0).round(),
                "live frames arrived after their time and were skipped"
            );
            late_unreported = 0;
            last_late_log = Some(Instant::now());
        }
    }
    stats
}

#[cfg(test)]
mod tests {
    use super::*;

    const FPS: f64 = 30.0;
    const P: f64 = 1.0 / FPS;

    fn clock() -> PlayoutClock {
        PlayoutClock::new(FPS, 15, Duration::from_millis(250))
    }

    /// Gaps between the send times of windows of 15 frames made `latencies[i]` after their
    /// audio, the audio of window i heard at 0.5·(i + 1) s.
    fn sends(latencies: &[f64]) -> (Vec<f64>, usize) {
        let mut c = clock();
        let mut out = Vec::new();
        let mut late = 0;
        let mut now = 0.0f64;
        for (w, latency) in latencies.iter().enumerate() {
            let heard = 0.5 * (w + 1) as f64;
            now = now.max(heard + latency);
            c.window(15 * w + 14, heard);
            for k in 15 * w..15 * (w + 1) {
                match c.slot(k, now) {
                    Slot::At(t) => {
                        now = t;
                        c.sent(t);
                        out.push(t);
                    }
                    Slot::Late => late += 1,
                }
            }
        }
        (out, late)
    }

    #[test]
    fn jitter_within_the_budget_leaves_every_frame_one_period_apart() {
        // Generation times 10-240 ms: all within the 250 ms budget.
        let (times, late) = sends(&[0.2, 0.01, 0.24, 0.05, 0.13, 0.01, 0.22]);
        assert_eq!(late, 0);
        assert_eq!(times.len(), 7 * 15);
        for w in times.windows(2) {
            assert!((w[1] - w[0] - P).abs() < 1e-9, "{w:?}");
        }
        // The last frame of a window leaves the delay after its audio: 14 periods + budget.
        assert!((times[14] - (0.5 + 14.0 * P + 0.25)).abs() < 1e-9);
    }

    #[test]
    fn a_window_over_the_budget_skips_its_late_frames_instead_of_bursting() {
        // The third window comes 0.45 s after its audio: its first frames are past due.
        let (times, late) = sends(&[0.1, 0.1, 0.45, 0.1]);
        // 0.45 − 0.25 = 0.2 s late = 6 periods; a frame up to half a period late still goes.
        assert_eq!(late, 6, "{times:?}");
        let gaps: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).collect();
        assert!(gaps.iter().all(|g| *g >= P / 2.0 - 1e-9), "{gaps:?}");
        assert_eq!(gaps.iter().filter(|g| **g > 1.5 * P).count(), 1, "{gaps:?}");
    }

    #[test]
    fn the_schedule_follows_a_moved_audio_clock_and_ignores_block_jitter() {
        let mut c = clock();
        assert_eq!(c.window(14, 0.5), None);
        // A block delivered 0.15 s late: within RESYNC_S, the schedule stays.
        assert_eq!(c.window(29, 1.15), None);
        // A reconnect: the audio of frame 44 was heard 2 s later than the clock expects.
        let shift = c.window(44, 3.5).unwrap();
        assert!((shift - 2.0).abs() < 1e-9, "{shift}");
        assert_eq!(c.slot(44, 3.5), Slot::At(3.5 + c.delay()));
    }

    #[test]
    fn a_frame_sent_late_is_not_followed_by_one_at_once() {
        let mut c = clock();
        c.window(14, 0.5);
        let delay = c.delay();
        let due = |k: usize| 0.5 + delay + (k as f64 - 14.0) * P;
        // Frame 3 went out 0.6 periods late (the player lost its core after deciding).
        c.sent(due(3) + 0.6 * P);
        // Frame 4 is due 0.4 periods after it: it waits to half a period after the send, 0.1
        // periods past due.
        let Slot::At(t) = c.slot(4, due(4) - 0.4 * P) else {
            panic!("frame 4 dropped")
        };
        assert!((t - (due(3) + 1.1 * P)).abs() < 1e-9, "{t}");
        // Sent 1.05 periods late instead: frame 4 could only leave 0.55 periods past due.
        c.sent(due(3) + 1.05 * P);
        assert_eq!(c.slot(4, due(4) + 0.05 * P), Slot::Late);
        assert!(matches!(c.slot(5, due(4) + 0.05 * P), Slot::At(_)));
    }
}
