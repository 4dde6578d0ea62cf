//! The evaluation's figures, each written as PNG and SVG with plotters: estimated versus true parameters
//! along the test trajectories grouped by load (the paper's Figs. 2 and 3, for every method), the per-step
//! error distribution of each method (cumulative, log axis), and the training curve from the run's `metrics.jsonl`.
//!
//! Text uses plotters' "ttf" feature (font-kit over fontconfig, the workspace's one font path), which finds
//! DejaVu Sans from Debian's fonts-dejavu-core. Without any font the figures are still drawn and written,
//! without captions, labels and legends, and the caller is told so ([`PlotOutcome::text`]).
//! This module never prints.

use crate::metrics::{cycle_estimate, Param, TrajEstimates};
use bcal_common::mdp::Calibrated;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;

/// Largest number of trajectories drawn per panel (evenly thinned beyond it, so SVGs stay small).
const MAX_TRAJ_DRAWN: usize = 400;
/// Points per error CDF, and its axis range, % of the parameter range (smaller errors sit at the left edge).
const CDF_POINTS: usize = 200;
const CDF_MIN_PCT: f64 = 1e-4;
const CDF_MAX_PCT: f64 = 100.0;

/// One method's estimates for the figures.
pub struct MethodSeries<'a> {
    pub name: &'a str,
    pub color: RGBColor,
    pub trajs: &'a [TrajEstimates],
}

/// Colour of each method, by report key.
pub fn method_color(key: &str) -> RGBColor {
    match key {
        "rl_lac" => RGBColor(214, 39, 40),
        "ukf" => RGBColor(31, 119, 180),
        _ => RGBColor(44, 160, 44),
    }
}

/// One `"kind":"validation"` line of `metrics.jsonl`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ValidationPoint {
    pub update: f64,
    pub nrmse_q_pct: Option<f64>,
    pub nrmse_r_pct: Option<f64>,
    pub cost: Option<f64>,
}

/// One `"kind":"train"` line of `metrics.jsonl`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrainPoint {
    pub update: f64,
    pub mean_cost: Option<f64>,
    pub critic_loss: Option<f64>,
}

/// A named line of a figure.
type Series<'a> = (&'a str, RGBColor, Vec<(f64, f64)>);

/// The training curve of a run, from `metrics.jsonl`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TrainingCurve {
    /// Every validation line.
    pub validation: Vec<ValidationPoint>,
    /// Every training line.
    pub train: Vec<TrainPoint>,
    /// Lines that were not JSON objects with an update number.
    pub skipped_lines: usize,
}

impl TrainingCurve {
    /// Parses JSON lines; a malformed line (e.g. the last one of a killed run) is counted and skipped.
    pub fn parse(text: &str) -> Self {
        let mut c = Self::default();
        for line in text.lines().filter(|l| !l.trim().is_empty()) {
            let Ok(v) = serde_json::from_str::<serde_json::Value>(line) else {
                c.skipped_lines += 1;
                continue;
            };
            let num = |k: &str| v.get(k).and_then(|x| x.as_f64()).filter(|x| x.is_finite());
            let Some(update) = num("update") else {
                c.skipped_lines += 1;
                continue;
            };
            match v.get("kind").and_then(|k| k.as_str()) {
                Some("validation") => c.validation.push(ValidationPoint {
                    update,
                    nrmse_q_pct: num("val_nrmse_q_pct"),
                    nrmse_r_pct: num("val_nrmse_r_pct"),
                    cost: num("val_tracking_error"),
                }),
                Some("train") => {
                    c.train.push(TrainPoint { update, mean_cost: num("mean_cost"), critic_loss: num("critic_loss") })
                }
                _ => {}
            }
        }
        c
    }

    pub fn is_empty(&self) -> bool {
        self.validation.is_empty() && self.train.is_empty()
    }
}

/// What [`write_all`] wrote.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlotOutcome {
    /// File names written into the folder.
    pub files: Vec<String>,
    /// Whether text (captions, labels, legends) could be drawn.
    pub text: bool,
    /// Figures that failed, with the reason (the others are still written).
    pub failures: Vec<String>,
}

/// True when plotters can lay out text with a system sans-serif font.
pub fn font_available() -> bool {
    ("sans-serif", 12).into_font().box_size("Ag0").is_ok()
}

type DrawResult = Result<(), String>;

fn err<E: std::fmt::Display>(e: E) -> String {
    e.to_string()
}

