//! Battery-model throughput: one Euler step (power input, the paper's hot loop) and a whole discharge.
//! `cargo bench -p bcal-common --bench battery`; the README quotes the steps/s figure.

use bcal_common::battery::{BatteryModel, Degradation, Load, LoadProfile};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use std::hint::black_box;

fn bench_step(c: &mut Criterion) {
    let model = BatteryModel::default();
    let d = Degradation::default();
    let x0 = model.initial_state(&d);
    let mut g = c.benchmark_group("battery");
    g.throughput(Throughput::Elements(1));
    g.bench_function("step_power_8w", |b| {
        let mut x = x0;
        let mut n = 0u32;
        b.iter(|| {
            let (next, _) = model.step(black_box(&x), Load::PowerW(8.0), 1.0, black_box(&d));
            // Restart before EOD so every timed step is a mid-discharge step.
            n += 1;
            x = if n.is_multiple_of(3000) { x0 } else { next };
            black_box(&x);
        })
    });
    let eod_steps = model
        .simulate_until_eod(&x0, &d, &LoadProfile::Constant(Load::PowerW(8.0)), 1.0, 100_000, |_| {})
        .unwrap()
        .rows as u64;
    g.throughput(Throughput::Elements(eod_steps));
    g.bench_function("discharge_to_eod_8w", |b| {
        b.iter(|| {
            model
                .simulate_until_eod(&x0, black_box(&d), &LoadProfile::Constant(Load::PowerW(8.0)), 1.0, 100_000, |r| {
                    black_box(r.voltage_v);
                })
                .unwrap()
        })
    });
    g.finish();
}

criterion_group!(benches, bench_step);
criterion_main!(benches);
