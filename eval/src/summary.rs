//! Several runs of the same setting (other seeds, other budgets) summarised as mean, standard deviation,
//! minimum and maximum of every headline figure: Table 1 (per-step and per-cycle NRMSE), Table 2 (step
//! cost), the EOD errors, and for RL the validation score of the delivered policy beside the best and the
//! last validation the learner saw. A headline figure is a spread over seeds, never one run.
//!
//! Inputs are each run's `report.json` and, when present, its `metrics.jsonl`; this module never prints.

use crate::metrics::Param;
use crate::report::{Report, METHODS};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write;

/// Mean, sample standard deviation, minimum and maximum of one figure over runs.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Spread {
    pub n: usize,
    pub mean: f64,
    pub std: f64,
    pub min: f64,
    pub max: f64,
}

impl Spread {
    pub fn of(values: &[f64]) -> Option<Self> {
        let v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return None;
        }
        let n = v.len();
        let mean = v.iter().sum::<f64>() / n as f64;
        let std = if n > 1 { (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt() } else { 0.0 };
        let min = v.iter().copied().fold(f64::INFINITY, f64::min);
        let max = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        Some(Self { n, mean, std, min, max })
    }

    /// "mean ± std (min-max)" with `digits` decimals.
    pub fn show(&self, digits: usize) -> String {
        format!("{:.d$} ± {:.d$} ({:.d$}-{:.d$})", self.mean, self.std, self.min, self.max, d = digits)
    }
}

/// The learner's validation curve of one run, read from metrics.jsonl.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ValidationTrace {
    /// (update, qMobile NRMSE %, Ro NRMSE %, tracking error) of every validation line.
    pub points: Vec<(u64, f64, f64, f64)>,
}

impl ValidationTrace {
    pub fn parse(metrics_jsonl: &str) -> Self {
        let points = metrics_jsonl
            .lines()
            .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
            .filter(|v| v.get("kind").and_then(|k| k.as_str()) == Some("validation"))
            .filter_map(|v| {
                let f = |k: &str| v.get(k).and_then(|x| x.as_f64());
                Some((
                    v.get("update")?.as_u64()?,
                    f("val_nrmse_q_pct")?,
                    f("val_nrmse_r_pct")?,
                    f("val_tracking_error")?,
                ))
            })
            .collect();
        Self { points }
    }

    /// The validation with the lowest mean of the two NRMSEs: (q, r).
    pub fn best_nrmse(&self) -> Option<(f64, f64)> {
        self.points.iter().min_by(|a, b| (a.1 + a.2).total_cmp(&(b.1 + b.2))).map(|p| (p.1, p.2))
    }

    /// The last validation: (q, r).
    pub fn last(&self) -> Option<(f64, f64)> {
        self.points.last().map(|p| (p.1, p.2))
    }
}

/// One run's report, of either setting.
pub enum AnyReport {
    Paper(Box<Report>),
    Measured(Box<crate::measured_eval::MeasuredReport>),
}

impl AnyReport {
    /// Parses report.json of either setting (the measured one says `"observation": "Measured"`).
    pub fn parse(text: &str) -> Result<Self, serde_json::Error> {
        let v: serde_json::Value = serde_json::from_str(text)?;
        if v.get("observation").and_then(|o| o.as_str()) == Some("Measured") {
            Ok(AnyReport::Measured(Box::new(serde_json::from_value(v)?)))
        } else {
            Ok(AnyReport::Paper(Box::new(serde_json::from_value(v)?)))
        }
    }

    fn experiment(&self) -> String {
        match self {
            AnyReport::Paper(r) => r.experiment.clone(),
            AnyReport::Measured(_) => "measured".into(),
        }
    }

    fn size(&self) -> (usize, bool) {
        match self {
            AnyReport::Paper(r) => (r.test_trajectories, r.quick),
            AnyReport::Measured(r) => (r.test_episodes, r.quick),
        }
    }
}

/// One run's inputs.
pub struct RunInput {
    pub name: String,
    pub report: AnyReport,
    pub validation: Option<ValidationTrace>,
}

/// One summarised figure.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Row {
    /// Method key ("rl_lac", "ukf", "direct_mapping").
    pub method: String,
    /// What is summarised, e.g. "nrmse_pct.q_mobile".
    pub figure: String,
    pub spread: Spread,
    /// The value of every run, in input order (None where the run lacks it).
    pub per_run: Vec<Option<f64>>,
}

/// What `summary.json` holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub runs: Vec<String>,
    pub experiment: String,
    pub rows: Vec<Row>,
    /// Settings that differ between the runs' reports (a summary mixes seeds, not setups): names of
    /// the fields that disagree, empty when they agree.
    pub mismatches: Vec<String>,
}

