//! Bounded single-producer single-consumer edges between pipeline threads (ringbuf), with a
//! declared policy when full: block (replay) or drop the newest item and count it (live input).
//!
//! Waiting threads park; the other side unparks them. The protocol is the classic
//! flag-then-recheck with sequentially consistent fences on both sides, so a wake-up is never
//! lost; a bounded park timeout is kept as a second line of defence.
//!
//! **Hand-offs in batches** (so that two threads do not wake each other once per pulse, which
//! on a machine with fewer cores than busy threads costs a system call and a context switch per
//! pulse): a sender blocked on a full queue resumes only once the queue has drained to half its
//! capacity ([`EdgeRx`] wakes it then, not on every item taken); a receiver parked on an empty
//! queue is woken by the sender once [`wake_batch`] items wait, and otherwise wakes by itself
//! after [`RECEIVER_PARK`] (1 ms) — the most a parked receiver adds to a pulse's latency.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering, fence};
use std::sync::{Arc, OnceLock};
use std::thread::{self, Thread};
use std::time::Duration;

use crossbeam_utils::CachePadded;
use ringbuf::traits::{Consumer, Observer, Producer, Split};
use ringbuf::{HeapCons, HeapProd, HeapRb};

/// What to do when an edge (bounded queue) is full.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum FullPolicy {
    /// Wait for room (replay: nothing is lost, the source slows down).
    #[default]
    Block,
    /// Drop the newest item and count it (live input: never stall the receiver).
    DropNewest,
}

/// How long a blocked sender parks before re-checking on its own.
const PARK_TIMEOUT: Duration = Duration::from_millis(50);
/// How long a receiver waiting on an empty queue parks before re-checking on its own: the
/// sender wakes it only once [`wake_batch`] items wait, so this bounds the latency added to an
/// item at low rates.
pub const RECEIVER_PARK: Duration = Duration::from_millis(1);
/// Busy spins before yielding (cheap when the other side is about to act).
const SPINS: u32 = 64;
/// Yields to other threads before parking. Few: on a machine with fewer cores than busy
/// threads every yield is a context switch taken from a thread with work.
const YIELDS: u32 = 16;

/// Items that must wait in a queue of `capacity` before the sender wakes a parked receiver:
/// a quarter of the capacity, at most 32, at least 1.
pub fn wake_batch(capacity: usize) -> usize {
    (capacity / 4).clamp(1, 32)
}

/// Occupancy down to which a full queue of `capacity` drains before its blocked sender
/// resumes: half the capacity.
fn resume_level(capacity: usize) -> usize {
    capacity / 2
}

/// State shared by the two ends. Fields written on every item by one side sit on their own
/// cache lines so the two cores do not fight over them.
struct Shared {
    tx_closed: AtomicBool,
    rx_closed: AtomicBool,
    rx_thread: OnceLock<Thread>,
    tx_thread: OnceLock<Thread>,
    capacity: usize,
    rx_waiting: CachePadded<AtomicBool>,
    tx_waiting: CachePadded<AtomicBool>,
    sent: CachePadded<AtomicU64>,
    dropped_full: CachePadded<AtomicU64>,
}

/// One step of waiting for the other side: spin, then yield, then park. Before parking, the
/// waiter raises its `waiting` flag and re-checks `still_blocked` behind a SeqCst fence; the other
/// side acts, fences, then reads the flag and unparks: one of the two always sees the other.
fn wait(spins: &mut u32, waiting: &AtomicBool, park: Duration, still_blocked: impl Fn() -> bool) {
    if *spins < SPINS + YIELDS {
        *spins += 1;
        if *spins <= SPINS {
            std::hint::spin_loop();
        } else {
            thread::yield_now();
        }
        return;
    }
    waiting.store(true, Ordering::SeqCst);
    fence(Ordering::SeqCst);
    if still_blocked() {
        thread::park_timeout(park);
    }
    waiting.store(false, Ordering::SeqCst);
}

/// [`EdgeRx::recv_deadline`] found nothing before its deadline.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TimedOut;

