//! A simulated V4L2 capture driver behind `devices::v4l2::CaptureQueue`, for the tests a
//! machine without cameras runs. It behaves as a driver does where the station relies on
//! it: `start` queues the buffers and turns streaming on (VIDIOC_STREAMON); sequence
//! numbers count from 0 there; timestamps are CLOCK_MONOTONIC at the start of exposure; a
//! frame that comes while every buffer is full is dropped, its number skipped; `stop`
//! turns streaming off. Externally triggered, it makes one frame per pulse on its
//! [`TriggerLine`] while streaming and nothing for a pulse before STREAMON; free-running,
//! it makes a frame every period from STREAMON on. [`SimulatedTrigger`] is a trigger box
//! wired to such lines.

use crate::devices::camera::monotonic_now;
use crate::devices::capture::Trigger;
use crate::devices::trigger::TriggerError;
use crate::devices::v4l2::{BufferMeta, CaptureQueue};
use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// How the simulated camera makes frames.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Mode {
    /// one frame per trigger pulse
    Triggered,
    /// a frame every period, from STREAMON on
    FreeRunning { period: Duration },
}

/// What the driver has done, for the tests to read.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct DriverCounts {
    /// STREAMONs
    pub starts: u32,
    /// pulses that came while not streaming (they make no frame)
    pub pulses_lost: u32,
    /// frames made while every buffer was full
    pub dropped: u32,
    /// frames handed to the application
    pub dequeued: u32,
}

struct State {
    mode: Mode,
    streaming: bool,
    started_at: Duration,
    /// free-running frames accounted for since STREAMON
    made: u64,
    next_sequence: u32,
    done: VecDeque<(Vec<u8>, BufferMeta)>,
    /// a buffer handed out and not yet queued again
    held: bool,
    buffers: usize,
    image: Vec<u8>,
    counts: DriverCounts,
}

impl State {
    /// A frame exposed at `at`: into a free buffer, or dropped.
    fn fill(&mut self, at: Duration) {
        let sequence = self.next_sequence;
        self.next_sequence = self.next_sequence.wrapping_add(1);
        if self.done.len() + usize::from(self.held) >= self.buffers {
            self.counts.dropped += 1;
            return;
        }
        self.done.push_back((
            self.image.clone(),
            BufferMeta {
                sequence,
                sec: at.as_secs() as i64,
                usec: at.subsec_micros() as i64,
                monotonic: true,
            },
        ));
    }

    /// The free-running frames due by `now`.
    fn catch_up(&mut self, now: Duration) {
        let Mode::FreeRunning { period } = self.mode else {
            return;
        };
        while self.streaming && self.started_at + period * (self.made as u32 + 1) <= now {
            self.made += 1;
            let at = self.started_at + period * self.made as u32;
            self.fill(at);
        }
    }

    /// When the next free-running frame is due.
    fn next_due(&self) -> Option<Duration> {
        match self.mode {
            Mode::FreeRunning { period } => Some(self.started_at + period * (self.made as u32 + 1)),
            Mode::Triggered => None,
        }
    }
}

type Shared = Arc<(Mutex<State>, Condvar)>;

/// One simulated camera's driver.
pub struct SimulatedDriver {
    shared: Shared,
}

/// The wire from the trigger box to one simulated camera.
#[derive(Clone)]
pub struct TriggerLine {
    shared: Shared,
}

impl SimulatedDriver {
    /// A driver with 4 buffers whose every frame is `image` (the bytes as the camera
    /// delivers them).
    pub fn new(mode: Mode, image: Vec<u8>) -> Self {
        SimulatedDriver {
            shared: Arc::new((
                Mutex::new(State {
                    mode,
                    streaming: false,
                    started_at: Duration::ZERO,
                    made: 0,
                    next_sequence: 0,
                    done: VecDeque::new(),
                    held: false,
                    buffers: 4,
                    image,
                    counts: DriverCounts::default(),
                }),
                Condvar::new(),
            )),
        }
    }

    /// The camera's trigger input (which also reads the driver's counts once the driver
    /// is boxed into a camera).
    pub fn line(&self) -> TriggerLine {
        TriggerLine {
            shared: self.shared.clone(),
        }
    }
}

impl TriggerLine {
    /// A pulse now: a frame exposed now if the camera streams and is triggered.
    pub fn pulse(&self) {
        let (lock, cond) = &*self.shared;
        let mut s = lock.lock().unwrap_or_else(|e| e.into_inner());
        if s.mode != Mode::Triggered {
            return;
        }
        if !s.streaming {
            s.counts.pulses_lost += 1;
            return;
        }
        s.fill(monotonic_now());
        cond.notify_all();
    }

    pub fn counts(&self) -> DriverCounts {
        self.shared
            .0
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .counts
    }

    pub fn streaming(&self) -> bool {
        self.shared
            .0
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .streaming
    }
}

