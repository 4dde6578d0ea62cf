//! The paper's three experiments (Appendix A): grids of degradation parameters and constant loads, each
//! trajectory simulated from its initial state until end of discharge, split by load (never by trajectory)
//! into three sets ([`Split`]): training (the lower loads), test (the paper's held-out highest loads) and a
//! validation set of its own, at a load between the two that is in neither and with parameter values off
//! the training grid. Every choice (hyperparameters, filter settings, early stopping, which checkpoint to
//! deliver) is made on validation; test is only ever reported.
//!
//! Generation runs on every core (rayon) and each split is cached on disk in its own compact binary file
//! keyed by a hash of the experiment's definition, the split and the model parameters: a changed
//! definition lands in a new file, a corrupt file is reported and regenerated, never used, and a process
//! reads only the split it needs (actors the training set, the learner the validation set). This module never prints: it returns what
//! happened ([`CacheStatus`]) and the caller tells the user.

use crate::battery::{BatteryModel, BatteryParams, Degradation, Load, LoadProfile, ModelError};
use crate::fsutil::write_atomic_with;
use crate::hash::fnv1a64;
use crate::math::{electro, N_STATE};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Bumped whenever the file layout or the simulation semantics change, so old caches are never read.
pub const CACHE_FORMAT_VERSION: u32 = 2;
const CACHE_MAGIC: &[u8; 8] = b"BCALDS\0\0";
/// Magic (8) + format version (4) + key (8) + payload length (8) + payload CRC32 (4).
const HEADER_LEN: usize = 32;

/// The three experiments of the paper's Appendix A (the CLI takes them by these kebab-case names).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum Experiment {
    /// qMobile varies (501 values, 4000..7000 C), Ro fixed at 0.117215 ohm, 11 loads 8..16 W.
    SingleQ,
    /// Ro varies (501 values, 0.1..0.2 ohm), qMobile fixed at 7600 C, 11 loads 8..16 W.
    SingleR,
    /// qMobile (101 values) and Ro (5 values) vary together, 9 loads 8..16 W.
    Multi,
}

impl Experiment {
    pub const ALL: [Experiment; 3] = [Experiment::SingleQ, Experiment::SingleR, Experiment::Multi];

    pub fn name(self) -> &'static str {
        match self {
            Experiment::SingleQ => "single-q",
            Experiment::SingleR => "single-r",
            Experiment::Multi => "multi",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|e| e.name() == s)
    }

    /// The paper's definition of this experiment.
    pub fn definition(self) -> ExperimentDef {
        let single_loads = Grid { start: 8.0, end: 16.0, n: 11 };
        match self {
            Experiment::SingleQ => ExperimentDef {
                experiment: self,
                q_mobile_c: Grid { start: 4000.0, end: 7000.0, n: 501 },
                r_o_ohm: Grid::single(0.117215),
                loads_w: single_loads,
                n_test_loads: 4,
                // Off the training grid (4000 + 6 k C) and at 13.2 W, between the training loads (<= 12.8)
                // and the test loads (>= 13.6).
                validation: ValidationDef {
                    loads_w: vec![13.2],
                    q_mobile_c: Grid { start: 4003.0, end: 6997.0, n: 48 },
                    r_o_ohm: Grid::single(0.117215),
                },
                dt_s: 1.0,
                max_steps: 100_000,
            },
            Experiment::SingleR => ExperimentDef {
                experiment: self,
                q_mobile_c: Grid::single(7600.0),
                r_o_ohm: Grid { start: 0.1, end: 0.2, n: 501 },
                loads_w: single_loads,
                n_test_loads: 4,
                validation: ValidationDef {
                    loads_w: vec![13.2],
                    q_mobile_c: Grid::single(7600.0),
                    r_o_ohm: Grid { start: 0.1001, end: 0.1999, n: 48 },
                },
                dt_s: 1.0,
                max_steps: 100_000,
            },
            Experiment::Multi => ExperimentDef {
                experiment: self,
                q_mobile_c: Grid { start: 4000.0, end: 7000.0, n: 101 },
                r_o_ohm: Grid { start: 0.1, end: 0.2, n: 5 },
                loads_w: Grid { start: 8.0, end: 16.0, n: 9 },
                n_test_loads: 3,
                // Half a grid step off both training grids, at 13.5 W (training <= 13, test >= 14).
                validation: ValidationDef {
                    loads_w: vec![13.5],
                    q_mobile_c: Grid { start: 4015.0, end: 6985.0, n: 12 },
                    r_o_ohm: Grid { start: 0.1125, end: 0.1875, n: 4 },
                },
                dt_s: 1.0,
                max_steps: 100_000,
            },
        }
    }
}

