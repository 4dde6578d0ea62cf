//! Checkpoints of the LAC learner: `run_dir/checkpoints/step-<N>/` holds the four networks and the two
//! log-multipliers as safetensors (readable from Python with `safetensors.torch.load_file`) and a
//! `meta.json` (update step, experiment, network shape, fingerprint, LAC config, CRC32 of every file).
//! `run_dir/checkpoints/LATEST` names the newest complete folder; it is the only thing `--resume` trusts.
//!
//! Atomicity: a checkpoint is written into a hidden temporary folder, every file and the folder fsynced,
//! then renamed to `step-<N>`; only then is `LATEST` replaced ([`bcal_common::fsutil`]). A crash at
//! any moment leaves `LATEST` naming an intact folder (or no `LATEST` at all). The two newest step
//! folders are kept; older ones and stale temporary folders are removed on a best-effort basis.
//!
//! What is NOT restored: Adam's moment estimates (they re-warm within a few hundred updates) and
//! libtorch's random generator (it is reseeded from the config seed and the step). The update counter,
//! the quarantine counter, the seconds trained, all weights, both targets, lambda and beta are restored
//! exactly.

use crate::lac::{Lac, LacError};
use bcal_common::config::{LacConfig, Validated};
use bcal_common::dataset::Experiment;
use bcal_common::fsutil::{sync_dir, write_atomic};
use bcal_common::policy::PolicyLayout;
use bcal_common::text::shown;
use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::path::{Path, PathBuf};
use tch::{nn, Kind, Tensor};

/// Folder under the run folder that holds the step folders.
pub const CHECKPOINTS_DIR: &str = "checkpoints";
/// File in [`CHECKPOINTS_DIR`] naming the newest complete step folder.
pub const LATEST_FILE: &str = "LATEST";
/// Step folders kept after a successful checkpoint.
pub const KEEP_CHECKPOINTS: usize = 2;
/// Version of the folder's layout; bump when files or names change.
pub const CHECKPOINT_FORMAT: u32 = 1;

const META_FILE: &str = "meta.json";
const ACTOR_FILE: &str = "actor.safetensors";
const CRITIC_FILE: &str = "critic.safetensors";
const ACTOR_TARGET_FILE: &str = "actor_target.safetensors";
const CRITIC_TARGET_FILE: &str = "critic_target.safetensors";
/// Holds the scalars `log_lambda` and `log_beta`.
const MULTIPLIERS_FILE: &str = "multipliers.safetensors";
const TENSOR_FILES: [&str; 5] = [ACTOR_FILE, CRITIC_FILE, ACTOR_TARGET_FILE, CRITIC_TARGET_FILE, MULTIPLIERS_FILE];

/// `meta.json`.
#[derive(Debug, serde::Serialize, serde::Deserialize)]
pub struct CheckpointMeta {
    pub format: u32,
    pub update_step: u64,
    pub quarantined: u64,
    pub experiment: Experiment,
    pub layout: PolicyLayout,
    /// [`PolicyLayout::fingerprint`] of `layout`.
    pub fingerprint: u64,
    pub lac: LacConfig,
    /// lr of lambda and beta actually used (`lac.lr_multipliers`, 0 meaning lr / 10, resolved).
    pub lr_multipliers: f64,
    /// H_target actually used (`lac.target_entropy`, None meaning the per-action default, resolved).
    pub target_entropy: f64,
    /// Seconds of training before this checkpoint, across restarts (absent in older checkpoints: 0).
    #[serde(default)]
    pub trained_s: f64,
    /// CRC32 of every tensor file, by file name.
    pub files: BTreeMap<String, u32>,
}

