//! A cell's capacity across discharges (the model `bcal diagnose` fits; `bcal_doctor::lifetime`'s module
//! doc gives its form and how it is fitted): a linear fade, condition terms, and capacity a rest gives back
//! and the next discharges wear off. Here are the model and [`LifeTracker`], which follows a cell's life
//! discharge by discharge: what `bcal calibrate`'s prior walk and a live stream carry between discharges
//! ([`LifeTracker::carry`], the one rule for both).

use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

/// The conditions of one discharge that the trend may depend on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Condition {
    pub ambient_c: f64,
    /// Mean current under load, A.
    pub current_a: f64,
}

/// What a lifetime series holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Quantity {
    /// Charge drawn under load to the cut-off, Ah.
    CapacityAh,
    /// The base model's fitted mobile charge, C.
    QMobileC,
}

/// The capacity a rest gives back on a cell whose training records cannot say (no rest among them long enough
/// to fit a recovery; NASA: "capacity jumps up by 0.02-0.15 Ah after rest gaps" on every cell of the set).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PopulationRecovery {
    /// A over the cell's capacity.
    pub amplitude_frac: f64,
    pub tau_rest_h: f64,
    pub decay_discharges: f64,
    /// The jump's uncertainty over its size: a population's value, not the cell's, so as wide as the jump.
    pub jump_sd_fraction: f64,
}

/// A model fitted on records with no rest this long (a day) takes [`POPULATION_RECOVERY`]: its records cannot say
/// what a long rest gives back.
pub const POPULATION_RECOVERY_UNSEEN_REST_S: f64 = 24.0 * 3600.0;

/// Known rests a cell without its own lifetime model (a live stream without one, `bcal calibrate` on training
/// records too few to fit one) needs before its life is followed by NASA's cells' recovery
/// ([`LifetimeModel::population`]), their median its usual rest: one rest alone (a weekend) is no usual one.
pub const POPULATION_RESTS: usize = 3;

/// The recovery of NASA's four cells in `../shared` whose training records fit and name one (`bcal calibrate
/// --data ../shared/data/nasa-pcoe --cell C`, `settings.prior.lifetime.model`; B0005 / B0006 / B0018 / B0029: A
/// over capacity 0.036 / 0.076 / 0.064 / 0.049, tau 15.2 / 37.6 / 42.3 / 2.5 h, wear-off 5.0 / 6.3 / 200 / 200
/// discharges, 200 the fit's bound): the medians, the wear-off's taken on its logarithm. A 3-day rest then gives
/// back 4.6 % of the capacity over a 3-hour one (their own models: 2.7 / 5.7 / 4.8 / 1.7 %).
pub const POPULATION_RECOVERY: PopulationRecovery =
    PopulationRecovery { amplitude_frac: 0.056, tau_rest_h: 26.4, decay_discharges: 35.5, jump_sd_fraction: 1.0 };

/// One series' lifetime model (see the module doc): what the calibrators can use as a prior.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LifetimeModel {
    /// What the series is (the unit of every value below).
    pub quantity: Quantity,
    /// a: the trend's value at `reference_cycle` with R = 0.
    pub intercept: f64,
    /// b: change per discharge (negative: fade).
    pub per_cycle: f64,
    pub reference_cycle: f64,
    /// c_T per K of ambient temperature above `reference.ambient_c`, and c_I per A of mean load current
    /// above `reference.current_a` (0 when the training records did not vary enough to fit them).
    pub per_kelvin: f64,
    pub per_ampere: f64,
    pub reference: Condition,
    /// A: what a rest long against `tau_rest_s` adds (0: no recovery in this model).
    pub amplitude: f64,
    /// tau: recovery time constant, s of rest (0 without recovery).
    pub tau_rest_s: f64,
    /// d: wear-off time constant, discharges (0 without recovery).
    pub decay_discharges: f64,
    /// The cell's usual rest between discharges, s (median of the known ones): the rest assumed where one is
    /// not known.
    pub usual_rest_s: f64,
    /// RMS of the one-ahead residuals on the training cycles (the prior's floor).
    pub residual_sd: f64,
    /// Width of a predicted recovery's uncertainty, as a fraction of its size (`bcal diagnose`'s setting).
    pub jump_sd_fraction: f64,
}

