//! libtorch smoke test: tch links, loads without LD_LIBRARY_PATH (rpath from
//! build.rs) and trains a small MLP on the CPU. Whether CUDA is available does
//! not matter: everything here runs on `Device::Cpu`.

use tch::nn::{self, Module, OptimizerConfig};
use tch::{Device, Kind, Reduction, Tensor};

const IN: i64 = 16;
const HIDDEN: i64 = 256;
const OUT: i64 = 2;
const BATCH: i64 = 256;
const STEPS: usize = 300;

fn mlp(p: &nn::Path) -> impl Module {
    nn::seq()
        .add(nn::linear(p / "l1", IN, HIDDEN, Default::default()))
        .add_fn(|x| x.relu())
        .add(nn::linear(p / "l2", HIDDEN, HIDDEN, Default::default()))
        .add_fn(|x| x.relu())
        .add(nn::linear(p / "l3", HIDDEN, OUT, Default::default()))
}

/// A fixed synthetic regression batch: y = [sin(x·a), tanh(x·b)].
fn batch(device: Device) -> (Tensor, Tensor) {
    let opts = (Kind::Float, device);
    let x = Tensor::randn([BATCH, IN], opts);
    let w = Tensor::randn([IN, OUT], opts) * 0.5;
    let z = x.matmul(&w);
    let y = Tensor::stack(&[z.select(1, 0).sin(), z.select(1, 1).tanh()], 1);
    (x, y)
}

#[test]
fn mlp_trains_on_cpu() -> anyhow::Result<()> {
    let started = std::time::Instant::now();
    let device = Device::Cpu;
    // One intra-op thread: the net is tiny, and test runners start several test
    // processes at once on 2 cores, where OpenMP's spinning threads would fight.
    tch::set_num_threads(1);
    tch::manual_seed(20_240_601);
    let (x, y) = batch(device);

    let vs = nn::VarStore::new(device);
    let net = mlp(&vs.root());
    let mut opt = nn::Adam::default().build(&vs, 1e-3)?;

    let first = net.forward(&x).mse_loss(&y, Reduction::Mean).double_value(&[]);
    let mut last = first;
    for _ in 0..STEPS {
        let loss = net.forward(&x).mse_loss(&y, Reduction::Mean);
        opt.backward_step(&loss);
        last = loss.double_value(&[]);
    }
    let last = last.min(net.forward(&x).mse_loss(&y, Reduction::Mean).double_value(&[]));
    eprintln!(
        "libtorch smoke: loss {first:.4e} -> {last:.4e} ({:.0}x) in {STEPS} Adam steps, {:.2?}",
        first / last,
        started.elapsed()
    );
    assert!(first.is_finite() && last.is_finite(), "loss not finite: {first} -> {last}");
    assert!(last * 10.0 <= first, "loss fell only {first:.4e} -> {last:.4e}");
    Ok(())
}

#[test]
fn cuda_probe_does_not_crash() {
    // libtorch_cpu.so is linked against libcudart/libcupti; asking must still work
    // (and answer false on a machine without a GPU or without libtorch_cuda).
    let cuda = tch::Cuda::is_available();
    eprintln!("tch::Cuda::is_available() = {cuda}, cuDNN = {}", tch::Cuda::cudnn_is_available());
    let t = Tensor::from_slice(&[1.0f32, 2.0, 3.0]).to_device(Device::Cpu);
    assert_eq!(t.sum(Kind::Float).double_value(&[]), 6.0);
}
