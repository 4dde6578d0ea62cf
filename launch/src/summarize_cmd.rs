//! `bcal summarize RUN...`: the headline figures of several evaluated runs (other seeds of one setting) as
//! mean, standard deviation, minimum and maximum, with every run's value: on stdout, and as summary.json and
//! summary.md when `--out DIR` is given.

use anyhow::Context;
use bcal_eval::summary::{self, AnyReport, RunInput, ValidationTrace};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct SummarizeArgs {
    /// Run folders, each with a report.json from `bcal eval` (and metrics.jsonl from training).
    #[arg(required = true, num_args = 1..)]
    pub runs: Vec<PathBuf>,
    /// Name of the report inside each run folder (e.g. a report written with `bcal eval --out`).
    #[arg(long, default_value = "report.json")]
    pub report: String,
    /// Folder to write summary.json and summary.md into.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn run(a: SummarizeArgs) -> anyhow::Result<()> {
    let mut inputs = Vec::new();
    // Each run counts once, and every run is a seed of one setting (their config.toml alike but the seed).
    let mut seen: Vec<(PathBuf, &PathBuf)> = Vec::new();
    let mut setting: Option<(String, &PathBuf)> = None;
    for dir in &a.runs {
        let canonical = std::fs::canonicalize(dir).unwrap_or_else(|_| dir.clone());
        if let Some((_, first)) = seen.iter().find(|(c, _)| *c == canonical) {
            anyhow::bail!("{} and {} are the same run: give each run once", first.display(), dir.display());
        }
        seen.push((canonical, dir));
        if let Ok(mut c) = bcal_common::config::TrainConfig::from_file(&dir.join("config.toml")) {
            c.seed = 0;
            let toml = c.to_toml();
            match &setting {
                Some((first, first_dir)) if *first != toml => anyhow::bail!(
                    "{} and {} were trained on different settings (their config.toml differ beyond the seed): \
                     summarize the seeds of one setting",
                    first_dir.display(),
                    dir.display()
                ),
                Some(_) => {}
                None => setting = Some((toml, dir)),
            }
        }
    }
    for dir in &a.runs {
        let path = dir.join(&a.report);
        let text = std::fs::read_to_string(&path).with_context(|| {
            format!("cannot read {}; evaluate the run first (bcal eval --run {})", path.display(), dir.display())
        })?;
        let report = AnyReport::parse(&text)
            .with_context(|| format!("{} is not a bcal report (written by another version?)", path.display()))?;
        let validation = std::fs::read_to_string(dir.join("metrics.jsonl")).ok().map(|t| ValidationTrace::parse(&t));
        inputs.push(RunInput { name: dir.display().to_string(), report, validation });
    }
    let s = summary::summarize(&inputs).map_err(anyhow::Error::msg)?;
    let md = summary::render_markdown(&s);
    print!("{md}");
    if let Some(out) = &a.out {
        std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
        for (name, bytes) in
            [("summary.json", serde_json::to_string_pretty(&s)?.into_bytes()), ("summary.md", md.into_bytes())]
        {
            let p = out.join(name);
            bcal_common::fsutil::write_atomic(&p, &bytes).with_context(|| format!("cannot write {}", p.display()))?;
        }
        println!("wrote {}/summary.json and summary.md", out.display());
    }
    Ok(())
}