impl std::str::FromStr for Experiment {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Self::parse(s).ok_or_else(|| {
            let names: Vec<&str> = Self::ALL.iter().map(|e| e.name()).collect();
            format!("unknown experiment `{s}`; one of {}", names.join(", "))
        })
    }
}

/// Which of the three disjoint sets of an experiment.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Split {
    /// The lower loads of the paper grid: what actors train on and observation scales come from.
    Train,
    /// Its own loads and parameter values: every tuning choice and checkpoint selection.
    Validation,
    /// The paper's held-out highest loads: only ever reported.
    Test,
}

impl Split {
    pub const ALL: [Split; 3] = [Split::Train, Split::Validation, Split::Test];

    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Validation => "validation",
            Split::Test => "test",
        }
    }
}

impl std::fmt::Display for Split {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The validation set of an experiment: loads in neither training nor test, parameters off the grid.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ValidationDef {
    pub loads_w: Vec<f64>,
    pub q_mobile_c: Grid,
    pub r_o_ohm: Grid,
}

impl std::fmt::Display for Experiment {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// `n` equally spaced values from `start` to `end`, both included (one value when `n` is 1).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Grid {
    pub start: f64,
    pub end: f64,
    pub n: usize,
}

impl Grid {
    pub fn single(v: f64) -> Self {
        Grid { start: v, end: v, n: 1 }
    }

    pub fn value(&self, k: usize) -> f64 {
        if self.n <= 1 {
            self.start
        } else {
            self.start + (self.end - self.start) * k as f64 / (self.n - 1) as f64
        }
    }

    pub fn values(&self) -> impl Iterator<Item = f64> + '_ {
        (0..self.n).map(|k| self.value(k))
    }
}

/// Everything that determines an experiment's trajectories; its hash keys the cache.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExperimentDef {
    pub experiment: Experiment,
    pub q_mobile_c: Grid,
    pub r_o_ohm: Grid,
    pub loads_w: Grid,
    /// The highest `n_test_loads` loads form the test set (extrapolation to unseen loads).
    pub n_test_loads: usize,
    /// The validation set, generated apart from the grid.
    pub validation: ValidationDef,
    pub dt_s: f64,
    /// Safety stop for a trajectory that never reaches EOD (an error, not a silent truncation).
    pub max_steps: usize,
}

impl ExperimentDef {
    /// Trajectories of the paper grid (training and test together).
    pub fn n_trajectories(&self) -> usize {
        self.q_mobile_c.n * self.r_o_ohm.n * self.loads_w.n
    }

    /// (degradation, load) of every trajectory of `split`, q-major, then Ro, then load.
    pub fn combos(&self, split: Split) -> Vec<(Degradation, f64)> {
        let (q_grid, r_grid, loads): (&Grid, &Grid, Vec<f64>) = match split {
            Split::Train => (&self.q_mobile_c, &self.r_o_ohm, self.train_loads_w()),
            Split::Test => (&self.q_mobile_c, &self.r_o_ohm, self.test_loads_w()),
            Split::Validation => {
                (&self.validation.q_mobile_c, &self.validation.r_o_ohm, self.validation.loads_w.clone())
            }
        };
        let mut combos = Vec::with_capacity(q_grid.n * r_grid.n * loads.len());
        for q in q_grid.values() {
            for r in r_grid.values() {
                for l in &loads {
                    combos.push((Degradation { q_mobile_c: q, r_o_ohm: r }, *l));
                }
            }
        }
        combos
    }