impl LifetimeModel {
    /// What a rest of `rest_s` adds to R: 1 - exp(-rest / tau).
    pub fn refill(&self, rest_s: f64) -> f64 {
        if self.amplitude == 0.0 {
            return 0.0;
        }
        1.0 - (-rest_s.max(0.0) / self.tau_rest_s).exp()
    }

    /// R one discharge later: worn off once, filled by the rest before it (the usual rest when unknown).
    pub fn next_recovery(&self, recovery: f64, rest_before_s: Option<f64>) -> f64 {
        if self.amplitude == 0.0 {
            return 0.0;
        }
        recovery * (-1.0 / self.decay_discharges).exp() + self.refill(rest_before_s.unwrap_or(self.usual_rest_s))
    }

    /// R under the usual rest forever (where a life without a known history starts).
    pub fn steady_recovery(&self) -> f64 {
        if self.amplitude == 0.0 {
            return 0.0;
        }
        self.refill(self.usual_rest_s) / (1.0 - (-1.0 / self.decay_discharges).exp())
    }

    /// The model's value at a cycle with recovery state `recovery` and conditions `at` (open loop).
    pub fn level(&self, cycle: u32, recovery: f64, at: Condition) -> f64 {
        self.intercept
            + self.per_cycle * (f64::from(cycle) - self.reference_cycle)
            + self.per_kelvin * (at.ambient_c - self.reference.ambient_c)
            + self.per_ampere * (at.current_a - self.reference.current_a)
            + self.amplitude * recovery
    }

    /// Why this model cannot move a carried value (None: it can): a series other than capacity, a number
    /// that is not finite, or a recovery without its time constants.
    pub fn unusable(&self) -> Option<String> {
        if self.quantity != Quantity::CapacityAh {
            return Some("it models qMobile, not the capacity in Ah (quantity = \"capacity_ah\")".into());
        }
        let numbers = [
            self.intercept,
            self.per_cycle,
            self.reference_cycle,
            self.per_kelvin,
            self.per_ampere,
            self.amplitude,
            self.tau_rest_s,
            self.decay_discharges,
            self.usual_rest_s,
            self.residual_sd,
            self.jump_sd_fraction,
        ];
        if numbers.iter().any(|x| !x.is_finite()) {
            return Some("a number in it is not finite".into());
        }
        if self.amplitude < 0.0 || (self.amplitude > 0.0 && !(self.tau_rest_s > 0.0 && self.decay_discharges > 0.0)) {
            return Some(
                "its recovery needs amplitude >= 0 and, when above 0, tau_rest_s and decay_discharges above 0".into(),
            );
        }
        None
    }

    /// A cell's capacity model with nothing known of it but a discharge's capacity and its usual rest: no fade
    /// and the recovery NASA's cells show ([`POPULATION_RECOVERY`]). What a live stream without the cell's own
    /// model follows the life with (a flat trend: each discharge's measured capacity carries the fade).
    pub fn population(capacity_ah: f64, usual_rest_s: f64) -> LifetimeModel {
        LifetimeModel {
            quantity: Quantity::CapacityAh,
            intercept: capacity_ah,
            per_cycle: 0.0,
            reference_cycle: 1.0,
            per_kelvin: 0.0,
            per_ampere: 0.0,
            reference: Condition::default(),
            amplitude: 0.0,
            tau_rest_s: 0.0,
            decay_discharges: 0.0,
            usual_rest_s,
            residual_sd: 0.0,
            jump_sd_fraction: 0.0,
        }
        .with_population_recovery()
    }

    /// [`LifetimeModel::population`] with the median of the known rests `rests_s` (those above 0) as the usual
    /// one; None with fewer than [`POPULATION_RESTS`] of them. The one rule a live stream without the cell's model
    /// and `bcal calibrate` on training records too few to fit one take it by.
    pub fn population_from_rests(capacity_ah: f64, rests_s: impl IntoIterator<Item = f64>) -> Option<LifetimeModel> {
        let mut rests: Vec<f64> = rests_s.into_iter().filter(|r| *r > 0.0).collect();
        if rests.len() < POPULATION_RESTS {
            return None;
        }
        Some(LifetimeModel::population(capacity_ah, crate::stats::median(&mut rests)?))
    }

