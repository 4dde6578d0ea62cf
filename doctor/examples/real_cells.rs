//! The doctor's real-cell table: diagnoses NASA PCoE cells on several subsamples of their cycles and
//! reports each run and the mean and spread over the subsamples. The doctor is deterministic, so the
//! "seeds" are cycle offsets: offset o fits cycles A+o, A+o+stride, ... up to B (`--cycles A..B`, default
//! 1..40) and judges C+o, C+o+stride, ... up to D (`--holdout C..D`, default 41..168), exactly what
//! `bcal diagnose --data DIR --cell CELL --cycles (A+o)..B --holdout (C+o)..D --stride S --out OUT` runs
//! (same defaults), without linking libtorch:
//!
//! ```sh
//! CARGO_TARGET_DIR=/work/target-doctor cargo run -p bcal-doctor --example real_cells -- \
//!   --data /work/shared/data/nasa-pcoe --cells B0005,B0006,B0018 --offsets 0,1,2 --out /tmp/real
//! ```
//!
//! Writes `diagnosis.json`, `diagnosis.md` and the residual plots per run into `--out/<cell>_o<offset>/`. `--settle-s S`
//! overrides how long after a load step samples are left out of the fit (`FitConfig::settle_s`).

use bcal_doctor::read::{parse_cycle_range, read_nasa};
use bcal_doctor::{diagnose, DiagnoseConfig, Diagnosis};
use std::path::PathBuf;
use std::time::Instant;

struct Args {
    data: PathBuf,
    cells: Vec<String>,
    offsets: Vec<u32>,
    stride: u32,
    cycles: (u32, u32),
    holdout: (u32, u32),
    out: PathBuf,
    /// Overrides the fit's settle window after load steps, s (the library default when absent).
    settle_s: Option<f64>,
}

fn parse() -> Result<Args, String> {
    let mut a = Args {
        data: PathBuf::from("/work/shared/data/nasa-pcoe"),
        cells: vec!["B0005".into(), "B0006".into(), "B0018".into()],
        offsets: vec![0, 1, 2],
        stride: 4,
        cycles: (1, 40),
        holdout: (41, 168),
        out: std::env::temp_dir().join("bcal_real_cells"),
        settle_s: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let value = it.next().ok_or_else(|| format!("{flag} needs a value"))?;
        let list = |v: &str| v.split(',').map(|s| s.trim().to_string()).collect::<Vec<_>>();
        let num = |v: &str| v.parse::<u32>().map_err(|e| format!("{flag} {v}: {e}"));
        match flag.as_str() {
            "--data" => a.data = value.into(),
            "--cells" => a.cells = list(&value),
            "--offsets" => a.offsets = list(&value).iter().map(|v| num(v)).collect::<Result<_, _>>()?,
            "--stride" => a.stride = num(&value)?.max(1),
            "--cycles" | "--holdout" => {
                let r = parse_cycle_range(&value).map_err(|e| e.to_string())?;
                *(if flag == "--cycles" { &mut a.cycles } else { &mut a.holdout }) = (*r.start(), *r.end());
            }
            "--out" => a.out = value.into(),
            "--settle-s" => a.settle_s = Some(value.parse::<f64>().map_err(|e| format!("{flag} {value}: {e}"))?),
            other => {
                return Err(format!(
                "unknown flag {other} (flags: --data --cells --cycles --holdout --offsets --stride --out --settle-s)"
            ))
            }
        }
    }
    Ok(a)
}

/// One diagnosis of one cell on one subsample.
struct Run {
    cell: String,
    diag: Diagnosis,
    secs: f64,
}

