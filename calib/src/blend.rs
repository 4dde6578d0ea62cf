//! A calibrator's prediction blended with its prior's. The two carry different information: the prior alone
//! is what the discharges before told, the calibrator adds this discharge's readings to it, and on real
//! cells each is the better one about half of the time (the prior alone predicts B0018's ends at half the
//! discharge to 0.24 % median, the joint UKF as delivered to 0.31 %; the joint UKF predicts B0005's capacity
//! worse than the prior it starts from). Where two predictions err independently enough, a weighted mean
//! errs less than either. The weight is the calibrator's share by inverse mean squared error over the last
//! [`BLEND_WINDOW`] discharges that ended (Bates and Granger's combination without the correlation term,
//! which needs more pairs than a cell's recent record holds to be estimated well), per share of the
//! discharge and per quantity (its end, its capacity): a prior that errs much more than the calibrator gets
//! little weight, never a switch. `bcal calibrate` (`bcal_realcell::tune::blend_runs`) and a live stream
//! ([`crate::stream`]) both use this. Pure arithmetic: nothing here reads or prints.

/// Discharges the weight learns on: the last that ended with both predictions scored.
pub const BLEND_WINDOW: usize = 15;
/// Fewest pairs a weight is learned from; before that, no blend (the calibrator alone).
pub const MIN_BLEND_PAIRS: usize = 8;

/// The calibrator's weight in the blend, from the absolute errors of (calibrator, prior) over the discharges
/// that ended (oldest first; the last [`BLEND_WINDOW`] finite pairs count): the prior's mean squared error
/// over the sum of both. None with fewer than [`MIN_BLEND_PAIRS`] pairs or no error at all.
pub fn blend_weight(errors: &[(f64, f64)]) -> Option<f64> {
    let pairs: Vec<&(f64, f64)> =
        errors.iter().rev().filter(|(a, p)| a.is_finite() && p.is_finite()).take(BLEND_WINDOW).collect();
    if pairs.len() < MIN_BLEND_PAIRS {
        return None;
    }
    let mse = |f: fn(&(f64, f64)) -> f64| pairs.iter().map(|p| f(p).powi(2)).sum::<f64>() / pairs.len() as f64;
    let (own, prior) = (mse(|p| p.0), mse(|p| p.1));
    (own + prior > 0.0).then(|| prior / (own + prior))
}

/// `weight` times `own` plus the rest times `prior`: a value, or a bound of an interval.
pub fn blended(weight: f64, own: f64, prior: f64) -> f64 {
    weight * own + (1.0 - weight) * prior
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_prediction_that_erred_less_weighs_more_and_only_the_recent_record_counts() {
        // Too few discharges: no blend.
        assert_eq!(blend_weight(&[(1.0, 1.0); MIN_BLEND_PAIRS - 1]), None);
        // Equal records: half each.
        assert_eq!(blend_weight(&[(1.0, 1.0); MIN_BLEND_PAIRS]), Some(0.5));
        // The prior erred twice as much: four times the weight on the calibrator.
        let w = blend_weight(&[(0.5, 1.0); 10]).unwrap();
        assert!((w - 0.8).abs() < 1e-12, "{w}");
        // An old record of a bad prior is forgotten once BLEND_WINDOW discharges with a good one have ended;
        // a failed prediction (infinite error) is not a score.
        let mut errors = vec![(0.1, 5.0); 20];
        errors.push((f64::INFINITY, 0.1));
        errors.extend([(1.0, 0.5); BLEND_WINDOW]);
        let w = blend_weight(&errors).unwrap();
        assert!((w - 0.2).abs() < 1e-12, "{w}");
        assert_eq!(blended(0.25, 100.0, 200.0), 175.0);
    }
}