/// Live counters of an edge, readable from any thread.
#[derive(Clone)]
pub struct EdgeStats(Arc<Shared>);

impl EdgeStats {
    /// Items accepted into the queue so far.
    pub fn sent(&self) -> u64 {
        self.0.sent.load(Ordering::Relaxed)
    }
    /// Items dropped because the queue was full (drop-newest policy).
    pub fn dropped_full(&self) -> u64 {
        self.0.dropped_full.load(Ordering::Relaxed)
    }
    /// Capacity, items.
    pub fn capacity(&self) -> usize {
        self.0.capacity
    }
}

/// The sending end of an edge.
pub struct EdgeTx<T> {
    prod: HeapProd<T>,
    shared: Arc<Shared>,
    policy: FullPolicy,
}

/// The receiving end of an edge.
pub struct EdgeRx<T> {
    cons: HeapCons<T>,
    shared: Arc<Shared>,
}

/// What became of an item given to [`EdgeTx::send`].
#[derive(Debug)]
pub enum Sent<T> {
    /// It is in the queue.
    Queued,
    /// The queue was full and the policy is drop-newest: here it is back, counted as dropped.
    Dropped(T),
    /// The receiver is gone: here it is back.
    Closed(T),
}

/// Creates an edge holding at most `capacity` items.
pub fn edge<T>(capacity: usize, policy: FullPolicy) -> (EdgeTx<T>, EdgeRx<T>) {
    let capacity = capacity.max(1);
    let (prod, cons) = HeapRb::<T>::new(capacity).split();
    let shared = Arc::new(Shared {
        tx_closed: AtomicBool::new(false),
        rx_closed: AtomicBool::new(false),
        rx_thread: OnceLock::new(),
        tx_thread: OnceLock::new(),
        capacity,
        rx_waiting: CachePadded::new(AtomicBool::new(false)),
        tx_waiting: CachePadded::new(AtomicBool::new(false)),
        sent: CachePadded::new(AtomicU64::new(0)),
        dropped_full: CachePadded::new(AtomicU64::new(0)),
    });
    (
        EdgeTx {
            prod,
            shared: shared.clone(),
            policy,
        },
        EdgeRx { cons, shared },
    )
}

impl<T> EdgeTx<T> {
    /// Live counters of this edge.
    pub fn stats(&self) -> EdgeStats {
        EdgeStats(self.shared.clone())
    }

    /// Items waiting in the queue now.
    pub fn len(&self) -> usize {
        self.prod.occupied_len()
    }

    /// True when no item waits in the queue.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Sends an item according to the edge's policy.
    pub fn send(&mut self, item: T) -> Sent<T> {
        let mut item = match self.prod.try_push(item) {
            Ok(()) => return self.after_push(),
            Err(item) => item,
        };
        if self.policy == FullPolicy::DropNewest {
            if self.shared.rx_closed.load(Ordering::Acquire) {
                return Sent::Closed(item);
            }
            self.shared.dropped_full.fetch_add(1, Ordering::Relaxed);
            return Sent::Dropped(item);
        }
        let _ = self.shared.tx_thread.set(thread::current());
        let resume = resume_level(self.shared.capacity);
        let mut spins = 0u32;
        loop {
            if self.shared.rx_closed.load(Ordering::Acquire) {
                return Sent::Closed(item);
            }
            // Resume only once the queue has drained to half (see the module's notes).
            if self.prod.occupied_len() <= resume {
                item = match self.prod.try_push(item) {
                    Ok(()) => return self.after_push(),
                    Err(item) => item,
                };
            }
            let (prod, shared) = (&self.prod, &self.shared);
            wait(&mut spins, &shared.tx_waiting, PARK_TIMEOUT, || {
                prod.occupied_len() > resume && !shared.rx_closed.load(Ordering::SeqCst)
            });
        }
    }