/// Mean and sample standard deviation.
fn mean_sd(xs: &[f64]) -> (f64, f64) {
    let n = xs.len() as f64;
    let m = xs.iter().sum::<f64>() / n;
    let var = if xs.len() > 1 { xs.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0) } else { 0.0 };
    (m, var.sqrt())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let a = parse()?;
    let mut rows: Vec<Run> = Vec::new();
    for cell in &a.cells {
        let (all, _) = read_nasa(&a.data, cell, None)?;
        for &o in &a.offsets {
            let pick = |from: u32, to: u32| {
                let wanted: Vec<u32> = (from..=to).step_by(a.stride as usize).collect();
                all.iter().filter(|d| wanted.contains(&d.cycle)).cloned().collect::<Vec<_>>()
            };
            let (train, held) = (pick(a.cycles.0 + o, a.cycles.1), pick(a.holdout.0 + o, a.holdout.1));
            eprintln!(
                "{cell} offset {o}: {} training, {} held-out records (bcal diagnose --data {} --cell {cell} --cycles {}..{} \
                 --holdout {}..{} --stride {})",
                train.len(),
                held.len(),
                a.data.display(),
                a.cycles.0 + o,
                a.cycles.1,
                a.holdout.0 + o,
                a.holdout.1,
                a.stride
            );
            let started = Instant::now();
            let mut cfg = DiagnoseConfig::default();
            if let Some(s) = a.settle_s {
                cfg.fit.settle_s = s;
            }
            let diag = diagnose(&cfg, &train, &held)?;
            let secs = started.elapsed().as_secs_f64();
            let dir = a.out.join(format!("{cell}_o{o}"));
            bcal_doctor::report::write_reports(&diag, &dir)?;
            bcal_doctor::plot::write_plots(&diag, &dir)?;
            let worst = diag.extended.heldout_cycles.iter().max_by(|x, y| x.rmse_mv.total_cmp(&y.rmse_mv));
            println!(
                "{cell} o{o}: cause {} (ranking {}), base {:.2} mV, extended {} {:.2} mV, gain {:.1} %, worst {} , \
                 rest before load base/extended {:.1}/{:.1} mV, {:.0} s",
                diag.cause,
                diag.ranking.iter().take(3).copied().collect::<Vec<_>>().join(", "),
                diag.base.heldout_rmse_mv,
                diag.extended.causes.join("+"),
                diag.extended.heldout_rmse_mv,
                diag.gain_pct,
                worst.map_or("-".into(), |w| format!("{:.1} mV (cycle {})", w.rmse_mv, w.cycle)),
                diag.base.heldout_structure.rest_before.rmse_mv,
                diag.extended.heldout_structure.rest_before.rmse_mv,
                secs
            );
            rows.push(Run { cell: cell.clone(), diag, secs });
        }
    }
    println!("\n| cell | named cause (runs) | extended model (runs) | base held-out mV | extended held-out mV | gain % | run time s |");
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    for cell in &a.cells {
        let mine: Vec<&Run> = rows.iter().filter(|r| &r.cell == cell).collect();
        let count = |f: &dyn Fn(&Diagnosis) -> String| {
            let mut names: Vec<(String, usize)> = Vec::new();
            for r in &mine {
                let k = f(&r.diag);
                match names.iter_mut().find(|(n, _)| *n == k) {
                    Some(e) => e.1 += 1,
                    None => names.push((k, 1)),
                }
            }
            names.iter().map(|(n, c)| format!("{n} ({c})")).collect::<Vec<_>>().join(", ")
        };
        let stat = |f: &dyn Fn(&Run) -> f64, digits: usize| {
            let xs: Vec<f64> = mine.iter().map(|r| f(r)).collect();
            let (m, sd) = mean_sd(&xs);
            let lo = xs.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            format!("{m:.digits$} +- {sd:.digits$} ({lo:.digits$}-{hi:.digits$})")
        };
        println!(
            "| {cell} | {} | {} | {} | {} | {} | {} |",
            count(&|d| d.cause.to_string()),
            count(&|d| d.extended.causes.join(" + ")),
            stat(&|r| r.diag.base.heldout_rmse_mv, 1),
            stat(&|r| r.diag.extended.heldout_rmse_mv, 1),
            stat(&|r| r.diag.gain_pct, 0),
            stat(&|r| r.secs, 0),
        );
    }
    Ok(())
}
