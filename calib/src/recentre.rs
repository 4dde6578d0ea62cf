//! End-of-discharge predictions recentred on a method's own record: a model that is wrong the same way
//! discharge after discharge (its end comes 0.25 % of the duration early on every one of B0006's, 0.3 %
//! late on B0018's) predicts better once that bias is taken off. At each share of the discharge the scores
//! read ([`EOD_FRACTIONS_PCT`]) the bias is the median of the method's signed relative errors there
//! (`(predicted - measured) / size`, size the predicted duration from the load-on, as the intervals measure
//! it) over the last [`WINDOW`] discharges that ended; a reading takes the share its own prediction puts
//! it at ([`share_bin`]). The recentred prediction is an alternative, not a replacement: it serves where it
//! has beaten the method's own on the last discharges, by the rule that gates every alternative
//! ([`crate::tune::earns`]), since a bias that flips from one discharge to the next (B0055's, after rests
//! of alternating length) is made worse by a shift. `bcal calibrate` (`bcal_realcell::recentre`) and a live
//! stream ([`crate::stream`]) both use this. Pure arithmetic: nothing here reads or prints.

pub use crate::widening::{share_bin, Outcome, EOD_FRACTIONS_PCT, WINDOW};

/// The signed relative error of a scored prediction: positive when the predicted end came late.
pub fn signed_error(o: &Outcome) -> f64 {
    (o.value - o.measured) / o.size
}

/// The bias at each share ([`EOD_FRACTIONS_PCT`]) from the scored predictions of the discharges that
/// ended (oldest first; only the last [`WINDOW`] count): the median signed relative error there, None at
/// a share without any.
pub fn biases(ended: &[Vec<Outcome>]) -> [Option<f64>; 3] {
    let recent = &ended[ended.len().saturating_sub(WINDOW)..];
    std::array::from_fn(|b| {
        let mut e: Vec<f64> = recent
            .iter()
            .flatten()
            .filter(|o| o.fraction == EOD_FRACTIONS_PCT[b])
            .map(signed_error)
            .filter(|e| e.is_finite())
            .collect();
        bcal_common::stats::median(&mut e)
    })
}

/// The shift, s, that recentres a predicted end `eod_s` made at `t_s` of a discharge loaded at
/// `load_on_s` under `biases` (to be added to the prediction and its bounds; 0 without a bias at its share).
/// The recentred end is never before `t_s`: the discharge is still running when the prediction is made.
pub fn shift_s(biases: &[Option<f64>; 3], load_on_s: f64, t_s: f64, eod_s: f64) -> f64 {
    biases[share_bin(load_on_s, t_s, eod_s)]
        .map_or(0.0, |bias| (-bias * (eod_s - load_on_s).max(1.0)).max((t_s - eod_s).min(0.0)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn outcome(fraction: u32, value: f64, measured: f64) -> Outcome {
        Outcome { value, below: 0.0, above: 0.0, size: value, measured, fraction }
    }

    /// A method that ends 1 % late at every share is shifted back onto the measured end; the window forgets
    /// discharges older than [`WINDOW`].
    #[test]
    fn a_steady_bias_is_taken_off_and_old_discharges_are_forgotten() {
        let late: Vec<Vec<Outcome>> =
            (0..WINDOW).map(|_| EOD_FRACTIONS_PCT.iter().map(|&f| outcome(f, 1010.0, 1000.0)).collect()).collect();
        let b = biases(&late);
        for x in b {
            assert!((x.unwrap() - 10.0 / 1010.0).abs() < 1e-12);
        }
        // A new discharge, loaded at 0, predicting 2020 s at half of it: the shift takes 1 % of it off.
        let s = shift_s(&b, 0.0, 1000.0, 2020.0);
        assert!((2020.0 + s - 2000.0).abs() < 1e-9, "recentred {}", 2020.0 + s);
        // Early discharges that were far off no longer count once a window of later ones has ended.
        let mut old: Vec<Vec<Outcome>> = (0..5).map(|_| vec![outcome(50, 2000.0, 1000.0)]).collect();
        old.extend(late);
        assert_eq!(biases(&old), b);
        // No record at a share: no shift there.
        let only_half = biases(&[vec![outcome(50, 1010.0, 1000.0)]]);
        assert!(only_half[0].is_none() && only_half[2].is_none());
        assert_eq!(shift_s(&only_half, 0.0, 100.0, 2000.0), 0.0);
        // Near its end a late method's recentred end would fall before the reading: it stops at the reading.
        let s = shift_s(&b, 0.0, 2015.0, 2020.0);
        assert!((2020.0 + s - 2015.0).abs() < 1e-9, "recentred {}", 2020.0 + s);
        // A record holding a non-finite error (a degenerate discharge) leaves the bias finite.
        let mut nan = vec![vec![outcome(50, f64::NAN, 1000.0)]];
        nan.push(vec![outcome(50, 1010.0, 1000.0)]);
        assert!((biases(&nan)[1].unwrap() - 10.0 / 1010.0).abs() < 1e-12);
    }
}