fn io_err(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> LacError {
    let path = path.to_path_buf();
    move |source| LacError::CheckpointIo { action, path, source }
}

// The reason may quote the damaged file (a parser's "unknown variant ..."): shown escaped and cut.
fn corrupt(path: &Path, why: impl Into<String>) -> LacError {
    LacError::CheckpointCorrupt { path: path.to_path_buf(), why: shown(&why.into(), 400) }
}

fn mismatch(path: &Path, why: impl Into<String>) -> LacError {
    LacError::CheckpointMismatch { path: path.to_path_buf(), why: shown(&why.into(), 400) }
}

/// Bound on a loaded log multiplier (log_lambda, log_beta); see [`Lac::load_latest`].
const LOG_MULTIPLIER_LIMIT: f64 = 80.0;

fn step_folder_name(step: u64) -> String {
    format!("step-{step}")
}

fn parse_step_folder(name: &str) -> Option<u64> {
    name.strip_prefix("step-")?.parse().ok()
}

fn fsync_file(path: &Path) -> Result<(), LacError> {
    std::fs::File::open(path).and_then(|f| f.sync_all()).map_err(io_err("fsync", path))
}

fn crc_of(path: &Path) -> Result<u32, LacError> {
    Ok(crc32fast::hash(&std::fs::read(path).map_err(io_err("read", path))?))
}

impl Lac {
    /// Writes `run_dir/checkpoints/step-<updates>/` atomically, points `LATEST` at it and keeps the
    /// [`KEEP_CHECKPOINTS`] newest step folders. Returns the step folder.
    pub fn save_checkpoint(&self, run_dir: &Path) -> Result<PathBuf, LacError> {
        let res = self.write_checkpoint(run_dir);
        if res.is_err() {
            // A failed write (disk full) leaves no partial folder behind to fill the disk further; the
            // previous checkpoint and LATEST were never touched.
            let dir = run_dir.join(CHECKPOINTS_DIR);
            let _ = std::fs::remove_dir_all(dir.join(format!(
                ".tmp-{}-{}",
                step_folder_name(self.updates),
                std::process::id()
            )));
            let _ = std::fs::remove_file(bcal_common::fsutil::temporary_path(&dir.join(LATEST_FILE)));
        }
        res
    }

    fn write_checkpoint(&self, run_dir: &Path) -> Result<PathBuf, LacError> {
        let dir = run_dir.join(CHECKPOINTS_DIR);
        std::fs::create_dir_all(&dir).map_err(io_err("create", &dir))?;
        let name = step_folder_name(self.updates);
        let tmp = dir.join(format!(".tmp-{name}-{}", std::process::id()));
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).map_err(io_err("remove", &tmp))?;
        }
        std::fs::create_dir(&tmp).map_err(io_err("create", &tmp))?;

        let mut files = BTreeMap::new();
        for (file, vs) in [
            (ACTOR_FILE, &self.actor_vs),
            (CRITIC_FILE, &self.critic_vs),
            (ACTOR_TARGET_FILE, &self.actor_target_vs),
            (CRITIC_TARGET_FILE, &self.critic_target_vs),
        ] {
            let path = tmp.join(file);
            vs.save(&path)?;
            fsync_file(&path)?;
            files.insert(file.to_string(), crc_of(&path)?);
        }
        let path = tmp.join(MULTIPLIERS_FILE);
        let (log_lambda, log_beta) = (self.log_lambda.detach(), self.log_beta.detach());
        Tensor::write_safetensors(&[("log_lambda", &log_lambda), ("log_beta", &log_beta)], &path)?;
        fsync_file(&path)?;
        files.insert(MULTIPLIERS_FILE.to_string(), crc_of(&path)?);

        let meta = CheckpointMeta {
            format: CHECKPOINT_FORMAT,
            update_step: self.updates,
            quarantined: self.quarantined,
            experiment: self.experiment,
            layout: self.layout.clone(),
            fingerprint: self.layout.fingerprint(),
            lac: self.lac_config.clone(),
            lr_multipliers: self.lr_multipliers,
            target_entropy: self.target_entropy,
            trained_s: self.trained_s,
            files,
        };
        let path = tmp.join(META_FILE);
        let json = serde_json::to_vec_pretty(&meta).expect("checkpoint metadata serialises");
        std::fs::File::create(&path)
            .and_then(|mut f| f.write_all(&json).and_then(|()| f.sync_all()))
            .map_err(io_err("write", &path))?;
        sync_dir(&tmp).map_err(io_err("fsync", &tmp))?;

        // Re-saving a step (e.g. SIGTERM right after a periodic checkpoint, or a fresh run in an old run
        // folder) replaces that folder.
        let folder = dir.join(&name);
        if folder.exists() {
            std::fs::remove_dir_all(&folder).map_err(io_err("replace", &folder))?;
        }
        std::fs::rename(&tmp, &folder).map_err(io_err("rename into place", &folder))?;
        sync_dir(&dir).map_err(io_err("fsync", &dir))?;

        let latest = dir.join(LATEST_FILE);
        write_atomic(&latest, format!("{name}\n").as_bytes()).map_err(io_err("write", &latest))?;

        prune(&dir, self.updates);
        Ok(folder)
    }

    /// Restores the checkpoint `run_dir/checkpoints/LATEST` names; `Ok(None)` when there is no `LATEST`.
    /// Refuses (with [`LacError::CheckpointMismatch`]) a checkpoint of another experiment or network
    /// shape, and (with [`LacError::CheckpointCorrupt`]) a missing, half-written or damaged one.
    ///
    /// Adam's moment estimates are not restored: the four optimisers start fresh. The update counter is.
    pub fn load_latest(cfg: &Validated, layout: PolicyLayout, run_dir: &Path) -> Result<Option<Self>, LacError> {
        let dir = run_dir.join(CHECKPOINTS_DIR);
        let latest = dir.join(LATEST_FILE);
        let name = match std::fs::read_to_string(&latest) {
            Ok(s) => s.trim().to_string(),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io_err("read", &latest)(e)),
        };
        let step = parse_step_folder(&name)
            .ok_or_else(|| corrupt(&latest, format!("it names {name:?}, not a step-<N> folder")))?;
        let folder = dir.join(&name);
        if !folder.is_dir() {
            return Err(corrupt(&folder, "LATEST names a folder that does not exist"));
        }

        let meta_path = folder.join(META_FILE);
        let text = std::fs::read(&meta_path).map_err(|e| corrupt(&meta_path, format!("cannot read: {e}")))?;
        let meta: CheckpointMeta =
            serde_json::from_slice(&text).map_err(|e| corrupt(&meta_path, format!("not valid metadata: {e}")))?;
        // Refusals drawn from meta.json name it: a damaged file and another run's read alike.
        if meta.format != CHECKPOINT_FORMAT {
            return Err(mismatch(
                &meta_path,
                format!("format {} but this build reads {CHECKPOINT_FORMAT}", meta.format),
            ));
        }
        if meta.update_step != step {
            return Err(corrupt(&folder, format!("meta.json says step {} in folder {name}", meta.update_step)));
        }
        if meta.experiment != cfg.config.experiment {
            return Err(mismatch(
                &meta_path,
                format!("trained on experiment {}, this run is {}", meta.experiment, cfg.config.experiment),
            ));
        }
        if meta.layout != layout || meta.fingerprint != layout.fingerprint() {
            return Err(mismatch(&meta_path, format!("network shape {:?}, this run needs {layout:?}", meta.layout)));
        }
        if meta.lac.hidden != cfg.config.lac.hidden {
            return Err(mismatch(
                &meta_path,
                format!("critic hidden {:?}, this run's lac.hidden is {:?}", meta.lac.hidden, cfg.config.lac.hidden),
            ));
        }
        for file in TENSOR_FILES {
            let path = folder.join(file);
            let want = *meta.files.get(file).ok_or_else(|| corrupt(&meta_path, format!("it lists no {file}")))?;
            let got = crc_of(&path).map_err(|e| corrupt(&path, e.to_string()))?;
            if got != want {
                return Err(corrupt(&path, format!("checksum {got:08x}, meta.json says {want:08x} (damaged)")));
            }
        }

        let mut lac = Lac::new(cfg, layout, cfg.config.seed.wrapping_add(step))?;
        load_var_store(&lac.actor_vs, &folder.join(ACTOR_FILE))?;
        load_var_store(&lac.critic_vs, &folder.join(CRITIC_FILE))?;
        load_var_store(&lac.actor_target_vs, &folder.join(ACTOR_TARGET_FILE))?;
        load_var_store(&lac.critic_target_vs, &folder.join(CRITIC_TARGET_FILE))?;
        let path = folder.join(MULTIPLIERS_FILE);
        let mut scalars = read_tensors(&path)?;
        for (name, var) in [("log_lambda", &mut lac.log_lambda), ("log_beta", &mut lac.log_beta)] {
            let src = scalars.remove(name).ok_or_else(|| corrupt(&path, format!("no tensor {name}")))?;
            copy_checked(&path, name, &src, var)?;
            // exp() of a log multiplier must stay finite and non-zero in f32 (|x| < 87): beyond is damage
            // that the checksum did not catch, and would poison every loss.
            let value = var.double_value(&[]);
            if !(-LOG_MULTIPLIER_LIMIT..=LOG_MULTIPLIER_LIMIT).contains(&value) {
                return Err(corrupt(
                    &path,
                    format!("{name} = {value:e} is outside [-{LOG_MULTIPLIER_LIMIT}, {LOG_MULTIPLIER_LIMIT}]"),
                ));
            }
        }
        lac.updates = step;
        lac.quarantined = meta.quarantined;
        lac.trained_s = meta.trained_s;
        Ok(Some(lac))
    }
}

