//! The measured-only evaluation's outputs: `report.json` ([`MeasuredReport`]), `report.md` (one table per
//! voltage-noise level, the end-of-discharge table, intervals, step cost, how every choice was made, and a
//! reading generated from the numbers) and the figures: estimates versus time with their 90 % intervals for
//! a few test cells, RL and the joint UKF side by side, and the training curve. Formats; never measures or
//! prints.

use crate::measured_eval::{MeasuredEvaluation, MeasuredReport, MethodScores, Trace, EOD_FRACTIONS, METHODS};
use crate::metrics::ParamValues;
use crate::plots::{font_available, write_training_curve};
use bcal_common::measured::scenario::Episode;
use bcal_common::nrmse::Param;
use plotters::prelude::*;
use std::fmt::Write;
use std::path::{Path, PathBuf};

/// Issue 18's targets, for the reading: the learned calibrator's second-half NRMSE against the joint UKF's,
/// its time to stay within 2 % against the UKF's, its step cost, us, and its coverage, %.
pub const TARGET_SECOND_HALF_RATIO: f64 = 0.8;
pub const TARGET_SETTLE_RATIO: f64 = 0.7;
pub const TARGET_STEP_US: f64 = 20.0;
pub const TARGET_COVERAGE_PCT: [f64; 2] = [85.0, 95.0];

fn f(v: Option<f64>, d: usize) -> String {
    match v {
        Some(x) if x.is_finite() => format!("{x:.d$}"),
        Some(_) => "inf".into(),
        None => "-".into(),
    }
}

fn name_of(key: &str) -> &str {
    METHODS.iter().find(|m| m.0 == key).map_or(key, |m| m.1)
}

fn pair(v: &ParamValues, d: usize) -> String {
    format!("{} / {}", f(v.q_mobile, d), f(v.r_o, d))
}

/// The method table of one test condition.
fn method_table(s: &mut String, methods: &std::collections::BTreeMap<String, MethodScores>) {
    let _ = writeln!(
        s,
        "| Method | NRMSE q / Ro % | second half q / Ro % | per cell: NRMSE / second half q / Ro % | time to 2 % q / Ro s | settled q / Ro | coverage q / Ro % | step us |\n| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"
    );
    for (key, name) in METHODS {
        let Some(m) = methods.get(key) else { continue };
        let _ = writeln!(
            s,
            "| {name} | {} | {} | {} ; {} | {} | {} | {} | {} |",
            pair(&m.nrmse_pct, 2),
            pair(&m.second_half_nrmse_pct, 2),
            pair(&m.all_cells.per_cell_nrmse_pct, 2),
            pair(&m.all_cells.per_cell_second_half_nrmse_pct, 2),
            pair(&m.time_to_2pct_s, 0),
            pair(&m.settled_fraction, 2),
            pair(&m.coverage_90_pct, 1),
            f(m.step_us, 2)
        );
    }
    let _ = writeln!(s);
}

/// The end-of-discharge table of one set of predictions (`which`: under the load so far, or under the
/// oracle load).
fn eod_table(
    s: &mut String,
    methods: &std::collections::BTreeMap<String, MethodScores>,
    which: fn(&MethodScores) -> &std::collections::BTreeMap<String, crate::measured_eval::EodSummary>,
) {
    let mut head = String::from("| Method |");
    let mut rule = String::from("| --- |");
    for fr in EOD_FRACTIONS {
        let _ = write!(head, " {0:.0} %: MAE s | median s | MAE % | failed |", fr * 100.0);
        rule.push_str(" ---: | ---: | ---: | ---: |");
    }
    let _ = writeln!(s, "{head}\n{rule}");
    for (key, name) in METHODS {
        let Some(m) = methods.get(key) else { continue };
        let mut row = format!("| {name} |");
        for fr in EOD_FRACTIONS {
            match which(m).get(&format!("{:.0}", fr * 100.0)) {
                Some(e) => {
                    let _ = write!(
                        row,
                        " {:.1} | {:.1} | {:.2} | {} of {} |",
                        e.mae_s,
                        e.median_abs_s,
                        e.mae_pct_of_discharge,
                        e.failures,
                        e.n + e.failures
                    );
                }
                None => row.push_str(" - | - | - | - |"),
            }
        }
        let _ = writeln!(s, "{row}");
    }
    let _ = writeln!(s);
}

