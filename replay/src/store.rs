//! The replay's data side, free of IPC so unit tests reach every rule: the ring buffer, the
//! sample-to-insert rate limiter, the quarantine of non-finite transitions and the per-actor loss
//! accounting. [`ReplayStore`] ties them together; `process` only moves messages in and out.

use bcal_common::config::ReplayConfig;
use bcal_common::wire::{ReplayCounters, Transition, TransitionBatchHeader};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use std::collections::HashMap;

/// Fixed-capacity FIFO of transitions: once full, each insert overwrites the oldest.
///
/// Memory is reserved up front but touched only as the buffer fills (the paper's 1e6 transitions are
/// 280 MB), so a short run never pays for the full capacity.
#[derive(Debug)]
pub struct RingBuffer {
    items: Vec<Transition>,
    capacity: usize,
    /// Slot the next insert writes once the buffer is full.
    next: usize,
}

impl RingBuffer {
    pub fn new(capacity: usize) -> Self {
        assert!(capacity > 0, "a ring buffer needs capacity");
        Self { items: Vec::with_capacity(capacity), capacity, next: 0 }
    }

    pub fn len(&self) -> usize {
        self.items.len()
    }

    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    pub fn push(&mut self, t: Transition) {
        if self.items.len() < self.capacity {
            self.items.push(t);
        } else {
            self.items[self.next] = t;
        }
        self.next = (self.next + 1) % self.capacity;
    }

    pub fn get(&self, i: usize) -> &Transition {
        &self.items[i]
    }

    /// The stored transitions in slot order and the slot the next insert overwrites once full (what a
    /// snapshot saves).
    pub fn parts(&self) -> (&[Transition], usize) {
        (&self.items, self.next)
    }

    /// A buffer holding `items` in slot order with `next` as the next slot to overwrite (what a snapshot
    /// restores); None when the parts do not fit `capacity`.
    pub fn from_parts(capacity: usize, items: Vec<Transition>, next: usize) -> Option<Self> {
        let consistent = capacity > 0
            && items.len() <= capacity
            && next < capacity
            && (items.len() == capacity || next == items.len() % capacity);
        consistent.then_some(Self { items, capacity, next })
    }

    /// Fills `out` with transitions drawn uniformly with replacement (DDPG/SAC/LAC replay).
    pub fn sample_into(&self, rng: &mut impl Rng, out: &mut [Transition]) {
        assert!(!self.items.is_empty(), "sampling an empty buffer");
        for o in out.iter_mut() {
            *o = self.items[rng.random_range(0..self.items.len())];
        }
    }
}

/// Reverb's `SampleToInsertRatio` limiter, counting single transitions (a batch of 256 is 256 samples).
///
/// With `diff = inserts * samples_per_insert - samples`, `min_diff = spi * min_size - error_buffer` and
/// `max_diff = spi * min_size + error_buffer`:
/// - sampling needs `inserts >= min_size` and `diff - n >= min_diff` after taking `n` samples, so the
///   learner cannot run ahead of the data (it waits for actors);
/// - inserting is free until `min_size` transitions are in, then needs `diff + n * spi <= max_diff`, so
///   actors cannot run more than `error_buffer / spi` transitions ahead of what the learner consumes.
///
/// Both blocked at once would deadlock, which happens when `2 * error_buffer < spi + batch`; the
/// constructor widens the error buffer to exclude that and reports the value it uses.
#[derive(Clone, Debug, PartialEq)]
pub struct RateLimiter {
    samples_per_insert: f64,
    min_size: u64,
    error_buffer: f64,
    inserts: u64,
    samples: u64,
}

impl RateLimiter {
    /// `min_size`: transitions before the first sample (learning_starts); `batch`: samples per request.
    pub fn new(samples_per_insert: f64, min_size: u64, error_buffer: f64, batch: u64) -> Self {
        let needed = 0.5 * (samples_per_insert + batch as f64) + 1.0;
        Self { samples_per_insert, min_size, error_buffer: error_buffer.max(needed), inserts: 0, samples: 0 }
    }

    pub fn from_config(cfg: &ReplayConfig, batch: usize) -> Self {
        Self::new(cfg.samples_per_insert, cfg.learning_starts as u64, cfg.ratio_error_buffer, batch as u64)
    }

    /// The error buffer in use (the configured one, or wider if it could deadlock).
    pub fn error_buffer(&self) -> f64 {
        self.error_buffer
    }

    fn min_diff(&self) -> f64 {
        self.samples_per_insert * self.min_size as f64 - self.error_buffer
    }

    fn max_diff(&self) -> f64 {
        self.samples_per_insert * self.min_size as f64 + self.error_buffer
    }

    fn diff(&self, inserts: u64, samples: u64) -> f64 {
        inserts as f64 * self.samples_per_insert - samples as f64
    }

    pub fn can_insert(&self, n: u64) -> bool {
        let after = self.inserts + n;
        after <= self.min_size || self.diff(after, self.samples) <= self.max_diff()
    }

