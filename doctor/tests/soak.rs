//! The soak run (not CI): the doctor's confusion matrix over many synthetic cells, every cause hidden
//! under several seeds by the independent generator in `common`. Ignored by default; run it with
//!
//! ```sh
//! BCAL_DOCTOR_SOAK_SEEDS=1..8 CARGO_TARGET_DIR=/work/target-doctor \
//!   cargo test -p bcal-doctor --test soak -- --ignored --nocapture
//! ```
//!
//! `BCAL_DOCTOR_SOAK_SEEDS` takes `A..B` (inclusive) or a comma list (default `1..5`);
//! `BCAL_DOCTOR_SOAK_CAUSES` limits the truths (comma list of cause names); `BCAL_DOCTOR_SOAK_OUT` also
//! writes the report (Markdown) to that file, and `BCAL_DOCTOR_SOAK_JSONL` appends every cell's candidate
//! figures to that file (one JSON line per cell). Rows are the hidden truth, columns the cause the doctor
//! named; held-out gains are per truth over the seeds. The last two rows are whole lives ([`LIFE_CAUSES`]:
//! a sensor offset over a constant-current life, recovery after rest), named by the voltage diagnosis and
//! the lifetime one together ([`life_named`]; `recovery` is its own column).

mod common;

use common::{diagnose_cell, diagnose_life, life_named, CAUSES, LIFE_CAUSES};
use std::fmt::Write as _;
use std::time::Instant;

/// Parses `A..B` (inclusive) or `a,b,c`.
fn parse_seeds(text: &str) -> Vec<u64> {
    if let Some((a, b)) = text.split_once("..") {
        let (a, b): (u64, u64) =
            (a.trim().parse().expect("seed"), b.trim().trim_start_matches('=').parse().expect("seed"));
        (a..=b).collect()
    } else {
        text.split(',').map(|s| s.trim().parse().expect("seed")).collect()
    }
}

struct Case {
    truth: &'static str,
    seed: u64,
    named: String,
    base_mv: f64,
    extended_mv: f64,
    gain_pct: f64,
}

