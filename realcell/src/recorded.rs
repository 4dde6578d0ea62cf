//! A real cell's recorded training discharges as training episodes of its own RL policy (issue 18, item 4):
//! the correction policy then learns, from the predictive cost alone, what the cell's model gets wrong on
//! this cell, beside the simulated cells around its diagnosed model. Each episode holds the discharge's
//! readings up to the cut-off, the measured voltage as the cell's own future (what the cost compares
//! with), the measured end of discharge, the measured current as the load, and the fit the discharge
//! before it hands on as its prior (its end fit, [`crate::carry`], where `bcal calibrate` starts it). There is no true parameter: the
//! cost needs none, and validation scores that read the truth leave these episodes out.

use crate::record::CellRecord;
use crate::tune::validation_records;
use bcal_common::battery::{Degradation, Load, LoadProfile};
use bcal_common::measured::extension::ModelExtension;
use bcal_common::measured::scenario::{Episode, EpisodeSpec, LoadKind, RecordedSet};

/// One recorded discharge (that reached the cut-off) as an episode starting at its first reading, with
/// `prior` as its calibrator's prior. None for a discharge cut short (no end of discharge to predict).
pub fn episode_of(r: &CellRecord, prior: Option<Degradation>) -> Option<Episode> {
    let eod = r.eod_s?;
    let t0 = r.samples.first()?.t_s;
    let mut samples = r.samples.clone();
    for s in &mut samples {
        s.t_s -= t0;
    }
    // The load: each reading's current held until the next (what the calibrators assume too).
    let segments: Vec<(f64, Load)> = samples.iter().map(|s| (s.t_s, Load::CurrentA(s.current_a.max(0.0)))).collect();
    let gaps: Vec<f64> = samples.windows(2).map(|w| w[1].t_s - w[0].t_s).collect();
    let interval_s = [gaps.iter().copied().fold(f64::INFINITY, f64::min), gaps.iter().copied().fold(0.0, f64::max)];
    Some(Episode {
        spec: EpisodeSpec {
            truth: Degradation { q_mobile_c: f64::NAN, r_o_ohm: f64::NAN },
            soc0: f64::NAN,
            kind: LoadKind::ConstantCurrent,
            profile: LoadProfile::Piecewise(segments),
            rest_s: r.load_on_s - t0,
            ambient_k: r.ambient_k,
            interval_s,
            noise_seed: 0,
            cell_error: Default::default(),
            request_known: false,
            prior,
        },
        true_voltage_v: samples.iter().map(|s| s.voltage_v).collect(),
        samples,
        eod_s: Some(eod - t0),
    })
}

/// The recorded set of a cell's training discharges (`records`, in cycle order, with the fits they hand
/// on): each starts from the fit of the one before it; the last training cycles (the validation cycles every
/// real-cell choice is made on) form its validation part.
pub fn recorded_set(cell: &str, records: &[CellRecord], fits: &[(Degradation, ModelExtension)]) -> RecordedSet {
    let validation: Vec<usize> = validation_records(records);
    let mut set = RecordedSet { cell: cell.to_string(), ..RecordedSet::default() };
    for (k, r) in records.iter().enumerate() {
        let prior = k.checked_sub(1).and_then(|j| fits.get(j)).map(|f| f.0);
        let Some(e) = episode_of(r, prior) else { continue };
        if validation.contains(&k) {
            set.validation.push(e);
        } else {
            set.train.push(e);
        }
    }
    set
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::measured::scenario::{Request, Sample};

    #[test]
    fn a_record_becomes_an_episode_from_its_first_reading_with_its_own_voltage_as_the_future() {
        let samples: Vec<Sample> = (0..6)
            .map(|k| Sample {
                t_s: 100.0 + 10.0 * k as f64,
                voltage_v: 4.1 - 0.1 * k as f64,
                current_a: if k == 0 { 0.0 } else { 2.0 },
                temperature_k: 297.0,
                request: Request::Unknown,
            })
            .collect();
        let r = CellRecord {
            cell: "T".into(),
            cycle: 7,
            source: "t".into(),
            load_on_s: 110.0,
            eod_s: Some(152.0),
            current_a: 2.0,
            data_capacity_ah: None,
            stated_capacity_ah: None,
            ambient_k: 297.0,
            rest_before_s: None,
            current_before_a: None,
            partial_start: false,
            short_start_seen: false,
            partial_start_seen: false,
            start_share_sd: None,
            stated_tail_ah: None,
            samples,
        };
        let prior = Degradation { q_mobile_c: 6000.0, r_o_ohm: 0.1 };
        let e = episode_of(&r, Some(prior)).unwrap();
        assert_eq!(e.samples[0].t_s, 0.0);
        assert_eq!((e.eod_s, e.spec.rest_s, e.spec.prior), (Some(52.0), 10.0, Some(prior)));
        assert_eq!(e.true_voltage_v, r.samples.iter().map(|s| s.voltage_v).collect::<Vec<_>>());
        assert_eq!(e.spec.profile.at(15.0), Load::CurrentA(2.0));
        assert_eq!(e.spec.profile.at(5.0), Load::CurrentA(0.0));
        assert!(e.spec.truth.q_mobile_c.is_nan(), "no true parameter exists for a recorded discharge");
        let short = CellRecord { eod_s: None, ..r };
        assert!(episode_of(&short, None).is_none());
    }
}