    pub fn can_sample(&self, n: u64) -> bool {
        self.inserts >= self.min_size && self.diff(self.inserts, self.samples + n) >= self.min_diff()
    }

    /// Inserts admitted before the limiter blocks (0 when blocked). Actors share it, so it is advisory.
    pub fn insert_credit(&self) -> u64 {
        let by_min_size = self.min_size.saturating_sub(self.inserts);
        let cap = ((self.max_diff() + self.samples as f64) / self.samples_per_insert).floor();
        let by_ratio = if cap > self.inserts as f64 { (cap - self.inserts as f64) as u64 } else { 0 };
        by_min_size.max(by_ratio)
    }

    /// Records inserts. Transitions already on the wire are always accepted (dropping them would lose
    /// paid-for data), so the count may overshoot the limit by what was in flight.
    pub fn record_inserts(&mut self, n: u64) {
        self.inserts += n;
    }

    pub fn record_samples(&mut self, n: u64) {
        self.samples += n;
    }

    /// (inserts, samples) counted so far (saved by a snapshot, so a restored replay keeps the ratio).
    pub fn counts(&self) -> (u64, u64) {
        (self.inserts, self.samples)
    }

    pub fn restore_counts(&mut self, inserts: u64, samples: u64) {
        self.inserts = inserts;
        self.samples = samples;
    }
}

/// Per-actor sequence accounting: a gap between what an actor says it published before a message and
/// what arrived from it so far is counted as dropped.
#[derive(Debug, Default)]
pub struct DropTracker {
    /// actor id -> (epoch, transitions expected before its next message).
    actors: HashMap<u32, (u64, u64)>,
}

impl DropTracker {
    /// Accounts one message of `n` transitions; returns the transitions newly found missing. The first
    /// message of an actor incarnation sets its baseline (a restarted replay cannot know what an actor
    /// sent to its predecessor).
    pub fn observe(&mut self, h: &TransitionBatchHeader, n: usize) -> u64 {
        let n = n as u64;
        match self.actors.get_mut(&h.actor_id) {
            Some((epoch, expected)) if *epoch == h.epoch => {
                let missing = h.published_before.saturating_sub(*expected);
                *expected = h.published_before + n;
                missing
            }
            _ => {
                self.actors.insert(h.actor_id, (h.epoch, h.published_before + n));
                0
            }
        }
    }

    /// Actor incarnations seen so far.
    pub fn actors_seen(&self) -> usize {
        self.actors.len()
    }
}

/// Ring buffer + limiter + quarantine + loss accounting, with the counters the replay reports.
#[derive(Debug)]
pub struct ReplayStore {
    pub ring: RingBuffer,
    pub limiter: RateLimiter,
    pub tracker: DropTracker,
    pub counters: ReplayCounters,
    rng: SmallRng,
}

impl ReplayStore {
    pub fn new(cfg: &ReplayConfig, batch: usize, seed: u64) -> Self {
        Self {
            ring: RingBuffer::new(cfg.capacity),
            limiter: RateLimiter::from_config(cfg, batch),
            tracker: DropTracker::default(),
            counters: ReplayCounters::default(),
            rng: SmallRng::seed_from_u64(seed),
        }
    }

    /// Takes one actor message: finite transitions go into the ring, the others are quarantined
    /// (counted, never stored), and sequence gaps are counted as dropped.
    pub fn ingest(&mut self, header: &TransitionBatchHeader, batch: &[Transition]) {
        let c = &mut self.counters;
        c.received_total += batch.len() as u64;
        c.dropped_total += self.tracker.observe(header, batch.len());
        let mut inserted = 0;
        for t in batch {
            if t.is_finite() {
                self.ring.push(*t);
                inserted += 1;
            } else {
                c.quarantined_total += 1;
            }
        }
        c.inserted_total += inserted;
        c.size = self.ring.len() as u64;
        self.limiter.record_inserts(inserted);
    }

    /// Whether a batch of `n` may be served now.
    pub fn can_sample(&self, n: usize) -> bool {
        !self.ring.is_empty() && self.limiter.can_sample(n as u64)
    }

    /// Fills `out` with a uniform batch and records it (call only after [`Self::can_sample`]).
    pub fn sample_into(&mut self, out: &mut [Transition]) {
        self.ring.sample_into(&mut self.rng, out);
        self.limiter.record_samples(out.len() as u64);
        self.counters.sampled_total += out.len() as u64;
        self.counters.batches_served += 1;
    }

