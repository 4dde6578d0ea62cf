//! Hostile checkpoints, by property (proptest): a real small checkpoint is saved once, then each case damages
//! a copy (truncation, bit flips, random bytes, files swapped with another checkpoint's, hostile meta.json,
//! LATEST pointing anywhere) and loads it. Loading never panics; an error names the damaged file and why;
//! whatever loads holds exactly the saved weights (checked by saving the loaded learner again and comparing
//! the tensor files byte for byte); the untouched original in another folder still loads afterwards.

use bcal_common::config::{TrainConfig, Validated};
use bcal_common::dataset::Experiment;
use bcal_common::policy::PolicyLayout;
use bcal_common::wire::Transition;
use bcal_learner::checkpoint::{CHECKPOINTS_DIR, LATEST_FILE};
use bcal_learner::{Lac, LacError};
use proptest::prelude::*;
use proptest::sample::Index;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

const HIDDEN: [usize; 2] = [4, 3];
const STEP: u64 = 3;
const TENSOR_FILES: [&str; 5] = [
    "actor.safetensors",
    "critic.safetensors",
    "actor_target.safetensors",
    "critic_target.safetensors",
    "multipliers.safetensors",
];
/// Every file of a step folder, and LATEST.
const FILES: [&str; 7] = [
    "meta.json",
    "actor.safetensors",
    "critic.safetensors",
    "actor_target.safetensors",
    "critic_target.safetensors",
    "multipliers.safetensors",
    LATEST_FILE,
];

fn cfg() -> Validated {
    let mut c = TrainConfig { experiment: Experiment::SingleQ, ..Default::default() };
    c.lac.hidden = HIDDEN.to_vec();
    c.lac.batch_size = 8;
    c.learner.torch_threads = 1;
    c.validate().unwrap()
}

fn layout() -> PolicyLayout {
    PolicyLayout { obs_dim: 15, act_dim: 1, hidden: HIDDEN.to_vec() }
}

/// Two checkpoints at the same step with different weights (seeds 1 and 2), and one at step 4, saved once.
struct Saved {
    a: tempfile::TempDir,
    b: tempfile::TempDir,
    later: tempfile::TempDir,
}

fn trained(seed: u64, updates: u64) -> Lac {
    let mut lac = Lac::new(&cfg(), layout(), seed).unwrap();
    let batch: Vec<Transition> = (0..8)
        .map(|i| {
            let mut t = Transition::default();
            for k in 0..15 {
                t.obs[k] = ((i * 15 + k) as f32 * 0.37).sin();
                t.next_obs[k] = ((i * 15 + k) as f32 * 0.53).cos();
            }
            t.action[0] = 0.5 - i as f32 * 0.1;
            t.cost = 0.1 * i as f32;
            t
        })
        .collect();
    for _ in 0..updates {
        lac.update(&batch).unwrap();
    }
    lac
}

fn saved() -> &'static Saved {
    static SAVED: OnceLock<Saved> = OnceLock::new();
    SAVED.get_or_init(|| {
        let dirs = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        trained(1, STEP).save_checkpoint(dirs.0.path()).unwrap();
        trained(2, STEP).save_checkpoint(dirs.1.path()).unwrap();
        trained(1, STEP + 1).save_checkpoint(dirs.2.path()).unwrap();
        Saved { a: dirs.0, b: dirs.1, later: dirs.2 }
    })
}

fn ckpt(run: &Path) -> PathBuf {
    run.join(CHECKPOINTS_DIR)
}

/// Path of `file` (a step-folder file or LATEST) in run `run`.
fn file_path(run: &Path, file: &str) -> PathBuf {
    if file == LATEST_FILE {
        ckpt(run).join(LATEST_FILE)
    } else {
        ckpt(run).join(format!("step-{STEP}")).join(file)
    }
}