    /// The smallest test load, W: trajectories at or above it are test trajectories.
    pub fn first_test_load_w(&self) -> f64 {
        self.loads_w.value(self.loads_w.n - self.n_test_loads)
    }

    pub fn is_test_load(&self, load_w: f64) -> bool {
        // Half a grid step of tolerance: the loads are grid values, never in between.
        let half_step = (self.loads_w.end - self.loads_w.start) / (2.0 * (self.loads_w.n.max(2) - 1) as f64);
        load_w > self.first_test_load_w() - half_step
    }

    pub fn test_loads_w(&self) -> Vec<f64> {
        self.loads_w.values().filter(|l| self.is_test_load(*l)).collect()
    }

    pub fn train_loads_w(&self) -> Vec<f64> {
        self.loads_w.values().filter(|l| !self.is_test_load(*l)).collect()
    }

    /// Cache key of one split: a stable hash over the serialised definition, split, model parameters and
    /// format version.
    pub fn cache_key(&self, split: Split, params: &BatteryParams) -> u64 {
        let bytes =
            bincode::serde::encode_to_vec((CACHE_FORMAT_VERSION, self, split, params), bincode::config::standard())
                .expect("definitions always serialise");
        fnv1a64(&bytes)
    }
}

/// One constant-load discharge from the initial state to the first step below VEOD.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Trajectory {
    /// The true degradation: seen only by the data generator, the evaluator and supervised baselines.
    pub degradation: Degradation,
    pub load_w: f64,
    /// Seven-state vector at t = 0, dt, 2 dt, ... through the EOD row; f32 halves the file and is far below
    /// any noise the calibrators meet.
    pub states: Vec<[f32; N_STATE]>,
    /// Terminal voltage at each row, V.
    pub voltage_v: Vec<f32>,
}

impl Trajectory {
    pub fn len(&self) -> usize {
        self.states.len()
    }

    pub fn is_empty(&self) -> bool {
        self.states.is_empty()
    }

    /// End-of-discharge time, s (the time of the last row).
    pub fn eod_s(&self, dt_s: f64) -> f64 {
        (self.states.len().saturating_sub(1)) as f64 * dt_s
    }
}

/// One split of a generated experiment: its definition and the split's trajectories, ordered q-major, then
/// Ro, then load.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Dataset {
    pub def: ExperimentDef,
    pub split: Split,
    pub trajectories: Vec<Trajectory>,
}

impl Dataset {
    /// `k` trajectories spread evenly over the split (all of them when k is 0 or >= their number).
    pub fn spread_indices(&self, k: usize) -> Vec<usize> {
        let n = self.trajectories.len();
        let k = if k == 0 { n } else { k.min(n) };
        (0..k).map(|i| i * n / k).collect()
    }

    pub fn total_steps(&self) -> usize {
        self.trajectories.iter().map(|t| t.len()).sum()
    }

    /// The loads of the split, sorted, each once.
    pub fn loads_w(&self) -> Vec<f64> {
        let mut loads: Vec<f64> = self.trajectories.iter().map(|t| t.load_w).collect();
        loads.sort_by(f64::total_cmp);
        loads.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
        loads
    }
}

#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error("trajectory q_mobile {q_mobile_c} C, Ro {r_o_ohm} ohm, load {load_w} W did not reach EOD within {max_steps} steps")]
    NoEod { q_mobile_c: f64, r_o_ohm: f64, load_w: f64, max_steps: usize },
    #[error("the {split} split of experiment {experiment} is empty; its definition puts no trajectory in it")]
    EmptySplit { experiment: Experiment, split: Split },
    #[error("cannot {action} dataset cache {path}: {source}; check that the folder exists and is writable (or set --cache-dir)")]
    Io { action: &'static str, path: PathBuf, source: std::io::Error },
}

