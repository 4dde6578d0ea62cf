//! The lifetime diagnosis alone (no voltage fits, so no qMobile series) on NASA PCoE cells: recovery after
//! rest, its size and time constants, and the held-out capacity gain, fitted on cycles 1..T and judged on
//! T+1 onwards. Runs in about a second per cell:
//!
//! ```sh
//! cargo run --release -p bcal-doctor --example lifetime -- /work/shared/data/nasa-pcoe B0005,B0006,B0018 40
//! ```

use bcal_doctor::lifetime::{assess, LifetimeConfig};
use bcal_doctor::read::{nasa_cutoff_v, read_nasa_with, ReadOptions};
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let root = PathBuf::from(args.first().map_or("/work/shared/data/nasa-pcoe", String::as_str));
    let cells = args.get(1).map_or("B0005,B0006,B0018", String::as_str);
    let last_train: u32 = args.get(2).map_or(Ok(40), |s| s.parse())?;
    println!("| cell | recovery | A Ah | tau h | d discharges | largest jump Ah | held-out capacity RMSE Ah one ahead (without -> with) | gain % | open loop (without -> with) | 90 % interval coverage |");
    println!("| --- | --- | ---: | ---: | ---: | ---: | --- | ---: | --- | ---: |");
    for cell in cells.split(',') {
        let (records, report) = read_nasa_with(&root, cell, None, &ReadOptions::default())?;
        let cfg = LifetimeConfig { cutoff_v: nasa_cutoff_v(&root, cell), ..LifetimeConfig::default() };
        let last = records.iter().map(|d| d.cycle).max().unwrap_or(1);
        let life = assess(&cfg, &records, &report.starts, &(1..=last_train), &(last_train + 1..=last), None)?;
        let f = |x: Option<f64>, p: usize| x.map_or("-".to_string(), |v| format!("{v:.p$}"));
        let c = life.capacity.as_ref();
        println!(
            "| {cell} | {} | {} | {} | {} | {} | {} -> {} | {} | {} -> {} | {} |",
            if life.recovery { "present" } else { "absent" },
            f(life.amplitude_ah, 3),
            f(life.tau_rest_h, 1),
            f(life.decay_discharges, 1),
            f(life.largest_jump_ah, 3),
            f(life.heldout_capacity_rmse_without_ah, 4),
            f(life.heldout_capacity_rmse_ah, 4),
            f(life.gain_pct, 0),
            f(c.map(|c| c.open_loop_rmse_without), 4),
            f(c.map(|c| c.open_loop_rmse), 4),
            f(c.map(|c| c.interval_coverage), 2),
        );
        eprintln!("{cell}: {} ({})", life.verdict, life.notes.join("; "));
    }
    Ok(())
}