/// `report.md` of a measured-only evaluation.
pub fn render_markdown(r: &MeasuredReport) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# bcal evaluation: measured-only calibration{}\n", if r.quick { " (quick)" } else { "" });
    let _ = writeln!(
        s,
        "The calibrators see only what a battery management system measures: terminal voltage, current and \
         temperature through a sensor model (headline: {:.1} mV voltage noise), read at intervals of {:?} s, from \
         any starting charge at rest, under constant-power, constant-current and piecewise loads. Nothing of the \
         simulated cell's internal state reaches them. Test: {} cells ({} readings) at loads never seen in \
         training ({}); every choice (the joint UKF's settings, the adaptive rule, the direct mapping's early \
         stopping, every method's interval scale, the delivered RL policy) was made on {} validation cells at loads \
         between training and test.\n",
        r.voltage_noise_mv,
        r.sampling_intervals_s,
        r.test_episodes,
        r.test_readings,
        r.test_loads,
        r.validation_episodes
    );
    for (k, why) in &r.not_evaluated {
        let _ = writeln!(s, "**{} was not evaluated:** {why}\n", name_of(k));
    }
    let describe = |p: f64| {
        if p > 0.0 {
            format!("cells carrying model error (each cause with probability {p})")
        } else {
            "cells of the exact model".to_string()
        }
    };
    for level in r.noise_levels.iter().chain(&r.other_model) {
        let other = r.other_model.as_ref().is_some_and(|o| std::ptr::eq(o, level));
        let _ = writeln!(
            s,
            "## {:.1} mV voltage noise, {}{}\n",
            level.voltage_noise_mv,
            describe(level.model_error_probability),
            if other { " (the other test condition)" } else { "" }
        );
        let _ = writeln!(
            s,
            "NRMSE in % of the Table-1 ranges (qMobile 4000-7000 C / Ro 0.1-0.2 ohm): pooled over every reading and \
             over the second half of each discharge, then per cell (each cell's figure, averaged over cells); median \
             time until the estimate enters and stays within 2 % (cells that settle, fraction); 90 % interval \
             coverage.\n"
        );
        method_table(&mut s, &level.methods);
    }
    let _ = writeln!(s, "## By sampling regime ({:.1} mV)\n", r.voltage_noise_mv);
    let _ = writeln!(
        s,
        "Pooled figures weigh each cell by its readings: 1 s cells hold most of them. Each regime apart, pooled and \
         per cell.\n"
    );
    let _ = writeln!(
        s,
        "| Method | regime | cells / readings | NRMSE q / Ro % | second half q / Ro % | per cell second half q / Ro % | coverage q / Ro % |\n| --- | --- | ---: | ---: | ---: | ---: | ---: |"
    );
    for (key, name) in METHODS {
        let Some(m) = r.methods.get(key) else { continue };
        for (regime, b) in &m.by_sampling {
            let _ = writeln!(
                s,
                "| {name} | {regime} | {} / {} | {} | {} | {} | {} |",
                b.cells,
                b.readings,
                pair(&b.nrmse_pct, 2),
                pair(&b.second_half_nrmse_pct, 2),
                pair(&b.per_cell_second_half_nrmse_pct, 2),
                pair(&b.coverage_90_pct, 1)
            );
        }
    }
    let _ = writeln!(s);
    let _ = writeln!(s, "## End-of-discharge prediction ({:.1} mV)\n", r.voltage_noise_mv);
    let _ = writeln!(
        s,
        "Made at 10 / 50 / 90 % of each discharge (load on to cut-off) from the calibrated state and parameters, \
         running the calibrator's model to the cut-off. As a BMS (and `bcal calibrate` on real cells) predicts: under \
         the load so far (its mean measured current, or its mean power where the load has been held at power). Absolute error in s (mean, median), mean in % of the discharge, and the \
         predictions that failed (the model never reached the cut-off), which the errors leave out.\n"
    );
    eod_table(&mut s, &r.methods, |m| &m.eod);
    let _ = writeln!(
        s,
        "The same under the cell's true future load (oracle load: the load is known, the cell is not; this isolates \
         the calibration's share of the error):\n"
    );
    eod_table(&mut s, &r.methods, |m| &m.eod_oracle_load);
    let _ = writeln!(s, "## How every choice was made (validation only)\n");
    if let Some(rl) = &r.rl {
        let _ = writeln!(s, "- RL-LAC policy: {rl}.");
    }
    for (k, v) in &r.interval_scales {
        let _ = writeln!(
            s,
            "- {}: 90 % interval = estimate +- {:.2} (qMobile) and {:.2} (Ro) of its own standard deviations (the scales \
             that cover 90 % of validation readings of each).",
            name_of(k),
            v[0],
            v[1]
        );
    }
    if let Some(b) = &r.ukf_settings {
        let _ = writeln!(
            s,
            "- Joint UKF{}: measurement std {:.1} mV, parameter random walk {:e} per sqrt(s), charge process noise {} C \
             per sqrt(s), prior std {:?} of the ranges.",
            if r.ukf.is_some() { " (tuned here on validation)" } else { " (the task's, tuned on validation when training started)" },
            b.meas_std_v * 1e3,
            b.param_walk_per_sqrt_s,
            b.charge_walk_c_per_sqrt_s,
            b.prior_std_z
        );
    }
    if let Some(u) = &r.ukf {
        let _ = writeln!(
            s,
            "- Joint UKF tuning: {} settings tried on {} validation cells. Numerical rescues on test: {:?}.",
            u.candidates, u.validation_episodes, u.counters_on_test
        );
    }
    if let Some(a) = &r.adaptive_ukf {
        let _ = writeln!(
            s,
            "- Adaptive UKF: {} covariance-matching rules tried on top of the joint UKF; chosen {:?} (validation mean NRMSE \
             {:.2} %, the joint UKF alone {:.2} %).",
            a.top.len(),
            a.best,
            a.top.first().map_or(f64::NAN, |t| t.1),
            a.without_rule_pct
        );
    }
    if let Some(d) = &r.direct_mapping {
        let _ = writeln!(
            s,
            "- Direct mapping: {} training pairs, {} updates in {:.0} s, stopped by {}, weights of update {} (validation \
             MSE {:.2e}).",
            d.pairs,
            d.updates,
            d.seconds,
            d.stopped_by.replace('_', " "),
            d.best_update,
            d.best_validation_loss
        );
    }
    crate::report::write_reading_plots_notes(&mut s, &reading(r), &r.plots, &r.notes);
    let _ = writeln!(s, "\nEvaluation took {:.0} s.", r.seconds);
    s
}