/// Why a cache file was not used.
#[derive(Clone, Debug, PartialEq)]
pub enum CacheStatus {
    /// Read from a valid cache file.
    Hit,
    /// No cache file existed: generated and written.
    Generated,
    /// A cache file existed but was corrupt (`reason`): regenerated and overwritten.
    Regenerated { reason: String },
}

/// What `load_or_generate` did, for the caller to report.
#[derive(Clone, Debug)]
pub struct LoadReport {
    pub path: PathBuf,
    pub status: CacheStatus,
    pub seconds: f64,
    pub file_bytes: u64,
}

/// Simulates every trajectory of one split of `def` on all cores.
pub fn generate(def: &ExperimentDef, model: &BatteryModel, split: Split) -> Result<Dataset, DatasetError> {
    let combos = def.combos(split);
    if combos.is_empty() {
        return Err(DatasetError::EmptySplit { experiment: def.experiment, split });
    }
    let trajectories = combos
        .into_par_iter()
        .map(|(d, load_w)| simulate_trajectory(model, &d, load_w, def.dt_s, def.max_steps))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Dataset { def: def.clone(), split, trajectories })
}

/// One constant-power trajectory from the degradation's initial state to EOD.
pub fn simulate_trajectory(
    model: &BatteryModel,
    d: &Degradation,
    load_w: f64,
    dt_s: f64,
    max_steps: usize,
) -> Result<Trajectory, DatasetError> {
    let mut states = Vec::with_capacity(4096);
    let mut voltage_v = Vec::with_capacity(4096);
    let out = model.simulate_until_eod(
        &model.initial_state(d),
        d,
        &LoadProfile::Constant(Load::PowerW(load_w)),
        dt_s,
        max_steps,
        |r| {
            let e = electro(&r.x);
            states.push(std::array::from_fn(|k| e[k] as f32));
            voltage_v.push(r.voltage_v as f32);
        },
    )?;
    if out.eod_s.is_none() {
        return Err(DatasetError::NoEod { q_mobile_c: d.q_mobile_c, r_o_ohm: d.r_o_ohm, load_w, max_steps });
    }
    states.shrink_to_fit();
    voltage_v.shrink_to_fit();
    Ok(Trajectory { degradation: *d, load_w, states, voltage_v })
}

/// The cache file of one split of `def` under `cache_dir`.
pub fn cache_path(cache_dir: &Path, def: &ExperimentDef, split: Split, params: &BatteryParams) -> PathBuf {
    cache_dir.join(format!("{}-{}-{:016x}.bcalds", def.experiment.name(), split.name(), def.cache_key(split, params)))
}

/// The default cache folder: `$BCAL_CACHE/datasets`, else `$HOME/.cache/bcal/datasets`, else `.cache/datasets`.
pub fn default_cache_dir() -> PathBuf {
    if let Some(c) = std::env::var_os("BCAL_CACHE") {
        return PathBuf::from(c).join("datasets");
    }
    match std::env::var_os("HOME") {
        Some(h) => PathBuf::from(h).join(".cache/bcal/datasets"),
        None => PathBuf::from(".cache/datasets"),
    }
}