fn read_tensors(path: &Path) -> Result<HashMap<String, Tensor>, LacError> {
    check_safetensors_framing(path)?;
    Ok(Tensor::read_safetensors(path)
        // libtorch appends a C++ backtrace to its message: keep its first line.
        .map_err(|e| corrupt(path, format!("unreadable safetensors: {}", e.to_string().lines().next().unwrap_or(""))))?
        .into_iter()
        .collect())
}

/// Checks what the safetensors reader (0.3) adds without overflow checks: the header length and every
/// tensor's data offsets must lie within the file. A file crafted past its checksum (offsets near 2^64)
/// would otherwise panic there instead of being refused.
fn check_safetensors_framing(path: &Path) -> Result<(), LacError> {
    let bytes = std::fs::read(path).map_err(|e| corrupt(path, format!("cannot read: {e}")))?;
    let bad = |why: String| corrupt(path, format!("unreadable safetensors: {why}"));
    let (len, rest) =
        bytes.split_first_chunk::<8>().ok_or_else(|| bad("shorter than its 8-byte header length".into()))?;
    let header_len = u64::from_le_bytes(*len);
    let data_len = (rest.len() as u64)
        .checked_sub(header_len)
        .ok_or_else(|| bad(format!("header of {header_len} bytes in a file of {}", bytes.len())))?;
    let header: HashMap<String, serde_json::Value> = serde_json::from_slice(&rest[..header_len as usize])
        .map_err(|e| bad(format!("header is not a JSON object: {e}")))?;
    for (name, info) in header.iter().filter(|(name, _)| *name != "__metadata__") {
        let offsets = info.get("data_offsets").and_then(|o| o.as_array()).map(|o| o.iter().map(|x| x.as_u64()));
        match offsets.map(|mut o| (o.next().flatten(), o.next().flatten(), o.next())) {
            Some((Some(from), Some(to), None)) if from <= to && to <= data_len => {}
            _ => {
                return Err(bad(format!(
                    "tensor {name:?}: data_offsets {} outside the {data_len} data bytes",
                    info["data_offsets"]
                )))
            }
        }
    }
    Ok(())
}

