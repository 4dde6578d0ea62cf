//! Simulated cells as a battery management system sees them: a hidden true cell (degradation parameters
//! drawn from the paper's ranges, any starting charge at rest equilibrium, constant-power, constant-current
//! or piecewise loads, optionally a thermal cell in a 10-45 C ambient) stepped by the reference model at
//! `truth_dt_s`, read at 1 s or irregular 10-20 s intervals through a sensor model (Gaussian noise and an
//! optional constant bias on voltage, current and temperature).
//!
//! Nothing downstream of [`Episode::samples`] may read the truth: calibrators get samples, the evaluator
//! gets the truth to score them. The three splits draw their loads from disjoint ranges (test loads are
//! never seen in training, validation sits between), and every episode's profile is its own random draw.

use crate::battery::{BatteryModel, BatteryParams, Degradation, Load, LoadProfile, ModelError};
use crate::dataset::Split;
use crate::math::{idx, ModelState};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

/// Kelvin of 0 deg C.
pub const KELVIN_0C: f64 = 273.15;

/// How the cell is loaded during an episode.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LoadKind {
    /// Constant power (the paper's input).
    ConstantPower,
    /// Constant current (the NASA cycler's).
    ConstantCurrent,
    /// Random power steps between rest and the episode's maximum, each held 10-600 s.
    Piecewise,
}

impl LoadKind {
    pub const ALL: [LoadKind; 3] = [LoadKind::ConstantPower, LoadKind::ConstantCurrent, LoadKind::Piecewise];

    pub fn name(self) -> &'static str {
        match self {
            LoadKind::ConstantPower => "constant-power",
            LoadKind::ConstantCurrent => "constant-current",
            LoadKind::Piecewise => "piecewise",
        }
    }
}

/// The sensor between the cell and every calibrator: Gaussian noise (one standard deviation) and a
/// constant bias per channel.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SensorConfig {
    /// Voltage noise, V (default 3 mV).
    pub voltage_noise_v: f64,
    /// Current noise, A (default 10 mA).
    pub current_noise_a: f64,
    /// Temperature noise, K (default 0.5 K).
    pub temperature_noise_k: f64,
    /// Constant voltage bias, V (default 0).
    pub voltage_bias_v: f64,
    /// Constant current bias, A (default 0).
    pub current_bias_a: f64,
}

impl Default for SensorConfig {
    fn default() -> Self {
        Self {
            voltage_noise_v: 0.003,
            current_noise_a: 0.010,
            temperature_noise_k: 0.5,
            voltage_bias_v: 0.0,
            current_bias_a: 0.0,
        }
    }
}

/// The loads of one split: each episode draws its level from these ranges.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SplitLoads {
    /// Constant-power level, and the maximum of a piecewise profile, W.
    pub power_w: [f64; 2],
    /// Constant-current level, A.
    pub current_a: [f64; 2],
}

