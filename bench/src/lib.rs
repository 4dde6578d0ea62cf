//! bcal-bench: measures every performance figure the README quotes, each beside the baseline it is compared
//! against, in one run (`bcal bench`; what each figure is: `docs/bench.md`).
//!
//! Five parts, each a module with one `measure` function:
//! - [`model`]: battery-model steps per second on one core (the unit of everything else);
//! - [`calib`]: UKF, RL policy and direct-mapping steps in us and in battery-model steps;
//! - [`transport`]: actor -> replay transitions per second and one-way latency through iceoryx2 across
//!   processes, beside an in-process crossbeam channel carrying the same batches;
//! - [`learner`]: LAC updates per second at batch 256 with the paper's networks;
//! - [`doctor`]: one diagnosis with every candidate cause, per record and cause (`--only doctor`).
//! - [`follow`]: latency per reading of `bcal calibrate --follow -` (a real process on pipes), beside the
//!   same stream stepped in process.
//!
//! [`run`] runs the selected parts into a [`BenchReport`] (serialised as bench.json); [`render_table`]
//! prints it. Like the evaluator, the library never prints: progress goes to a callback. Timing never
//! fails anything: the report states what was measured and under which load.

pub mod calib;
pub mod doctor;
pub mod follow;
pub mod learner;
pub mod model;
pub mod transport;

use anyhow::Context;
use bcal_common::battery::BatteryModel;
use bcal_common::config::TrainConfig;
use bcal_common::dataset::{self, CacheStatus, Experiment, Split};
use bcal_common::mdp::MdpSpec;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::Path;
use std::time::{Duration, Instant};

pub use follow::SpawnFollow;
pub use transport::{publish, PublisherArgs, SpawnPublisher};

/// Which parts to run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Parts {
    pub model: bool,
    pub calib: bool,
    pub transport: bool,
    pub learner: bool,
    #[serde(default)]
    pub doctor: bool,
    pub follow: bool,
}

impl Parts {
    pub const ALL: Parts =
        Parts { model: true, calib: true, transport: true, learner: true, doctor: true, follow: true };
    pub const NONE: Parts =
        Parts { model: false, calib: false, transport: false, learner: false, doctor: false, follow: false };
    pub const NAMES: [&'static str; 6] = ["model", "calib", "transport", "learner", "doctor", "follow"];

    /// Parses a comma-separated list of [`Self::NAMES`].
    pub fn parse(list: &str) -> Result<Self, String> {
        let mut p = Parts::NONE;
        for name in list.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            match name {
                "model" => p.model = true,
                "calib" => p.calib = true,
                "transport" => p.transport = true,
                "learner" => p.learner = true,
                "doctor" => p.doctor = true,
                "follow" => p.follow = true,
                other => return Err(format!("unknown part `{other}`; the parts are {}", Self::NAMES.join(", "))),
            }
        }
        if p == Parts::NONE {
            return Err(format!("name at least one part of {}", Self::NAMES.join(", ")));
        }
        Ok(p)
    }
}

/// Every knob of a run; [`Settings::full`] is `bcal bench`, [`Settings::quick`] is `--quick`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Settings {
    pub quick: bool,
    pub parts: Parts,
    /// Battery-model steps timed in the model part.
    pub model_steps: usize,
    /// Whole discharges timed in the model part.
    pub model_discharges: usize,
    /// Steps timed per calibrator row (the evaluator's `timing_steps`).
    pub calib_steps: usize,
    pub transport: transport::TransportSettings,
    /// Timed window per learner row, s.
    pub learner_window_s: f64,
    /// (hidden widths, libtorch threads) of each learner row; the first is the reference of the ratios.
    pub learner_rows: Vec<(Vec<usize>, usize)>,
    /// Learner minibatch (the paper's 256).
    pub learner_batch: usize,
    /// Records of the doctor part's diagnosis.
    #[serde(default)]
    pub doctor_records: usize,
    /// Readings timed per calibrator in the follow part.
    #[serde(default)]
    pub follow_readings: usize,
}

