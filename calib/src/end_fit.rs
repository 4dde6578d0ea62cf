//! The qMobile that puts the model's end of discharge where the cell's was: a discharge followed to its
//! cut-off has measured the charge the cell holds, and one number of the model answers it. The model runs
//! from the rest before the load (its starting charge read off the mean rest voltage, as the calibrators
//! read it) through the recorded readings, at the Ro given, and qMobile is found by bisection within the
//! calibrator's range such that the voltage reaches the cut-off at the measured end; where the model ends
//! above the cut-off (an electrode's surface empties, its voltage stops falling), [`end_fit`] keeps the knee
//! the cell goes on down apart. A live stream carries it into the next discharge ([`crate::stream`]), as
//! `bcal calibrate` carries each record's (`bcal_realcell::carry`). Pure arithmetic: nothing here reads or
//! prints.

use bcal_common::battery::Degradation;
use bcal_common::measured::cellmodel::{xn_from_rest_voltage, CellModel, REST_CURRENT_A};
use bcal_common::measured::scenario::Sample;
use bcal_common::measured::tracker::TrackerSpec;

/// Bisection steps: a range of a few thousand coulombs to below a millicoulomb. Each runs the model through
/// the whole discharge: the reading that ends a discharge is the stream's slowest (B0005's discharges 41-80
/// through `bcal calibrate --follow`: at most 21 ms, against 0.6 ms for any reading without the fit).
const BISECTIONS: usize = 25;
/// The part of the rest before the load the model is run through, s (NASA's records rest under a minute).
const REST_RUN_S: f64 = 600.0;
/// How many of the latest discharges the model's knee is taken over (median), by `bcal calibrate` and a live
/// stream alike.
pub const KNEE_WINDOW: usize = 3;

/// When a discharge's warmth is read, s after its load came on: its temperature then against the last
/// [`KNEE_WINDOW`] discharges' at the same time moves its knee ([`KneeWarmth`]). Chosen on B0055's training
/// cycles (fitted on 1-25, judged on 26-34, of 200 / 300 / 450 / 600 / 900 s; `examples/knee_by_temperature.py`).
pub const KNEE_WARMTH_AT_S: f64 = 600.0;
/// Pairs of moves a knee's warmth slope needs before it moves a knee, and the most recent it learns from.
const KNEE_WARMTH_MIN_PAIRS: usize = 8;
const KNEE_WARMTH_PAIRS: usize = 30;
/// The most discharges [`KneeWarmth::learn`] reads: its pairs and the window before the first.
pub const KNEE_WARMTH_SEEN: usize = KNEE_WARMTH_PAIRS + KNEE_WINDOW;
/// A discharge whose temperature at [`KNEE_WARMTH_AT_S`] lies further than this from the last discharges' ran in
/// other conditions (an ambient that changed: NASA's B0038-B0044 move 20 K between blocks), K: it neither
/// teaches nor moves a knee. B0055's discharges lie within 2.1 K of the last three's.
const KNEE_WARMTH_MAX_K: f64 = 3.0;

/// How a knee moves with the cell's warmth, learned on the cell's own discharges. On a cold cell the tail a
/// discharge runs below the model's end is long and moves from one discharge to the next with how warm the
/// cell runs (B0055 at 4 C: 341 s, its move against the median of the last three 2.46 % of the discharge at
/// the median, as large as the joint UKF's end error at half; 0.64 correlated with the temperature 600 s
/// after the load-on against the last three's, 0.93 with that at the end); on a warm cell it barely moves
/// (0.06-0.11 %) and the slope learned there is near zero.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct KneeWarmth {
    /// The median temperature at [`KNEE_WARMTH_AT_S`] of the last [`KNEE_WINDOW`] discharges, K.
    pub reference_k: f64,
    /// The knee's move per kelvin of this discharge's temperature then above `reference_k`, C/K.
    pub c_per_k: f64,
    /// The pairs it was learned on.
    pub pairs: usize,
}

