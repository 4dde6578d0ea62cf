//! Writes a [`Diagnosis`] as `diagnosis.json` (machine-readable, the schema and more) and
//! `diagnosis.md` (the human summary: verdict, candidate table, residual structure, per-cycle fits).

use crate::analysis::Structure;
use crate::diagnose::{Diagnosis, ModelResult};
use crate::error::DoctorError;
use crate::lifetime::Lifetime;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Writes `diagnosis.json` and `diagnosis.md` into `out_dir` (created if needed); returns their paths.
pub fn write_reports(diag: &Diagnosis, out_dir: &Path) -> Result<Vec<PathBuf>, DoctorError> {
    std::fs::create_dir_all(out_dir).map_err(|e| DoctorError::Write { path: out_dir.to_path_buf(), source: e })?;
    let json_path = out_dir.join("diagnosis.json");
    let json = serde_json::to_string_pretty(diag)?;
    std::fs::write(&json_path, json).map_err(|e| DoctorError::Write { path: json_path.clone(), source: e })?;
    let md_path = out_dir.join("diagnosis.md");
    std::fs::write(&md_path, markdown(diag)).map_err(|e| DoctorError::Write { path: md_path.clone(), source: e })?;
    Ok(vec![json_path, md_path])
}

fn structure_rows(out: &mut String, name: &str, s: &Structure) {
    let _ = writeln!(
        out,
        "| {name} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} / {:.1} / {:.1} | {:+.2} | {:+.2} | {:+.2} | {:+.2} |",
        s.under_load.rmse_mv,
        s.rest_before.rmse_mv,
        s.load_on.rmse_mv,
        s.plateau.rmse_mv,
        s.knee.rmse_mv,
        s.relaxation.rmse_mv,
        s.thirds[0].rmse_mv,
        s.thirds[1].rmse_mv,
        s.thirds[2].rmse_mv,
        s.corr_soc,
        s.corr_current,
        s.corr_time,
        s.corr_temperature,
    );
}

fn params_text(m: &ModelResult) -> String {
    if m.params.is_empty() {
        return "-".into();
    }
    m.params.iter().map(|(k, v)| format!("{k} = {v:.4}")).collect::<Vec<_>>().join(", ")
}

/// What a model with shared parameters at their bounds ([`crate::diagnose::at_bounds`]) says to the user
/// (None when none is).
pub fn at_bounds_warning(m: &ModelResult) -> Option<String> {
    if m.at_bounds.is_empty() {
        return None;
    }
    let named: Vec<String> = m.at_bounds.iter().map(|p| format!("{p} = {:.4}", m.params[p])).collect();
    Some(format!(
        "warning: {} at the bound of {} range: the cause stands in for an effect beyond what it can hold, so the \
         extended model's curve outside the fit window is an extrapolation (a calibrator's model carrying it can \
         predict the end of discharge and the capacity worse than the base model)",
        named.join(", "),
        if named.len() == 1 { "its" } else { "their" }
    ))
}