/// A fresh copy of run `from` (only LATEST and the step folder).
fn copy_run(from: &Path) -> tempfile::TempDir {
    let to = tempfile::tempdir().unwrap();
    let src = std::fs::read_dir(ckpt(from)).unwrap();
    for entry in src {
        let entry = entry.unwrap();
        let dest = ckpt(to.path()).join(entry.file_name());
        if entry.path().is_dir() {
            std::fs::create_dir_all(&dest).unwrap();
            for f in std::fs::read_dir(entry.path()).unwrap() {
                let f = f.unwrap();
                std::fs::copy(f.path(), dest.join(f.file_name())).unwrap();
            }
        } else {
            std::fs::create_dir_all(ckpt(to.path())).unwrap();
            std::fs::copy(entry.path(), dest).unwrap();
        }
    }
    to
}

fn load(run: &Path) -> Result<Option<Lac>, LacError> {
    Lac::load_latest(&cfg(), layout(), run)
}

/// The tensor files of a learner saved afresh: equal bytes mean equal weights, targets and multipliers.
fn resaved(lac: &Lac) -> Vec<Vec<u8>> {
    let dir = tempfile::tempdir().unwrap();
    let folder = lac.save_checkpoint(dir.path()).unwrap();
    TENSOR_FILES.iter().map(|f| std::fs::read(folder.join(f)).unwrap()).collect()
}

fn original_tensors(run: &Path) -> Vec<Vec<u8>> {
    TENSOR_FILES.iter().map(|f| std::fs::read(file_path(run, f)).unwrap()).collect()
}

/// The outcome of loading damaged copy `run` whose `damaged` files were changed: an error names one of them
/// (its path, or its file name inside another path's message) and says why; a success holds exactly the
/// saved weights of `a`. Then the untouched original still loads.
fn check(run: &Path, damaged: &[&str]) -> Result<(), TestCaseError> {
    match load(run) {
        Ok(Some(lac)) => {
            prop_assert_eq!(lac.updates(), STEP);
            prop_assert!(resaved(&lac) == original_tensors(saved().a.path()), "loaded weights differ from the saved");
        }
        // Documented: no LATEST means no checkpoint (a fresh start).
        Ok(None) => prop_assert!(!file_path(run, LATEST_FILE).exists(), "a damaged checkpoint loaded as none"),
        Err(e) => {
            let msg = e.to_string();
            prop_assert!(
                matches!(
                    e,
                    LacError::CheckpointCorrupt { .. }
                        | LacError::CheckpointMismatch { .. }
                        | LacError::CheckpointIo { .. }
                ),
                "unexpected error kind: {e:?}"
            );
            prop_assert!(msg.contains(&run.display().to_string()), "the error does not name the folder: {msg}");
            prop_assert!(damaged.iter().any(|f| msg.contains(f)), "the error names none of {damaged:?}: {msg}");
            prop_assert!(msg.len() < 2000, "overlong message: {msg}");
            prop_assert!(!msg.chars().any(char::is_control), "control characters in the message: {msg:?}");
        }
    }
    let original = load(saved().a.path()).unwrap().expect("the original checkpoint");
    prop_assert!(resaved(&original) == original_tensors(saved().a.path()));
    Ok(())
}

/// One edit of a file's bytes.
#[derive(Clone, Debug)]
enum Edit {
    Truncate(Index),
    FlipBit(Index, u8),
    /// Overwrites bytes from a position.
    Overwrite(Index, Vec<u8>),
    Insert(Index, Vec<u8>),
    /// Replaces the whole file.
    Replace(Vec<u8>),
    Delete,
    /// Replaces the file by an empty folder.
    Folder,
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        2 => any::<Index>().prop_map(Edit::Truncate),
        4 => (any::<Index>(), 0u8..8).prop_map(|(i, b)| Edit::FlipBit(i, b)),
        2 => (any::<Index>(), prop::collection::vec(any::<u8>(), 1..16)).prop_map(|(i, b)| Edit::Overwrite(i, b)),
        1 => (any::<Index>(), prop::collection::vec(any::<u8>(), 1..16)).prop_map(|(i, b)| Edit::Insert(i, b)),
        1 => prop::collection::vec(any::<u8>(), 0..64).prop_map(Edit::Replace),
        1 => Just(Edit::Delete),
        1 => Just(Edit::Folder),
    ]
}