impl KneeWarmth {
    /// Learned for a discharge at `current_a` on `seen` (each ended discharge's temperature at
    /// [`KNEE_WARMTH_AT_S`], K, its knee, C, and its current at the load-on, A, in order; the discharges with
    /// all three), of which those at the same current: each one's knee move against the median of the
    /// [`KNEE_WINDOW`] before it, against its temperature's, least squares over the last
    /// [`KNEE_WARMTH_PAIRS`] (the slope about their means; the move predicted without an intercept, as the
    /// knee's median carries the level). None before [`KNEE_WARMTH_MIN_PAIRS`] pairs.
    pub fn learn(seen: &[(f64, f64, f64)], current_a: f64) -> Option<Self> {
        // At its own current only (the first loaded reading's, not moved by more than the twins' ratio): a knee
        // at 4 A says nothing of one at 1 A ("B0041").
        let same = |a: f64| {
            crate::prior_width::current_move(a, current_a)
                .is_some_and(|x| x.abs() <= crate::prior_width::MOVED_RATIO.ln())
        };
        let seen: Vec<(f64, f64)> = seen.iter().filter(|s| same(s.2)).map(|s| (s.0, s.1)).collect();
        if seen.len() < KNEE_WINDOW {
            return None;
        }
        let median = |v: &mut Vec<f64>| bcal_common::stats::median(v).unwrap_or(0.0);
        let moves: Vec<(f64, f64)> = (KNEE_WINDOW..seen.len())
            .map(|j| {
                let last = &seen[j - KNEE_WINDOW..j];
                let (mut w, mut k): (Vec<f64>, Vec<f64>) = last.iter().copied().unzip();
                (seen[j].0 - median(&mut w), seen[j].1 - median(&mut k))
            })
            .filter(|m| m.0.abs() <= KNEE_WARMTH_MAX_K)
            .collect();
        let moves = &moves[moves.len().saturating_sub(KNEE_WARMTH_PAIRS)..];
        if moves.len() < KNEE_WARMTH_MIN_PAIRS {
            return None;
        }
        let n = moves.len() as f64;
        let (mx, my) = (moves.iter().map(|m| m.0).sum::<f64>() / n, moves.iter().map(|m| m.1).sum::<f64>() / n);
        let sxx: f64 = moves.iter().map(|m| (m.0 - mx).powi(2)).sum();
        let sxy: f64 = moves.iter().map(|m| (m.0 - mx) * (m.1 - my)).sum();
        let mut last: Vec<f64> = seen[seen.len() - KNEE_WINDOW..].iter().map(|s| s.0).collect();
        Some(Self {
            reference_k: median(&mut last),
            c_per_k: if sxx > 1e-12 { sxy / sxx } else { 0.0 },
            pairs: moves.len(),
        })
    }

    /// The knee's move, C, for a discharge whose temperature at [`KNEE_WARMTH_AT_S`] was `warmth_k` (none
    /// in other conditions than the last discharges').
    pub fn move_c(&self, warmth_k: f64) -> f64 {
        let off_k = warmth_k - self.reference_k;
        if off_k.abs() <= KNEE_WARMTH_MAX_K {
            self.c_per_k * off_k
        } else {
            0.0
        }
    }
}

/// How much of the knee's warmth move a method's end of discharge still needs at one share of the discharge,
/// from its record there: `errors` holds, per discharge that ended (oldest first), its signed end error with
/// the whole move and without it (any one unit). A method that reads the voltage has read part of the warmth
/// by late in a discharge (B0055's joint UKF at 90 %: the whole move took its mean error 1.70 -> 1.93 % where
/// at half it took the median 2.45 -> 1.67 %), so the move it takes is the share of it that minimises the
/// squared errors of the last [`crate::blend::BLEND_WINDOW`] discharges it moved, held to [0, 1] (from none
/// of it read to all of it). None before [`crate::blend::MIN_BLEND_PAIRS`] such discharges (the whole move).
pub fn warmth_share(errors: &[(f64, f64)]) -> Option<f64> {
    let moved: Vec<(f64, f64)> = errors
        .iter()
        .rev()
        .filter(|(m, u)| m.is_finite() && u.is_finite() && m != u)
        .take(crate::blend::BLEND_WINDOW)
        .map(|&(m, u)| (u, m - u))
        .collect();
    if moved.len() < crate::blend::MIN_BLEND_PAIRS {
        return None;
    }
    // The errors with a share `a` of the move are u + a * d: least squares in `a`.
    let dd: f64 = moved.iter().map(|(_, d)| d * d).sum();
    let ud: f64 = moved.iter().map(|(u, d)| u * d).sum();
    Some((-ud / dd).clamp(0.0, 1.0))
}