/// Plain statements derived from the numbers, so the reading cannot contradict the tables: the learned
/// calibrator against issue 18's targets (all relative to the joint UKF, and the adaptive UKF's second half).
pub fn reading(r: &MeasuredReport) -> Vec<String> {
    let mut out = Vec::new();
    let get = |k: &str| r.methods.get(k);
    let ok = |b: bool| if b { "met" } else { "missed" };
    if let (Some(rl), Some(ukf)) = (get("rl_lac"), get("ukf")) {
        for p in Param::BOTH {
            let (a, b) = (rl.second_half_nrmse_pct.get(p), ukf.second_half_nrmse_pct.get(p));
            if let (Some(a), Some(b)) = (a, b) {
                out.push(format!(
                    "{}: second-half NRMSE RL-LAC {a:.2} % vs joint UKF {b:.2} %, ratio {:.2} (target <= {TARGET_SECOND_HALF_RATIO}: {}); over every reading {} vs {} %.",
                    p.label(),
                    a / b,
                    ok(a <= TARGET_SECOND_HALF_RATIO * b),
                    f(rl.nrmse_pct.get(p), 2),
                    f(ukf.nrmse_pct.get(p), 2)
                ));
            }
            if let (Some(a), Some(b)) = (rl.time_to_2pct_s.get(p), ukf.time_to_2pct_s.get(p)) {
                out.push(format!(
                    "{}: RL-LAC settles within 2 % in {a:.0} s (median), the UKF in {b:.0} s: ratio {:.2} (target <= {TARGET_SETTLE_RATIO}: {}).",
                    p.label(),
                    a / b.max(1e-9),
                    ok(a <= TARGET_SETTLE_RATIO * b)
                ));
            }
        }
        for fr in ["10", "50"] {
            if let (Some(a), Some(b)) = (rl.eod.get(fr), ukf.eod.get(fr)) {
                out.push(format!(
                    "End of discharge at {fr} % (load so far): RL-LAC MAE {:.1} s ({} failed), joint UKF {:.1} s ({} failed): {}.",
                    a.mae_s,
                    a.failures,
                    b.mae_s,
                    b.failures,
                    ok(a.mae_s <= b.mae_s && a.failures <= b.failures)
                ));
            }
        }
    }
    if let (Some(rl), Some(ad)) = (get("rl_lac"), get("adaptive_ukf")) {
        let beats: Vec<bool> = Param::BOTH
            .iter()
            .map(|p| match (rl.second_half_nrmse_pct.get(*p), ad.second_half_nrmse_pct.get(*p)) {
                (Some(a), Some(b)) => a < b,
                _ => false,
            })
            .collect();
        out.push(format!(
            "Against the adaptive UKF (a rule, no learning), second half: RL-LAC {} vs {} % (q / Ro): {}.",
            pair(&rl.second_half_nrmse_pct, 2),
            pair(&ad.second_half_nrmse_pct, 2),
            if beats.iter().all(|b| *b) {
                "learning beats the rule"
            } else {
                "learning does not beat the rule on both"
            }
        ));
    }
    if let (Some(ad), Some(ukf)) = (get("adaptive_ukf"), get("ukf")) {
        out.push(format!(
            "The adaptive rule against the tuned filter it adapts, second half: {} vs {} % (q / Ro).",
            pair(&ad.second_half_nrmse_pct, 2),
            pair(&ukf.second_half_nrmse_pct, 2)
        ));
    }
    if let Some(rl) = get("rl_lac") {
        if let Some(us) = rl.step_us {
            out.push(format!(
                "RL-LAC costs {us:.2} us per reading (the filter it corrects and the policy): {} the {TARGET_STEP_US} us target.",
                if us <= TARGET_STEP_US { "meets" } else { "misses" }
            ));
        }
        let cov: Vec<String> =
            Param::BOTH.iter().map(|p| format!("{} {} %", p.label(), f(rl.coverage_90_pct.get(*p), 1))).collect();
        out.push(format!(
            "RL-LAC's 90 % intervals cover {} of the test readings (target {}-{} %).",
            cov.join(", "),
            TARGET_COVERAGE_PCT[0],
            TARGET_COVERAGE_PCT[1]
        ));
    }
    if let Some(u) = get("uncalibrated") {
        out.push(format!(
            "The uncalibrated prior scores {} (NRMSE q / Ro %): the error every calibrator starts from.",
            pair(&u.nrmse_pct, 2)
        ));
    }
    out
}