/// Everything that defines the episodes of the measured-only setting.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ScenarioConfig {
    /// True qMobile range, C (the paper's).
    pub q_mobile_c: [f64; 2],
    /// True Ro range, ohm (the paper's).
    pub r_o_ohm: [f64; 2],
    /// Starting charge as a fraction of qMobile (mole-fraction window of the negative electrode).
    pub soc0: [f64; 2],
    /// Rest before the load starts, s (the calibrator reads its starting charge from it).
    pub rest_s: [f64; 2],
    /// Sampling intervals, s: each episode picks one range with equal probability, then every interval is
    /// drawn uniformly from it in whole seconds (the NASA cycler's is about 10-20 s).
    pub sample_interval_s: Vec<[f64; 2]>,
    /// Load kinds, each episode picks one with equal probability.
    pub load_kinds: Vec<LoadKind>,
    /// Hold time of each piecewise segment, s.
    pub segment_hold_s: [f64; 2],
    /// Probability that a piecewise segment is a rest.
    pub segment_rest_probability: f64,
    /// Probability that an episode's readings do not say what load was asked for (`Request::Unknown`), as a
    /// cycler's export does not: every input a calibrator meets on real records then also occurs in
    /// training (default 0.5).
    pub unknown_request_probability: f64,
    pub train: SplitLoads,
    pub validation: SplitLoads,
    pub test: SplitLoads,
    /// Thermal cell (self-heating, temperature read by the sensor) in an ambient drawn from
    /// `ambient_c`; otherwise isothermal at the model's 292.1 K.
    pub thermal: bool,
    pub ambient_c: [f64; 2],
    /// Euler step of the true cell, s; must stay below 2 t_o (12.2 s) for the ohmic lag to be stable.
    pub truth_dt_s: f64,
    /// Voltage at which a discharge ends, V.
    pub cutoff_v: f64,
    /// Longest episode, s (an episode that never reaches the cut-off is cut here).
    pub max_duration_s: f64,
    /// Episodes in the validation and test sets.
    pub validation_episodes: usize,
    pub test_episodes: usize,
    pub sensor: SensorConfig,
    /// The true cells' model: the base one, or the doctor's extended one (a real cell's setting).
    pub model: super::extension::ModelExtension,
    /// What each cell carries beyond that model, drawn per episode (none by default).
    pub model_error: ModelErrorConfig,
    /// Each simulated episode's calibrator starts from a prior drawn around the truth with these standard
    /// deviations, fractions of the qMobile and Ro ranges (a real cell's calibrator starts from the last
    /// discharge's fit); None (default): from the calibrator's own prior.
    pub prior_sd_z: Option<[f64; 2]>,
    /// Capacity regained over a long rest that the prior does not know (only with `prior_sd_z`).
    pub rest_jump: RestJumpConfig,
    /// Recorded discharges of a real cell that training also learns from (`bcal cell-config` writes them).
    pub recorded: RecordedConfig,
}

/// Recorded discharges of a real cell as training episodes: their readings, the measured voltage as the
/// cell's own future (what the predictive cost compares with), the measured end of discharge, the current as
/// the load, and the offline fit of the discharge before each as its prior. No true parameter exists for
/// them: the predictive cost needs none, and scores that read the truth leave them out.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RecordedConfig {
    /// A JSON file of [`RecordedSet`] (relative to the config file's folder, or absolute); None: none.
    pub path: Option<String>,
    /// Share of training episodes drawn from its training discharges (the rest are simulated).
    pub share: f64,
}

/// A cell that regained capacity over a long rest (NASA cells do): with `probability`, an episode's prior
/// sits below its truth's qMobile by a fraction drawn uniformly from `q_mobile_frac`, as the previous
/// discharge's fit sits below a cell that has rested since (issue 18, item 4). Off by default.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RestJumpConfig {
    pub probability: f64,
    pub q_mobile_frac: [f64; 2],
}

impl Default for RestJumpConfig {
    fn default() -> Self {
        Self { probability: 0.0, q_mobile_frac: [0.0, 0.04] }
    }
}

/// The recorded discharges of one cell: training and validation (the last training cycles).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RecordedSet {
    pub cell: String,
    pub train: Vec<Episode>,
    pub validation: Vec<Episode>,
}

impl RecordedSet {
    /// The file's bytes (bincode: a recorded episode's unknown truth is NaN, which JSON cannot hold).
    pub fn to_bytes(&self) -> Vec<u8> {
        bincode::serde::encode_to_vec(self, bincode::config::standard()).expect("recorded sets always serialise")
    }

    /// Reads a set written by `bcal cell-config`.
    pub fn load(path: &std::path::Path) -> Result<Self, String> {
        let bytes =
            std::fs::read(path).map_err(|e| format!("cannot read the recorded discharges {}: {e}", path.display()))?;
        let redo = |why: String| {
            format!(
                "{}: not a set of recorded discharges ({why}); write it again with bcal cell-config",
                path.display()
            )
        };
        let (set, used): (Self, usize) =
            bincode::serde::decode_from_slice(&bytes, bincode::config::standard()).map_err(|e| redo(e.to_string()))?;
        if used != bytes.len() {
            return Err(redo(format!("{} trailing bytes", bytes.len() - used)));
        }
        Ok(set)
    }
}

