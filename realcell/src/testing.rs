//! What the crate's tests share: a cell record simulated by the simulator's own integrator and sampling.

use crate::record::CellRecord;
use bcal_common::battery::{Degradation, Load};
use bcal_common::measured::scenario::{simulate, EpisodeSpec, Request, Sample, ScenarioConfig};

/// A 2 A constant-current discharge of the simulated cell `truth` after a minute's rest at its ambient,
/// from `soc0` of a full cell's charge, sampled every 9-19 s (noise seed `noise_seed`), as the record of
/// `cycle`: requests unknown, as on a cycler's record.
pub fn simulated_record(
    cfg: &ScenarioConfig,
    truth: Degradation,
    soc0: f64,
    noise_seed: u64,
    cycle: u32,
) -> CellRecord {
    simulated_record_under(cfg, truth, soc0, noise_seed, cycle, Load::CurrentA(2.0))
}

/// [`simulated_record`] under `load` after the rest (a current, or a power held constant).
pub fn simulated_record_under(
    cfg: &ScenarioConfig,
    truth: Degradation,
    soc0: f64,
    noise_seed: u64,
    cycle: u32,
    load: Load,
) -> CellRecord {
    let ambient_k = cfg.model.params().tb0_k;
    let ep = simulate(cfg, &EpisodeSpec::rest_then(truth, soc0, load, ambient_k, noise_seed))
        .expect("the simulator runs its own default cell");
    let samples: Vec<Sample> = ep.samples.iter().map(|s| Sample { request: Request::Unknown, ..*s }).collect();
    // The load's own current; under a power, the loaded readings' mean (as a record read from data has it).
    let current_a = match load {
        Load::CurrentA(a) => a,
        Load::PowerW(_) => crate::record::load_mean(&samples).current_a().expect("a load"),
    };
    CellRecord {
        cell: "T".into(),
        cycle,
        source: "simulated".into(),
        load_on_s: samples.iter().find(|s| s.current_a > 0.5).expect("a load").t_s,
        eod_s: ep.eod_s,
        current_a,
        data_capacity_ah: None,
        stated_capacity_ah: None,
        ambient_k,
        rest_before_s: None,
        current_before_a: None,
        partial_start: false,
        short_start_seen: false,
        partial_start_seen: false,
        start_share_sd: None,
        stated_tail_ah: None,
        samples,
    }
}