/// Estimates versus time with 90 % bands for a few test cells, RL and the joint UKF side by side: a row per
/// cell and parameter, a column per method, the truth in black.
fn draw_estimates<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    episodes: &[&Episode],
    series: &[(&str, RGBColor, Vec<&Trace>)],
    text: bool,
) -> Result<(), String> {
    let err = |e: &dyn std::fmt::Display| e.to_string();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let cols = series.len().max(1);
    let panels = root.split_evenly((episodes.len().max(1) * 2, cols));
    for (k, e) in episodes.iter().enumerate() {
        for (j, p) in Param::BOTH.into_iter().enumerate() {
            for (m, (name, color, traces)) in series.iter().enumerate() {
                let area = &panels[(k * 2 + j) * cols + m];
                let t_end = e.samples.last().map_or(1.0, |s| s.t_s).max(1.0);
                let truth = p.value(&e.spec.truth);
                let [lo, hi] = p.range();
                let pad = 0.35 * (hi - lo);
                let mut b = ChartBuilder::on(area);
                b.margin(8);
                if text {
                    b.caption(
                        format!("{name}: {} ({}, {:.0} s), {}", p.label(), e.spec.kind.name(), t_end, p.unit()),
                        ("sans-serif", 13),
                    )
                    .x_label_area_size(28)
                    .y_label_area_size(55);
                }
                let mut chart = b.build_cartesian_2d(0.0..t_end, (lo - pad)..(hi + pad)).map_err(|e| err(&e))?;
                if text {
                    chart
                        .configure_mesh()
                        .x_desc("time, s")
                        .light_line_style(TRANSPARENT)
                        .draw()
                        .map_err(|e| err(&e))?;
                }
                let t = traces[k];
                let band: Vec<(f64, f64, f64)> = e
                    .samples
                    .iter()
                    .zip(&t.intervals)
                    .filter_map(|(s, iv)| {
                        iv.map(|iv| {
                            let [a, b] = if p == Param::QMobile { iv.q_mobile_c } else { iv.r_o_ohm };
                            (s.t_s, a, b)
                        })
                    })
                    .collect();
                if band.len() > 1 {
                    let mut poly: Vec<(f64, f64)> = band.iter().map(|b| (b.0, b.2)).collect();
                    poly.extend(band.iter().rev().map(|b| (b.0, b.1)));
                    chart
                        .draw_series(std::iter::once(Polygon::new(poly, color.mix(0.2).filled())))
                        .map_err(|e| err(&e))?;
                }
                let line: Vec<(f64, f64)> =
                    e.samples.iter().zip(&t.estimates).map(|(s, d)| (s.t_s, p.value(d))).collect();
                chart.draw_series(LineSeries::new(line, color.stroke_width(2))).map_err(|e| err(&e))?;
                chart
                    .draw_series(LineSeries::new(vec![(0.0, truth), (t_end, truth)], BLACK.stroke_width(1)))
                    .map_err(|e| err(&e))?;
            }
        }
    }
    root.present().map_err(|e| err(&e))
}