/// Writes every figure as PNG and SVG into `dir`. `text = None` detects the font.
pub fn write_all(
    dir: &Path,
    calibrated: Calibrated,
    methods: &[MethodSeries],
    training: Option<&TrainingCurve>,
    text: Option<bool>,
) -> PlotOutcome {
    let text = text.unwrap_or_else(font_available);
    let mut out = PlotOutcome { text, ..Default::default() };
    let params = crate::metrics::params_of(calibrated);
    let n_methods = methods.len().max(1);
    let mut figure = |stem: &str, size: (u32, u32), fig: Fig| {
        for ext in ["png", "svg"] {
            let name = format!("{stem}.{ext}");
            let path = dir.join(&name);
            let res = if ext == "png" {
                render(BitMapBackend::new(&path, size).into_drawing_area(), fig, text)
            } else {
                render(SVGBackend::new(&path, size).into_drawing_area(), fig, text)
            };
            match res {
                Ok(()) => out.files.push(name),
                Err(e) => out.failures.push(format!("{name}: {e}")),
            }
        }
    };
    if !methods.is_empty() {
        let size = (560 * params.len() as u32 + 80, 300 * n_methods as u32 + 40);
        figure("params_vs_truth", size, Fig::Params { params, methods });
        figure("error_distribution", (560 * params.len() as u32 + 80, 420), Fig::Errors { params, methods });
    }
    if let Some(tc) = training.filter(|t| !t.is_empty()) {
        figure("training_curve", (1200, 420), Fig::Training(tc));
    }
    out
}

/// Writes only the training curve (PNG and SVG) into `dir`; returns the file names written and failures.
pub fn write_training_curve(dir: &Path, tc: &TrainingCurve, text: bool) -> (Vec<String>, Vec<String>) {
    let (mut files, mut failures) = (Vec::new(), Vec::new());
    for ext in ["png", "svg"] {
        let name = format!("training_curve.{ext}");
        let path = dir.join(&name);
        let res = if ext == "png" {
            render(BitMapBackend::new(&path, (1200, 420)).into_drawing_area(), Fig::Training(tc), text)
        } else {
            render(SVGBackend::new(&path, (1200, 420)).into_drawing_area(), Fig::Training(tc), text)
        };
        match res {
            Ok(()) => files.push(name),
            Err(e) => failures.push(format!("{name}: {e}")),
        }
    }
    (files, failures)
}

