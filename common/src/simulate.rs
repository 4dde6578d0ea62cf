//! One discharge of the model from a new cell's state (progpy's x0) until the first step below VEOD, as
//! `bcal simulate` and the Python package's `bcal.simulate` both run it: one request type, one trace, one
//! set of error messages, so the two faces cannot drift apart. The CLI writes the trace as CSV; Python
//! turns it into NumPy arrays. Nothing here prints.

use crate::battery::{BatteryModel, BatteryParams, Degradation, Load, LoadProfile, ModelError};
use crate::math::ModelState;

/// What to simulate. Defaults are the CLI's.
#[derive(Clone, Debug, PartialEq)]
pub struct SimulateRequest {
    /// Mobile lithium charge qMobile, C. Default 7600 (new cell).
    pub q_mobile: f64,
    /// Ohmic resistance Ro, ohm. Default 0.117215 (new cell).
    pub r_o: f64,
    /// Constant power, W (exactly one of `load_w` and `current_a`).
    pub load_w: Option<f64>,
    /// Constant discharge current, A, positive while discharging.
    pub current_a: Option<f64>,
    /// Load steps after the start: (start_s, value) in the unit of the first load (W or A), start times
    /// increasing; each holds until the next. Empty: a constant load.
    pub steps: Vec<(f64, f64)>,
    /// The bulk temperature follows progpy's heat balance (progpy always does); off: isothermal at 292.1 K.
    pub thermal: bool,
    /// Euler step, s. Default 1.
    pub dt_s: f64,
    /// Most steps before giving up on reaching VEOD. Default 200 000.
    pub max_steps: usize,
}

impl Default for SimulateRequest {
    fn default() -> Self {
        let d = Degradation::default();
        Self {
            q_mobile: d.q_mobile_c,
            r_o: d.r_o_ohm,
            load_w: None,
            current_a: None,
            steps: Vec::new(),
            thermal: false,
            dt_s: 1.0,
            max_steps: 200_000,
        }
    }
}

/// Every step of one discharge, t = 0 to the EOD row included.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Trace {
    pub time_s: Vec<f64>,
    pub voltage_v: Vec<f64>,
    /// Current drawn over the step that starts at this row, A (P / V for a power load; 0 on the EOD row).
    pub current_a: Vec<f64>,
    /// The load's own value at this row: W for a power load, A for a current load.
    pub input: Vec<f64>,
    /// The full model state at each row (electrochemical states and the bulk temperature, K).
    pub state: Vec<ModelState>,
    /// Time of the first row below VEOD, s.
    pub eod_s: f64,
}

/// Why a simulation could not run or end; the messages are the CLI's.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SimulateError {
    #[error("give exactly one of --load-w or --current-a")]
    LoadChoice,
    #[error("{name} = {value}: {why}")]
    BadArgument { name: &'static str, value: f64, why: String },
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error("the voltage stayed above VEOD for {max_steps} steps ({seconds} s); raise --max-steps or the load")]
    NoEod { max_steps: usize, seconds: f64 },
}

/// A finite number > 0, or the message the CLI gives for it.
pub fn positive(v: f64) -> Result<f64, String> {
    if !v.is_finite() {
        return Err(format!("`{v}` is not a finite number"));
    }
    if v <= 0.0 {
        return Err(format!("{v} must be greater than 0"));
    }
    Ok(v)
}

/// A finite number >= 0, or the message the CLI gives for it.
pub fn non_negative(v: f64) -> Result<f64, String> {
    if !v.is_finite() {
        return Err(format!("`{v}` is not a finite number"));
    }
    if v < 0.0 {
        return Err(format!("{v} must not be negative"));
    }
    Ok(v)
}

impl SimulateRequest {
    /// The load over time, after checking every argument as the CLI's parsers do.
    pub fn profile(&self) -> Result<LoadProfile, SimulateError> {
        let bad = |name: &'static str, value: f64| move |why: String| SimulateError::BadArgument { name, value, why };
        positive(self.q_mobile).map_err(bad("q_mobile", self.q_mobile))?;
        non_negative(self.r_o).map_err(bad("ro", self.r_o))?;
        positive(self.dt_s).map_err(bad("dt_s", self.dt_s))?;
        // Explicit Euler on the ohmic lag (time constant t_o) is stable only below 2 t_o, as the config checks.
        let limit_s = 2.0 * BatteryParams::default().t_o_s;
        if self.dt_s >= limit_s {
            return Err(SimulateError::BadArgument {
                name: "dt_s",
                value: self.dt_s,
                why: format!(
                    "must be below {limit_s:.2} s: explicit Euler on the ohmic lag is unstable beyond 2 t_o (1 s is \
                     the reference's step)"
                ),
            });
        }
        let (name, first, make): (&'static str, f64, fn(f64) -> Load) = match (self.load_w, self.current_a) {
            (Some(p), None) => ("load_w", p, Load::PowerW),
            (None, Some(i)) => ("current_a", i, Load::CurrentA),
            _ => return Err(SimulateError::LoadChoice),
        };
        positive(first).map_err(bad(name, first))?;
        if self.steps.is_empty() {
            return Ok(LoadProfile::Constant(make(first)));
        }
        let mut segs = vec![(0.0, make(first))];
        for &(start_s, value) in &self.steps {
            positive(start_s).map_err(bad("steps start_s", start_s))?;
            positive(value).map_err(bad(name, value))?;
            if start_s <= segs.last().map_or(0.0, |s| s.0) {
                return Err(SimulateError::BadArgument {
                    name: "steps start_s",
                    value: start_s,
                    why: "load steps must start in increasing time order".into(),
                });
            }
            segs.push((start_s, make(value)));
        }
        Ok(LoadProfile::Piecewise(segs))
    }
}