    fn after_push(&mut self) -> Sent<T> {
        // Only this side writes `sent`: a plain load + store is enough and cheaper.
        let n = self.shared.sent.load(Ordering::Relaxed);
        self.shared.sent.store(n + 1, Ordering::Relaxed);
        fence(Ordering::SeqCst);
        if self.shared.rx_waiting.load(Ordering::SeqCst)
            && self.prod.occupied_len() >= wake_batch(self.shared.capacity)
            && let Some(t) = self.shared.rx_thread.get()
        {
            t.unpark();
        }
        Sent::Queued
    }
}

impl<T> Drop for EdgeTx<T> {
    fn drop(&mut self) {
        self.shared.tx_closed.store(true, Ordering::SeqCst);
        if let Some(t) = self.shared.rx_thread.get() {
            t.unpark();
        }
    }
}

impl<T> EdgeRx<T> {
    /// Items waiting in the queue now.
    pub fn len(&self) -> usize {
        self.cons.occupied_len()
    }

    /// True when no item waits in the queue.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Takes the next item, waiting for one; `None` once the sender is gone and the queue is
    /// drained.
    pub fn recv(&mut self) -> Option<T> {
        let _ = self.shared.rx_thread.set(thread::current());
        let mut spins = 0u32;
        loop {
            if let Some(item) = self.cons.try_pop() {
                self.after_pop();
                return Some(item);
            }
            if self.shared.tx_closed.load(Ordering::SeqCst) {
                // The sender may have pushed just before closing.
                let last = self.cons.try_pop();
                if last.is_some() {
                    self.after_pop();
                }
                return last;
            }
            let (cons, shared) = (&self.cons, &self.shared);
            let batch = wake_batch(shared.capacity);
            wait(&mut spins, &shared.rx_waiting, RECEIVER_PARK, || {
                cons.occupied_len() < batch && !shared.tx_closed.load(Ordering::SeqCst)
            });
        }
    }

    /// As [`recv`](Self::recv), but gives up at `deadline` (to within the 1 ms park):
    /// `Err(TimedOut)` when it passed with nothing to take.
    pub fn recv_deadline(&mut self, deadline: std::time::Instant) -> Result<Option<T>, TimedOut> {
        let _ = self.shared.rx_thread.set(thread::current());
        let mut spins = 0u32;
        loop {
            if let Some(item) = self.cons.try_pop() {
                self.after_pop();
                return Ok(Some(item));
            }
            if self.shared.tx_closed.load(Ordering::SeqCst) {
                let last = self.cons.try_pop();
                if last.is_some() {
                    self.after_pop();
                }
                return Ok(last);
            }
            if std::time::Instant::now() >= deadline {
                return Err(TimedOut);
            }
            let (cons, shared) = (&self.cons, &self.shared);
            let batch = wake_batch(shared.capacity);
            wait(&mut spins, &shared.rx_waiting, RECEIVER_PARK, || {
                cons.occupied_len() < batch && !shared.tx_closed.load(Ordering::SeqCst)
            });
        }
    }

    fn after_pop(&mut self) {
        fence(Ordering::SeqCst);
        if self.shared.tx_waiting.load(Ordering::SeqCst)
            && self.cons.occupied_len() <= resume_level(self.shared.capacity)
            && let Some(t) = self.shared.tx_thread.get()
        {
            t.unpark();
        }
    }
}

