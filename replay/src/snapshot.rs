//! Replay-buffer snapshots (`replay.snapshot_every_s` > 0): the ring buffer, the limiter's counts and the
//! replay counters saved to `DIR/replay/snapshot.bin`, so a replay restarted after a crash resumes with the
//! transitions already paid for instead of refilling from empty.
//!
//! Format (little-endian): a fixed header — magic, format version, [`WIRE_VERSION`], the size of one
//! [`Transition`], capacity, next slot, length, the seven [`ReplayCounters`], the limiter's inserts and
//! samples, and a CRC-32 of everything after it — then the transitions as raw `repr(C)` bytes. Written to
//! a temporary name, fsynced and renamed, so the previous snapshot survives a crash or a full disk.

use crate::store::{ReplayStore, RingBuffer};
use bcal_common::wire::{ReplayCounters, Transition, WIRE_VERSION};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

const MAGIC: [u8; 8] = *b"BCALRPL\0";
const FORMAT_VERSION: u32 = 1;
/// u64 fields of the header after magic and the four u32s: capacity, next, len, 7 counters, inserts,
/// samples.
const HEADER_U64S: usize = 3 + 7 + 2;
const HEADER_LEN: usize = 8 + 4 * 4 + 8 * HEADER_U64S + 4;

#[derive(Debug, thiserror::Error)]
pub enum SnapshotError {
    #[error("cannot read snapshot {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error(
        "cannot write snapshot {path}: {source} (disk full or folder not writable?); the previous snapshot is kept"
    )]
    Write { path: PathBuf, source: std::io::Error },
    #[error("snapshot {path} is unusable: {why}")]
    Invalid { path: PathBuf, why: String },
}

/// Everything a snapshot holds.
#[derive(Clone, Debug, PartialEq)]
pub struct Snapshot {
    pub capacity: usize,
    pub next: usize,
    pub items: Vec<Transition>,
    pub counters: ReplayCounters,
    pub inserts: u64,
    pub samples: u64,
}

/// `DIR/replay/snapshot.bin`.
pub fn path(run_dir: &Path) -> PathBuf {
    run_dir.join("replay").join("snapshot.bin")
}

impl Snapshot {
    /// A copy of the store's state (the copy is what a background thread writes while the loop goes on).
    pub fn of(store: &ReplayStore) -> Self {
        let (items, next) = store.ring.parts();
        let (inserts, samples) = store.limiter.counts();
        Self {
            capacity: store.ring.capacity(),
            next,
            items: items.to_vec(),
            counters: store.counters,
            inserts,
            samples,
        }
    }

    /// Puts the snapshot's state into a freshly made store; refuses a capacity other than the store's
    /// (the config changed between runs).
    pub fn restore_into(self, store: &mut ReplayStore) -> Result<usize, String> {
        if self.capacity != store.ring.capacity() {
            return Err(format!(
                "its capacity is {} but replay.capacity is now {}",
                self.capacity,
                store.ring.capacity()
            ));
        }
        let n = self.items.len();
        store.ring = RingBuffer::from_parts(self.capacity, self.items, self.next)
            .ok_or_else(|| "its ring-buffer fields are inconsistent".to_string())?;
        store.limiter.restore_counts(self.inserts, self.samples);
        store.counters = ReplayCounters { size: n as u64, ..self.counters };
        Ok(n)
    }

    fn header_u64s(&self) -> [u64; HEADER_U64S] {
        let c = &self.counters;
        [
            self.capacity as u64,
            self.next as u64,
            self.items.len() as u64,
            c.received_total,
            c.inserted_total,
            c.quarantined_total,
            c.dropped_total,
            c.sampled_total,
            c.batches_served,
            c.size,
            self.inserts,
            self.samples,
        ]
    }