/// Runs `req` to the end of discharge.
pub fn simulate(req: &SimulateRequest) -> Result<Trace, SimulateError> {
    let profile = req.profile()?;
    let model = BatteryModel::new(BatteryParams::default(), req.thermal)?;
    let d = Degradation { q_mobile_c: req.q_mobile, r_o_ohm: req.r_o };
    let mut tr = Trace::default();
    let outcome = model.simulate_until_eod(&model.initial_state(&d), &d, &profile, req.dt_s, req.max_steps, |r| {
        tr.time_s.push(r.t_s);
        tr.voltage_v.push(r.voltage_v);
        tr.current_a.push(r.current_a);
        tr.input.push(match r.load {
            Load::PowerW(p) => p,
            Load::CurrentA(i) => i,
        });
        tr.state.push(r.x);
    })?;
    match outcome.eod_s {
        Some(t) => {
            tr.eod_s = t;
            Ok(tr)
        }
        None => Err(SimulateError::NoEod { max_steps: req.max_steps, seconds: req.max_steps as f64 * req.dt_s }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A step past the explicit-Euler limit gave an end at 75 s (dt 15) and voltages of -7 V (dt 30): refused.
    #[test]
    fn a_step_past_the_stability_limit_is_refused() {
        let req = |dt_s| SimulateRequest { load_w: Some(8.0), dt_s, ..SimulateRequest::default() };
        for dt_s in [12.2, 15.0, 30.0, 1e6] {
            let e = simulate(&req(dt_s)).unwrap_err().to_string();
            assert!(e.contains("unstable beyond 2 t_o") && e.contains("12.17"), "{e}");
        }
        assert!(simulate(&req(12.0)).is_ok());
    }

    #[test]
    fn eight_watts_ends_at_the_reference_eod() {
        let tr = simulate(&SimulateRequest { load_w: Some(8.0), ..Default::default() }).unwrap();
        assert_eq!(tr.eod_s, 3102.0);
        assert_eq!(tr.time_s.len(), 3103);
        assert!(tr.voltage_v[3102] < 3.0 && tr.voltage_v[3101] >= 3.0);
        assert_eq!(tr.current_a[3102], 0.0);
        assert!((tr.current_a[0] - 8.0 / tr.voltage_v[0]).abs() < 1e-15);
    }

    #[test]
    fn a_load_step_switches_at_its_start() {
        let tr = simulate(&SimulateRequest { current_a: Some(1.0), steps: vec![(100.0, 3.0)], ..Default::default() })
            .unwrap();
        assert_eq!((tr.input[99], tr.input[100]), (1.0, 3.0));
        assert_eq!((tr.current_a[99], tr.current_a[100]), (1.0, 3.0));
        let e = simulate(&SimulateRequest {
            current_a: Some(1.0),
            steps: vec![(100.0, 3.0), (50.0, 2.0)],
            ..Default::default()
        })
        .unwrap_err();
        assert!(e.to_string().contains("increasing time order"), "{e}");
    }

    #[test]
    fn bad_arguments_are_named_as_the_cli_names_them() {
        let e = simulate(&SimulateRequest::default()).unwrap_err();
        assert_eq!(e.to_string(), "give exactly one of --load-w or --current-a");
        let e = simulate(&SimulateRequest { load_w: Some(-1.0), ..Default::default() }).unwrap_err();
        assert_eq!(e.to_string(), "load_w = -1: -1 must be greater than 0");
        let e = simulate(&SimulateRequest { current_a: Some(2.0), r_o: f64::NAN, ..Default::default() }).unwrap_err();
        assert!(e.to_string().contains("ro = NaN"), "{e}");
        let e = simulate(&SimulateRequest { current_a: Some(0.01), max_steps: 10, ..Default::default() }).unwrap_err();
        assert_eq!(e, SimulateError::NoEod { max_steps: 10, seconds: 10.0 });
    }
}