    pub fn inserts_allowed(&self) -> bool {
        self.limiter.can_insert(1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(v: f32) -> Transition {
        Transition { cost: v, ..Transition::default() }
    }

    #[test]
    fn ring_buffer_wraps_and_overwrites_the_oldest() {
        let mut r = RingBuffer::new(3);
        for v in 0..5 {
            r.push(t(v as f32));
        }
        assert_eq!(r.len(), 3);
        let mut costs: Vec<f32> = (0..3).map(|i| r.get(i).cost).collect();
        // Slots 0 and 1 were overwritten by 3 and 4; slot 2 still holds 2.
        assert_eq!(costs, vec![3.0, 4.0, 2.0]);
        r.push(t(5.0));
        costs = (0..3).map(|i| r.get(i).cost).collect();
        assert_eq!(costs, vec![3.0, 4.0, 5.0]);
        // Uniform sampling only ever returns what is held, and reaches every slot.
        let mut rng = SmallRng::seed_from_u64(1);
        let mut out = vec![Transition::default(); 3000];
        r.sample_into(&mut rng, &mut out);
        for want in [3.0, 4.0, 5.0] {
            let k = out.iter().filter(|x| x.cost == want).count();
            assert!((800..1200).contains(&k), "{want}: {k}");
        }
        assert!(out.iter().all(|x| [3.0, 4.0, 5.0].contains(&x.cost)));
    }

    #[test]
    fn limiter_follows_reverbs_arithmetic() {
        // spi 2, min size 10, error buffer 20: min_diff 0, max_diff 40.
        let mut l = RateLimiter::new(2.0, 10, 20.0, 4);
        assert_eq!(l.error_buffer(), 20.0);
        assert!(!l.can_sample(1), "nothing before min size");
        // Inserts are free up to min size...
        assert!(l.can_insert(10));
        l.record_inserts(10);
        // ...then allowed while diff = 2 * inserts - samples <= 40: up to 20 inserts with no sample.
        assert!(l.can_insert(10));
        assert!(!l.can_insert(11));
        assert_eq!(l.insert_credit(), 10);
        l.record_inserts(10);
        assert!(!l.can_insert(1));
        assert_eq!(l.insert_credit(), 0);
        // diff 40: samples allowed while diff - n >= 0.
        assert!(l.can_sample(40));
        assert!(!l.can_sample(41));
        l.record_samples(4);
        // Four samples buy two inserts (spi 2).
        assert!(l.can_insert(2));
        assert!(!l.can_insert(3));
        assert_eq!(l.insert_credit(), 2);
        l.record_samples(36);
        assert!(!l.can_sample(1), "the learner waits for data");
        assert!(l.can_insert(20));
    }

    #[test]
    fn limiter_never_deadlocks_on_a_narrow_error_buffer() {
        // error buffer 1 with batches of 64 would block both sides; it is widened.
        let mut l = RateLimiter::new(1.0, 64, 1.0, 64);
        assert!(l.error_buffer() >= 0.5 * (1.0 + 64.0));
        l.record_inserts(64);
        for _ in 0..1000 {
            let (i, s) = (l.can_insert(1), l.can_sample(64));
            assert!(i || s, "deadlock at {l:?}");
            if s {
                l.record_samples(64);
            } else {
                l.record_inserts(1);
            }
        }
    }

    #[test]
    fn non_finite_transitions_are_quarantined_and_counted() {
        let cfg = ReplayConfig { capacity: 10, learning_starts: 2, ..ReplayConfig::default() };
        let mut s = ReplayStore::new(&cfg, 2, 1);
        let mut bad = t(1.0);
        bad.obs[3] = f32::NAN;
        let mut inf = t(1.0);
        inf.cost = f32::INFINITY;
        let h = TransitionBatchHeader { actor_id: 0, len: 4, ..Default::default() };
        s.ingest(&h, &[t(1.0), bad, t(2.0), inf]);
        assert_eq!(s.counters.received_total, 4);
        assert_eq!(s.counters.inserted_total, 2);
        assert_eq!(s.counters.quarantined_total, 2);
        assert_eq!(s.ring.len(), 2);
        let mut out = vec![Transition::default(); 2];
        assert!(s.can_sample(2));
        s.sample_into(&mut out);
        assert!(out.iter().all(|x| x.is_finite()));
        assert_eq!(s.counters.sampled_total, 2);
        assert_eq!(s.counters.batches_served, 1);
    }

    #[test]
    fn sequence_gaps_count_as_dropped_and_restarts_set_a_new_baseline() {
        let cfg = ReplayConfig { capacity: 100, learning_starts: 2, ..ReplayConfig::default() };
        let mut s = ReplayStore::new(&cfg, 2, 1);
        let batch = [t(0.0); 4];
        let h = |epoch, published_before| TransitionBatchHeader {
            actor_id: 3,
            len: 4,
            epoch,
            seq: 0,
            published_before,
            weights_version: 0,
            sent_mono_ns: 0,
        };
        s.ingest(&h(1, 0), &batch);
        s.ingest(&h(1, 4), &batch);
        assert_eq!(s.counters.dropped_total, 0);
        // Message covering 8..12 never arrived.
        s.ingest(&h(1, 12), &batch);
        assert_eq!(s.counters.dropped_total, 4);
        // A restarted actor (new epoch) starts over without a false drop.
        s.ingest(&h(2, 0), &batch);
        assert_eq!(s.counters.dropped_total, 4);
        assert_eq!(s.counters.received_total, 16);
        assert_eq!(s.tracker.actors_seen(), 1);
    }
}