impl CaptureQueue for SimulatedDriver {
    fn start(&mut self) -> std::io::Result<()> {
        let mut s = self.shared.0.lock().unwrap_or_else(|e| e.into_inner());
        s.streaming = true;
        s.started_at = monotonic_now();
        s.made = 0;
        s.next_sequence = 0;
        s.done.clear();
        s.held = false;
        s.counts.starts += 1;
        Ok(())
    }

    fn next(&mut self, timeout: Duration) -> std::io::Result<(Vec<u8>, BufferMeta)> {
        let until = Instant::now() + timeout;
        let (lock, cond) = &*self.shared;
        let mut s = lock.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            if !s.streaming {
                // VIDIOC_DQBUF before STREAMON: poll() reports an error, no frame comes
                return Err(std::io::Error::other("not streaming"));
            }
            let now = monotonic_now();
            s.catch_up(now);
            if let Some(frame) = s.done.pop_front() {
                // the buffer handed out before is queued again, this one is held
                s.held = true;
                s.counts.dequeued += 1;
                return Ok(frame);
            }
            let left = until.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(std::io::ErrorKind::TimedOut.into());
            }
            let wait = match s.next_due() {
                Some(due) => left.min(due.saturating_sub(now).max(Duration::from_micros(50))),
                None => left,
            };
            s = cond
                .wait_timeout(s, wait)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    fn stop(&mut self) {
        let mut s = self.shared.0.lock().unwrap_or_else(|e| e.into_inner());
        s.streaming = false;
        s.done.clear();
        s.held = false;
    }
}

/// A trigger box wired to simulated cameras: `arm` takes as long as a serial round trip
/// (`arm_delay`), `fire` pulses every line and keeps the moment it did.
pub struct SimulatedTrigger {
    pub lines: Vec<TriggerLine>,
    pub arm_delay: Duration,
    /// the monotonic moments of the pulses fired
    pub fired: Arc<Mutex<Vec<Duration>>>,
}

impl Trigger for SimulatedTrigger {
    fn kind(&self) -> &'static str {
        "simulated"
    }
    fn arm(&mut self, _: u32) -> Result<(), TriggerError> {
        std::thread::sleep(self.arm_delay);
        Ok(())
    }
    fn fire(&mut self, _: u32, _: u32) -> Result<Option<u64>, TriggerError> {
        let at = monotonic_now();
        for l in &self.lines {
            l.pulse();
        }
        self.fired
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(at);
        Ok(None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_simulated_driver_behaves_as_a_driver() {
        // triggered: a pulse before STREAMON makes nothing; sequence counts from STREAMON
        let mut d = SimulatedDriver::new(Mode::Triggered, vec![1, 2, 3]);
        let line = d.line();
        line.pulse();
        assert_eq!(line.counts().pulses_lost, 1);
        assert!(d.next(Duration::from_millis(5)).is_err(), "not streaming");
        d.start().unwrap();
        assert_eq!(
            d.next(Duration::from_millis(5)).unwrap_err().kind(),
            std::io::ErrorKind::TimedOut,
            "no pulse, no frame"
        );
        let before = monotonic_now();
        line.pulse();
        line.pulse();
        let (bytes, m) = d.next(Duration::from_millis(5)).unwrap();
        assert_eq!((bytes, m.sequence), (vec![1, 2, 3], 0));
        let at = Duration::from_secs(m.sec as u64) + Duration::from_micros(m.usec as u64);
        assert!(at >= before - Duration::from_micros(1) && m.monotonic);
        assert_eq!(d.next(Duration::ZERO).unwrap().1.sequence, 1);
        // 3 free buffers while one is held: the fourth pulse is dropped, its number skipped
        for _ in 0..4 {
            line.pulse();
        }
        assert_eq!(line.counts().dropped, 1);
        let seqs: Vec<u32> = (0..3)
            .map(|_| d.next(Duration::ZERO).unwrap().1.sequence)
            .collect();
        assert_eq!(seqs, vec![2, 3, 4]);
        line.pulse();
        assert_eq!(d.next(Duration::ZERO).unwrap().1.sequence, 6);
        d.stop();
        d.start().unwrap();
        line.pulse();
        assert_eq!(
            d.next(Duration::ZERO).unwrap().1.sequence,
            0,
            "from 0 again"
        );

        // free-running: frames keep coming, a period apart
        let mut d = SimulatedDriver::new(
            Mode::FreeRunning {
                period: Duration::from_millis(2),
            },
            vec![0],
        );
        d.start().unwrap();
        let a = d.next(Duration::from_millis(50)).unwrap().1;
        let b = d.next(Duration::from_millis(50)).unwrap().1;
        assert_eq!((a.sequence, b.sequence), (0, 1));
        assert_eq!(
            b.usec + b.sec * 1_000_000 - a.usec - a.sec * 1_000_000,
            2_000
        );
        assert_eq!(d.line().counts().starts, 1);
    }
}