/// Applies `edit` to `path`; false when the file no longer exists as a file.
fn apply(path: &Path, edit: &Edit) -> bool {
    let Ok(mut bytes) = std::fs::read(path) else { return false };
    let n = bytes.len();
    match edit {
        Edit::Truncate(i) => bytes.truncate(i.index(n + 1)),
        Edit::FlipBit(i, b) if n > 0 => bytes[i.index(n)] ^= 1 << b,
        Edit::Overwrite(i, with) if n > 0 => {
            let at = i.index(n);
            for (k, b) in with.iter().enumerate() {
                if let Some(slot) = bytes.get_mut(at + k) {
                    *slot = *b;
                }
            }
        }
        Edit::Insert(i, with) => {
            let at = i.index(n + 1);
            bytes.splice(at..at, with.iter().copied());
        }
        Edit::Replace(with) => bytes = with.clone(),
        Edit::Delete => {
            std::fs::remove_file(path).unwrap();
            return false;
        }
        Edit::Folder => {
            std::fs::remove_file(path).unwrap();
            std::fs::create_dir(path).unwrap();
            return false;
        }
        _ => {}
    }
    std::fs::write(path, bytes).unwrap();
    true
}

fn crc_in_meta(run: &Path, file: &str) {
    let meta_path = file_path(run, "meta.json");
    let mut meta: serde_json::Value = serde_json::from_slice(&std::fs::read(&meta_path).unwrap()).unwrap();
    let crc = crc32fast::hash(&std::fs::read(file_path(run, file)).unwrap());
    meta["files"][file] = serde_json::json!(crc);
    std::fs::write(&meta_path, serde_json::to_vec_pretty(&meta).unwrap()).unwrap();
}

/// Hostile JSON text for one node of meta.json.
fn hostile_json() -> impl Strategy<Value = String> {
    const TOKENS: &[&str] = &[
        "1e400",
        "-1e400",
        "18446744073709551616",
        "18446744073709551615",
        "-1",
        "-0",
        "0",
        "4294967296",
        "1.5",
        "NaN",
        "Infinity",
        "null",
        "true",
        "\"\"",
        "\"3\"",
        "\"single-r\"",
        "\"\\ud800\"",
        "\"\\u0000\"",
        "[]",
        "{}",
        "[3]",
        "{\"a\": 1}",
        "[1, 2, 3]",
        "[4, 3, 1]",
        "[4, 3]",
        "1e-400",
    ];
    prop_oneof![
        4 => prop::sample::select(TOKENS).prop_map(str::to_string),
        1 => (1usize..200_000).prop_map(|d| "[".repeat(d) + &"]".repeat(d)),
        1 => (1usize..200_000).prop_map(|d| "{\"a\":".repeat(d) + "1" + &"}".repeat(d)),
        1 => (1usize..200_000).prop_map(|d| "[".repeat(d)),
        1 => prop::collection::vec(b'1'..=b'9', 20..400).prop_map(|d| String::from_utf8(d).unwrap()),
        1 => any::<i64>().prop_map(|v| v.to_string()),
        1 => any::<f64>().prop_map(|v| format!("{v:e}")),
    ]
}

/// What happens to one node of meta.json.
#[derive(Clone, Debug)]
enum MetaEdit {
    /// Replaces the node by raw JSON text.
    Replace(Index, String),
    /// Removes the node (from its object or array).
    Remove(Index),
    /// Adds an unknown key with raw JSON text at the top level.
    AddKey(String),
    /// Repeats a top-level key with raw JSON text (the later value wins in most parsers).
    DuplicateKey(Index, String),
}

fn meta_edit() -> impl Strategy<Value = MetaEdit> {
    prop_oneof![
        4 => (any::<Index>(), hostile_json()).prop_map(|(i, j)| MetaEdit::Replace(i, j)),
        2 => any::<Index>().prop_map(MetaEdit::Remove),
        1 => hostile_json().prop_map(MetaEdit::AddKey),
        1 => (any::<Index>(), hostile_json()).prop_map(|(i, j)| MetaEdit::DuplicateKey(i, j)),
    ]
}

/// JSON pointers of every node below the root.
fn pointers(v: &serde_json::Value, at: String, out: &mut Vec<String>) {
    match v {
        serde_json::Value::Object(m) => {
            for (k, c) in m {
                let p = format!("{at}/{}", k.replace('~', "~0").replace('/', "~1"));
                out.push(p.clone());
                pointers(c, p, out);
            }
        }
        serde_json::Value::Array(a) => {
            for (k, c) in a.iter().enumerate() {
                let p = format!("{at}/{k}");
                out.push(p.clone());
                pointers(c, p, out);
            }
        }
        _ => {}
    }
}