/// Reads the cached split of `def`, or generates and caches it. A corrupt cache file is regenerated and
/// the reason returned in the report.
pub fn load_or_generate(
    def: &ExperimentDef,
    model: &BatteryModel,
    cache_dir: &Path,
    split: Split,
) -> Result<(Dataset, LoadReport), DatasetError> {
    let started = Instant::now();
    let path = cache_path(cache_dir, def, split, &model.params);
    let key = def.cache_key(split, &model.params);
    let mut status = CacheStatus::Generated;
    if path.exists() {
        match read_cache(&path, key) {
            Ok(ds) if ds.def == *def && ds.split == split => {
                let file_bytes = fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
                let seconds = started.elapsed().as_secs_f64();
                return Ok((ds, LoadReport { path, status: CacheStatus::Hit, seconds, file_bytes }));
            }
            Ok(_) => status = CacheStatus::Regenerated { reason: "definition differs from the file name's key".into() },
            Err(reason) => status = CacheStatus::Regenerated { reason },
        }
    }
    let ds = generate(def, model, split)?;
    let file_bytes = write_cache(&path, key, &ds)?;
    let seconds = started.elapsed().as_secs_f64();
    Ok((ds, LoadReport { path, status, seconds, file_bytes }))
}

/// Writes the dataset atomically so a crash never leaves a half file under the final name. Returns the
/// file size in bytes.
pub fn write_cache(path: &Path, key: u64, ds: &Dataset) -> Result<u64, DatasetError> {
    let io = |action, source| DatasetError::Io { action, path: path.to_path_buf(), source };
    if let Some(dir) = path.parent() {
        fs::create_dir_all(dir).map_err(|e| io("create the folder of", e))?;
    }
    let payload = bincode::serde::encode_to_vec(ds, bincode::config::standard()).expect("datasets always serialise");
    let mut header = Vec::with_capacity(HEADER_LEN);
    header.extend_from_slice(CACHE_MAGIC);
    header.extend_from_slice(&CACHE_FORMAT_VERSION.to_le_bytes());
    header.extend_from_slice(&key.to_le_bytes());
    header.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    header.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
    write_atomic_with(path, |f| {
        f.write_all(&header)?;
        f.write_all(&payload)
    })
    .map_err(|e| io("write", e))?;
    Ok((HEADER_LEN + payload.len()) as u64)
}