    /// This model with the recovery NASA's cells show ([`POPULATION_RECOVERY`]) where it has none and its cell's
    /// usual rest is known, its level under the usual rest kept: for a cell whose training records held no rest
    /// long enough to fit its own. Unchanged otherwise.
    pub fn with_population_recovery(&self) -> LifetimeModel {
        let p = POPULATION_RECOVERY;
        let usable = self.usual_rest_s > 0.0 && self.intercept > 0.0;
        if self.amplitude != 0.0 || self.quantity != Quantity::CapacityAh || !usable {
            return *self;
        }
        let mut m = *self;
        m.amplitude = p.amplitude_frac * self.intercept;
        m.tau_rest_s = p.tau_rest_h * 3600.0;
        m.decay_discharges = p.decay_discharges;
        m.jump_sd_fraction = p.jump_sd_fraction;
        m.intercept -= m.amplitude * m.steady_recovery();
        m
    }

    /// This model with its recovery's amplitude times `scale` (its level under the usual rest kept): the size a
    /// cell's own records said ([`LifeTracker::recovery_scale`]).
    pub fn with_recovery_scaled(&self, scale: f64) -> LifetimeModel {
        if self.amplitude == 0.0 || scale == 1.0 {
            return *self;
        }
        let mut m = *self;
        m.intercept += m.amplitude * m.steady_recovery();
        m.amplitude *= scale.max(0.0);
        m.intercept -= m.amplitude * m.steady_recovery();
        m
    }

    /// The jump a rest of `rest_s` gives over the usual rest, before it wears off.
    pub fn jump_over_usual(&self, rest_s: f64) -> f64 {
        self.amplitude * (self.refill(rest_s) - self.refill(self.usual_rest_s))
    }
}

/// A prediction one or more discharges ahead.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Prediction {
    pub value: f64,
    /// One standard deviation of it: the one-ahead residual sd and a share of the predicted recovery change.
    pub sd: f64,
    /// The part of the change since the last measured value that recovery accounts for.
    pub recovery_change: f64,
    /// One standard deviation of that part.
    pub recovery_sd: f64,
}

/// A prior for qMobile at the next discharge.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct QMobilePrior {
    pub mean_c: f64,
    pub sd_c: f64,
}

/// Follows a cell's life discharge by discharge with a [`LifetimeModel`]: what a calibrator keeps between
/// discharges. [`LifeTracker::predict`] gives the value a coming discharge should show from the last measured
/// one and the rest before it; [`LifeTracker::observe`] takes the measured value once known.
#[derive(Clone, Debug, PartialEq)]
pub struct LifeTracker {
    pub model: LifetimeModel,
    /// The cycle the recovery state stands at (`None` before the first).
    cycle: Option<u32>,
    recovery: f64,
    condition: Condition,
    /// The last measured value, with the cycle, recovery state and conditions it was measured at.
    last: Option<(u32, f64, f64, Condition)>,
    /// Whether the recovery's size is learned from the measured values ([`LifeTracker::learning_its_recovery`]).
    learns: bool,
    /// What the measured values said of the recovery's scale: the sums of g^2 / s^2 and g y / s^2 over the
    /// measured changes y across a rest longer than the usual (less the model's fade and the drift below) whose
    /// recovery part at scale 1 was g.
    scale_info: f64,
    scale_xy: f64,
    /// The last measured changes across a usual rest (no recovery part), less the model's fade: the fade the
    /// model does not hold ([`LifetimeModel::population`] holds none), taken off a jump before it is read.
    drift: VecDeque<f64>,
}

/// How many of the last changes across a usual rest [`LifeTracker`]'s drift is the mean of.
const DRIFT_CHANGES: usize = 8;

/// The floor of a measured capacity change's noise when the recovery's scale is learned, as a share of the
/// capacity: a model with no residual of its own ([`LifetimeModel::population`]) would otherwise take one change
/// as exact.
pub const CHANGE_NOISE_FLOOR_FRAC: f64 = 0.003;

