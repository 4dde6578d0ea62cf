//! Latency per reading of `bcal calibrate --follow -`, the live loop: a real `bcal` process is started per
//! calibrator, and for each reading of a 2 A discharge (the base model at 6000 C / 0.14 ohm, a reading
//! every 10 s after a 30 s rest) the bench writes one CSV line to its standard input and times until that
//! reading's JSON estimate line comes back on its standard output: two pipes, the parse, the calibrator
//! step, the EOD prediction (a model run to the cut-off) and the JSON line. The first reading is left out
//! of the figures (it waits for the process to start). The baseline is the same stream stepped in this
//! process on the same readings (no pipes, no parsing, no printing).

use bcal_calib::stream::{resolve, CalibratorKind, Reading, Stream};
use bcal_common::battery::{BatteryModel, Degradation, Load};
use serde::{Deserialize, Serialize};
use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};
use std::time::Instant;

/// Builds the command of one `bcal calibrate --follow - --calibrator KIND` process.
pub type SpawnFollow<'a> = &'a dyn Fn(&str) -> Command;

/// The calibrators timed.
pub const KINDS: [&str; 3] = ["ukf", "adaptive_ukf", "fit"];

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FollowRow {
    pub calibrator: String,
    /// Readings timed (the first, which waits for the process to start, is not).
    pub readings: u64,
    /// Write of a reading to its estimate read back, us.
    pub latency_p50_us: f64,
    pub latency_p90_us: f64,
    pub latency_max_us: f64,
    /// The same stream in process (step + prediction), median us.
    pub in_process_p50_us: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FollowReport {
    pub rows: Vec<FollowRow>,
}

/// `n` readings (time_s, voltage_v, current_a): 30 s rest, then 2 A, one every 10 s (the discharge repeats
/// from a full cell when it reaches 3.1 V, so any `n` works).
fn readings(n: usize) -> Vec<Reading> {
    let m = BatteryModel::default();
    let d = Degradation { q_mobile_c: 6000.0, r_o_ohm: 0.14 };
    let (mut x, mut t, mut out) = (m.initial_state(&d), 0.0f64, Vec::with_capacity(n));
    while out.len() < n {
        let i = if t < 30.0 { 0.0 } else { 2.0 };
        let v = m.voltage_v(&x, &d);
        if v < 3.1 {
            x = m.initial_state(&d);
            continue;
        }
        if (t as u64).is_multiple_of(10) {
            out.push(Reading { time_s: t, voltage_v: v, current_a: i, temperature_c: None });
        }
        x = m.step(&x, Load::CurrentA(i), 1.0, &d).0;
        t += 1.0;
    }
    out
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

fn in_process_us(kind: &str, rs: &[Reading]) -> anyhow::Result<f64> {
    // The follow loop's own setup and stream: the kind alone (no config, policy or model), with its prior
    // alone beside it, as `--follow` runs it.
    let setup = resolve(kind.parse::<CalibratorKind>()?, None, None, None)?;
    let mut s = Stream::of(&setup, None, None)?;
    let mut us: Vec<f64> = rs
        .iter()
        .map(|r| {
            let t0 = Instant::now();
            std::hint::black_box(s.step(r).ok());
            t0.elapsed().as_secs_f64() * 1e6
        })
        .collect();
    us.sort_by(f64::total_cmp);
    Ok(quantile(&us, 0.5))
}

/// Times `n` readings through a follow process per calibrator of [`KINDS`].
pub fn measure(n: usize, spawn: SpawnFollow, progress: &mut dyn FnMut(&str)) -> anyhow::Result<FollowReport> {
    use anyhow::Context;
    let rs = readings(n.max(2));
    let mut rows = Vec::new();
    for kind in KINDS {
        progress(&format!("follow: {n} readings through `bcal calibrate --follow - --calibrator {kind}` ..."));
        let mut child = spawn(kind)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .context("cannot start bcal calibrate --follow")?;
        let mut stdin = child.stdin.take().context("piped stdin")?;
        let mut lines = BufReader::new(child.stdout.take().context("piped stdout")?).lines();
        writeln!(stdin, "time_s,voltage_v,current_a")?;
        let mut us = Vec::with_capacity(n);
        for (k, r) in rs.iter().enumerate() {
            let t0 = Instant::now();
            writeln!(stdin, "{},{},{}", r.time_s, r.voltage_v, r.current_a)?;
            stdin.flush()?;
            let line = lines.next().context("the follow process ended before answering")??;
            if k > 0 {
                us.push(t0.elapsed().as_secs_f64() * 1e6);
            }
            anyhow::ensure!(line.starts_with('{'), "not an estimate line: {line}");
        }
        drop(stdin);
        let status = child.wait()?;
        anyhow::ensure!(status.success(), "bcal calibrate --follow exited with {status}");
        us.sort_by(f64::total_cmp);
        let row = FollowRow {
            calibrator: kind.to_string(),
            readings: us.len() as u64,
            latency_p50_us: quantile(&us, 0.5),
            latency_p90_us: quantile(&us, 0.9),
            latency_max_us: us[us.len() - 1],
            in_process_p50_us: in_process_us(kind, &rs)?,
        };
        progress(&format!(
            "follow: {kind}: reading to estimate p50 {:.0} us, p90 {:.0} us (in process {:.0} us)",
            row.latency_p50_us, row.latency_p90_us, row.in_process_p50_us
        ));
        rows.push(row);
    }
    Ok(FollowReport { rows })
}