/// Writes the figures, report.json and report.md into `dir`; returns the files written.
pub fn write_outputs(eval: &mut MeasuredEvaluation, dir: &Path, plot_episodes: usize) -> std::io::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir)?;
    let text = font_available();
    let mut written = Vec::new();
    let r = &mut eval.report;
    // A few 1 s cells of different load kinds, the longest of each kind (the most to see).
    let mut picks: Vec<usize> = Vec::new();
    for kind in bcal_common::measured::LoadKind::ALL {
        let best = (0..eval.episodes.len())
            .filter(|&i| eval.episodes[i].spec.kind == kind && eval.episodes[i].spec.interval_s[1] <= 1.0)
            .max_by_key(|&i| eval.episodes[i].samples.len());
        picks.extend(best);
    }
    picks.truncate(plot_episodes);
    let series: Vec<(&str, RGBColor, Vec<&Trace>)> =
        [("rl_lac", "RL-LAC", RGBColor(214, 39, 40)), ("ukf", "Joint UKF", RGBColor(31, 119, 180))]
            .into_iter()
            .filter_map(|(key, name, color)| {
                eval.traces
                    .iter()
                    .find(|t| t.0 == key)
                    .map(|(_, tr)| (name, color, picks.iter().map(|&i| &tr[i]).collect()))
            })
            .collect();
    if !picks.is_empty() && !series.is_empty() {
        let eps: Vec<&Episode> = picks.iter().map(|&i| &eval.episodes[i]).collect();
        let size = (1200, 2 * 240 * picks.len() as u32 + 20);
        for ext in ["png", "svg"] {
            let name = format!("estimates_vs_time.{ext}");
            let path = dir.join(&name);
            let res = if ext == "png" {
                draw_estimates(&BitMapBackend::new(&path, size).into_drawing_area(), &eps, &series, text)
            } else {
                draw_estimates(&SVGBackend::new(&path, size).into_drawing_area(), &eps, &series, text)
            };
            match res {
                Ok(()) => {
                    r.plots.push(name);
                    written.push(path);
                }
                Err(e) => r.notes.push(format!("plot {name} failed: {e}")),
            }
        }
    }
    if let Some(tc) = eval.training_curve.as_ref().filter(|t| !t.is_empty()) {
        let (files, failures) = write_training_curve(dir, tc, text);
        written.extend(files.iter().map(|f| dir.join(f)));
        r.plots.extend(files);
        r.notes.extend(failures.into_iter().map(|f| format!("plot failed: {f}")));
    }
    if !text {
        r.notes.push("no sans-serif font was found: plots have no text; install fonts-dejavu-core".into());
    }
    let p = dir.join("report.json");
    bcal_common::fsutil::write_atomic(&p, serde_json::to_string_pretty(&r).expect("reports serialise").as_bytes())?;
    written.push(p);
    let p = dir.join("report.md");
    bcal_common::fsutil::write_atomic(&p, render_markdown(r).as_bytes())?;
    written.push(p);
    Ok(written)
}

/// The scores of a method at the headline level, for callers that summarise.
pub fn headline<'a>(r: &'a MeasuredReport, key: &str) -> Option<&'a MethodScores> {
    r.methods.get(key)
}