impl LifeTracker {
    /// A tracker before the first discharge, its recovery at the usual rest's steady state.
    pub fn new(model: LifetimeModel) -> Self {
        Self {
            cycle: None,
            recovery: model.steady_recovery(),
            condition: model.reference,
            last: None,
            learns: false,
            scale_info: 0.0,
            scale_xy: 0.0,
            drift: VecDeque::new(),
            model,
        }
    }

    /// A tracker that learns the size of the cell's own recovery from its measured values, starting from the
    /// model's: a scale on the amplitude, 1 with a standard deviation of the model's `jump_sd_fraction` before
    /// anything is measured, updated (least squares with that prior) by each measured change beside what the
    /// fade and the scaled recovery expected. For a recovery that is not the cell's own
    /// ([`LifetimeModel::population`]), walked over a cell's training records: NASA's B0025 regains nothing
    /// after rests of 9 and 13 days where the median cell regains 5 % of its capacity, and its 87 h rest before
    /// cycle 6 says so (`bcal calibrate`'s `population_life`). Not on judged discharges: there the scale took up
    /// the difference between the population's time constants and the cell's (`docs/realcell.md`).
    pub fn learning_its_recovery(model: LifetimeModel) -> Self {
        Self { learns: true, ..Self::new(model) }
    }

    /// The recovery's scale (1: the model's own amplitude; held within 0 and 1 + 3 prior standard deviations) and
    /// its standard deviation, from what was measured.
    pub fn recovery_scale(&self) -> (f64, f64) {
        let tau = self.model.jump_sd_fraction;
        if !self.learns || tau <= 0.0 {
            return (1.0, tau);
        }
        let prior = tau.powi(-2);
        let scale = (prior + self.scale_xy) / (prior + self.scale_info);
        (scale.clamp(0.0, 1.0 + 3.0 * tau), (prior + self.scale_info).sqrt().recip())
    }

    /// Moves to discharge `cycle` (later than the current one), with the rest before it and its conditions;
    /// discharges in between had the usual rest.
    pub fn advance_to(&mut self, cycle: u32, rest_before_s: Option<f64>, at: Condition) {
        self.condition = at;
        if let Some(now) = self.cycle {
            if cycle <= now {
                return;
            }
            for _ in now + 1..cycle {
                self.recovery = self.model.next_recovery(self.recovery, None);
            }
        }
        self.recovery = self.model.next_recovery(self.recovery, rest_before_s);
        self.cycle = Some(cycle);
    }

    /// What the current discharge should show: the last measured value plus the model's change since (its
    /// open-loop value before anything was measured).
    pub fn expected(&self) -> Prediction {
        let m = &self.model;
        let cycle = self.cycle.unwrap_or(m.reference_cycle.round().max(1.0) as u32);
        let here = m.level(cycle, self.recovery, self.condition);
        // The model's change and its recovery part g at the model's amplitude; the recovery moves by the
        // learned scale of it.
        let (value, g) = match self.last {
            Some((c, v, r, at)) => (v + here - m.level(c, r, at), m.amplitude * (self.recovery - r)),
            None => (here, m.amplitude * (self.recovery - m.steady_recovery())),
        };
        let (scale, scale_sd) = self.recovery_scale();
        let recovery_sd = scale_sd * g.abs();
        Prediction {
            value: value + (scale - 1.0) * g,
            sd: m.residual_sd.hypot(recovery_sd),
            recovery_change: scale * g,
            recovery_sd,
        }
    }

    /// The prediction for discharge `cycle` after a rest of `rest_before_s` (the usual when `None`).
    pub fn predict(&self, cycle: u32, rest_before_s: Option<f64>, at: Condition) -> Prediction {
        let mut t = self.clone();
        t.advance_to(cycle, rest_before_s, at);
        t.expected()
    }

    /// The capacity (or whatever the model's quantity is) of discharge `cycle` after a rest of
    /// `rest_before_s`, at the last measured discharge's conditions.
    pub fn predict_capacity(&self, cycle: u32, rest_before_s: f64) -> f64 {
        let at = self.last.map_or(self.model.reference, |l| l.3);
        self.predict(cycle, Some(rest_before_s), at).value
    }