/// What simulated cells carry that the calibrators' model lacks, as real cells do (issue 18, item 4): the
/// doctor's ageing causes beyond qMobile and Ro (electrode balance, charge transfer, diffusion) and a
/// voltage-sensor offset. Each is present in an episode's cell with `probability`, its size drawn
/// uniformly from its range (factors log-uniformly), independently of the others. The default ranges span
/// what `bcal diagnose` fitted on the NASA cells over their lives (xp_shift 0.01 -> 0.11, xn_shift
/// -0.04 -> -0.15 on B0005; kinetics factors down to a fifth); probability 0 (the default) is the exact
/// model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelErrorConfig {
    /// Probability that an episode's cell carries each cause (0: every cell is the model itself).
    pub probability: f64,
    /// Shift of the positive electrode's mole fraction at full charge, added to the model's.
    pub xp_shift: [f64; 2],
    /// Shift of the negative electrode's mole fraction at full charge, added to the model's.
    pub xn_shift: [f64; 2],
    /// Factor on both Butler-Volmer rate constants (log-uniform).
    pub kinetics_scale: [f64; 2],
    /// Factor on the bulk-surface diffusion time (log-uniform).
    pub diffusion_scale: [f64; 2],
    /// Constant voltage-sensor offset, V.
    pub voltage_bias_v: [f64; 2],
}

impl Default for ModelErrorConfig {
    fn default() -> Self {
        Self {
            probability: 0.0,
            xp_shift: [-0.02, 0.1],
            xn_shift: [-0.15, 0.02],
            kinetics_scale: [0.2, 1.5],
            diffusion_scale: [0.3, 3.0],
            voltage_bias_v: [-0.015, 0.015],
        }
    }
}

/// What one episode's cell carries beyond the model (neutral: nothing).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CellError {
    pub xp_shift: f64,
    pub xn_shift: f64,
    pub kinetics_scale: f64,
    pub diffusion_scale: f64,
    pub voltage_bias_v: f64,
}

impl Default for CellError {
    fn default() -> Self {
        Self { xp_shift: 0.0, xn_shift: 0.0, kinetics_scale: 1.0, diffusion_scale: 1.0, voltage_bias_v: 0.0 }
    }
}

impl CellError {
    /// Whether the cell is the model itself.
    pub fn is_none(&self) -> bool {
        *self == CellError::default()
    }

    /// The true cell's model: `model` with this error.
    pub fn apply(&self, model: &super::extension::ModelExtension) -> super::extension::ModelExtension {
        super::extension::ModelExtension {
            xp_shift: model.xp_shift + self.xp_shift,
            xn_shift: model.xn_shift + self.xn_shift,
            kinetics_scale: model.kinetics_scale * self.kinetics_scale,
            t_diffusion_s: model.t_diffusion_s * self.diffusion_scale,
            ..model.clone()
        }
    }

    fn draw(cfg: &ModelErrorConfig, rng: &mut SmallRng) -> Self {
        let p = cfg.probability.clamp(0.0, 1.0);
        let mut e = CellError::default();
        let log_uniform = |rng: &mut SmallRng, [lo, hi]: [f64; 2]| uniform(rng, [lo.ln(), hi.ln()]).exp();
        if rng.random_bool(p) {
            e.xp_shift = uniform(rng, cfg.xp_shift);
            e.xn_shift = uniform(rng, cfg.xn_shift);
        }
        if rng.random_bool(p) {
            e.kinetics_scale = log_uniform(rng, cfg.kinetics_scale);
        }
        if rng.random_bool(p) {
            e.diffusion_scale = log_uniform(rng, cfg.diffusion_scale);
        }
        if rng.random_bool(p) {
            e.voltage_bias_v = uniform(rng, cfg.voltage_bias_v);
        }
        e
    }
}

