//! Analysis behind docs/calibrator.md (`cargo run --release -p bcal-calib --example constant [P]`, P the model-error probability): the mean relative cost of each constant action, and of a policy binned by elapsed time and sampling.
#[path = "shared/mod.rs"]
mod shared;
use bcal_calib::env::correction_cost;
use bcal_calib::Correction;
use bcal_common::dataset::Split;
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::scenario::{draw_spec, episode_set, simulate, Episode};
use bcal_common::measured::tracker::JointUkfSettings;
use rand::SeedableRng;
use rayon::prelude::*;

const G: usize = 9;

fn grid() -> Vec<[f32; 2]> {
    let g: Vec<f32> = (0..G).map(|k| -1.0 + 2.0 * k as f32 / (G - 1) as f32).collect();
    let mut v = Vec::new();
    for &a in &g {
        for &b in &g {
            v.push([a, b]);
        }
    }
    v
}

/// (bin, costs of every grid action) at every `stride`-th reading.
fn points(spec: &MeasuredSpec, eps: &[Episode], stride: usize) -> Vec<(usize, Vec<f64>)> {
    let gr = grid();
    eps.par_iter()
        .flat_map_iter(|e| {
            let mut c = Correction::of_task(spec);
            let mut out = Vec::new();
            let n = e.samples.len();
            let end = e.samples[n - 1].t_s;
            for (k, s) in e.samples.iter().enumerate() {
                c.ingest(s);
                if k % stride != 0 || k + 1 >= n {
                    continue;
                }
                let frac = ((s.t_s / end) * 4.0).floor().min(3.0) as usize;
                let bin = frac + 4 * usize::from(e.spec.interval_s[0] > 1.0);
                let costs = gr
                    .iter()
                    .map(|a| {
                        c.apply_action(a);
                        correction_cost(spec, &c, e, k)
                    })
                    .collect();
                out.push((bin, costs));
            }
            out
        })
        .collect()
}

fn main() {
    let p: f64 = std::env::args().nth(1).map_or(0.5, |s| s.parse().unwrap());
    let mut spec = MeasuredSpec::default();
    spec.scenario.model_error.probability = p;
    spec.ukf = Some(if p > 0.0 {
        JointUkfSettings {
            meas_std_v: 0.01,
            param_walk_per_sqrt_s: 1e-5,
            charge_walk_c_per_sqrt_s: 1.0,
            ..Default::default()
        }
    } else {
        shared::tuned_ukf()
    });
    let mut rng = rand::rngs::SmallRng::seed_from_u64(7);
    let train: Vec<Episode> = (0..160)
        .filter_map(|_| simulate(&spec.scenario, &draw_spec(&spec.scenario, Split::Train, &mut rng)).ok())
        .collect();
    let val = episode_set(&spec.scenario, Split::Validation, 48).unwrap();
    let tr = points(&spec, &train, 25);
    let va = points(&spec, &val, 10);
    let gr = grid();
    let mean = |pts: &[(usize, Vec<f64>)], a: usize, bin: Option<usize>| {
        let v: Vec<f64> = pts.iter().filter(|p| bin.is_none_or(|b| p.0 == b)).map(|p| p.1[a]).collect();
        v.iter().sum::<f64>() / v.len().max(1) as f64
    };
    let zero = gr.iter().position(|a| a[0] == 0.0 && a[1] == 0.0).unwrap();
    let best = (0..gr.len()).min_by(|&a, &b| mean(&tr, a, None).total_cmp(&mean(&tr, b, None))).unwrap();
    println!("p {p}: {} train / {} validation points", tr.len(), va.len());
    println!(
        "constant: best on train {:?} train {:.3} validation {:.3} (zero {:.3})",
        gr[best],
        mean(&tr, best, None),
        mean(&va, best, None),
        mean(&va, zero, None)
    );
    let mut vsum = 0.0;
    let mut vn = 0.0;
    for bin in 0..8 {
        let b = (0..gr.len()).min_by(|&a, &c| mean(&tr, a, Some(bin)).total_cmp(&mean(&tr, c, Some(bin)))).unwrap();
        let nv = va.iter().filter(|p| p.0 == bin).count() as f64;
        println!(
            "bin {bin} (quarter {}, {}): best {:?} train {:.3} validation {:.3} vs zero {:.3} ({nv} points)",
            bin % 4,
            if bin >= 4 { "10-20 s" } else { "1 s" },
            gr[b],
            mean(&tr, b, Some(bin)),
            mean(&va, b, Some(bin)),
            mean(&va, zero, Some(bin))
        );
        vsum += mean(&va, b, Some(bin)) * nv;
        vn += nv;
    }
    println!("binned policy on validation: {:.3}", vsum / vn);
}