#[test]
#[ignore = "soak run, not CI: set BCAL_DOCTOR_SOAK_SEEDS and pass --ignored"]
fn confusion_matrix() {
    let seeds = parse_seeds(&std::env::var("BCAL_DOCTOR_SOAK_SEEDS").unwrap_or_else(|_| "1..5".into()));
    let all: Vec<&'static str> = CAUSES.iter().chain(&LIFE_CAUSES).copied().collect();
    let causes: Vec<&'static str> = match std::env::var("BCAL_DOCTOR_SOAK_CAUSES") {
        Ok(list) => list.split(',').map(|c| *all.iter().find(|k| **k == c.trim()).expect("a known cause")).collect(),
        Err(_) => all.clone(),
    };
    // Columns: every cause the voltage diagnosis can name, then recovery (the lifetime diagnosis's).
    let columns: Vec<&'static str> = CAUSES.iter().copied().chain(["recovery"]).collect();
    let started = Instant::now();
    let mut cases = Vec::new();
    for &cause in &causes {
        for &seed in &seeds {
            let t0 = Instant::now();
            let (truth, diag, named) = if LIFE_CAUSES.contains(&cause) {
                let (truth, diag) = diagnose_life(cause, seed);
                let named = life_named(&diag);
                (format!("{truth:?}"), diag, named)
            } else {
                let (truth, diag) = diagnose_cell(cause, seed);
                (format!("{:?}", truth.effect), diag.clone(), diag.cause.to_string())
            };
            let life = diag.lifetime.as_ref().map_or(String::new(), |l| format!("; lifetime: {}", l.verdict));
            let ranking: Vec<String> = diag
                .candidates
                .iter()
                .take(3)
                .map(|c| format!("{} {:.2} mV ({:+.0} %)", c.cause, c.heldout_rmse_mv, c.gain_pct))
                .collect();
            eprintln!(
                "{cause:>18} seed {seed:>3}: named {named:<18} ({}) base {:.2} mV -> extended {} {:.2} mV ({:.0} %), noise {:.2} mV; \
                 top {}{life}; {:.1} s; truth {}",
                diag.named_on,
                diag.base.heldout_rmse_mv,
                diag.extended.causes.join("+"),
                diag.extended.heldout_rmse_mv,
                diag.gain_pct,
                diag.noise_mv,
                ranking.join(", "),
                t0.elapsed().as_secs_f64(),
                truth
            );
            if let Ok(path) = std::env::var("BCAL_DOCTOR_SOAK_JSONL") {
                // Every candidate's figures, for studying ranking rules offline.
                let line = serde_json::json!({
                    "truth": cause, "seed": seed, "named": named, "named_on": diag.named_on, "noise_mv": diag.noise_mv,
                    "base_train_mv": diag.base.train_rmse_mv, "base_heldout_mv": diag.base.heldout_rmse_mv,
                    "extended": diag.extended.causes, "extended_heldout_mv": diag.extended.heldout_rmse_mv,
                    "candidates": diag.candidates.iter().map(|c| serde_json::json!({
                        "cause": c.cause, "train_mv": c.train_rmse_mv, "heldout_mv": c.heldout_rmse_mv,
                        "score_mv": c.score_mv, "gain_pct": c.gain_pct, "shared": c.params.len(),
                        "per_cycle": c.cycle_params.len(),
                    })).collect::<Vec<_>>(),
                });
                let mut f = std::fs::OpenOptions::new().create(true).append(true).open(&path).unwrap();
                std::io::Write::write_all(&mut f, format!("{line}\n").as_bytes()).unwrap();
            }
            cases.push(Case {
                truth: cause,
                seed,
                named,
                base_mv: diag.base.heldout_rmse_mv,
                extended_mv: diag.extended.heldout_rmse_mv,
                gain_pct: diag.gain_pct,
            });
        }
    }
    let mut report = String::new();
    let seed_text: Vec<String> = seeds.iter().map(u64::to_string).collect();
    writeln!(
        report,
        "seeds {} ({} cells, {:.0} s)\n",
        seed_text.join(","),
        cases.len(),
        started.elapsed().as_secs_f64()
    )
    .unwrap();
    writeln!(report, "| truth \\ named | {} | other |", columns.join(" | ")).unwrap();
    writeln!(report, "| --- |{}", " ---: |".repeat(columns.len() + 1)).unwrap();
    for &truth in &causes {
        let other = cases.iter().filter(|c| c.truth == truth && !columns.contains(&c.named.as_str())).count();
        let counts: Vec<String> = columns
            .iter()
            .map(|named| cases.iter().filter(|c| c.truth == truth && c.named == *named).count())
            .chain([other])
            .map(|n| if n == 0 { ".".to_string() } else { n.to_string() })
            .collect();
        writeln!(report, "| {truth} | {} |", counts.join(" | ")).unwrap();
    }
    writeln!(report, "\n| truth | named right | base held-out mV (mean) | extended held-out mV (mean, max) | gain % (mean, min) | misses |").unwrap();
    writeln!(report, "| --- | ---: | ---: | ---: | ---: | --- |").unwrap();
    for &truth in &causes {
        let mine: Vec<&Case> = cases.iter().filter(|c| c.truth == truth).collect();
        let n = mine.len() as f64;
        // A current-sensor gain is mostly absorbed by qMobile and Ro (see hidden_effects.rs): `none` is right
        // for it as well as `current_gain`.
        // A whole life hiding an offset is right when `voltage_offset` is named (and no recovery).
        let is_right = |c: &Case| {
            c.named == truth
                || (truth == "current_gain" && c.named == "none")
                || (truth == "voltage_offset_life" && c.named == "voltage_offset")
        };
        let right = mine.iter().filter(|c| is_right(c)).count();
        let mean = |f: fn(&Case) -> f64| mine.iter().map(|c| f(c)).sum::<f64>() / n;
        let max = |f: fn(&Case) -> f64| mine.iter().map(|c| f(c)).fold(f64::NEG_INFINITY, f64::max);
        let min = |f: fn(&Case) -> f64| mine.iter().map(|c| f(c)).fold(f64::INFINITY, f64::min);
        let misses: Vec<String> =
            mine.iter().filter(|c| !is_right(c)).map(|c| format!("seed {}: {}", c.seed, c.named)).collect();
        writeln!(
            report,
            "| {truth} | {right}/{} | {:.2} | {:.2}, {:.2} | {:.0}, {:.0} | {} |",
            mine.len(),
            mean(|c| c.base_mv),
            mean(|c| c.extended_mv),
            max(|c| c.extended_mv),
            mean(|c| c.gain_pct),
            min(|c| c.gain_pct),
            if misses.is_empty() { "-".to_string() } else { misses.join("; ") }
        )
        .unwrap();
    }
    println!("{report}");
    if let Ok(path) = std::env::var("BCAL_DOCTOR_SOAK_OUT") {
        std::fs::write(&path, &report).unwrap();
    }
}
