//! `bcal simulate`: one discharge to EOD, printed as a summary and optionally written as CSV.

use crate::cli::SimulateArgs;
use anyhow::{bail, Context};
use bcal_common::battery::{BatteryModel, BatteryParams, Degradation, Load, LoadProfile};
use bcal_common::math::idx;
use std::io::{BufWriter, Write};

pub fn run(a: SimulateArgs) -> anyhow::Result<()> {
    let model = BatteryModel::new(BatteryParams::default(), a.thermal)?;
    let d = Degradation { q_mobile_c: a.q_mobile, r_o_ohm: a.ro };
    let (load, input_col) = match (a.load_w, a.current_a) {
        (Some(p), None) => (Load::PowerW(p), "load_w"),
        (None, Some(i)) => (Load::CurrentA(i), "current_a"),
        _ => bail!("give exactly one of --load-w or --current-a"),
    };
    let mut out = match &a.out {
        Some(path) => {
            let f = std::fs::File::create(path).with_context(|| {
                format!("cannot create {}: check the folder exists and is writable", path.display())
            })?;
            let mut w = BufWriter::new(f);
            write!(w, "t_s,voltage_v,qpS,qpB,qnB,qnS,Vo,Vsn,Vsp,{input_col}")?;
            if a.thermal {
                write!(w, ",tb_k")?;
            }
            writeln!(w)?;
            Some(w)
        }
        None => None,
    };
    let mut write_err = None;
    let outcome = model.simulate_until_eod(
        &model.initial_state(&d),
        &d,
        &LoadProfile::Constant(load),
        a.dt,
        a.max_steps,
        |r| {
            let Some(w) = out.as_mut() else { return };
            if write_err.is_some() {
                return;
            }
            let input = match r.load {
                Load::PowerW(p) => p,
                Load::CurrentA(i) => i,
            };
            let x = &r.x;
            let mut res = write!(
                w,
                "{},{},{},{},{},{},{},{},{},{}",
                r.t_s,
                r.voltage_v,
                x[idx::QP_S],
                x[idx::QP_B],
                x[idx::QN_B],
                x[idx::QN_S],
                x[idx::V_O],
                x[idx::V_SN],
                x[idx::V_SP],
                input
            );
            if a.thermal && res.is_ok() {
                res = write!(w, ",{}", x[idx::T_B]);
            }
            if let Err(e) = res.and_then(|_| writeln!(w)) {
                write_err = Some(e);
            }
        },
    )?;
    if let Some(e) = write_err {
        bail!("writing the CSV failed: {e}");
    }
    if let Some(mut w) = out {
        w.flush().context("writing the CSV failed")?;
    }
    match outcome.eod_s {
        Some(t) => {
            println!("EOD {t} s ({:.1} min), {} rows", t / 60.0, outcome.rows);
        }
        None => bail!(
            "the voltage stayed above VEOD for {} steps ({} s); raise --max-steps or the load",
            a.max_steps,
            a.max_steps as f64 * a.dt
        ),
    }
    if let Some(p) = &a.out {
        println!("wrote {}", p.display());
    }
    Ok(())
}