/// Copies `src` into the variable after checking shape, dtype and finiteness.
fn copy_checked(path: &Path, name: &str, src: &Tensor, var: &mut Tensor) -> Result<(), LacError> {
    if src.size() != var.size() || src.kind() != Kind::Float {
        return Err(mismatch(
            path,
            format!("{name} is {:?} {:?}, the network needs {:?} {:?}", src.kind(), src.size(), var.kind(), var.size()),
        ));
    }
    if !bool::try_from(src.isfinite().all())? {
        return Err(corrupt(path, format!("{name} holds non-finite values")));
    }
    tch::no_grad(|| var.f_copy_(src))?;
    Ok(())
}

/// Loads exactly the variables of `vs` (no missing, no extra names), refusing shape changes.
fn load_var_store(vs: &nn::VarStore, path: &Path) -> Result<(), LacError> {
    let mut tensors = read_tensors(path)?;
    for (name, mut var) in vs.variables() {
        let src = tensors.remove(&name).ok_or_else(|| mismatch(path, format!("no tensor {name}")))?;
        copy_checked(path, &name, &src, &mut var)?;
    }
    if let Some(extra) = tensors.keys().next() {
        return Err(mismatch(path, format!("unexpected tensor {extra} (another network shape)")));
    }
    Ok(())
}

