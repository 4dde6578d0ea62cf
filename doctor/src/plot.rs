//! Residual plots of the base versus the extended model on held-out cycles, each written as PNG and SVG
//! with plotters (text through its `ttf` feature, which finds a system font via fontconfig; CI installs
//! libfontconfig-dev and libfreetype-dev).
//!
//! - `residual_time`: measured - model (mV) against time since the load went on, one line per cycle.
//! - `residual_soc`: the same against the fraction of the fit window's charge drawn (the knee is on the right).
//! - `heldout_rmse`: each held-out cycle's RMSE, base and extended.

use crate::analysis::RecordResidual;
use crate::diagnose::Diagnosis;
use crate::error::DoctorError;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::{Path, PathBuf};

/// Pixel size of every figure.
const SIZE: (u32, u32) = (1200, 560);

/// Writes the three figures as PNG and SVG into `out_dir`; returns their paths.
pub fn write_plots(diag: &Diagnosis, out_dir: &Path) -> Result<Vec<PathBuf>, DoctorError> {
    std::fs::create_dir_all(out_dir).map_err(|e| DoctorError::Write { path: out_dir.to_path_buf(), source: e })?;
    let mut paths = Vec::new();
    for (stem, kind) in [("residual_time", Kind::Time), ("residual_soc", Kind::Soc), ("heldout_rmse", Kind::Rmse)] {
        let png = out_dir.join(format!("{stem}.png"));
        draw(BitMapBackend::new(&png, SIZE).into_drawing_area(), diag, kind)
            .map_err(|message| DoctorError::Plot { path: png.clone(), message })?;
        let svg = out_dir.join(format!("{stem}.svg"));
        draw(SVGBackend::new(&svg, SIZE).into_drawing_area(), diag, kind)
            .map_err(|message| DoctorError::Plot { path: svg.clone(), message })?;
        paths.push(png);
        paths.push(svg);
    }
    Ok(paths)
}

#[derive(Clone, Copy, PartialEq)]
enum Kind {
    Time,
    Soc,
    Rmse,
}

fn draw<DB: DrawingBackend>(root: DrawingArea<DB, Shift>, diag: &Diagnosis, kind: Kind) -> Result<(), String> {
    let e = |err: DrawingAreaErrorKind<DB::ErrorType>| err.to_string();
    root.fill(&WHITE).map_err(e)?;
    let ext_name =
        if diag.extended.causes.is_empty() { "no extension".to_string() } else { diag.extended.causes.join(" + ") };
    if kind == Kind::Rmse {
        let b = &diag.base.heldout_cycles;
        let x = &diag.extended.heldout_cycles;
        let (c0, c1) = (b.first().map_or(0, |c| c.cycle), b.last().map_or(1, |c| c.cycle).max(1));
        let y_max = b.iter().chain(x).map(|c| c.rmse_mv).fold(1.0, f64::max) * 1.1;
        let mut chart = ChartBuilder::on(&root)
            .caption(
                format!("{}: held-out RMSE per cycle, base vs extended ({ext_name})", diag.cell),
                ("sans-serif", 22),
            )
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(c0 as f64 - 1.0..c1 as f64 + 1.0, 0.0..y_max)
            .map_err(e)?;
        chart.configure_mesh().x_desc("cycle").y_desc("RMSE under load, mV").draw().map_err(e)?;
        for (series, color, name) in [(b, RED, "base"), (x, BLUE, "extended")] {
            chart
                .draw_series(LineSeries::new(series.iter().map(|c| (c.cycle as f64, c.rmse_mv)), color.stroke_width(2)))
                .map_err(e)?
                .label(name)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
            chart
                .draw_series(series.iter().map(|c| Circle::new((c.cycle as f64, c.rmse_mv), 3, color.filled())))
                .map_err(e)?;
        }
        chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw().map_err(e)?;
        return root.present().map_err(e);
    }
    let panels = root.split_evenly((1, 2));
    let sets: [(&str, &[RecordResidual]); 2] =
        [("base", &diag.base.heldout_residuals), (ext_name.as_str(), &diag.extended.heldout_residuals)];
    let x_of = |r: &RecordResidual, k: usize| if kind == Kind::Time { r.time_s[k] } else { r.discharged_fraction[k] };
    let in_window = |r: &RecordResidual, k: usize| {
        if kind == Kind::Time {
            true
        } else {
            r.fitted[k]
        }
    };
    let mut y_abs: f64 = 10.0;
    let (mut x_lo, mut x_hi) = (0.0f64, 1.0f64);
    for (_, set) in &sets {
        for r in set.iter() {
            for k in 0..r.residual_mv.len() {
                if in_window(r, k) {
                    y_abs = y_abs.max(r.residual_mv[k].abs());
                    x_lo = x_lo.min(x_of(r, k));
                    x_hi = x_hi.max(x_of(r, k));
                }
            }
        }
    }
    let y_abs = y_abs.min(400.0) * 1.05;
    let n = sets[0].1.len().max(1);
    for (area, (title, set)) in panels.iter().zip(sets) {
        let mut chart = ChartBuilder::on(area)
            .caption(format!("{}: {title}, held-out", diag.cell), ("sans-serif", 20))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(55)
            .build_cartesian_2d(x_lo..x_hi, -y_abs..y_abs)
            .map_err(e)?;
        chart
            .configure_mesh()
            .x_desc(if kind == Kind::Time { "time since load on, s" } else { "fraction of charge drawn" })
            .y_desc("measured - model, mV")
            .draw()
            .map_err(e)?;
        for (j, r) in set.iter().enumerate() {
            let color = HSLColor(0.66 * j as f64 / n as f64, 0.8, 0.45);
            let pts = (0..r.residual_mv.len()).filter(|&k| in_window(r, k)).map(|k| (x_of(r, k), r.residual_mv[k]));
            chart.draw_series(LineSeries::new(pts, color.stroke_width(1))).map_err(e)?;
        }
        chart.draw_series(LineSeries::new([(x_lo, 0.0), (x_hi, 0.0)], BLACK.stroke_width(1))).map_err(e)?;
    }
    root.present().map_err(e)
}