impl Default for ScenarioConfig {
    fn default() -> Self {
        Self {
            q_mobile_c: [4000.0, 7000.0],
            r_o_ohm: [0.1, 0.2],
            soc0: [0.4, 1.0],
            rest_s: [10.0, 60.0],
            sample_interval_s: vec![[1.0, 1.0], [10.0, 20.0]],
            load_kinds: LoadKind::ALL.to_vec(),
            segment_hold_s: [10.0, 600.0],
            segment_rest_probability: 0.15,
            unknown_request_probability: 0.5,
            // Disjoint levels: test extrapolates to loads above training, validation sits between.
            train: SplitLoads { power_w: [8.0, 13.0], current_a: [2.0, 3.25] },
            validation: SplitLoads { power_w: [13.0, 14.0], current_a: [3.25, 3.5] },
            test: SplitLoads { power_w: [14.0, 16.0], current_a: [3.5, 4.0] },
            thermal: false,
            ambient_c: [10.0, 45.0],
            truth_dt_s: 1.0,
            cutoff_v: 3.0,
            max_duration_s: 20_000.0,
            validation_episodes: 48,
            test_episodes: 96,
            sensor: SensorConfig::default(),
            model: super::extension::ModelExtension::default(),
            model_error: ModelErrorConfig::default(),
            prior_sd_z: None,
            rest_jump: RestJumpConfig::default(),
            recorded: RecordedConfig::default(),
        }
    }
}

impl ScenarioConfig {
    pub fn loads(&self, split: Split) -> &SplitLoads {
        match split {
            Split::Train => &self.train,
            Split::Validation => &self.validation,
            Split::Test => &self.test,
        }
    }

    /// The base seed of a split's fixed episode set (training episodes are drawn from the run's seed).
    pub fn split_seed(split: Split) -> u64 {
        match split {
            Split::Train => 0x7ea1,
            Split::Validation => 0x5a11d,
            Split::Test => 0x7e57,
        }
    }
}

/// The hidden truth and the plan of one episode.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeSpec {
    pub truth: Degradation,
    /// Starting charge, fraction of qMobile.
    pub soc0: f64,
    pub kind: LoadKind,
    /// The true load over time (load on after the rest).
    pub profile: LoadProfile,
    pub rest_s: f64,
    /// Ambient (and starting) temperature, K.
    pub ambient_k: f64,
    /// Interval range this episode samples with, s.
    pub interval_s: [f64; 2],
    /// Seed of the sampling times and the sensor noise.
    pub noise_seed: u64,
    /// What the cell carries beyond the model (scoring reads it; calibrators never do).
    #[serde(default)]
    pub cell_error: CellError,
    /// Whether the readings say what load was asked for (a BMS knows; a cycler's export does not).
    #[serde(default = "yes")]
    pub request_known: bool,
    /// The calibrator's prior for this episode (None: the calibrator's own): a recorded discharge starts
    /// from the offline fit of the one before it, as `bcal calibrate` starts it; a simulated one, with
    /// `ScenarioConfig::prior_sd_z`, from a draw around its truth.
    #[serde(default)]
    pub prior: Option<Degradation>,
}

impl EpisodeSpec {
    /// A cycler's discharge: a minute's rest at `ambient_k`, then `load` held (a current, or a power), sampled
    /// every 9-19 s, the requests unknown, from `soc0` of the charge `truth` holds.
    pub fn rest_then(truth: Degradation, soc0: f64, load: Load, ambient_k: f64, noise_seed: u64) -> Self {
        let (kind, rest) = match load {
            Load::CurrentA(_) => (LoadKind::ConstantCurrent, Load::CurrentA(0.0)),
            Load::PowerW(_) => (LoadKind::ConstantPower, Load::PowerW(0.0)),
        };
        Self {
            truth,
            soc0,
            kind,
            profile: LoadProfile::Piecewise(vec![(0.0, rest), (60.0, load)]),
            rest_s: 60.0,
            ambient_k,
            interval_s: [9.0, 19.0],
            noise_seed,
            cell_error: CellError::default(),
            request_known: false,
            prior: None,
        }
    }
}

fn yes() -> bool {
    true
}

/// One sensor reading.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    pub t_s: f64,
    /// Terminal voltage, V.
    pub voltage_v: f64,
    /// Current, A, positive while discharging.
    pub current_a: f64,
    /// Cell temperature, K.
    pub temperature_k: f64,
    /// The load the system asked for at this time (a BMS knows what it asked for; a cycler's export may not).
    pub request: Request,
}

/// The load a reading says was asked for.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Request {
    /// Not recorded (measured data): only the measured current is known.
    Unknown,
    /// No load.
    Rest,
    /// Constant power, W.
    PowerW(f64),
    /// Constant current, A.
    CurrentA(f64),
}