/// Reads and verifies a cache file; the error is a human-readable reason the file cannot be used.
pub fn read_cache(path: &Path, key: u64) -> Result<Dataset, String> {
    let bytes = fs::read(path).map_err(|e| format!("unreadable: {e}"))?;
    if bytes.len() < HEADER_LEN {
        return Err(format!("truncated: {} bytes, shorter than the {HEADER_LEN}-byte header", bytes.len()));
    }
    if &bytes[0..8] != CACHE_MAGIC {
        return Err("not a bcal dataset file (bad magic)".into());
    }
    let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
    let u64_at = |o: usize| u64::from_le_bytes(bytes[o..o + 8].try_into().expect("8 bytes"));
    let version = u32_at(8);
    if version != CACHE_FORMAT_VERSION {
        return Err(format!("format version {version}, this build reads {CACHE_FORMAT_VERSION}"));
    }
    if u64_at(12) != key {
        return Err("key differs from the experiment definition".into());
    }
    let len = u64_at(20) as usize;
    let payload = &bytes[HEADER_LEN..];
    if payload.len() != len {
        return Err(format!("truncated or padded: payload {} bytes, header says {len}", payload.len()));
    }
    if crc32fast::hash(payload) != u32_at(28) {
        return Err("checksum mismatch (the file is corrupt)".into());
    }
    let (ds, used): (Dataset, usize) = bincode::serde::decode_from_slice(payload, bincode::config::standard())
        .map_err(|e| format!("undecodable payload: {e}"))?;
    if used != len {
        return Err("trailing bytes after the payload".into());
    }
    Ok(ds)
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn tiny_def() -> ExperimentDef {
        ExperimentDef {
            experiment: Experiment::Multi,
            q_mobile_c: Grid { start: 4000.0, end: 7000.0, n: 3 },
            r_o_ohm: Grid { start: 0.1, end: 0.2, n: 2 },
            loads_w: Grid { start: 8.0, end: 16.0, n: 9 },
            n_test_loads: 3,
            validation: ValidationDef {
                loads_w: vec![13.5],
                q_mobile_c: Grid { start: 4500.0, end: 6500.0, n: 2 },
                r_o_ohm: Grid { start: 0.125, end: 0.175, n: 2 },
            },
            dt_s: 1.0,
            max_steps: 100_000,
        }
    }

    #[test]
    fn paper_grids_sizes_and_load_split() {
        let q = Experiment::SingleQ.definition();
        assert_eq!(q.n_trajectories(), 5511);
        assert_eq!(q.q_mobile_c.value(1), 4006.0);
        assert_eq!(q.q_mobile_c.value(500), 7000.0);
        let loads: Vec<f64> = q.loads_w.values().map(|l| (l * 10.0).round() / 10.0).collect();
        assert_eq!(loads, vec![8.0, 8.8, 9.6, 10.4, 11.2, 12.0, 12.8, 13.6, 14.4, 15.2, 16.0]);
        let test: Vec<f64> = q.test_loads_w().iter().map(|l| (l * 10.0).round() / 10.0).collect();
        assert_eq!(test, vec![13.6, 14.4, 15.2, 16.0]);
        assert_eq!(q.train_loads_w().len(), 7);
        assert_eq!(q.combos(Split::Train).len() + q.combos(Split::Test).len(), 5511);

        let r = Experiment::SingleR.definition();
        assert_eq!(r.n_trajectories(), 5511);
        assert!((r.r_o_ohm.value(1) - 0.1002).abs() < 1e-12);

        let m = Experiment::Multi.definition();
        assert_eq!(m.n_trajectories(), 101 * 5 * 9);
        assert_eq!(m.q_mobile_c.value(1), 4030.0);
        assert_eq!(m.test_loads_w(), vec![14.0, 15.0, 16.0]);
        assert_eq!(m.train_loads_w(), vec![8.0, 9.0, 10.0, 11.0, 12.0, 13.0]);
    }

    /// The validation set shares no load with training or test and no parameter value with the grid.
    #[test]
    fn validation_loads_and_parameters_are_in_neither_training_nor_test() {
        for e in Experiment::ALL {
            let def = e.definition();
            let val = def.combos(Split::Validation);
            assert!(val.len() >= 48, "{e}: {} validation trajectories", val.len());
            let max_train = def.train_loads_w().into_iter().fold(0.0, f64::max);
            let min_test = def.test_loads_w().into_iter().fold(f64::INFINITY, f64::min);
            let off = |v: f64, g: &Grid| {
                g.n == 1 || g.values().all(|x| (x - v).abs() > 1e-3 * (g.end - g.start) / g.n as f64)
            };
            for (d, l) in &val {
                assert!(*l > max_train && *l < min_test, "{e}: validation load {l}");
                assert!(off(d.q_mobile_c, &def.q_mobile_c) && off(d.r_o_ohm, &def.r_o_ohm), "{e}: {d:?} on the grid");
            }
        }
    }

    #[test]
    fn generated_splits_hold_their_loads_and_reach_eod() {
        let def = tiny_def();
        let model = BatteryModel::default();
        let train = generate(&def, &model, Split::Train).unwrap();
        let test = generate(&def, &model, Split::Test).unwrap();
        let val = generate(&def, &model, Split::Validation).unwrap();
        assert_eq!((train.trajectories.len(), test.trajectories.len(), val.trajectories.len()), (36, 18, 4));
        assert!(test.trajectories.iter().all(|t| t.load_w >= 14.0));
        assert!(train.trajectories.iter().all(|t| t.load_w <= 13.0));
        assert_eq!(val.loads_w(), vec![13.5]);
        for t in train.trajectories.iter().chain(&test.trajectories).chain(&val.trajectories) {
            let n = t.len();
            assert!(t.voltage_v[n - 1] < 3.0 && t.voltage_v[..n - 1].iter().all(|v| *v >= 3.0));
        }
        // More capacity lasts longer at the same load and resistance.
        let eod = |q: f64| {
            train.trajectories.iter().find(|t| t.degradation.q_mobile_c == q && t.load_w == 8.0).unwrap().len()
        };
        assert!(eod(7000.0) > eod(5500.0) && eod(5500.0) > eod(4000.0));
        assert_eq!(train.spread_indices(4), vec![0, 9, 18, 27]);
        assert_eq!(train.spread_indices(0).len(), 36);
    }

    #[test]
    fn cache_roundtrip_hit_and_changed_definition_regenerates() {
        let dir = tempfile::tempdir().unwrap();
        let model = BatteryModel::default();
        let def = tiny_def();
        let (a, r1) = load_or_generate(&def, &model, dir.path(), Split::Train).unwrap();
        assert_eq!(r1.status, CacheStatus::Generated);
        let (b, r2) = load_or_generate(&def, &model, dir.path(), Split::Train).unwrap();
        assert_eq!(r2.status, CacheStatus::Hit);
        assert_eq!(a, b);
        // Each split has its own file.
        let (v, rv) = load_or_generate(&def, &model, dir.path(), Split::Validation).unwrap();
        assert_eq!((rv.status, v.split), (CacheStatus::Generated, Split::Validation));
        assert_ne!(rv.path, r1.path);
        let changed = ExperimentDef { loads_w: Grid { start: 8.0, end: 12.0, n: 5 }, n_test_loads: 1, ..def.clone() };
        assert_ne!(cache_path(dir.path(), &changed, Split::Train, &model.params), r1.path);
        let (c, r3) = load_or_generate(&changed, &model, dir.path(), Split::Train).unwrap();
        assert_eq!(r3.status, CacheStatus::Generated);
        assert_eq!(c.trajectories.len(), 3 * 2 * 4);
        // Different model parameters are a different key too.
        let p2 = BatteryParams { t_diffusion_s: 6e6, ..BatteryParams::default() };
        assert_ne!(def.cache_key(Split::Train, &p2), def.cache_key(Split::Train, &model.params));
    }

    #[test]
    fn corrupt_cache_is_reported_and_regenerated() {
        let dir = tempfile::tempdir().unwrap();
        let model = BatteryModel::default();
        let def = tiny_def();
        let (good, r) = load_or_generate(&def, &model, dir.path(), Split::Test).unwrap();
        let bytes = fs::read(&r.path).unwrap();

        // Each damage must be named and must not be used.
        let flip = |at: usize, v: Option<u8>| {
            let mut b = bytes.clone();
            b[at] = v.unwrap_or(b[at] ^ 0x55);
            b
        };
        let damages: Vec<(Vec<u8>, &str)> = vec![
            (flip(bytes.len() / 2, None), "checksum"),
            (bytes[..bytes.len() - 10].to_vec(), "truncated"),
            (bytes[..10].to_vec(), "truncated"),
            (flip(0, Some(b'X')), "magic"),
            (flip(8, Some(99)), "format version"),
        ];
        for (damaged, why) in damages {
            fs::write(&r.path, &damaged).unwrap();
            let (ds, rep) = load_or_generate(&def, &model, dir.path(), Split::Test).unwrap();
            match &rep.status {
                CacheStatus::Regenerated { reason } => assert!(reason.contains(why), "{why}: got {reason}"),
                s => panic!("{why}: expected regeneration, got {s:?}"),
            }
            assert_eq!(ds, good);
            // And the regenerated file is valid again.
            assert_eq!(load_or_generate(&def, &model, dir.path(), Split::Test).unwrap().1.status, CacheStatus::Hit);
        }
    }

    #[test]
    fn unwritable_cache_folder_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let blocker = dir.path().join("file");
        fs::write(&blocker, b"x").unwrap();
        let err =
            load_or_generate(&tiny_def(), &BatteryModel::default(), &blocker.join("sub"), Split::Train).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("cannot") && msg.contains("sub"), "{msg}");
    }
}