/// The temperature of a discharge's readings `samples` (in time order) at `t_s`, K, linear between the
/// readings around it; None before the first or after the last.
pub fn temperature_at_k(samples: &[Sample], t_s: f64) -> Option<f64> {
    let k = samples.iter().position(|s| s.t_s >= t_s)?;
    let b = &samples[k];
    if k == 0 {
        return (b.t_s - t_s).abs().lt(&1e-9).then_some(b.temperature_k);
    }
    let a = &samples[k - 1];
    let span = b.t_s - a.t_s;
    Some(if span > 0.0 {
        a.temperature_k + (b.temperature_k - a.temperature_k) * (t_s - a.t_s) / span
    } else {
        b.temperature_k
    })
}

/// The current through a knee, A, to turn its time into charge and back: the load's own current, or under a
/// power the current it draws at the cut-off (the knee lies there, where the current is highest; measured and
/// applied the same way, so a knee's time carries over unchanged between discharges at the same power).
pub fn knee_current_a(load: bcal_common::battery::Load, cutoff_v: f64) -> f64 {
    match load {
        bcal_common::battery::Load::CurrentA(a) => a,
        bcal_common::battery::Load::PowerW(w) => w / cutoff_v,
    }
}

/// The mean voltage of a discharge's readings at rest before its load (`samples` from its start), V: what its
/// starting charge is read off, and what tells a start from a partial charge
/// ([`bcal_common::measured::short_start`]). None when the first reading is already loaded.
pub fn rest_voltage_v(samples: &[Sample]) -> Option<f64> {
    let rest: Vec<f64> =
        samples.iter().take_while(|s| s.current_a.abs() < REST_CURRENT_A).map(|s| s.voltage_v).collect();
    (!rest.is_empty()).then(|| rest.iter().sum::<f64>() / rest.len() as f64)
}

/// The qMobile, C, under which the model's voltage reaches `spec.cutoff_v` at `end_s`, given the
/// discharge's readings from its rest on (`samples`, in time order; those after `end_s` are ignored) and
/// Ro `r_o_ohm`. None without a rest reading before the load, without a reading before `end_s`, or when no
/// qMobile within the calibrator's range puts the end there.
pub fn q_mobile_to_end(spec: &TrackerSpec, samples: &[Sample], end_s: f64, r_o_ohm: f64) -> Option<f64> {
    let run = Run::new(spec, samples)?;
    run.bracket(end_s, r_o_ohm).map(|(lo, hi)| 0.5 * (lo + hi))
}

/// A discharge's end fit with the model's knee kept apart ([`end_fit`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EndFit {
    /// The qMobile that empties the model where the cell passed the model's own end voltage, C.
    pub q_mobile_c: f64,
    /// The charge the cell delivered from there to its cut-off, C (0 where the model reaches the cut-off
    /// itself).
    pub knee_c: f64,
    /// When the cell passed the model's end voltage, s (the end itself where the knee is 0).
    pub passed_s: f64,
}

