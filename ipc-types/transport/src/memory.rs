//! In-memory ports on a [`FakeClock`]: the test doubles of a stream.
//!
//! [`Scripted`] delivers samples at scripted times and moves the fake clock while a loop waits on
//! it, so a process loop's deadline logic runs in microseconds of real time and deterministically.
//! [`Recorder`] keeps what a loop published, with the fake time it was published at.

use std::cell::RefCell;
use std::collections::VecDeque;
use std::rc::Rc;

use crate::clock::{Clock, FakeClock};
use crate::port::{PortError, Publish, Receive};

/// A source that delivers `(arrival_ns, sample)` pairs at their times on a shared [`FakeClock`].
///
/// `wait_until(deadline)` returns at once while a delivered sample is untaken (as an iceoryx2
/// listener with a pending notification does); otherwise it moves the clock to the earlier of the
/// deadline and the next arrival. Like the product's subscribers it keeps at most `buffer` samples,
/// dropping the oldest (safe overflow).
#[derive(Debug)]
pub struct Scripted<T> {
    clock: FakeClock,
    arrivals: VecDeque<(u64, T)>,
    delivered: VecDeque<T>,
    buffer: usize,
    /// Calls to `wait_until` so far.
    pub waits: u64,
}

impl<T: Copy> Scripted<T> {
    /// A source on `clock` delivering `arrivals` (sorted by time here), keeping at most `buffer`.
    pub fn new(clock: &FakeClock, mut arrivals: Vec<(u64, T)>, buffer: usize) -> Self {
        arrivals.sort_by_key(|a| a.0);
        Self {
            clock: clock.clone(),
            arrivals: arrivals.into(),
            delivered: VecDeque::new(),
            buffer: buffer.max(1),
            waits: 0,
        }
    }

    /// Samples not yet delivered.
    pub fn remaining(&self) -> usize {
        self.arrivals.len()
    }

    fn deliver_due(&mut self) {
        let now = self.clock.now_ns();
        while self.arrivals.front().is_some_and(|a| a.0 <= now) {
            let (_, s) = self.arrivals.pop_front().expect("checked");
            if self.delivered.len() == self.buffer {
                self.delivered.pop_front();
            }
            self.delivered.push_back(s);
        }
    }
}

impl<T: Copy> Receive<T> for Scripted<T> {
    fn wait_until(&mut self, deadline_ns: u64) -> Result<(), PortError> {
        self.waits += 1;
        self.deliver_due();
        if !self.delivered.is_empty() {
            return Ok(());
        }
        let now = self.clock.now_ns();
        let wake = match self.arrivals.front() {
            Some(&(t, _)) => t.min(deadline_ns),
            None => deadline_ns,
        };
        if wake > now {
            self.clock.set(wake);
        }
        self.deliver_due();
        Ok(())
    }

    fn take_latest(&mut self) -> Result<Option<T>, PortError> {
        self.deliver_due();
        let last = self.delivered.pop_back();
        self.delivered.clear();
        Ok(last)
    }

    fn drain(&mut self, f: &mut dyn FnMut(&T)) -> Result<usize, PortError> {
        self.deliver_due();
        let n = self.delivered.len();
        for s in self.delivered.drain(..) {
            f(&s);
        }
        Ok(n)
    }
}

/// A publisher that keeps every value with the clock time it was published at. Clones share the
/// record, so a test keeps one handle and gives the loop the other.
#[derive(Debug, Clone)]
pub struct Recorder<T, C: Clock = FakeClock> {
    clock: C,
    log: Rc<RefCell<Vec<(u64, T)>>>,
}

impl<T: Copy, C: Clock + Clone> Recorder<T, C> {
    /// An empty recorder stamping with `clock`.
    pub fn new(clock: &C) -> Self {
        Self {
            clock: clock.clone(),
            log: Rc::new(RefCell::new(Vec::new())),
        }
    }

    /// Everything published so far, `(time_ns, value)`.
    pub fn records(&self) -> Vec<(u64, T)> {
        self.log.borrow().clone()
    }

    /// The values published so far.
    pub fn values(&self) -> Vec<T> {
        self.log.borrow().iter().map(|r| r.1).collect()
    }
}

impl<T: Copy, C: Clock> Publish<T> for Recorder<T, C> {
    fn publish(&mut self, value: &T) -> Result<(), PortError> {
        self.log.borrow_mut().push((self.clock.now_ns(), *value));
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scripted_source_moves_the_clock_to_the_next_arrival_or_the_deadline() {
        let clock = FakeClock::at(0);
        let mut s = Scripted::new(&clock, vec![(100, 1u32), (100, 2), (300, 3)], 4);
        s.wait_until(50).unwrap();
        assert_eq!(clock.now_ns(), 50, "deadline first");
        assert_eq!(s.take_latest().unwrap(), None);
        s.wait_until(1_000).unwrap();
        assert_eq!(clock.now_ns(), 100, "woken by the arrival");
        assert_eq!(s.take_latest().unwrap(), Some(2), "newest of two");
        s.wait_until(1_000).unwrap();
        assert_eq!(clock.now_ns(), 300);
        let mut got = Vec::new();
        assert_eq!(s.drain(&mut |v| got.push(*v)).unwrap(), 1);
        assert_eq!(got, vec![3]);
        assert_eq!(s.remaining(), 0);
    }

    #[test]
    fn a_full_buffer_drops_the_oldest() {
        let clock = FakeClock::at(0);
        let mut s = Scripted::new(&clock, (0..10u32).map(|i| (5, i)).collect(), 3);
        clock.set(10);
        let mut got = Vec::new();
        s.drain(&mut |v| got.push(*v)).unwrap();
        assert_eq!(got, vec![7, 8, 9]);
    }

    #[test]
    fn the_recorder_stamps_with_the_clock() {
        let clock = FakeClock::at(7);
        let mut r = Recorder::new(&clock);
        let handle = r.clone();
        r.publish(&1u8).unwrap();
        clock.advance(3);
        r.publish(&2u8).unwrap();
        assert_eq!(handle.records(), vec![(7, 1), (10, 2)]);
    }
}
