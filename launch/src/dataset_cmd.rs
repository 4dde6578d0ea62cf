//! `bcal dataset generate|info`: the paper's experiment sets, generated on all cores and cached.

use crate::cli::{DatasetAction, DatasetArgs, DatasetSelect};
use anyhow::{bail, Context};
use bcal_common::battery::BatteryModel;
use bcal_common::dataset::{self, CacheStatus, Dataset};

pub fn run(a: DatasetArgs) -> anyhow::Result<()> {
    match a.action {
        DatasetAction::Generate(s) => generate(s),
        DatasetAction::Info(s) => info(s),
    }
}

fn generate(s: DatasetSelect) -> anyhow::Result<()> {
    let model = BatteryModel::default();
    let cache_dir = s.cache_dir.clone().unwrap_or_else(dataset::default_cache_dir);
    println!("{:<9} {:>7} {:>10} {:>9} {:>9}  status / file", "set", "trajs", "steps", "seconds", "MB");
    for e in s.experiment.experiments() {
        let def = e.definition();
        if s.force {
            let path = dataset::cache_path(&cache_dir, &def, &model.params);
            if path.exists() {
                std::fs::remove_file(&path).with_context(|| format!("cannot remove {}", path.display()))?;
            }
        }
        let (ds, rep) = dataset::load_or_generate(&def, &model, &cache_dir)?;
        let status = match &rep.status {
            CacheStatus::Hit => "cached".to_string(),
            CacheStatus::Generated => "generated".to_string(),
            CacheStatus::Regenerated { reason } => format!("REGENERATED (cache was corrupt: {reason})"),
        };
        println!(
            "{:<9} {:>7} {:>10} {:>9.2} {:>9.1}  {status}: {}",
            e.name(),
            ds.trajectories.len(),
            ds.total_steps(),
            rep.seconds,
            rep.file_bytes as f64 / 1e6,
            rep.path.display()
        );
    }
    Ok(())
}

fn info(s: DatasetSelect) -> anyhow::Result<()> {
    let model = BatteryModel::default();
    let cache_dir = s.cache_dir.clone().unwrap_or_else(dataset::default_cache_dir);
    for e in s.experiment.experiments() {
        let def = e.definition();
        let path = dataset::cache_path(&cache_dir, &def, &model.params);
        if !path.exists() {
            bail!("{e} is not cached at {}; run `bcal dataset generate --experiment {e}` first", path.display());
        }
        let ds = dataset::read_cache(&path, def.cache_key(&model.params)).map_err(|why| {
            anyhow::anyhow!("{} cannot be used: {why}; run `bcal dataset generate --experiment {e}`", path.display())
        })?;
        print_info(&ds);
    }
    Ok(())
}

fn print_info(ds: &Dataset) {
    let def = &ds.def;
    let describe = |name: &str, it: &mut dyn Iterator<Item = &bcal_common::dataset::Trajectory>| {
        let (mut n, mut steps, mut min, mut max) = (0usize, 0usize, f64::INFINITY, 0.0f64);
        for t in it {
            n += 1;
            steps += t.len();
            let eod = t.eod_s(def.dt_s);
            min = min.min(eod);
            max = max.max(eod);
        }
        println!("  {name:<5} {n:>6} trajectories, {steps:>9} steps, EOD {min:.0}..{max:.0} s");
    };
    println!("{}:", def.experiment);
    println!(
        "  qMobile {}..{} C ({} values), Ro {}..{} ohm ({} values), loads {}..{} W ({} values), dt {} s",
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
    let fmt = |v: Vec<f64>| v.iter().map(|l| format!("{l:.1}")).collect::<Vec<_>>().join(", ");
    println!("  train loads W: {}", fmt(def.train_loads_w()));
    println!("  test loads W:  {}", fmt(def.test_loads_w()));
    describe("train", &mut ds.train());
    describe("test", &mut ds.test());
}