/// The end fit with the model's knee kept apart: where the model ends by an electrode's surface emptying
/// (about 3.0 V at 2 A on NASA's cells, 2.7 V on a cold cell), above a lower cut-off, the cell goes on down
/// its knee to the cut-off, and a qMobile that put the model's end at the cut-off would hold that knee's
/// charge as more charge throughout, of which a discharge started at a share f of full gets f (a part-charged
/// start ends early by the rest). So qMobile is fitted to empty the model where the cell's voltage last
/// passed the voltage the model ends at (under [`q_mobile_to_end`]'s qMobile), and the charge drawn from
/// there to the cut-off is the knee, which predictions add back from any start. Where the model reaches the
/// cut-off itself, or the cell's readings never pass its end voltage, the knee is 0 and qMobile is
/// [`q_mobile_to_end`]'s. None where that is.
pub fn end_fit(spec: &TrackerSpec, samples: &[Sample], end_s: f64, r_o_ohm: f64) -> Option<EndFit> {
    let run = Run::new(spec, samples)?;
    let (lo, hi) = run.bracket(end_s, r_o_ohm)?;
    let at_cutoff = EndFit { q_mobile_c: 0.5 * (lo + hi), knee_c: 0.0, passed_s: end_s };
    // Just above the bracket the model has not emptied by the end: its voltage there is the one it ends at.
    let (v_end, _) = run.at(hi, r_o_ohm, end_s)?;
    let (_, emptied) = run.at(lo, r_o_ohm, end_s)?;
    if !emptied || !v_end.is_finite() || v_end <= spec.cutoff_v {
        return Some(at_cutoff);
    }
    // The last time before the end the cell's voltage came down through it (an early dip under a cold
    // cell's load is not its knee), between two loaded readings.
    let before: Vec<&Sample> = samples.iter().take_while(|s| s.t_s <= end_s).collect();
    let Some(k) = (1..before.len()).rev().find(|&k| {
        let (a, b) = (before[k - 1], before[k]);
        a.current_a >= REST_CURRENT_A && b.current_a >= REST_CURRENT_A && a.voltage_v >= v_end && b.voltage_v < v_end
    }) else {
        return Some(at_cutoff);
    };
    let (a, b) = (before[k - 1], before[k]);
    let passed_s = a.t_s + (a.voltage_v - v_end) / (a.voltage_v - b.voltage_v) * (b.t_s - a.t_s);
    let Some((lo, hi)) = run.bracket(passed_s, r_o_ohm) else { return Some(at_cutoff) };
    let knee_c = 3600.0 * (crate::eod::charge_to_ah(samples, end_s) - crate::eod::charge_to_ah(samples, passed_s));
    Some(EndFit { q_mobile_c: 0.5 * (lo + hi), knee_c: knee_c.max(0.0), passed_s })
}

/// The model run from a discharge's rest through its readings.
struct Run<'s> {
    spec: &'s TrackerSpec,
    samples: &'s [Sample],
    model: bcal_common::battery::BatteryModel,
    /// Readings at rest before the load, and the first of them the model starts at.
    rest_n: usize,
    from: usize,
    xn0: f64,
    t0_k: f64,
    ref_k: f64,
}

impl<'s> Run<'s> {
    fn new(spec: &'s TrackerSpec, samples: &'s [Sample]) -> Option<Self> {
        let model = spec.model.model().ok()?;
        let rest_n = samples.iter().take_while(|s| s.current_a.abs() < REST_CURRENT_A).count();
        let first = samples.first()?;
        let rest_v = rest_voltage_v(samples)?;
        if rest_n >= samples.len() {
            return None;
        }
        let t0_k = if spec.use_measured_temperature { first.temperature_k } else { model.params.tb0_k };
        let xn0 = xn_from_rest_voltage(&model, rest_v, t0_k);
        let ref_k = spec.model.reference_k.unwrap_or(first.temperature_k);
        // The model starts at rest where the last [`REST_RUN_S`] of the rest begin: a rest logged for hours
        // (a live stream's) would otherwise be run through on every bisection step (seconds at the cut-off
        // after a rest of a few hundred thousand readings), for a state the rest current barely moves.
        let load_on_s = samples[rest_n].t_s;
        let from = samples[..rest_n].partition_point(|s| s.t_s < load_on_s - REST_RUN_S).min(rest_n - 1);
        Some(Self { spec, samples, model, rest_n, from, xn0, t0_k, ref_k })
    }

    fn temperature_k(&self, s: &Sample) -> f64 {
        if self.spec.use_measured_temperature {
            s.temperature_k
        } else {
            self.model.params.tb0_k
        }
    }

    /// The model's voltage at `at_s` under qMobile `q`, and whether an electrode's surface has emptied by
    /// then. None without a loaded reading before `at_s`.
    fn at(&self, q: f64, r_o_ohm: f64, at_s: f64) -> Option<(f64, bool)> {
        let upto = self.samples.partition_point(|s| s.t_s <= at_s);
        if upto < 2 || upto <= self.rest_n {
            return None;
        }
        let d = Degradation { q_mobile_c: q, r_o_ohm };
        let mut cell = CellModel::at_rest(self.model.clone(), self.xn0, self.t0_k, self.spec.max_substep_s)
            .with_arrhenius(&self.spec.model, self.ref_k);
        for w in self.samples[self.from..upto].windows(2) {
            cell.advance_between(&w[0], &w[1], &d, self.temperature_k(&w[1]));
        }
        let last = &self.samples[upto - 1];
        cell.advance(last.current_a, at_s - last.t_s, &d, self.temperature_k(last));
        let emptied = cell.model.surface_empty(&cell.state(&cell.track, &d), &d);
        Some((cell.voltage(&d), emptied))
    }