/// A figure to draw on any backend.
#[derive(Clone, Copy)]
enum Fig<'a> {
    Params { params: &'a [Param], methods: &'a [MethodSeries<'a>] },
    Errors { params: &'a [Param], methods: &'a [MethodSeries<'a>] },
    Training(&'a TrainingCurve),
}

fn render<DB: DrawingBackend>(root: DrawingArea<DB, Shift>, fig: Fig, text: bool) -> DrawResult {
    root.fill(&WHITE).map_err(err)?;
    match fig {
        Fig::Params { params, methods } => draw_params(&root, params, methods, text)?,
        Fig::Errors { params, methods } => draw_errors(&root, params, methods, text)?,
        Fig::Training(tc) => draw_training(&root, tc, text)?,
    }
    root.present().map_err(err)
}

/// Trajectory order of the paper's figures: grouped by load (left to right increasing), then by the true
/// value of the parameter.
fn traj_order(trajs: &[TrajEstimates], p: Param) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..trajs.len()).collect();
    idx.sort_by(|&a, &b| {
        trajs[a].load_w.total_cmp(&trajs[b].load_w).then(p.value(&trajs[a].truth).total_cmp(&p.value(&trajs[b].truth)))
    });
    if idx.len() > MAX_TRAJ_DRAWN {
        let step = idx.len() as f64 / MAX_TRAJ_DRAWN as f64;
        idx = (0..MAX_TRAJ_DRAWN).map(|k| idx[(k as f64 * step) as usize]).collect();
    }
    idx
}

fn quantile(v: &mut [f64], q: f64) -> f64 {
    bcal_common::stats::quantile(v, q).unwrap_or(f64::NAN)
}

fn draw_params<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    params: &[Param],
    methods: &[MethodSeries],
    text: bool,
) -> DrawResult {
    let panels = root.split_evenly((methods.len(), params.len()));
    for (m_i, m) in methods.iter().enumerate() {
        for (p_i, &p) in params.iter().enumerate() {
            let area = &panels[m_i * params.len() + p_i];
            let order = traj_order(m.trajs, p);
            let [lo, hi] = p.range();
            let pad = 0.15 * (hi - lo);
            let mut b = ChartBuilder::on(area);
            b.margin(8);
            if text {
                b.caption(
                    format!("{}: {} ({}) along test trajectories", m.name, p.label(), p.unit()),
                    ("sans-serif", 15),
                )
                .x_label_area_size(30)
                .y_label_area_size(60);
            }
            let mut chart =
                b.build_cartesian_2d(0f64..order.len().max(1) as f64, (lo - pad)..(hi + pad)).map_err(err)?;
            if text {
                chart
                    .configure_mesh()
                    .disable_x_mesh()
                    .light_line_style(TRANSPARENT)
                    .x_label_formatter(&|x| format!("{x:.0}"))
                    .x_desc("test trajectory (grouped by load, low to high; by true value within a load)")
                    .y_desc(p.unit())
                    .draw()
                    .map_err(err)?;
            } else {
                chart
                    .plotting_area()
                    .draw(&Rectangle::new([(0.0, lo - pad), (order.len() as f64, hi + pad)], BLACK))
                    .map_err(err)?;
            }
            // Load-group separators.
            let mut prev_load = None;
            for (x, &k) in order.iter().enumerate() {
                let load = m.trajs[k].load_w;
                if prev_load.is_some_and(|l: f64| (l - load).abs() > 1e-9) {
                    chart
                        .draw_series(std::iter::once(PathElement::new(
                            vec![(x as f64, lo - pad), (x as f64, hi + pad)],
                            RGBColor(200, 200, 200),
                        )))
                        .map_err(err)?;
                }
                prev_load = Some(load);
            }
            // 10-90 % band of the per-step estimates, the per-cycle median, and the truth.
            let mut bars = Vec::with_capacity(order.len());
            let mut meds = Vec::with_capacity(order.len());
            for (x, &k) in order.iter().enumerate() {
                let t = &m.trajs[k];
                if t.estimates.is_empty() {
                    continue;
                }
                let mut v: Vec<f64> = t.estimates.iter().map(|d| p.value(d)).collect();
                let (q10, q90) = (quantile(&mut v, 0.1), quantile(&mut v, 0.9));
                bars.push(PathElement::new(vec![(x as f64 + 0.5, q10), (x as f64 + 0.5, q90)], m.color.mix(0.35)));
                meds.push(Circle::new((x as f64 + 0.5, p.value(&cycle_estimate(t))), 2, m.color.filled()));
            }
            chart.draw_series(bars).map_err(err)?;
            let s = chart.draw_series(meds).map_err(err)?;
            if text {
                s.label("estimate: median (dot), 10-90 % of steps (bar)")
                    .legend(move |(x, y)| Circle::new((x + 8, y), 3, m.color.filled()));
            }
            let truth: Vec<(f64, f64)> =
                order.iter().enumerate().map(|(x, &k)| (x as f64 + 0.5, p.value(&m.trajs[k].truth))).collect();
            let s = chart.draw_series(LineSeries::new(truth, BLACK.stroke_width(1))).map_err(err)?;
            if text {
                s.label("true value").legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLACK));
                chart
                    .configure_series_labels()
                    .background_style(WHITE.mix(0.8))
                    .border_style(BLACK)
                    .label_font(("sans-serif", 12))
                    .position(SeriesLabelPosition::UpperLeft)
                    .draw()
                    .map_err(err)?;
            }
        }
    }
    Ok(())
}

fn draw_errors<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    params: &[Param],
    methods: &[MethodSeries],
    text: bool,
) -> DrawResult {
    let panels = root.split_evenly((1, params.len()));
    for (p_i, &p) in params.iter().enumerate() {
        // Empirical CDF of |error| on a log axis: methods whose errors differ by orders of magnitude stay
        // readable side by side (a shared linear histogram hides the accurate one in one bin).
        let cdfs: Vec<Vec<(f64, f64)>> = methods
            .iter()
            .map(|m| {
                let mut e: Vec<f64> = m
                    .trajs
                    .iter()
                    .flat_map(|t| t.estimates.iter().map(move |d| p.err_pct(d, &t.truth).abs()))
                    .map(|v| v.clamp(CDF_MIN_PCT, CDF_MAX_PCT))
                    .collect();
                e.sort_by(f64::total_cmp);
                let n = e.len();
                (0..=CDF_POINTS)
                    .filter(|_| n > 0)
                    .map(|k| {
                        let q = k as f64 / CDF_POINTS as f64;
                        (e[((n - 1) as f64 * q).round() as usize], q)
                    })
                    .collect()
            })
            .collect();
        let mut b = ChartBuilder::on(&panels[p_i]);
        b.margin(10);
        if text {
            b.caption(format!("{}: per-step |error|, cumulative", p.label()), ("sans-serif", 15))
                .x_label_area_size(35)
                .y_label_area_size(60);
        }
        let mut chart = b.build_cartesian_2d((CDF_MIN_PCT..CDF_MAX_PCT).log_scale(), 0.0..1.0).map_err(err)?;
        if text {
            chart
                .configure_mesh()
                .x_desc("|estimate - truth|, % of range (log)")
                .y_desc("fraction of steps at or below")
                .light_line_style(TRANSPARENT)
                .draw()
                .map_err(err)?;
        } else {
            chart
                .plotting_area()
                .draw(&Rectangle::new([(CDF_MIN_PCT, 0.0), (CDF_MAX_PCT, 1.0)], BLACK))
                .map_err(err)?;
        }
        for (m, pts) in methods.iter().zip(cdfs) {
            let color = m.color;
            let s = chart.draw_series(LineSeries::new(pts, color.stroke_width(2))).map_err(err)?;
            if text {
                s.label(m.name)
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2)));
            }
        }
        if text {
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .label_font(("sans-serif", 12))
                .position(SeriesLabelPosition::LowerRight)
                .draw()
                .map_err(err)?;
        }
    }
    Ok(())
}