/// The figures of a measured-only report (its headline noise level), by (method, figure).
fn figures_measured(r: &crate::measured_eval::MeasuredReport) -> BTreeMap<(String, String), f64> {
    let mut out = BTreeMap::new();
    for (key, m) in &r.methods {
        let mut put = |fig: String, val: Option<f64>| {
            if let Some(x) = val.filter(|x| x.is_finite()) {
                out.insert((key.clone(), fig), x);
            }
        };
        for p in Param::BOTH {
            put(format!("nrmse_pct.{}", p.key()), m.nrmse_pct.get(p));
            put(format!("second_half_nrmse_pct.{}", p.key()), m.second_half_nrmse_pct.get(p));
            put(format!("time_to_2pct_s.{}", p.key()), m.time_to_2pct_s.get(p));
            put(format!("coverage_90_pct.{}", p.key()), m.coverage_90_pct.get(p));
        }
        put("step_us".into(), m.step_us);
        for (f, e) in &m.eod {
            put(format!("eod.at_{f}pct.mae_s"), Some(e.mae_s));
        }
    }
    // Every noise level's accuracy (the headline level's is above too).
    for level in &r.noise_levels {
        for (key, m) in &level.methods {
            for p in Param::BOTH {
                let mv = level.voltage_noise_mv;
                for (fig, v) in
                    [("nrmse_pct", m.nrmse_pct.get(p)), ("second_half_nrmse_pct", m.second_half_nrmse_pct.get(p))]
                {
                    if let Some(x) = v.filter(|x| x.is_finite()) {
                        out.insert((key.clone(), format!("at_{mv}mv.{fig}.{}", p.key())), x);
                    }
                }
            }
        }
    }
    out
}

/// The figures of one report, by (method, figure).
fn figures(r: &AnyReport, v: Option<&ValidationTrace>) -> BTreeMap<(String, String), f64> {
    match r {
        AnyReport::Paper(p) => figures_paper(p, v),
        AnyReport::Measured(m) => {
            let mut out = figures_measured(m);
            if let Some(v) = v {
                let pick =
                    |pair: Option<(f64, f64)>, p: Param| pair.map(|(q, r)| if p == Param::QMobile { q } else { r });
                for p in Param::BOTH {
                    for (fig, val) in [
                        ("training_best_validation_nrmse_pct", pick(v.best_nrmse(), p)),
                        ("training_last_validation_nrmse_pct", pick(v.last(), p)),
                    ] {
                        if let Some(x) = val {
                            out.insert(("rl_lac".into(), format!("{fig}.{}", p.key())), x);
                        }
                    }
                }
            }
            out
        }
    }
}

/// The figures of one paper-setting report, by (method, figure).
fn figures_paper(r: &Report, v: Option<&ValidationTrace>) -> BTreeMap<(String, String), f64> {
    let mut out = BTreeMap::new();
    let params = r.calibrated_params();
    for (key, _) in METHODS {
        let Some(m) = r.methods.get(key) else { continue };
        let mut put = |fig: String, val: Option<f64>| {
            if let Some(x) = val {
                out.insert((key.to_string(), fig), x);
            }
        };
        for p in &params {
            put(format!("nrmse_pct.{}", p.key()), m.accuracy.nrmse_pct.get(*p));
            put(format!("cycle_nrmse_pct.{}", p.key()), m.accuracy.cycle_nrmse_pct.get(*p));
        }
        put("step_us".into(), Some(m.step_us));
        put("eod.at_10pct.mae_s".into(), Some(m.eod.at_10pct.mae_s));
        put("eod.at_50pct.mae_s".into(), Some(m.eod.at_50pct.mae_s));
        if let Some(rl) = &m.rl {
            for p in &params {
                put(format!("validation_nrmse_pct.{}", p.key()), rl.validation_nrmse_pct.get(*p));
            }
            put("update_step".into(), Some(rl.update_step as f64));
            if let Some(v) = v {
                let pick =
                    |pair: Option<(f64, f64)>, p: Param| pair.map(|(q, r)| if p == Param::QMobile { q } else { r });
                for p in &params {
                    put(format!("training_best_validation_nrmse_pct.{}", p.key()), pick(v.best_nrmse(), *p));
                    put(format!("training_last_validation_nrmse_pct.{}", p.key()), pick(v.last(), *p));
                }
            }
        }
    }
    out
}