    /// Whether a value was measured yet.
    pub fn has_observed(&self) -> bool {
        self.last.is_some()
    }

    /// The recovery state at the current discharge.
    pub fn recovery(&self) -> f64 {
        self.recovery
    }

    /// How the value carried from the last discharge (`last_capacity_ah`: its measured capacity, None when
    /// it did not reach its cut-off) moves to discharge `cycle` after a rest of `rest_before_s`: the relative
    /// change of capacity the model expects (fade and recovery since the last measured capacity), and the
    /// uncertainty of the recovery part. No measured capacity: no change.
    pub fn carry(&self, cycle: u32, rest_before_s: Option<f64>, at: Condition, last_capacity_ah: Option<f64>) -> Carry {
        match last_capacity_ah {
            Some(c) if c > 0.0 => {
                let p = self.predict(cycle, rest_before_s, at);
                Carry { ratio: (p.value / c).clamp(0.8, 1.25), jump_sd_rel: p.recovery_sd / c }
            }
            _ => Carry::NONE,
        }
    }

    /// Records the value measured on the current discharge.
    pub fn observe(&mut self, value: f64) {
        let cycle = self.cycle.unwrap_or(1);
        if let Some((c, v, r, at)) = self.last.filter(|_| self.learns && self.model.amplitude > 0.0) {
            let m = &self.model;
            let g = m.amplitude * (self.recovery - r);
            let fade = m.level(cycle, self.recovery, self.condition) - m.level(c, r, at) - g;
            let noise = m.residual_sd.max(CHANGE_NOISE_FLOOR_FRAC * value.abs());
            let y = value - v - fade;
            // A change across a usual rest tells the drift; one across a longer rest, the jump. The small
            // changes of the recovery wearing off between are left out: a fade the model does not hold would
            // read as a recovery wearing off (NASA's recovery on a cell fading 13 mAh a discharge rose to four
            // times its size).
            if y.is_finite() && g.abs() < 0.2 * noise {
                if self.drift.len() == DRIFT_CHANGES {
                    self.drift.pop_front();
                }
                self.drift.push_back(y);
            } else if y.is_finite() && g > noise {
                let drift =
                    if self.drift.is_empty() { 0.0 } else { self.drift.iter().sum::<f64>() / self.drift.len() as f64 };
                self.scale_info += (g / noise).powi(2);
                self.scale_xy += g * (y - drift) / noise.powi(2);
            }
        }
        self.last = Some((cycle, value, self.recovery, self.condition));
    }

    /// A prior for qMobile on discharge `cycle` from the last calibrated qMobile (`q_mobile_last_c`, on the
    /// last observed discharge): scaled by the predicted relative change of this tracker's quantity, widened
    /// by its relative uncertainty. Before any observation the prior is centred on `q_mobile_last_c`.
    pub fn q_mobile_prior(
        &self,
        q_mobile_last_c: f64,
        cycle: u32,
        rest_before_s: Option<f64>,
        at: Condition,
    ) -> QMobilePrior {
        let p = self.predict(cycle, rest_before_s, at);
        let last = self.last.map_or(p.value - p.recovery_change, |l| l.1);
        if last == 0.0 || !last.is_finite() {
            return QMobilePrior { mean_c: q_mobile_last_c, sd_c: f64::INFINITY };
        }
        QMobilePrior { mean_c: q_mobile_last_c * p.value / last, sd_c: q_mobile_last_c * p.sd / last.abs() }
    }
}

/// What [`LifeTracker::carry`] gives: how a carried qMobile moves to the next discharge.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Carry {
    /// The expected capacity over the last measured one (clamped to 0.8-1.25): qMobile follows it.
    pub ratio: f64,
    /// One standard deviation of the recovery's change, relative to the last capacity.
    pub jump_sd_rel: f64,
}

impl Carry {
    pub const NONE: Carry = Carry { ratio: 1.0, jump_sd_rel: 0.0 };