impl Settings {
    /// `bcal bench`: about a minute on an idle 2-core machine.
    pub fn full() -> Self {
        let cores = cores();
        let mut learner_rows = vec![(calib::HIDDEN_PAPER.to_vec(), 1)];
        if cores > 1 {
            learner_rows.push((calib::HIDDEN_PAPER.to_vec(), cores));
        }
        learner_rows.push((calib::HIDDEN_DEFAULT.to_vec(), 1));
        Self {
            quick: false,
            parts: Parts::ALL,
            model_steps: 20_000_000,
            model_discharges: 2_000,
            calib_steps: 20_000,
            transport: transport::TransportSettings {
                actors: vec![1, 2, 4],
                warmup_s: 0.5,
                window_s: 3.0,
                paced_rate: 400.0,
            },
            learner_window_s: 6.0,
            learner_rows,
            learner_batch: 256,
            doctor_records: 24,
            follow_readings: 300,
        }
    }

    /// `--quick`: every figure, short windows (under 20 s with a cold dataset cache).
    pub fn quick() -> Self {
        Self {
            quick: true,
            model_steps: 3_000_000,
            model_discharges: 300,
            calib_steps: 3_000,
            transport: transport::TransportSettings {
                actors: vec![1, 2, 4],
                warmup_s: 0.1,
                window_s: 0.4,
                paced_rate: 400.0,
            },
            learner_window_s: 0.8,
            learner_rows: vec![(calib::HIDDEN_PAPER.to_vec(), 1), (calib::HIDDEN_DEFAULT.to_vec(), 1)],
            doctor_records: 6,
            follow_readings: 60,
            ..Self::full()
        }
    }
}

/// Facts about the machine the figures come from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Machine {
    pub cores: u64,
    pub cpu_model: String,
    pub avx2: bool,
    pub fma: bool,
    /// 1-minute load average when the run started and when it ended (other processes compete for cores).
    pub loadavg_start: f64,
    pub loadavg_end: f64,
}

fn cores() -> usize {
    std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
}

fn loadavg() -> f64 {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|v| v.parse().ok()))
        .unwrap_or(f64::NAN)
}

fn machine(loadavg_start: f64) -> Machine {
    let cpu_model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().into())
        })
        .unwrap_or_else(|| "unknown".to_string());
    #[cfg(target_arch = "x86_64")]
    let (avx2, fma) = (std::is_x86_feature_detected!("avx2"), std::is_x86_feature_detected!("fma"));
    #[cfg(not(target_arch = "x86_64"))]
    let (avx2, fma) = (false, false);
    Machine { cores: cores() as u64, cpu_model, avx2, fma, loadavg_start, loadavg_end: loadavg() }
}

/// The data set the calibrator timings run on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DatasetFacts {
    pub experiment: String,
    pub trajectories: u64,
    /// `cached` or `generated`.
    pub source: String,
    /// Time to read or generate it, s.
    pub seconds: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LearnerReport {
    pub rows: Vec<LearnerRowWithRatio>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LearnerRowWithRatio {
    #[serde(flatten)]
    pub row: learner::LearnerRow,
    /// updates/s relative to the first row (the paper's networks on one thread).
    pub ratio_to_first: f64,
}

/// Everything one run measured (bench.json).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BenchReport {
    pub version: String,
    pub machine: Machine,
    pub settings: Settings,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dataset: Option<DatasetFacts>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<model::ModelReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calib: Option<calib::CalibReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub transport: Option<transport::TransportReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub learner: Option<LearnerReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub doctor: Option<doctor::DoctorRow>,
    pub follow: Option<follow::FollowReport>,
    /// Wall time of the whole run, s.
    pub seconds: f64,
}