impl Request {
    fn of(load: Load) -> Self {
        match load {
            Load::CurrentA(0.0) => Request::Rest,
            Load::CurrentA(a) => Request::CurrentA(a),
            Load::PowerW(w) => Request::PowerW(w),
        }
    }
}

/// A simulated discharge: the readings and, for scoring only, the truth.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Episode {
    pub spec: EpisodeSpec,
    pub samples: Vec<Sample>,
    /// Noise-free terminal voltage at each sample, V (scoring and plots only).
    pub true_voltage_v: Vec<f64>,
    /// Time the true voltage first fell below the cut-off (or the model emptied above it: an electrode's
    /// surface at its clip, [`BatteryModel::surface_empty`]), s; `None` when the episode hit its length limit.
    pub eod_s: Option<f64>,
}

/// The model state of a cell at rest with the negative electrode at mole fraction `xn` everywhere (and the
/// positive at the matching xp: lithium moves between them, so xp + xn is conserved), overpotentials zero.
pub fn rest_state(model: &BatteryModel, d: &Degradation, xn: f64, t_k: f64) -> ModelState {
    let p = &model.params;
    let q_max = model.q_max_c(d);
    let xp = p.xp_min + p.xn_max - xn;
    let mut x = ModelState::zeros();
    x[idx::QP_S] = q_max * xp * p.vol_s_fraction;
    x[idx::QP_B] = q_max * xp * (1.0 - p.vol_s_fraction);
    x[idx::QN_B] = q_max * xn * (1.0 - p.vol_s_fraction);
    x[idx::QN_S] = q_max * xn * p.vol_s_fraction;
    x[idx::T_B] = t_k;
    x
}

/// Negative-electrode mole fraction at a starting charge `soc` (fraction of qMobile).
pub fn xn_of_soc(params: &BatteryParams, soc: f64) -> f64 {
    params.xn_min + soc * (params.xn_max - params.xn_min)
}

fn uniform(rng: &mut SmallRng, [lo, hi]: [f64; 2]) -> f64 {
    if hi > lo {
        rng.random_range(lo..hi)
    } else {
        lo
    }
}

/// Draws one episode's plan for `split` from `rng`.
pub fn draw_spec(cfg: &ScenarioConfig, split: Split, rng: &mut SmallRng) -> EpisodeSpec {
    let loads = cfg.loads(split);
    let truth = Degradation { q_mobile_c: uniform(rng, cfg.q_mobile_c), r_o_ohm: uniform(rng, cfg.r_o_ohm) };
    let soc0 = uniform(rng, cfg.soc0);
    let kind = cfg.load_kinds[rng.random_range(0..cfg.load_kinds.len())];
    let rest_s = uniform(rng, cfg.rest_s).round().max(1.0);
    let profile = match kind {
        LoadKind::ConstantPower => LoadProfile::Piecewise(vec![
            (0.0, Load::CurrentA(0.0)),
            (rest_s, Load::PowerW(uniform(rng, loads.power_w))),
        ]),
        LoadKind::ConstantCurrent => LoadProfile::Piecewise(vec![
            (0.0, Load::CurrentA(0.0)),
            (rest_s, Load::CurrentA(uniform(rng, loads.current_a))),
        ]),
        LoadKind::Piecewise => {
            let max_w = uniform(rng, loads.power_w);
            let mut segs = vec![(0.0, Load::CurrentA(0.0))];
            let mut t = rest_s;
            // The first segment is under load, so every episode starts discharging after its rest.
            while t < cfg.max_duration_s {
                let rest = segs.len() > 1 && rng.random_bool(cfg.segment_rest_probability.clamp(0.0, 1.0));
                // Loads below a fifth of the maximum are rests in all but name: draw from [max / 5, max].
                let load = if rest { Load::CurrentA(0.0) } else { Load::PowerW(rng.random_range(0.2 * max_w..=max_w)) };
                segs.push((t, load));
                t += uniform(rng, cfg.segment_hold_s).round().max(1.0);
            }
            LoadProfile::Piecewise(segs)
        }
    };
    let ambient_k = if cfg.thermal { KELVIN_0C + uniform(rng, cfg.ambient_c) } else { cfg.model.params().tb0_k };
    let interval_s = cfg.sample_interval_s[rng.random_range(0..cfg.sample_interval_s.len())];
    let noise_seed = rng.random();
    let request_known = !rng.random_bool(cfg.unknown_request_probability.clamp(0.0, 1.0));
    // Drawn last, and only when asked for: episode sets without them stay what they were.
    let cell_error =
        if cfg.model_error.probability > 0.0 { CellError::draw(&cfg.model_error, rng) } else { CellError::default() };
    let prior = cfg.prior_sd_z.map(|sd| {
        let span = [cfg.q_mobile_c[1] - cfg.q_mobile_c[0], cfg.r_o_ohm[1] - cfg.r_o_ohm[0]];
        let n = |rng: &mut SmallRng, s: f64| Normal::new(0.0, s.max(0.0)).expect("finite sd").sample(rng);
        let mut p = Degradation {
            q_mobile_c: (truth.q_mobile_c + n(rng, sd[0]) * span[0]).max(1.0),
            r_o_ohm: (truth.r_o_ohm + n(rng, sd[1]) * span[1]).max(1e-4),
        };
        // Drawn only when asked for, so episode sets without jumps stay what they were.
        let j = &cfg.rest_jump;
        if j.probability > 0.0 && rng.random_bool(j.probability.clamp(0.0, 1.0)) {
            p.q_mobile_c = (p.q_mobile_c - uniform(rng, j.q_mobile_frac) * truth.q_mobile_c).max(1.0);
        }
        p
    });
    EpisodeSpec {
        truth,
        soc0,
        kind,
        profile,
        rest_s,
        ambient_k,
        interval_s,
        noise_seed,
        cell_error,
        request_known,
        prior,
    }
}