/// The Markdown summary.
pub fn markdown(d: &Diagnosis) -> String {
    let mut o = String::new();
    let _ = writeln!(o, "# Diagnosis of {}\n", d.cell);
    let _ = writeln!(
        o,
        "**Cause: `{}`{}.** Base model held-out RMSE {:.1} mV; extended model ({}) {:.1} mV: gain {:.1} %. \
         Noise estimate {:.1} mV.\n",
        d.cause,
        if d.named_on == "rest_before" { " (named on the rest before the load: the load showed nothing)" } else { "" },
        d.base.heldout_rmse_mv,
        if d.extended.causes.is_empty() { "no extension".to_string() } else { d.extended.causes.join(" + ") },
        d.extended.heldout_rmse_mv,
        d.gain_pct,
        d.noise_mv
    );
    let _ = writeln!(
        o,
        "Extended model parameters shared by all cycles (fitted on the training cycles only, frozen on held-out \
         ones): {}\n",
        params_text(&d.extended)
    );
    if let Some(w) = at_bounds_warning(&d.extended) {
        let _ = writeln!(o, "**{w}**\n");
    }
    let mut per_cycle = vec!["q_mobile_c", "r_o_ohm"];
    per_cycle.extend(d.extended.cycle_params.iter().copied());
    let _ = writeln!(
        o,
        "Per-cycle parameters (calibrated on every cycle by the same bounded least squares, held-out cycles \
         included, as a calibrator would): {}. Per-cycle parameters beyond qMobile and Ro are penalised in the \
         ranking score as the BIC counts them (m per cycle over C held-out cycles and N held-out samples multiply \
         the RMSE by exp(m C ln N / 2N)), but by no less than 1 + {} m; each shared parameter costs {} of the \
         RMSE.\n",
        per_cycle.join(", "),
        d.settings.min_cycle_penalty,
        d.settings.penalty_per_param
    );
    let _ = writeln!(
        o,
        "A cause is named when its held-out gain reaches {} %, over the fit window or over the fit window and the \
         rest before the load (which no parameter is calibrated on; the model predicts it from full charge).\n",
        d.settings.min_gain_pct
    );
    let _ = writeln!(o, "## Candidates (fitted on training cycles, judged on held-out cycles)\n");
    let _ = writeln!(
        o,
        "| rank | cause | shared params | per-cycle params | train RMSE mV | held-out RMSE mV | gain % | gain with rest % | score mV | removes |"
    );
    let _ = writeln!(o, "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for (k, c) in d.candidates.iter().enumerate() {
        let params = c.params.iter().map(|(k, v)| format!("{k} = {v:.4}")).collect::<Vec<_>>().join(", ");
        let removes = c.removes.as_ref().map_or(String::new(), |e| {
            format!(
                "{}: {:.1} -> {:.1} mV; corr({}) {:+.2} -> {:+.2}",
                e.part, e.base_rmse_mv, e.rmse_mv, e.correlation.0, e.correlation.1, e.correlation.2
            )
        });
        let _ = writeln!(
            o,
            "| {} | `{}` | {} | {} | {:.2} | {:.2} | {:.1} | {:.1} | {:.2} | {} |",
            k + 1,
            c.cause,
            if params.is_empty() { "-".to_string() } else { params },
            if c.cycle_params.is_empty() { "-".to_string() } else { c.cycle_params.join(", ") },
            c.train_rmse_mv,
            c.heldout_rmse_mv,
            c.gain_pct,
            c.record_gain_pct,
            c.score_mv,
            removes
        );
    }
    let _ =
        writeln!(o, "\n## Where the residual lives (measured - model, RMSE mV; correlations of the loaded residual)\n");
    let _ = writeln!(
        o,
        "| model | under load | rest before | load-on | plateau | knee | relaxation | thirds | corr SOC | corr current | corr time | corr temperature |"
    );
    let _ = writeln!(o, "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    structure_rows(&mut o, "base, training", &d.base_train_structure);
    structure_rows(&mut o, "base, held-out", &d.base.heldout_structure);
    structure_rows(&mut o, "extended, held-out", &d.extended.heldout_structure);
    let _ = writeln!(o, "\n## Per-cycle fits (held-out)\n");
    let _ = writeln!(
        o,
        "| cycle | base qMobile C | base Ro ohm | base RMSE mV | extended qMobile C | extended Ro ohm | extended per-cycle | extended RMSE mV |"
    );
    let _ = writeln!(o, "| --- | --- | --- | --- | --- | --- | --- | --- |");
    for (b, e) in d.base.heldout_cycles.iter().zip(&d.extended.heldout_cycles) {
        let extra = e.extra.iter().map(|(k, v)| format!("{k} = {v:.4}")).collect::<Vec<_>>().join(", ");
        let _ = writeln!(
            o,
            "| {} | {:.0} | {:.4} | {:.1} | {:.0} | {:.4} | {} | {:.1} |",
            b.cycle,
            b.q_mobile_c,
            b.r_o_ohm,
            b.rmse_mv,
            e.q_mobile_c,
            e.r_o_ohm,
            if extra.is_empty() { "-".to_string() } else { extra },
            e.rmse_mv
        );
    }
    if !d.rest_candidates.is_empty() {
        let _ = writeln!(
            o,
            "\n## Candidates judged with the rest before the load (the load showed nothing, the rest did)\n\n\
             Fitted on the training loads and rests, judged on the held-out loads and rests; best first by that \
             RMSE{}.\n",
            if d.named_on == "rest_before" { " (the verdict rests on this table)" } else { " (none gained enough)" }
        );
        let _ = writeln!(o, "| cause | shared params | held-out load RMSE mV | gain % | gain with rest % |");
        let _ = writeln!(o, "| --- | --- | --- | --- | --- |");
        for c in &d.rest_candidates {
            let params = c.params.iter().map(|(k, v)| format!("{k} = {v:.4}")).collect::<Vec<_>>().join(", ");
            let _ = writeln!(
                o,
                "| `{}` | {} | {:.2} | {:.1} | {:.1} |",
                c.cause, params, c.heldout_rmse_mv, c.gain_pct, c.record_gain_pct
            );
        }
    }
    if let Some(l) = &d.lifetime {
        lifetime_section(&mut o, l);
    }
    let _ = writeln!(o, "\n## Records\n");
    let excluded: Vec<String> = d
        .records
        .iter()
        .filter(|r| r.role == "excluded")
        .map(|r| format!("cycle {} ({}): {}", r.cycle, r.file, r.note.clone().unwrap_or_default()))
        .collect();
    let _ = writeln!(
        o,
        "{} training and {} held-out records; {} truncated; {} excluded{}",
        d.records.iter().filter(|r| r.role == "train").count(),
        d.records.iter().filter(|r| r.role == "heldout").count(),
        d.truncated_count,
        excluded.len(),
        if excluded.is_empty() { ".".to_string() } else { format!(":\n\n- {}", excluded.join("\n- ")) }
    );
    let s = &d.settings;
    let _ = writeln!(
        o,
        "\nSettings: simulator step <= {} s, load above {} A, fit floor {} V, samples within {} s of a load step left \
         out, naming gain >= {} %, step gain >= {} %, penalty {} per shared and at least {} per per-cycle parameter, \
         noise factor {}, at most {} causes.",
        s.dt_max_s,
        s.load_threshold_a,
        s.v_floor_v,
        s.settle_s,
        s.min_gain_pct,
        s.min_step_gain_pct,
        s.penalty_per_param,
        s.min_cycle_penalty,
        s.noise_factor,
        s.max_causes
    );
    o
}

/// The cell's life: the verdict on recovery after rest, the model's numbers, the held-out capacity errors,
/// and the per-cycle series.
fn lifetime_section(o: &mut String, l: &Lifetime) {
    let f = |x: Option<f64>, p: usize| x.map_or("-".to_string(), |v| format!("{v:.p$}"));
    let _ = writeln!(o, "\n## The cell's life across discharges\n");
    let _ = writeln!(
        o,
        "**Recovery after rest{}:** {}. Fitted on cycles {}-{}, judged on {}-{}; capacity is the charge drawn \
         under load to the cut-off. Model: capacity = trend (linear in cycle, and in ambient temperature and load \
         current when they vary) + A R, where each rest fills R by 1 - exp(-rest / tau) and each discharge wears \
         it off by exp(-1 / d).\n",
        if l.recovery { "" } else { " not named" },
        l.verdict,
        l.train_cycles.0,
        l.train_cycles.1,
        l.heldout_cycles.0,
        l.heldout_cycles.1
    );
    let _ = writeln!(
        o,
        "| A Ah | tau h | d discharges | usual rest h | longest rest h | its jump Ah | held-out capacity RMSE one ahead, \
         without -> with, Ah | gain % |"
    );
    let _ = writeln!(o, "| --- | --- | --- | --- | --- | --- | --- | --- |");
    let _ = writeln!(
        o,
        "| {} | {} | {} | {} | {} | {} | {} -> {} | {} |",
        f(l.amplitude_ah, 3),
        f(l.tau_rest_h, 1),
        f(l.decay_discharges, 1),
        f(l.usual_rest_s.map(|s| s / 3600.0), 1),
        f(l.longest_rest_s.map(|s| s / 3600.0), 1),
        f(l.largest_jump_ah, 3),
        f(l.heldout_capacity_rmse_without_ah, 4),
        f(l.heldout_capacity_rmse_ah, 4),
        f(l.gain_pct, 0)
    );
    for s in [&l.capacity, &l.q_mobile].into_iter().flatten() {
        let _ = writeln!(
            o,
            "\n{:?}: {} training and {} held-out values; one ahead {:.4} -> {:.4} ({:.0} %), open loop {:.4} -> {:.4} \
             ({:.0} %); {:.0} % of held-out values inside the one-ahead 90 % interval.",
            s.quantity,
            s.train_points,
            s.heldout_points,
            s.heldout_rmse_without,
            s.heldout_rmse,
            s.gain_pct,
            s.open_loop_rmse_without,
            s.open_loop_rmse,
            s.open_loop_gain_pct,
            100.0 * s.interval_coverage
        );
    }
    for n in &l.notes {
        let _ = writeln!(o, "\nNote: {n}");
    }
    let _ = writeln!(
        o,
        "\n| cycle | role | rest before h | capacity Ah | predicted Ah (with / without recovery) | R | ambient C | current A | base qMobile C | base Ro ohm |"
    );
    let _ = writeln!(o, "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for p in &l.series {
        let _ = writeln!(
            o,
            "| {} | {} | {} | {} | {} / {} | {} | {:.1} | {:.2} | {} | {} |",
            p.cycle,
            p.role,
            f(p.rest_before_s.map(|s| s / 3600.0), 1),
            f(p.capacity_ah, 4),
            f(p.predicted_ah, 4),
            f(p.predicted_without_recovery_ah, 4),
            f(p.recovery, 3),
            p.condition.ambient_c,
            p.condition.current_a,
            f(p.q_mobile_c, 0),
            f(p.r_o_ohm, 4)
        );
    }
}