    /// Writes the snapshot atomically ([`bcal_common::fsutil`]).
    pub fn save(&self, path: &Path) -> Result<(), SnapshotError> {
        let werr = |source| SnapshotError::Write { path: path.to_path_buf(), source };
        let dir = path.parent().unwrap_or(Path::new("."));
        std::fs::create_dir_all(dir).map_err(werr)?;
        let mut head = Vec::with_capacity(HEADER_LEN);
        head.extend_from_slice(&MAGIC);
        for v in [FORMAT_VERSION, WIRE_VERSION, std::mem::size_of::<Transition>() as u32, 0] {
            head.extend_from_slice(&v.to_le_bytes());
        }
        for v in self.header_u64s() {
            head.extend_from_slice(&v.to_le_bytes());
        }
        let body = transition_bytes(&self.items);
        let mut crc = crc32fast::Hasher::new();
        crc.update(&head[8..]);
        crc.update(body);
        head.extend_from_slice(&crc.finalize().to_le_bytes());
        debug_assert_eq!(head.len(), HEADER_LEN);

        bcal_common::fsutil::write_atomic_with(path, |f| {
            f.write_all(&head)?;
            f.write_all(body)
        })
        .map_err(werr)
    }

    /// Reads and checks a snapshot (magic, versions, sizes, CRC); every refusal says why.
    pub fn load(path: &Path) -> Result<Self, SnapshotError> {
        let invalid = |why: String| SnapshotError::Invalid { path: path.to_path_buf(), why };
        let mut f = std::fs::File::open(path).map_err(|source| SnapshotError::Read { path: path.into(), source })?;
        let mut head = [0u8; HEADER_LEN];
        f.read_exact(&mut head).map_err(|_| invalid("shorter than its header (truncated)".into()))?;
        if head[..8] != MAGIC {
            return Err(invalid("not a bcal replay snapshot (bad magic)".into()));
        }
        let u32_at = |i: usize| u32::from_le_bytes(head[8 + 4 * i..12 + 4 * i].try_into().expect("4 bytes"));
        let (format, wire, t_size) = (u32_at(0), u32_at(1), u32_at(2));
        if format != FORMAT_VERSION {
            return Err(invalid(format!("format version {format}, this build reads {FORMAT_VERSION}")));
        }
        if wire != WIRE_VERSION || t_size as usize != std::mem::size_of::<Transition>() {
            return Err(invalid(format!(
                "written with wire version {wire} ({t_size}-byte transitions); this build has version {WIRE_VERSION} \
                 ({}-byte transitions)",
                std::mem::size_of::<Transition>()
            )));
        }
        let u64_at = |i: usize| u64::from_le_bytes(head[24 + 8 * i..32 + 8 * i].try_into().expect("8 bytes"));
        let h: Vec<u64> = (0..HEADER_U64S).map(u64_at).collect();
        let stored_crc = u32::from_le_bytes(head[HEADER_LEN - 4..].try_into().expect("4 bytes"));
        let (capacity, next, len) = (h[0], h[1], h[2]);
        let file_len = f.metadata().map_err(|source| SnapshotError::Read { path: path.into(), source })?.len();
        let expected = HEADER_LEN as u64 + len.saturating_mul(std::mem::size_of::<Transition>() as u64);
        if len > capacity || file_len != expected {
            return Err(invalid(format!(
                "{len} transitions of capacity {capacity} need {expected} bytes, the file has {file_len} (truncated?)"
            )));
        }
        let mut items = vec![Transition::default(); len as usize];
        f.read_exact(transition_bytes_mut(&mut items))
            .map_err(|source| SnapshotError::Read { path: path.into(), source })?;
        let mut crc = crc32fast::Hasher::new();
        crc.update(&head[8..HEADER_LEN - 4]);
        crc.update(transition_bytes(&items));
        if crc.finalize() != stored_crc {
            return Err(invalid("CRC mismatch (the file was damaged)".into()));
        }
        Ok(Self {
            capacity: capacity as usize,
            next: next as usize,
            items,
            counters: ReplayCounters {
                received_total: h[3],
                inserted_total: h[4],
                quarantined_total: h[5],
                dropped_total: h[6],
                sampled_total: h[7],
                batches_served: h[8],
                size: h[9],
            },
            inserts: h[10],
            samples: h[11],
        })
    }
}

fn transition_bytes(items: &[Transition]) -> &[u8] {
    // SAFETY: Transition is repr(C) plain f32 data without padding (wire.rs asserts its size), so its
    // memory is fully initialised bytes; the slice covers exactly the items.
    unsafe { std::slice::from_raw_parts(items.as_ptr().cast::<u8>(), std::mem::size_of_val(items)) }
}