const MARK: &str = "\"@@HOSTILE@@\"";

/// meta.json text after `edit` (pretty-printed again; raw JSON spliced in at the edited node).
fn edited_meta(text: &[u8], edit: &MetaEdit) -> Vec<u8> {
    let mut v: serde_json::Value = serde_json::from_slice(text).unwrap();
    let mut all = Vec::new();
    pointers(&v, String::new(), &mut all);
    let raw = match edit {
        MetaEdit::Replace(i, json) => {
            *v.pointer_mut(&all[i.index(all.len())]).unwrap() = serde_json::json!("@@HOSTILE@@");
            Some(json)
        }
        MetaEdit::Remove(i) => {
            let p = &all[i.index(all.len())];
            let (parent, key) = p.rsplit_once('/').unwrap();
            match v.pointer_mut(parent).unwrap() {
                serde_json::Value::Object(m) => {
                    m.remove(&key.replace("~1", "/").replace("~0", "~"));
                }
                serde_json::Value::Array(a) => {
                    a.remove(key.parse::<usize>().unwrap());
                }
                _ => unreachable!(),
            }
            None
        }
        MetaEdit::AddKey(json) => {
            v["zz_unknown"] = serde_json::json!("@@HOSTILE@@");
            Some(json)
        }
        MetaEdit::DuplicateKey(i, json) => {
            let keys: Vec<String> = v.as_object().unwrap().keys().cloned().collect();
            let key = &keys[i.index(keys.len())];
            let text = serde_json::to_string_pretty(&v).unwrap();
            let needle = format!("\n  \"{key}\":");
            let text = text.replacen(&needle, &format!("\n  \"{key}\": {json},{needle}"), 1);
            return text.into_bytes();
        }
    };
    let text = serde_json::to_string_pretty(&v).unwrap();
    match raw {
        Some(json) => text.replacen(MARK, json, 1).into_bytes(),
        None => text.into_bytes(),
    }
}