/// Simulates `spec` to the cut-off (or until the model is empty) and reads it through the sensor.
pub fn simulate(cfg: &ScenarioConfig, spec: &EpisodeSpec) -> Result<Episode, ModelError> {
    let true_model = spec.cell_error.apply(&cfg.model);
    let params = BatteryParams { tb0_k: spec.ambient_k, ..true_model.params() };
    let mut model = BatteryModel::new(params, cfg.thermal)?;
    model.check_degradation(&spec.truth)?;
    let kn_kp = (model.params.kn, model.params.kp);
    let ref_k = cfg.model.reference_k.unwrap_or(spec.ambient_k);
    let arrhenius = cfg.model.temperature_dependent();
    let mut rng = SmallRng::seed_from_u64(spec.noise_seed);
    let s = &cfg.sensor;
    let normal = |sd: f64| Normal::new(0.0, sd.max(0.0)).expect("finite standard deviation");
    let (nv, ni, nt) = (normal(s.voltage_noise_v), normal(s.current_noise_a), normal(s.temperature_noise_k));
    let dt = cfg.truth_dt_s;
    let mut x = rest_state(&model, &spec.truth, xn_of_soc(&model.params, spec.soc0), spec.ambient_k);
    let mut t_s = 0.0;
    let mut next_sample_s = 0.0;
    let mut samples = Vec::new();
    let mut true_voltage_v = Vec::new();
    let mut eod_s = None;
    loop {
        // The doctor's thermal extension: Ro and the rate constants at the cell's temperature.
        let mut truth = spec.truth;
        if arrhenius {
            truth.r_o_ohm *= cfg.model.apply_at(&mut model, kn_kp, x[idx::T_B], ref_k);
        }
        let v = model.voltage_v(&x, &truth);
        if !v.is_finite() || x.iter().any(|q| !q.is_finite()) {
            return Err(ModelError::NonFinite { t_s });
        }
        let load = spec.profile.at(t_s);
        let i = match load {
            Load::CurrentA(a) => a,
            Load::PowerW(w) => {
                if v <= 0.0 {
                    return Err(ModelError::NonPositiveVoltage { t_s, voltage_v: v });
                }
                w / v
            }
        };
        let under_load = t_s >= spec.rest_s;
        let ended = under_load && (v < cfg.cutoff_v || model.surface_empty(&x, &truth));
        // The cut-off reading is taken under load, as a cycler reads it before it opens the circuit.
        if t_s + 1e-9 >= next_sample_s || ended {
            samples.push(Sample {
                t_s,
                voltage_v: v + s.voltage_bias_v + spec.cell_error.voltage_bias_v + nv.sample(&mut rng),
                current_a: i + s.current_bias_a + ni.sample(&mut rng),
                temperature_k: x[idx::T_B] + nt.sample(&mut rng),
                request: if spec.request_known { Request::of(load) } else { Request::Unknown },
            });
            true_voltage_v.push(v);
            next_sample_s = t_s + uniform(&mut rng, spec.interval_s).round().max(dt);
        }
        if ended {
            eod_s = Some(t_s);
            break;
        }
        if t_s >= cfg.max_duration_s {
            break;
        }
        x = model.step_current(&x, i, dt, &truth);
        t_s += dt;
    }
    Ok(Episode { spec: spec.clone(), samples, true_voltage_v, eod_s })
}