    /// The bracket (lo, hi) of qMobile, within [`BISECTIONS`] halvings of the calibrator's range, across
    /// which the model's end moves through `end_s`: under `lo` it has ended by then (below the cut-off, or
    /// an electrode's surface emptied: its voltage stops falling there, about 3.0 V at 2 A, as
    /// `crate::predict_eod_s` reads it), under `hi` not yet. None when no qMobile in range puts it there.
    fn bracket(&self, end_s: f64, r_o_ohm: f64) -> Option<(f64, f64)> {
        let margin_v = |q: f64| -> Option<f64> {
            let (v, emptied) = self.at(q, r_o_ohm, end_s)?;
            let v = v - self.spec.cutoff_v;
            Some(if v.is_finite() && !emptied { v } else { -1.0 })
        };
        let (mut lo, mut hi) = (self.spec.q_mobile_range_c[0], self.spec.q_mobile_range_c[1]);
        if margin_v(lo)? >= 0.0 || margin_v(hi)? <= 0.0 {
            return None;
        }
        for _ in 0..BISECTIONS {
            let mid = 0.5 * (lo + hi);
            if margin_v(mid)? > 0.0 {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        Some((lo, hi))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::measured::scenario::{draw_spec, simulate, ScenarioConfig};
    use rand::SeedableRng;

    /// A method that has read 40 % of the warmth by a share needs the rest: its errors with the whole move and
    /// without it give the share back (within the scatter of its other errors); one that read none needs all
    /// of it, one that read more than all none; too few moved discharges (a move of zero tells nothing) give
    /// none, and only the last window counts.
    #[test]
    fn the_share_of_the_warmth_move_a_method_still_needs_comes_from_its_record() {
        let mut rng = rand::rngs::SmallRng::seed_from_u64(7);
        use rand::Rng;
        let record = |needs: f64, rng: &mut rand::rngs::SmallRng| -> Vec<(f64, f64)> {
            (0..crate::blend::BLEND_WINDOW)
                .map(|_| {
                    // The move the knee takes, s, and the error the method's end would have without it: short by
                    // the share of the move it has not read, plus its own scatter.
                    let move_s: f64 = rng.random_range(-60.0..60.0);
                    let unmoved = -needs * move_s + rng.random_range(-5.0..5.0);
                    (unmoved + move_s, unmoved)
                })
                .collect()
        };
        let share = warmth_share(&record(0.6, &mut rng)).unwrap();
        assert!((share - 0.6).abs() < 0.1, "{share}");
        assert_eq!(warmth_share(&record(1.4, &mut rng)), Some(1.0));
        assert_eq!(warmth_share(&record(-0.5, &mut rng)), Some(0.0));
        let mut few = record(0.6, &mut rng);
        few.truncate(crate::blend::MIN_BLEND_PAIRS - 1);
        few.extend([(3.0, 3.0); 10]);
        assert_eq!(warmth_share(&few), None, "unmoved discharges teach nothing");
        let mut old = record(0.0, &mut rng);
        old.extend(record(1.0, &mut rng));
        assert!(warmth_share(&old).unwrap() > 0.9);
    }

    /// Simulated discharges (the simulator's own integrator and sampling, 3 mV noise, four validation
    /// draws, piecewise power and constant current among them) ended where the cell's true voltage crossed
    /// the cut-off (the knee: before it, a flat voltage curve tells little of the charge): the fitted qMobile
    /// lies within 2 % of the cell's, off the candidates' grid, for that cut-off and for one the model never
    /// reaches; readings without the rest before the load give none.
    #[test]
    fn the_end_of_a_simulated_discharge_gives_back_its_q_mobile() {
        let cfg = ScenarioConfig::default();
        let spec = TrackerSpec::default();
        let mut emptied = 0;
        for seed in [3u64, 11, 19, 27] {
            let mut rng = rand::rngs::SmallRng::seed_from_u64(seed);
            let ep_spec = draw_spec(&cfg, bcal_common::dataset::Split::Validation, &mut rng);
            let ep = simulate(&cfg, &ep_spec).unwrap();
            let samples = &ep.samples;
            let k = ep.true_voltage_v.iter().position(|v| *v < spec.cutoff_v).unwrap();
            let (va, vb) = (ep.true_voltage_v[k - 1], ep.true_voltage_v[k]);
            let (a, b) = (&samples[k - 1], &samples[k]);
            let end_s = a.t_s + (va - spec.cutoff_v) / (va - vb) * (b.t_s - a.t_s);
            let truth = ep_spec.truth;
            let q = q_mobile_to_end(&spec, &samples[..k], end_s, truth.r_o_ohm).expect("a fit");
            assert!((q / truth.q_mobile_c - 1.0).abs() < 0.02, "seed {seed}: {q} C against {} C", truth.q_mobile_c);
            // A cut-off below the voltage where the model's electrode surface empties (NASA's 2.5 V and 2.2 V
            // cells): the simulated cell's end is its emptying above that cut-off, and the model's end is read
            // the same way, so its end gives back its charge.
            let deep_cfg = ScenarioConfig { cutoff_v: 2.5, ..cfg.clone() };
            let deep = simulate(&deep_cfg, &ep_spec).unwrap();
            let end_s = deep.eod_s.expect("the cell empties");
            emptied += usize::from(*deep.true_voltage_v.last().unwrap() > deep_cfg.cutoff_v);
            let deep_spec = TrackerSpec { cutoff_v: deep_cfg.cutoff_v, ..spec.clone() };
            let q_deep = q_mobile_to_end(&deep_spec, &deep.samples, end_s, truth.r_o_ohm).expect("a fit below 3 V");
            assert!((q_deep / truth.q_mobile_c - 1.0).abs() < 0.02, "seed {seed}, 2.5 V: {q_deep} C");
            let loaded: Vec<Sample> = samples[..k].iter().filter(|s| s.current_a > REST_CURRENT_A).copied().collect();
            assert_eq!(q_mobile_to_end(&spec, &loaded, end_s, truth.r_o_ohm), None, "no rest, no start");
        }
        assert!(emptied > 0, "no cell emptied above 2.5 V: the deep cut-off went untested");
    }

    /// A rest logged for five hours before the load, its readings carrying a current sensor's 40 mA offset
    /// (below what counts as a load): the fit runs the model through the last 600 s of it only (the same
    /// fit as with those 600 s alone logged), so the offset's charge over the rest (720 C, a tenth of the
    /// cell's) is not taken from the cell: the fit stays within 5 % of the one with a 30 s rest and no
    /// offset.
    #[test]
    fn a_long_logged_rest_is_not_run_through() {
        let cfg = ScenarioConfig::default();
        let spec = TrackerSpec::default();
        let mut rng = rand::rngs::SmallRng::seed_from_u64(5);
        let ep_spec = draw_spec(&cfg, bcal_common::dataset::Split::Validation, &mut rng);
        let ep = simulate(&cfg, &ep_spec).unwrap();
        let k = ep.true_voltage_v.iter().position(|v| *v < spec.cutoff_v).unwrap();
        let end_s = ep.samples[k].t_s;
        let loaded = ep.samples.iter().position(|s| s.current_a > REST_CURRENT_A).unwrap();
        let rest = ep.samples[0];
        let with_rest = |rest_s: f64, offset_a: f64| {
            let mut v: Vec<Sample> =
                (0..rest_s as usize).map(|t| Sample { t_s: t as f64 - rest_s, current_a: offset_a, ..rest }).collect();
            v.extend(ep.samples[loaded..k].iter().copied());
            q_mobile_to_end(&spec, &v, end_s, ep_spec.truth.r_o_ohm).expect("a fit")
        };
        let (short, long) = (with_rest(30.0, 0.0), with_rest(18_000.0, 0.04));
        assert_eq!(long, with_rest(REST_RUN_S, 0.04), "the rest before its last {REST_RUN_S} s is not run through");
        assert!((long / short - 1.0).abs() < 0.05, "five hours at 40 mA: {long} C against {short} C");
    }
}