/// Runs the selected parts: model, calib, learner, then transport (the table prints transport before the
/// learner). `spawn` builds the command of one transport publisher process, `spawn_follow` that of one
/// `bcal calibrate --follow -`; `cache_dir` is the dataset cache (experiment multi).
pub fn run(
    settings: &Settings,
    cache_dir: &Path,
    spawn: SpawnPublisher,
    spawn_follow: SpawnFollow,
    progress: &mut dyn FnMut(&str),
) -> anyhow::Result<BenchReport> {
    let started = Instant::now();
    let loadavg_start = loadavg();
    let model = BatteryModel::default();
    let parts = settings.parts;
    let mut report = BenchReport {
        version: env!("CARGO_PKG_VERSION").to_string(),
        machine: machine(loadavg_start),
        settings: settings.clone(),
        dataset: None,
        model: None,
        calib: None,
        transport: None,
        learner: None,
        doctor: None,
        follow: None,
        seconds: 0.0,
    };
    if parts.model {
        progress("model: timing battery-model steps and whole discharges (one core) ...");
        let m = model::measure(&model, settings.model_steps, settings.model_discharges)?;
        progress(&format!(
            "model: {:.1} ns per step ({:.2} M steps/s); a {}-step discharge {:.0} us",
            m.step_ns,
            m.steps_per_s / 1e6,
            m.discharge_steps,
            m.discharge_us
        ));
        report.model = Some(m);
    }
    if parts.calib {
        let experiment = Experiment::Multi;
        progress(&format!("calib: loading the {experiment} data set from {} ...", cache_dir.display()));
        let def = experiment.definition();
        let (train, _) = dataset::load_or_generate(&def, &model, cache_dir, Split::Train)
            .with_context(|| format!("dataset {experiment} train in {}", cache_dir.display()))?;
        let (ds, rep) = dataset::load_or_generate(&def, &model, cache_dir, Split::Test)
            .with_context(|| format!("dataset {experiment} test in {}", cache_dir.display()))?;
        let source = match rep.status {
            CacheStatus::Hit => "cached",
            CacheStatus::Generated | CacheStatus::Regenerated { .. } => "generated",
        };
        progress(&format!("calib: dataset {experiment} test split {source} in {:.1} s", rep.seconds));
        report.dataset = Some(DatasetFacts {
            experiment: experiment.to_string(),
            trajectories: ds.trajectories.len() as u64,
            source: source.into(),
            seconds: rep.seconds,
        });
        let cfg = TrainConfig { experiment, ..Default::default() };
        let spec = MdpSpec::new(experiment, &cfg.env, &train);
        drop(train);
        report.calib = Some(calib::measure(&ds, &spec, &model, settings.calib_steps, progress)?);
    }
    if parts.learner {
        let mut rows: Vec<LearnerRowWithRatio> = Vec::new();
        for (hidden, threads) in &settings.learner_rows {
            progress(&format!(
                "learner: LAC updates, batch {}, networks {}, {threads} libtorch thread(s) ...",
                settings.learner_batch,
                shape(hidden)
            ));
            let row = learner::measure(
                hidden,
                settings.learner_batch,
                *threads,
                Duration::from_secs_f64(settings.learner_window_s),
            )?;
            progress(&format!("learner: {:.1} updates/s ({:.2} ms per update)", row.updates_per_s, row.ms_per_update));
            let first = rows.first().map_or(row.updates_per_s, |r| r.row.updates_per_s);
            rows.push(LearnerRowWithRatio { ratio_to_first: row.updates_per_s / first, row });
        }
        report.learner = Some(LearnerReport { rows });
    }
    if parts.doctor {
        progress(&format!("doctor: one diagnosis, every cause, {} simulated records ...", settings.doctor_records));
        let row = doctor::measure(settings.doctor_records)?;
        progress(&format!(
            "doctor: {:.1} s, {:.3} s per record and cause",
            row.seconds, row.seconds_per_record_and_cause
        ));
        report.doctor = Some(row);
    }
    if parts.follow {
        report.follow = Some(follow::measure(settings.follow_readings, spawn_follow, progress)?);
    }
    // Last: from the transport part on, iceoryx2 captures Ctrl-C for the rest of the process (the part's
    // loops ask for it; later work would not).
    if parts.transport {
        report.transport = Some(transport::measure(&settings.transport, spawn, progress)?);
    }
    report.machine.loadavg_end = loadavg();
    report.seconds = started.elapsed().as_secs_f64();
    Ok(report)
}

/// `256x3` for three hidden layers of 256.
pub fn shape(hidden: &[usize]) -> String {
    format!("{}x{}", hidden.first().copied().unwrap_or(0), hidden.len())
}

