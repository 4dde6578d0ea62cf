//! `bcal dataset generate|info`: the paper's experiment sets with their training, validation and test
//! splits, generated on all cores and cached (one file per split).

use crate::cli::{DatasetAction, DatasetArgs, DatasetSelect};
use anyhow::{bail, Context};
use bcal_common::battery::BatteryModel;
use bcal_common::dataset::{self, CacheStatus, Dataset, Split};

pub fn run(a: DatasetArgs) -> anyhow::Result<()> {
    match a.action {
        DatasetAction::Generate(s) => generate(s),
        DatasetAction::Info(s) => info(s),
    }
}

fn generate(s: DatasetSelect) -> anyhow::Result<()> {
    let model = BatteryModel::default();
    let cache_dir = s.cache_dir.clone().unwrap_or_else(dataset::default_cache_dir);
    println!("{:<9} {:<10} {:>7} {:>10} {:>9} {:>9}  status / file", "set", "split", "trajs", "steps", "seconds", "MB");
    for e in s.experiments() {
        let def = e.definition();
        for split in Split::ALL {
            if s.force {
                let path = dataset::cache_path(&cache_dir, &def, split, &model.params);
                if path.exists() {
                    std::fs::remove_file(&path).with_context(|| format!("cannot remove {}", path.display()))?;
                }
            }
            let (ds, rep) = dataset::load_or_generate(&def, &model, &cache_dir, split)?;
            let status = match &rep.status {
                CacheStatus::Hit => "cached".to_string(),
                CacheStatus::Generated => "generated".to_string(),
                CacheStatus::Regenerated { reason } => format!("REGENERATED (cache was corrupt: {reason})"),
            };
            println!(
                "{:<9} {:<10} {:>7} {:>10} {:>9.2} {:>9.1}  {status}: {}",
                e.name(),
                split.name(),
                ds.trajectories.len(),
                ds.total_steps(),
                rep.seconds,
                rep.file_bytes as f64 / 1e6,
                rep.path.display()
            );
        }
    }
    Ok(())
}

fn info(s: DatasetSelect) -> anyhow::Result<()> {
    let model = BatteryModel::default();
    let cache_dir = s.cache_dir.clone().unwrap_or_else(dataset::default_cache_dir);
    for e in s.experiments() {
        let def = e.definition();
        println!("{e}:");
        println!(
            "  grid: qMobile {}..{} C ({} values), Ro {}..{} ohm ({} values), loads {}..{} W ({} values), dt {} s",
            def.q_mobile_c.start,
            def.q_mobile_c.end,
            def.q_mobile_c.n,
            def.r_o_ohm.start,
            def.r_o_ohm.end,
            def.r_o_ohm.n,
            def.loads_w.start,
            def.loads_w.end,
            def.loads_w.n,
            def.dt_s
        );
        for split in Split::ALL {
            let path = dataset::cache_path(&cache_dir, &def, split, &model.params);
            if !path.exists() {
                bail!(
                    "{e} {split} is not cached at {}; run `bcal dataset generate --experiment {e}` first",
                    path.display()
                );
            }
            let ds = dataset::read_cache(&path, def.cache_key(split, &model.params)).map_err(|why| {
                anyhow::anyhow!(
                    "{} cannot be used: {why}; run `bcal dataset generate --experiment {e}`",
                    path.display()
                )
            })?;
            print_split(&ds);
        }
    }
    Ok(())
}

fn print_split(ds: &Dataset) {
    let (mut steps, mut min, mut max) = (0usize, f64::INFINITY, 0.0f64);
    for t in &ds.trajectories {
        steps += t.len();
        let eod = t.eod_s(ds.def.dt_s);
        min = min.min(eod);
        max = max.max(eod);
    }
    let range = |f: fn(&bcal_common::battery::Degradation) -> f64| {
        let v: Vec<f64> = ds.trajectories.iter().map(|t| f(&t.degradation)).collect();
        (v.iter().copied().fold(f64::INFINITY, f64::min), v.iter().copied().fold(0.0, f64::max))
    };
    let (q0, q1) = range(|d| d.q_mobile_c);
    let (r0, r1) = range(|d| d.r_o_ohm);
    let loads: Vec<String> = ds.loads_w().iter().map(|l| format!("{l:.1}")).collect();
    println!(
        "  {:<10} {:>5} trajectories, {steps:>9} steps, EOD {min:.0}..{max:.0} s, loads {} W, qMobile {q0:.0}..{q1:.0} C, \
         Ro {r0:.4}..{r1:.4} ohm",
        ds.split.name(),
        ds.trajectories.len(),
        loads.join(", ")
    );
}