    /// The carried estimate moved: qMobile scaled by the ratio, Ro carried.
    pub fn mean(&self, carried: &crate::battery::Degradation) -> crate::battery::Degradation {
        crate::battery::Degradation { q_mobile_c: carried.q_mobile_c * self.ratio, r_o_ohm: carried.r_o_ohm }
    }

    /// A prior width (z units of qMobile and Ro, qMobile's range `q_span_c` C wide) with the jump's own
    /// uncertainty added in quadrature to qMobile's.
    pub fn widen_z(&self, sd_z: [f64; 2], carried_q_mobile_c: f64, q_span_c: f64) -> [f64; 2] {
        [sd_z[0].hypot(self.jump_sd_rel * carried_q_mobile_c / q_span_c), sd_z[1]]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const USUAL_S: f64 = 3.0 * 3600.0;
    const AT: Condition = Condition { ambient_c: 24.0, current_a: 2.0 };

    /// A cell of 1.8 Ah fading `fade_ah` a discharge, every rest the usual but a 72 h one before cycles 8 and 16,
    /// after which it regains `jump_ah` (worn off over the discharges after it as NASA's cells' does): the
    /// capacity each cycle measures, with a small deterministic noise.
    fn measured(cycle: u32, jump_ah: f64, fade_ah: f64) -> f64 {
        let since = [16, 8].into_iter().find(|c| cycle >= *c).map_or(f64::INFINITY, |c| f64::from(cycle - c));
        let noise = 0.002 * (f64::from(cycle) * 2.3).sin();
        1.8 - fade_ah * f64::from(cycle) + jump_ah * (-since / POPULATION_RECOVERY.decay_discharges).exp() + noise
    }

    fn rest(cycle: u32) -> f64 {
        if cycle == 8 || cycle == 16 {
            72.0 * 3600.0
        } else {
            USUAL_S
        }
    }

    /// The recovery part a tracker following cycles 1-15 predicts for cycle 16.
    fn predicted_jump(mut t: LifeTracker, jump_ah: f64, fade_ah: f64) -> Prediction {
        for c in 1..=15 {
            t.advance_to(c, Some(rest(c)), AT);
            t.observe(measured(c, jump_ah, fade_ah));
        }
        t.predict(16, Some(rest(16)), AT)
    }

    /// NASA's cells' recovery taken for a cell that regains nothing after a long rest is learned off after the
    /// first: the tracker predicts under a quarter of the population's jump after the second, and its
    /// uncertainty shrinks with it; a cell that regains what the population does keeps most of it, fading
    /// slowly or fast (13 mAh a discharge, a fade the population model does not hold and that must not read as
    /// recovery); a tracker that does not learn predicts the population's jump whatever the cell did.
    #[test]
    fn a_tracker_learns_the_size_of_the_cells_own_recovery() {
        let m = LifetimeModel::population(1.8, USUAL_S);
        let fixed = predicted_jump(LifeTracker::new(m), 0.0, 0.002);
        let population_jump = fixed.recovery_change;
        assert!(population_jump > 0.07, "the population's jump after 72 h: {population_jump} Ah");
        let none = predicted_jump(LifeTracker::learning_its_recovery(m), 0.0, 0.002);
        assert!(none.recovery_change < 0.25 * population_jump, "learned {none:?} against {population_jump}");
        assert!(none.recovery_sd < 0.5 * fixed.recovery_sd, "{none:?} against {fixed:?}");
        for fade_ah in [0.002, 0.013] {
            let like = predicted_jump(LifeTracker::learning_its_recovery(m), 0.09, fade_ah);
            let ratio = like.recovery_change / population_jump;
            assert!(ratio > 0.7 && ratio < 1.4, "fade {fade_ah}: learned {like:?} against {population_jump}");
        }
        // Without a long rest the scale stays where it started.
        let mut t = LifeTracker::learning_its_recovery(m);
        for c in 1..=7 {
            t.advance_to(c, Some(USUAL_S), AT);
            t.observe(1.8 - 0.002 * f64::from(c));
        }
        let (scale, sd) = t.recovery_scale();
        assert!((scale - 1.0).abs() < 1e-6 && (sd - 1.0).abs() < 1e-6, "{scale} {sd}");
    }
}