/// Numbers for a table: 3 significant digits, thousands separated.
fn num(v: f64) -> String {
    if !v.is_finite() {
        return "-".into();
    }
    let a = v.abs();
    if a >= 1000.0 {
        let s = format!("{:.0}", v.abs());
        let mut out = String::new();
        for (k, c) in s.chars().enumerate() {
            if k > 0 && (s.len() - k).is_multiple_of(3) {
                out.push(',');
            }
            out.push(c);
        }
        if v < 0.0 {
            out.insert(0, '-');
        }
        out
    } else if a >= 100.0 {
        format!("{v:.0}")
    } else if a >= 10.0 {
        format!("{v:.1}")
    } else if a >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

/// The report as the tables `bcal bench` prints.
pub fn render_table(r: &BenchReport) -> String {
    let mut o = String::new();
    let m = &r.machine;
    let _ = writeln!(
        o,
        "bcal bench {} ({}): {} cores, {}, AVX2 {}, FMA {}; load average {:.2} -> {:.2}; {:.0} s",
        r.version,
        if r.settings.quick { "quick" } else { "full" },
        m.cores,
        m.cpu_model,
        if m.avx2 { "yes" } else { "no" },
        if m.fma { "yes" } else { "no" },
        m.loadavg_start,
        m.loadavg_end,
        r.seconds
    );
    if m.loadavg_start.max(m.loadavg_end) > 0.5 {
        let _ = writeln!(o, "note: other processes were running (load average above 0.5): figures may be disturbed");
    }
    if let Some(md) = &r.model {
        let _ = writeln!(o, "\n## Battery model (one core)\n");
        let _ = writeln!(o, "| figure | value |");
        let _ = writeln!(o, "| --- | ---: |");
        let _ = writeln!(o, "| one Euler step at 8 W, ns | {} |", num(md.step_ns));
        let _ = writeln!(o, "| steps per second | {} |", num(md.steps_per_s));
        let _ = writeln!(o, "| whole {}-step discharge at 8 W, us | {} |", md.discharge_steps, num(md.discharge_us));
        let _ = writeln!(o, "| steps per second within a discharge | {} |", num(md.discharge_steps_per_s));
    }
    if let Some(c) = &r.calib {
        let _ = writeln!(
            o,
            "\n## Calibrator steps (one thread; baseline: one battery-model step = {} us, same process, same states)\n",
            num(c.model_step_us)
        );
        let _ = writeln!(o, "| step | us | battery-model steps |");
        let _ = writeln!(o, "| --- | ---: | ---: |");
        for row in &c.rows {
            let _ = writeln!(o, "| {} | {} | {} |", row.label, num(row.us), num(row.model_steps));
        }
    }
    if let Some(f) = &r.follow {
        let _ = writeln!(
            o,
            "\n## Live readings: `bcal calibrate --follow -` (reading written to its estimate read back, through \
             pipes; baseline: the same stream stepped in process)\n"
        );
        let _ = writeln!(o, "| calibrator | readings | p50 us | p90 us | max us | in process p50 us |");
        let _ = writeln!(o, "| --- | ---: | ---: | ---: | ---: | ---: |");
        for row in &f.rows {
            let _ = writeln!(
                o,
                "| {} | {} | {} | {} | {} | {} |",
                row.calibrator,
                row.readings,
                num(row.latency_p50_us),
                num(row.latency_p90_us),
                num(row.latency_max_us),
                num(row.in_process_p50_us)
            );
        }
    }
    if let Some(t) = &r.transport {
        let _ = writeln!(
            o,
            "\n## Transport actor -> replay (batches of {} transitions, {} B each; baseline: in-process crossbeam \
             channel, same batches)\n",
            t.publish_batch, t.transition_bytes
        );
        let _ = writeln!(
            o,
            "| actors | iceoryx2 transitions/s | batches/s | latency mean / p50 / p99 us | crossbeam transitions/s \
             | latency mean / p50 / p99 us | throughput ratio | latency ratio |"
        );
        let _ = writeln!(o, "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
        for row in t.rows.iter().chain(&t.paced) {
            let who = match row.rate_per_actor {
                Some(rate) => format!("{} at {} batches/s", row.actors, num(rate)),
                None => row.actors.to_string(),
            };
            let lat = |f: &transport::Flow| {
                format!("{} / {} / {}", num(f.latency_mean_us), num(f.latency_p50_us), num(f.latency_p99_us))
            };
            let _ = writeln!(
                o,
                "| {who} | {} | {} | {} | {} | {} | {} | {} |",
                num(row.iceoryx2.transitions_per_s),
                num(row.iceoryx2.messages_per_s),
                lat(&row.iceoryx2),
                num(row.crossbeam.transitions_per_s),
                lat(&row.crossbeam),
                num(row.throughput_ratio),
                num(row.latency_ratio)
            );
        }
        let shares: Vec<String> = t
            .rows
            .iter()
            .filter(|r| r.actors > 1)
            .map(|r| {
                let f = |f: &transport::Flow| {
                    f.per_actor_messages.iter().map(|&m| num(m as f64)).collect::<Vec<_>>().join("/")
                };
                format!("{} actors: iceoryx2 {}, crossbeam {}", r.actors, f(&r.iceoryx2), f(&r.crossbeam))
            })
            .collect();
        if !shares.is_empty() {
            let _ = writeln!(o, "\nbatches received per actor in the window: {}", shares.join("; "));
        }
    }
    if let Some(l) = &r.learner {
        let _ = writeln!(o, "\n## Learner (LAC updates in process; baseline: the first row)\n");
        let _ =
            writeln!(o, "| networks | batch | libtorch threads | updates/s | ms per update | transitions/s | ratio |");
        let _ = writeln!(o, "| --- | ---: | ---: | ---: | ---: | ---: | ---: |");
        for w in &l.rows {
            let row = &w.row;
            let _ = writeln!(
                o,
                "| {} | {} | {} | {} | {} | {} | {} |",
                shape(&row.hidden),
                row.batch,
                row.torch_threads,
                num(row.updates_per_s),
                num(row.ms_per_update),
                num(row.samples_per_s),
                num(w.ratio_to_first)
            );
        }
    }
    if let Some(d) = &r.doctor {
        let _ = writeln!(o, "\n## Doctor (one diagnosis, every candidate cause; `bcal diagnose`'s defaults)\n");
        let _ = writeln!(o, "| records | causes | samples per record | step s | s | s per record and cause | named |");
        let _ = writeln!(o, "| ---: | ---: | ---: | ---: | ---: | ---: | --- |");
        let _ = writeln!(
            o,
            "| {} | {} | {} | {} | {} | {} | {} |",
            d.records,
            d.causes,
            d.samples,
            num(d.dt_s),
            num(d.seconds),
            num(d.seconds_per_record_and_cause),
            d.cause
        );
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_parse_and_refuse_unknown_names() {
        assert_eq!(
            Parts::parse("model,learner").unwrap(),
            Parts { calib: false, transport: false, doctor: false, follow: false, ..Parts::ALL }
        );
        assert!(Parts::parse("model,gpu").unwrap_err().contains("unknown part `gpu`"));
        assert!(Parts::parse(" , ").is_err());
    }

    #[test]
    fn numbers_read_well() {
        assert_eq!(num(9_912_345.4), "9,912,345");
        assert_eq!(num(1000.0), "1,000");
        assert_eq!(num(100.6), "101");
        assert_eq!(num(21.54), "21.5");
        assert_eq!(num(5.78), "5.78");
        assert_eq!(num(0.2112), "0.211");
        assert_eq!(num(f64::NAN), "-");
    }

    #[test]
    fn a_publisher_that_cannot_start_is_named() {
        let s = transport::TransportSettings { actors: vec![1], warmup_s: 0.02, window_s: 0.1, paced_rate: 0.0 };
        let spawn = |_: &PublisherArgs| std::process::Command::new("/nonexistent/bcal");
        let e = transport::measure(&s, &spawn, &mut |_| {}).unwrap_err();
        assert!(format!("{e:#}").contains("/nonexistent/bcal"), "{e:#}");
    }
}