/// Best effort: removes step folders beyond the [`KEEP_CHECKPOINTS`] newest (never `current`) and stale
/// temporary folders. A failure here leaves extra folders behind, never a broken checkpoint.
fn prune(dir: &Path, current: u64) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    let mut steps = Vec::new();
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if let Some(step) = parse_step_folder(&name) {
            steps.push((step, entry.path()));
        } else if name.starts_with(".tmp-step-") && entry.path().is_dir() {
            let _ = std::fs::remove_dir_all(entry.path());
        }
    }
    steps.sort_by_key(|s| std::cmp::Reverse(s.0));
    for (step, path) in steps.into_iter().skip(KEEP_CHECKPOINTS) {
        if step != current {
            let _ = std::fs::remove_dir_all(path);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::config::TrainConfig;
    use bcal_common::wire::Transition;

    fn cfg() -> Validated {
        let mut c = TrainConfig { experiment: Experiment::SingleQ, ..Default::default() };
        c.lac.hidden = vec![8, 6];
        c.lac.batch_size = 16;
        c.learner.torch_threads = 1;
        c.validate().unwrap()
    }

    fn all_vars(lac: &Lac) -> Vec<(String, Vec<f32>)> {
        let mut out = Vec::new();
        for (tag, vs) in [
            ("actor", &lac.actor_vs),
            ("critic", &lac.critic_vs),
            ("actor_target", &lac.actor_target_vs),
            ("critic_target", &lac.critic_target_vs),
            ("lambda", &lac.lambda_vs),
            ("beta", &lac.beta_vs),
        ] {
            let mut vars: Vec<_> = vs.variables().into_iter().collect();
            vars.sort_by(|a, b| a.0.cmp(&b.0));
            for (name, t) in vars {
                out.push((format!("{tag}/{name}"), Vec::<f32>::try_from(&t.detach().flatten(0, -1)).unwrap()));
            }
        }
        out
    }

    /// Every variable of all six stores (networks, targets, multipliers) survives a round trip bit for bit.
    #[test]
    fn every_variable_round_trips_exactly() {
        let cfg = cfg();
        let layout = PolicyLayout { obs_dim: 4, act_dim: 1, hidden: vec![8, 6] };
        let mut lac = Lac::new(&cfg, layout.clone(), 3).unwrap();
        let batch: Vec<Transition> = (0..16)
            .map(|i| {
                let mut t = Transition::default();
                t.obs[..4].copy_from_slice(&[i as f32 * 0.1, 0.2, -0.3, 0.4]);
                t.next_obs[..4].copy_from_slice(&[0.1, i as f32 * -0.05, 0.3, 0.0]);
                t.action[0] = 0.5 - i as f32 * 0.05;
                t.cost = 0.1 * i as f32;
                t
            })
            .collect();
        for _ in 0..5 {
            lac.update(&batch).unwrap();
        }
        let run = tempfile::tempdir().unwrap();
        lac.save_checkpoint(run.path()).unwrap();
        let back = Lac::load_latest(&cfg, layout, run.path()).unwrap().unwrap();
        assert_eq!(all_vars(&lac), all_vars(&back));
        assert_eq!(back.updates(), 5);
        assert_eq!(lac.lambda(), back.lambda());
        assert_eq!(lac.beta(), back.beta());
    }
}