fn transition_bytes_mut(items: &mut [Transition]) -> &mut [u8] {
    // SAFETY: as above; and every bit pattern is a valid f32, so any bytes written make valid Transitions.
    unsafe { std::slice::from_raw_parts_mut(items.as_mut_ptr().cast::<u8>(), std::mem::size_of_val(items)) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::config::ReplayConfig;
    use bcal_common::wire::TransitionBatchHeader;

    fn store_with(n: usize, capacity: usize) -> ReplayStore {
        let cfg = ReplayConfig { capacity, learning_starts: 4, ..ReplayConfig::default() };
        let mut s = ReplayStore::new(&cfg, 2, 1);
        let batch: Vec<Transition> = (0..n).map(|i| Transition { cost: i as f32, ..Transition::default() }).collect();
        s.ingest(&TransitionBatchHeader { len: n as u32, ..Default::default() }, &batch);
        let mut out = [Transition::default(); 2];
        s.sample_into(&mut out);
        s
    }

    #[test]
    fn a_wrapped_buffer_round_trips_with_its_counters_and_limiter() {
        let dir = tempfile::tempdir().unwrap();
        let p = path(dir.path());
        let store = store_with(13, 10); // wrapped: next = 3
        let snap = Snapshot::of(&store);
        snap.save(&p).unwrap();
        let back = Snapshot::load(&p).unwrap();
        assert_eq!(back, snap);
        let mut fresh = ReplayStore::new(&ReplayConfig { capacity: 10, ..ReplayConfig::default() }, 2, 9);
        assert_eq!(back.restore_into(&mut fresh).unwrap(), 10);
        assert_eq!(fresh.ring.parts(), store.ring.parts());
        assert_eq!(fresh.limiter.counts(), store.limiter.counts());
        assert_eq!(fresh.counters, store.counters);
        // The next insert overwrites the oldest slot, as it would have before the crash.
        assert_eq!(fresh.ring.parts().1, 3);
    }

    #[test]
    fn damaged_truncated_or_foreign_snapshots_are_refused_with_the_reason() {
        let dir = tempfile::tempdir().unwrap();
        let p = path(dir.path());
        Snapshot::of(&store_with(6, 10)).save(&p).unwrap();
        let good = std::fs::read(&p).unwrap();
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (good[..good.len() - 5].to_vec(), "truncated"),
            (good[..20].to_vec(), "header"),
            (
                {
                    let mut b = good.clone();
                    let last = b.len() - 1;
                    b[last] ^= 0x40;
                    b
                },
                "CRC",
            ),
            (
                {
                    let mut b = good.clone();
                    b[0] = b'X';
                    b
                },
                "magic",
            ),
            (
                {
                    let mut b = good.clone();
                    b[12..16].copy_from_slice(&(WIRE_VERSION + 1).to_le_bytes());
                    b
                },
                "wire version",
            ),
        ];
        for (bytes, want) in cases {
            std::fs::write(&p, &bytes).unwrap();
            let e = Snapshot::load(&p).unwrap_err().to_string();
            assert!(e.contains(want) && e.contains("snapshot.bin"), "{want}: {e}");
        }
        // A capacity change between runs is refused, not silently truncated.
        Snapshot::of(&store_with(6, 10)).save(&p).unwrap();
        let mut other = ReplayStore::new(&ReplayConfig { capacity: 20, ..ReplayConfig::default() }, 2, 1);
        let e = Snapshot::load(&p).unwrap().restore_into(&mut other).unwrap_err();
        assert!(e.contains("capacity"), "{e}");
    }

    #[test]
    fn a_failed_write_keeps_the_previous_snapshot() {
        let dir = tempfile::tempdir().unwrap();
        let p = path(dir.path());
        let first = Snapshot::of(&store_with(4, 10));
        first.save(&p).unwrap();
        // The temporary file cannot be created where a folder of that name stands.
        std::fs::create_dir(bcal_common::fsutil::temporary_path(&p)).unwrap();
        let e = Snapshot::of(&store_with(8, 10)).save(&p).unwrap_err();
        assert!(matches!(e, SnapshotError::Write { .. }) && e.to_string().contains("previous snapshot is kept"), "{e}");
        assert_eq!(Snapshot::load(&p).unwrap(), first);
    }
}