/// Summarises runs of one experiment; runs of different experiments are refused.
pub fn summarize(runs: &[RunInput]) -> Result<Summary, String> {
    let first = runs.first().ok_or("no runs to summarise")?;
    let experiment = first.report.experiment();
    let mut mismatches = Vec::new();
    for r in runs {
        if r.report.experiment() != experiment {
            return Err(format!(
                "run {} is of experiment {}, run {} of {experiment}: summarise one experiment at a time",
                r.name,
                r.report.experiment(),
                first.name
            ));
        }
        let ((n, quick), (n0, quick0)) = (r.report.size(), first.report.size());
        if n != n0 && !mismatches.contains(&"test set size".into()) {
            mismatches.push("test set size".to_string());
        }
        if quick != quick0 && !mismatches.contains(&"quick".into()) {
            mismatches.push("quick".to_string());
        }
    }
    let per_run: Vec<BTreeMap<(String, String), f64>> =
        runs.iter().map(|r| figures(&r.report, r.validation.as_ref())).collect();
    let mut keys: Vec<(String, String)> = per_run.iter().flat_map(|m| m.keys().cloned()).collect();
    let order = |m: &str| {
        METHODS.iter().position(|x| x.0 == m).or_else(|| crate::measured_eval::METHODS.iter().position(|x| x.0 == m))
    };
    keys.sort_by_key(|(m, f)| (order(m).unwrap_or(9), f.clone()));
    keys.dedup();
    let rows = keys
        .into_iter()
        .filter_map(|k| {
            let vals: Vec<Option<f64>> = per_run.iter().map(|m| m.get(&k).copied()).collect();
            let present: Vec<f64> = vals.iter().flatten().copied().collect();
            Spread::of(&present).map(|spread| Row { method: k.0, figure: k.1, spread, per_run: vals })
        })
        .collect();
    Ok(Summary { runs: runs.iter().map(|r| r.name.clone()).collect(), experiment, rows, mismatches })
}

/// `summary.md`: one table, mean ± std (min-max) over the runs, and every run's value.
pub fn render_markdown(s: &Summary) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "# bcal summary: {} runs of {}\n", s.runs.len(), s.experiment);
    let _ = writeln!(out, "Runs: {}.\n", s.runs.join(", "));
    if !s.mismatches.is_empty() {
        let _ = writeln!(
            out,
            "**Warning:** the runs differ in {}; they are not repeats of one setup.\n",
            s.mismatches.join(", ")
        );
    }
    let _ = writeln!(out, "| method | figure | mean ± std (min-max) | n | per run |\n| --- | --- | --- | ---: | --- |");
    for r in &s.rows {
        let name = METHODS
            .iter()
            .chain(crate::measured_eval::METHODS.iter())
            .find(|m| m.0 == r.method)
            .map_or(r.method.as_str(), |m| m.1);
        let digits = if r.figure.starts_with("update") || r.figure.contains("mae_s") { 1 } else { 3 };
        let each: Vec<String> =
            r.per_run.iter().map(|v| v.map_or("-".into(), |x| format!("{x:.d$}", d = digits))).collect();
        let _ = writeln!(
            out,
            "| {name} | {} | {} | {} | {} |",
            r.figure,
            r.spread.show(digits),
            r.spread.n,
            each.join(", ")
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_is_mean_sample_std_min_max_and_skips_non_finite() {
        let s = Spread::of(&[1.0, 2.0, 3.0, f64::NAN]).unwrap();
        assert_eq!((s.n, s.mean, s.std, s.min, s.max), (3, 2.0, 1.0, 1.0, 3.0));
        assert_eq!(Spread::of(&[5.0]).unwrap().std, 0.0);
        assert!(Spread::of(&[]).is_none());
        assert_eq!(s.show(1), "2.0 ± 1.0 (1.0-3.0)");
    }

    #[test]
    fn validation_trace_picks_the_best_and_the_last() {
        let t = ValidationTrace::parse(
            "{\"kind\":\"validation\",\"update\":1,\"val_nrmse_q_pct\":5.0,\"val_nrmse_r_pct\":5.0,\"val_tracking_error\":0.3}\n\
             {\"kind\":\"train\",\"update\":2}\n\
             {\"kind\":\"validation\",\"update\":3,\"val_nrmse_q_pct\":1.0,\"val_nrmse_r_pct\":2.0,\"val_tracking_error\":0.1}\n\
             {\"kind\":\"validation\",\"update\":4,\"val_nrmse_q_pct\":4.0,\"val_nrmse_r_pct\":1.0,\"val_tracking_error\":0.2}\n",
        );
        assert_eq!(t.points.len(), 3);
        assert_eq!(t.best_nrmse(), Some((1.0, 2.0)));
        assert_eq!(t.last(), Some((4.0, 1.0)));
    }
}