/// The fixed episode set of a split (validation or test): `n` episodes from the split's seed.
pub fn episode_set(cfg: &ScenarioConfig, split: Split, n: usize) -> Result<Vec<Episode>, ModelError> {
    let mut rng = SmallRng::seed_from_u64(ScenarioConfig::split_seed(split));
    (0..n).map(|_| simulate(cfg, &draw_spec(cfg, split, &mut rng))).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rest_state_reads_its_open_circuit_voltage_and_conserves_lithium() {
        let m = BatteryModel::default();
        let d = Degradation::default();
        // A full cell is the model's own initial state.
        let full = rest_state(&m, &d, m.params.xn_max, m.params.tb0_k);
        assert_eq!(full, m.initial_state(&d));
        let half = rest_state(&m, &d, xn_of_soc(&m.params, 0.5), m.params.tb0_k);
        let total = |x: &ModelState| x[idx::QP_S] + x[idx::QP_B] + x[idx::QN_B] + x[idx::QN_S];
        assert!((total(&half) - total(&full)).abs() < 1e-9 * total(&full));
        assert!(m.voltage_v(&half, &d) < m.voltage_v(&full, &d));
    }

    #[test]
    fn episodes_reach_the_cutoff_with_noisy_samples_at_their_interval() {
        let cfg = ScenarioConfig::default();
        let mut rng = SmallRng::seed_from_u64(3);
        let mut kinds = std::collections::BTreeSet::new();
        for _ in 0..12 {
            let spec = draw_spec(&cfg, Split::Train, &mut rng);
            kinds.insert(spec.kind.name());
            let e = simulate(&cfg, &spec).unwrap();
            let eod = e.eod_s.expect("every training episode discharges to the cut-off");
            assert!(eod > spec.rest_s);
            let n = e.samples.len();
            assert_eq!(e.true_voltage_v.len(), n);
            // The last sample is the cut-off one, read under load.
            assert!(e.true_voltage_v[n - 1] < cfg.cutoff_v && e.samples[n - 1].t_s == eod);
            assert!(e.samples[n - 1].current_a > 0.5 && e.samples[n - 1].request != Request::Rest);
            // Rest first: the first sample reads no load (its request is Rest, or Unknown when the episode
            // hides its requests as a BMS without them does).
            assert!(matches!(e.samples[0].request, Request::Rest | Request::Unknown), "{:?}", e.samples[0].request);
            assert!(e.samples[0].current_a.abs() < 0.05);
            // Intervals follow the episode's range (the last one may be shorter: the cut-off is read at once).
            for w in e.samples[..n - 1].windows(2) {
                let dt = w[1].t_s - w[0].t_s;
                assert!(dt >= spec.interval_s[0].round() - 1e-9 && dt <= spec.interval_s[1].round() + 1e-9, "{dt}");
            }
            // Noise of about 3 mV on the voltage.
            let rms = (e.samples.iter().zip(&e.true_voltage_v).map(|(s, v)| (s.voltage_v - v).powi(2)).sum::<f64>()
                / n as f64)
                .sqrt();
            assert!(rms > 0.001 && rms < 0.006 || n < 30, "voltage noise {rms}");
        }
        assert!(kinds.len() >= 2, "{kinds:?}");
    }

    /// A long rest's regained capacity: the prior lags the truth's qMobile by the drawn fraction in as many
    /// episodes as asked, and never sits above it (prior spread zero, so only the jump moves it).
    #[test]
    fn rest_jumps_put_the_prior_below_the_truth_as_often_and_as_far_as_asked() {
        let cfg = ScenarioConfig {
            prior_sd_z: Some([0.0, 0.0]),
            rest_jump: RestJumpConfig { probability: 0.3, q_mobile_frac: [0.02, 0.04] },
            ..ScenarioConfig::default()
        };
        let mut rng = SmallRng::seed_from_u64(11);
        let specs: Vec<EpisodeSpec> = (0..400).map(|_| draw_spec(&cfg, Split::Train, &mut rng)).collect();
        let mut jumped = 0;
        for s in &specs {
            let (p, t) = (s.prior.expect("a prior is drawn"), s.truth);
            assert_eq!(p.r_o_ohm, t.r_o_ohm);
            let frac = 1.0 - p.q_mobile_c / t.q_mobile_c;
            if frac != 0.0 {
                assert!((0.02..=0.04).contains(&frac), "jump {frac}");
                jumped += 1;
            }
        }
        assert!((90..=150).contains(&jumped), "{jumped} of 400 jumped at probability 0.3");
        // Off by default: the same draws as a config without the option.
        let plain = ScenarioConfig { rest_jump: RestJumpConfig::default(), ..cfg.clone() };
        let mut rng = SmallRng::seed_from_u64(11);
        assert!((0..50).all(|_| {
            let s = draw_spec(&plain, Split::Train, &mut rng);
            s.prior == Some(s.truth)
        }));
    }

    #[test]
    fn a_recorded_set_with_unknown_truths_reads_back_and_a_damaged_file_is_refused() {
        let cfg = ScenarioConfig::default();
        let mut rng = SmallRng::seed_from_u64(5);
        let mut spec = draw_spec(&cfg, Split::Train, &mut rng);
        let mut e = simulate(&cfg, &spec).unwrap();
        spec.truth = Degradation { q_mobile_c: f64::NAN, r_o_ohm: f64::NAN };
        spec.soc0 = f64::NAN;
        spec.prior = Some(Degradation { q_mobile_c: 7000.0, r_o_ohm: 0.12 });
        e.spec = spec;
        let set = RecordedSet { cell: "B0018".into(), train: vec![e.clone()], validation: vec![e] };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cell.recorded.bin");
        std::fs::write(&path, set.to_bytes()).unwrap();
        let back = RecordedSet::load(&path).unwrap();
        assert!(back.train[0].spec.truth.q_mobile_c.is_nan() && back.validation[0].spec.soc0.is_nan());
        assert_eq!(back.train[0].samples, set.train[0].samples);
        assert_eq!(back.train[0].spec.prior, set.train[0].spec.prior);
        let bytes = set.to_bytes();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        let err = RecordedSet::load(&path).unwrap_err();
        assert!(err.contains("cell.recorded.bin") && err.contains("bcal cell-config"), "{err}");
    }

    #[test]
    fn split_loads_are_disjoint_and_episode_sets_repeat() {
        let cfg = ScenarioConfig::default();
        let level = |e: &Episode| match &e.spec.profile {
            LoadProfile::Piecewise(s) => s[1..]
                .iter()
                .map(|(_, l)| match l {
                    Load::PowerW(w) => *w / 4.0, // compare powers and currents on one rough scale
                    Load::CurrentA(a) => *a,
                })
                .fold(0.0, f64::max),
            LoadProfile::Constant(_) => unreachable!(),
        };
        let val = episode_set(&cfg, Split::Validation, 8).unwrap();
        let again = episode_set(&cfg, Split::Validation, 8).unwrap();
        assert_eq!(val, again, "a split's episode set is the same every time");
        let test = episode_set(&cfg, Split::Test, 8).unwrap();
        for e in &test {
            let train_max = match e.spec.kind {
                LoadKind::ConstantCurrent => cfg.train.current_a[1],
                _ => cfg.train.power_w[1] / 4.0,
            };
            if e.spec.kind != LoadKind::Piecewise {
                assert!(level(e) > train_max, "test load {} within training's", level(e));
            }
        }
        assert_ne!(val[0].spec.truth, test[0].spec.truth);
    }
}