fn draw_training<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, tc: &TrainingCurve, text: bool) -> DrawResult {
    let panels = root.split_evenly((1, 2));
    let x_max = tc.validation.iter().map(|v| v.update).chain(tc.train.iter().map(|v| v.update)).fold(1.0, f64::max);
    // Left: validation NRMSE (%) per parameter.
    let series_left: Vec<Series> = vec![
        (
            "val NRMSE qMobile %",
            RGBColor(214, 39, 40),
            tc.validation.iter().filter_map(|v| v.nrmse_q_pct.map(|y| (v.update, y))).collect(),
        ),
        (
            "val NRMSE Ro %",
            RGBColor(31, 119, 180),
            tc.validation.iter().filter_map(|v| v.nrmse_r_pct.map(|y| (v.update, y))).collect(),
        ),
    ];
    // Right: costs.
    let series_right: Vec<Series> = vec![
        (
            "train mean cost",
            RGBColor(44, 160, 44),
            tc.train.iter().filter_map(|v| v.mean_cost.map(|y| (v.update, y))).collect(),
        ),
        (
            "val tracking error",
            RGBColor(148, 103, 189),
            tc.validation.iter().filter_map(|v| v.cost.map(|y| (v.update, y))).collect(),
        ),
    ];
    for (area, series, title) in [
        (&panels[0], series_left, "held-out validation NRMSE (%)"),
        (&panels[1], series_right, "MDP cost (normalised state error)"),
    ] {
        let y_max = series.iter().flat_map(|s| s.2.iter().map(|p| p.1)).fold(1e-9, f64::max) * 1.1;
        let mut b = ChartBuilder::on(area);
        b.margin(10);
        if text {
            b.caption(format!("training: {title}"), ("sans-serif", 15)).x_label_area_size(35).y_label_area_size(60);
        }
        let mut chart = b.build_cartesian_2d(0.0..x_max, 0.0..y_max).map_err(err)?;
        if text {
            chart
                .configure_mesh()
                .x_desc("learner update")
                .x_label_formatter(&|x| format!("{x:.0}"))
                .light_line_style(TRANSPARENT)
                .draw()
                .map_err(err)?;
        } else {
            chart.plotting_area().draw(&Rectangle::new([(0.0, 0.0), (x_max, y_max)], BLACK)).map_err(err)?;
        }
        for (name, color, pts) in series {
            if pts.is_empty() {
                continue;
            }
            let s = chart.draw_series(LineSeries::new(pts, color.stroke_width(2))).map_err(err)?;
            if text {
                s.label(name).legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2)));
            }
        }
        if text {
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .label_font(("sans-serif", 12))
                .position(SeriesLabelPosition::UpperRight)
                .draw()
                .map_err(err)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn training_curve_parses_and_skips_bad_lines() {
        let text = r#"{"kind":"train","update":100,"critic_loss":0.5,"mean_cost":2.0}
{"kind":"validation","update":2000,"t_s":30.0,"val_tracking_error":0.1,"val_nrmse_q_pct":4.0,"val_nrmse_r_pct":1.0}
{"kind":"validation","upd
{"kind":"other","update":5}
"#;
        let c = TrainingCurve::parse(text);
        assert_eq!(c.train, vec![TrainPoint { update: 100.0, mean_cost: Some(2.0), critic_loss: Some(0.5) }]);
        let v = ValidationPoint { update: 2000.0, nrmse_q_pct: Some(4.0), nrmse_r_pct: Some(1.0), cost: Some(0.1) };
        assert_eq!(c.validation, vec![v]);
        assert_eq!(c.skipped_lines, 1);
    }
}