impl<T> Drop for EdgeRx<T> {
    fn drop(&mut self) {
        self.shared.rx_closed.store(true, Ordering::SeqCst);
        if let Some(t) = self.shared.tx_thread.get() {
            t.unpark();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recv_deadline_times_out_when_quiet_and_still_sees_items_and_the_end() {
        use std::time::{Duration, Instant};
        let (mut tx, mut rx) = edge::<u64>(4, FullPolicy::Block);
        let t0 = Instant::now();
        assert_eq!(
            rx.recv_deadline(t0 + Duration::from_millis(20)),
            Err(TimedOut)
        );
        assert!(t0.elapsed() >= Duration::from_millis(20));
        assert!(matches!(tx.send(7), Sent::Queued));
        assert_eq!(rx.recv_deadline(Instant::now()), Ok(Some(7)));
        drop(tx);
        assert_eq!(
            rx.recv_deadline(Instant::now() + Duration::from_secs(5)),
            Ok(None)
        );
    }

    #[test]
    fn blocking_edge_delivers_everything_in_order() {
        let (mut tx, mut rx) = edge::<u64>(4, FullPolicy::Block);
        let h = thread::spawn(move || {
            for i in 0..100_000u64 {
                assert!(matches!(tx.send(i), Sent::Queued));
            }
        });
        let mut expect = 0u64;
        while let Some(v) = rx.recv() {
            assert_eq!(v, expect);
            expect += 1;
        }
        h.join().unwrap();
        assert_eq!(expect, 100_000);
    }

    #[test]
    fn a_lone_item_reaches_a_parked_receiver_within_its_park_time() {
        use std::time::Instant;
        // Below the wake batch the sender does not wake the receiver: it must find the item
        // itself when its short park ends.
        let (mut tx, mut rx) = edge::<Instant>(1024, FullPolicy::Block);
        assert_eq!(wake_batch(1024), 32);
        let h = thread::spawn(move || {
            let mut worst = Duration::ZERO;
            while let Some(sent_at) = rx.recv() {
                worst = worst.max(sent_at.elapsed());
            }
            worst
        });
        for _ in 0..5 {
            thread::sleep(Duration::from_millis(30)); // the receiver parks meanwhile
            assert!(matches!(tx.send(Instant::now()), Sent::Queued));
        }
        thread::sleep(Duration::from_millis(30));
        drop(tx);
        let worst = h.join().unwrap();
        // 1 ms park; generous for a loaded machine, far below the 50 ms of a lost wake-up.
        assert!(
            worst < Duration::from_millis(25),
            "lone item waited {worst:?}"
        );
    }

    #[test]
    fn a_blocked_sender_resumes_once_the_queue_has_drained_to_half() {
        let (mut tx, mut rx) = edge::<u32>(8, FullPolicy::Block);
        for i in 0..8 {
            assert!(matches!(tx.send(i), Sent::Queued));
        }
        let h = thread::spawn(move || {
            assert!(matches!(tx.send(8), Sent::Queued));
            tx
        });
        thread::sleep(Duration::from_millis(30)); // the sender finds the queue full and waits
        // Taking one item leaves 7 > 4 waiting: the sender stays blocked.
        assert_eq!(rx.recv(), Some(0));
        thread::sleep(Duration::from_millis(30));
        assert_eq!(rx.len(), 7);
        for want in 1..4 {
            assert_eq!(rx.recv(), Some(want));
        }
        let tx = h.join().unwrap(); // 4 left: it resumed and queued its item
        assert_eq!(rx.len(), 5);
        drop(tx);
        let rest: Vec<u32> = std::iter::from_fn(|| rx.recv()).collect();
        assert_eq!(rest, vec![4, 5, 6, 7, 8]);
    }

    #[test]
    fn drop_newest_counts_exactly() {
        let (mut tx, mut rx) = edge::<u32>(3, FullPolicy::DropNewest);
        let mut dropped = 0;
        for i in 0..10 {
            if let Sent::Dropped(v) = tx.send(i) {
                assert_eq!(v, i);
                dropped += 1;
            }
        }
        assert_eq!(dropped, 7);
        assert_eq!(tx.stats().dropped_full(), 7);
        assert_eq!(tx.stats().sent(), 3);
        drop(tx);
        let got: Vec<u32> = std::iter::from_fn(|| rx.recv()).collect();
        assert_eq!(got, vec![0, 1, 2]);
    }

    #[test]
    fn blocked_sender_is_released_when_receiver_goes() {
        let (mut tx, rx) = edge::<u32>(1, FullPolicy::Block);
        assert!(matches!(tx.send(1), Sent::Queued));
        let h = thread::spawn(move || tx.send(2));
        thread::sleep(Duration::from_millis(20));
        drop(rx);
        assert!(matches!(h.join().unwrap(), Sent::Closed(2)));
    }
}
