//! `bcal simulate`: one discharge to EOD ([`bcal_common::simulate`], which the Python package's
//! `bcal.simulate` runs too), printed as a summary and optionally written as CSV.

use crate::cli::SimulateArgs;
use anyhow::Context;
use bcal_common::math::idx;
use bcal_common::simulate::{simulate, SimulateRequest};
use std::io::{BufWriter, Write};

pub fn run(a: SimulateArgs) -> anyhow::Result<()> {
    let req = SimulateRequest {
        q_mobile: a.q_mobile,
        r_o: a.ro,
        load_w: a.load_w,
        current_a: a.current_a,
        steps: Vec::new(),
        thermal: a.thermal,
        dt_s: a.dt,
        max_steps: a.max_steps,
    };
    let tr = simulate(&req)?;
    if let Some(path) = &a.out {
        let f = std::fs::File::create(path)
            .with_context(|| format!("cannot create {}: check the folder exists and is writable", path.display()))?;
        let mut w = BufWriter::new(f);
        let input_col = if a.load_w.is_some() { "load_w" } else { "current_a" };
        write!(w, "t_s,voltage_v,qpS,qpB,qnB,qnS,Vo,Vsn,Vsp,{input_col}")?;
        if a.thermal {
            write!(w, ",tb_k")?;
        }
        writeln!(w)?;
        for k in 0..tr.time_s.len() {
            let x = &tr.state[k];
            write!(
                w,
                "{},{},{},{},{},{},{},{},{},{}",
                tr.time_s[k],
                tr.voltage_v[k],
                x[idx::QP_S],
                x[idx::QP_B],
                x[idx::QN_B],
                x[idx::QN_S],
                x[idx::V_O],
                x[idx::V_SN],
                x[idx::V_SP],
                tr.input[k]
            )?;
            if a.thermal {
                write!(w, ",{}", x[idx::T_B])?;
            }
            writeln!(w)?;
        }
        w.flush().context("writing the CSV failed")?;
    }
    println!("EOD {} s ({:.1} min), {} rows", tr.eod_s, tr.eod_s / 60.0, tr.time_s.len());
    if let Some(p) = &a.out {
        println!("wrote {}", p.display());
    }
    Ok(())
}