/// `n` cases per property, or `BCAL_FUZZ_CASES` of them (a soak run, not for CI).
fn cases(n: u32) -> ProptestConfig {
    let n = std::env::var("BCAL_FUZZ_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(n);
    ProptestConfig { cases: n, max_shrink_iters: 500, ..ProptestConfig::default() }
}

proptest! {
    #![proptest_config(cases(128))]

    /// Byte damage to any file (meta.json, a tensor file, LATEST): an error naming that file, or (a harmless
    /// edit such as JSON whitespace) exactly the saved weights.
    #[test]
    fn damaged_files_are_refused_naming_the_file(which in 0usize..FILES.len(), edits in prop::collection::vec(edit(), 1..4)) {
        let run = copy_run(saved().a.path());
        let file = FILES[which];
        let path = file_path(run.path(), file);
        for e in &edits {
            if !apply(&path, e) {
                break;
            }
        }
        check(run.path(), &[file])?;
    }

    /// The same damage to a tensor file with meta.json's checksum updated to match (a CRC collision, or a
    /// tool that rewrote both): the safetensors parser and the shape, dtype and finiteness checks still refuse
    /// it naming the file, or it loads finite weights of the right shapes. Never a panic.
    #[test]
    fn damaged_tensor_files_with_matching_checksums_never_panic(
        which in 0usize..TENSOR_FILES.len(),
        edits in prop::collection::vec(edit(), 1..3),
    ) {
        let run = copy_run(saved().a.path());
        let file = TENSOR_FILES[which];
        let path = file_path(run.path(), file);
        let mut exists = true;
        for e in &edits {
            exists = apply(&path, e);
            if !exists {
                break;
            }
        }
        if exists {
            crc_in_meta(run.path(), file);
        }
        match load(run.path()) {
            Ok(Some(lac)) => {
                prop_assert!(lac.actor_flat_params().iter().all(|x| x.is_finite()));
                prop_assert!(lac.lambda().is_finite() && lac.beta().is_finite());
            }
            Ok(None) => prop_assert!(false, "loaded as no checkpoint"),
            Err(e) => {
                let msg = e.to_string();
                prop_assert!(msg.contains(file), "the error does not name {file}: {msg}");
                prop_assert!(!msg.chars().any(char::is_control), "control characters in the message: {msg:?}");
            }
        }
    }

    /// Files swapped in from a checkpoint of the same step with other weights, or of a later step, in any
    /// non-empty proper subset: always refused, naming a swapped file (or the folder's meta.json).
    #[test]
    fn files_swapped_between_checkpoints_are_refused(mask in 1u32..63, later in any::<bool>()) {
        let run = copy_run(saved().a.path());
        let donor = if later { saved().later.path() } else { saved().b.path() };
        let donor_file = |f: &str| {
            let p = file_path(donor, f);
            if later { p.to_string_lossy().replace(&format!("step-{STEP}"), &format!("step-{}", STEP + 1)).into() } else { p }
        };
        let swapped: Vec<&str> = FILES[..6].iter().enumerate().filter(|(k, _)| mask & (1 << k) != 0).map(|(_, f)| *f).collect();
        for f in &swapped {
            std::fs::copy(donor_file(f), file_path(run.path(), f)).unwrap();
        }
        // A swapped tensor file is named with its checksum; swapped metadata disagrees with every kept file.
        let mut named: Vec<&str> = swapped.clone();
        if swapped.contains(&"meta.json") {
            named.extend(FILES[..6].iter().copied());
        }
        prop_assert!(load(run.path()).is_err(), "a mixed checkpoint ({swapped:?} from {}) loaded", donor.display());
        check(run.path(), &named)?;
    }

    /// Hostile meta.json (huge, negative, fractional or non-finite numbers, wrong types, deep nesting, missing,
    /// unknown or repeated keys): an error naming meta.json and why, or exactly the saved weights.
    #[test]
    fn hostile_metadata_is_refused_or_harmless(edits in prop::collection::vec(meta_edit(), 1..3)) {
        let run = copy_run(saved().a.path());
        let path = file_path(run.path(), "meta.json");
        let mut text = std::fs::read(&path).unwrap();
        for e in &edits {
            // Only JSON a previous edit left parseable can be edited structurally.
            if serde_json::from_slice::<serde_json::Value>(&text).is_err() {
                break;
            }
            text = edited_meta(&text, e);
        }
        std::fs::write(&path, &text).unwrap();
        check(run.path(), &["meta.json"])?;
    }

    /// LATEST naming anything: paths outside the folder, absolute paths, missing steps, other step folders,
    /// noise. An error naming LATEST (or the folder it names), never a checkpoint outside `checkpoints/`.
    #[test]
    fn latest_pointing_anywhere_is_refused(target in prop_oneof![
        4 => prop::sample::select(&[
            "../../etc/passwd", "/etc/passwd", "step-3/../../../etc/passwd", "../step-3", "step-3/..", "./step-3",
            "step-99", "step-", "step--1", "step-+3", "step-03", "step-3 step-4", "", "\n", "step-3\0",
            "step-18446744073709551616", "step-18446744073709551615", "step-3/meta.json", "checkpoints/step-3",
            "LATEST", ".", "..", "step-1e1", "STEP-3", "step-٣",
        ][..]).prop_map(|s: &str| s.as_bytes().to_vec()),
        1 => prop::collection::vec(any::<u8>(), 0..40),
        1 => prop::collection::vec(prop::sample::select(&b"step-0123./\n "[..]), 0..20),
    ]) {
        let run = copy_run(saved().a.path());
        let latest = file_path(run.path(), LATEST_FILE);
        std::fs::write(&latest, &target).unwrap();
        // Something a traversal could reach: a complete step folder outside `checkpoints/`.
        let outside = run.path().join(format!("step-{STEP}"));
        std::fs::create_dir(&outside).unwrap();
        for f in &FILES[..6] {
            std::fs::copy(file_path(saved().b.path(), f), outside.join(f)).unwrap();
        }
        match load(run.path()) {
            Ok(Some(lac)) => {
                // Only a name that trims to this run's own step folder may load.
                let name = String::from_utf8_lossy(&target).trim().to_string();
                prop_assert_eq!(name, format!("step-{STEP}"));
                prop_assert!(resaved(&lac) == original_tensors(saved().a.path()));
            }
            Ok(None) => prop_assert!(false, "a LATEST file loaded as no checkpoint"),
            Err(e) => {
                let msg = e.to_string();
                prop_assert!(msg.contains(&ckpt(run.path()).display().to_string()), "{msg}");
                prop_assert!(msg.contains("LATEST"), "the error does not name LATEST: {msg}");
                prop_assert!(!msg.chars().any(char::is_control), "control characters in the message: {msg:?}");
            }
        }
    }
}

/// Hand-made safetensors headers with a recomputed checksum: offsets that overflow (found here: safetensors
/// 0.3 panicked with "attempt to add with overflow"), a zero-size shape with a dimension beyond i64 (libtorch's
/// multi-line error is cut to its first line), another dtype, a header length beyond the file, NaN scalars.
#[test]
fn crafted_safetensors_headers_are_refused_naming_the_file() {
    let header = |json: &str, data: usize| {
        let mut out = (json.len() as u64).to_le_bytes().to_vec();
        out.extend_from_slice(json.as_bytes());
        out.extend(std::iter::repeat_n(0u8, data));
        out
    };
    let max = u64::MAX;
    let cases: Vec<(&str, Vec<u8>)> = vec![
        (
            "overflowing end",
            header(
                &format!(r#"{{"log_lambda":{{"dtype":"U8","shape":[{}],"data_offsets":[0,{}]}}}}"#, max - 3, max - 3),
                0,
            ),
        ),
        (
            "zero-size huge dim",
            header(
                &format!(
                    r#"{{"log_lambda":{{"dtype":"F32","shape":[0,{max}],"data_offsets":[0,0]}},"log_beta":{{"dtype":"F32","shape":[],"data_offsets":[0,4]}}}}"#
                ),
                4,
            ),
        ),
        (
            "f64 scalars",
            header(
                r#"{"log_lambda":{"dtype":"F64","shape":[],"data_offsets":[0,8]},"log_beta":{"dtype":"F64","shape":[],"data_offsets":[8,16]}}"#,
                16,
            ),
        ),
        ("unsupported dtype", header(r#"{"log_lambda":{"dtype":"F8_E4M3","shape":[],"data_offsets":[0,1]}}"#, 1)),
        ("header beyond file", {
            let mut b = header("{}", 0);
            b[0] = 0xff;
            b[5] = 0x01;
            b
        }),
        ("nan scalars", {
            let mut b = header(
                r#"{"log_lambda":{"dtype":"F32","shape":[],"data_offsets":[0,4]},"log_beta":{"dtype":"F32","shape":[],"data_offsets":[4,8]}}"#,
                0,
            );
            b.extend(f32::NAN.to_le_bytes());
            b.extend(0f32.to_le_bytes());
            b
        }),
    ];
    for (what, bytes) in cases {
        let run = copy_run(saved().a.path());
        let file = "multipliers.safetensors";
        std::fs::write(file_path(run.path(), file), &bytes).unwrap();
        crc_in_meta(run.path(), file);
        let e = load(run.path()).err().unwrap_or_else(|| panic!("{what}: loaded"));
        let msg = e.to_string();
        assert!(msg.contains(file) && msg.len() < 400 && !msg.chars().any(char::is_control), "{what}: {msg:?}");
    }
}

/// Found by the properties: meta.json without `lac.hidden` (serde fills the default) was refused as "another
/// run" naming only the step folder. Refusals drawn from meta.json now name it.
#[test]
fn a_missing_metadata_key_is_refused_naming_meta_json() {
    let run = copy_run(saved().a.path());
    let path = file_path(run.path(), "meta.json");
    let mut meta: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    meta["lac"].as_object_mut().unwrap().remove("hidden");
    std::fs::write(&path, serde_json::to_vec_pretty(&meta).unwrap()).unwrap();
    let msg = load(run.path()).err().expect("refused").to_string();
    assert!(msg.contains(&path.display().to_string()) && msg.contains("critic hidden [128, 128]"), "{msg}");
}
