use tch::nn::{self, Module, OptimizerConfig};
use tch::{Device, Kind, Reduction, Tensor};
#[test]
fn probe() {
    if let Ok(n) = std::env::var("NT") { tch::set_num_threads(n.parse().unwrap()); }
    let t0 = std::time::Instant::now();
    eprintln!("threads={} interop={}", tch::get_num_threads(), tch::get_num_interop_threads());
    tch::manual_seed(1);
    let a = Tensor::randn([256, 256], (Kind::Float, Device::Cpu));
    eprintln!("first op {:?}", t0.elapsed());
    let t = std::time::Instant::now();
    for _ in 0..100 { let _ = a.matmul(&a); }
    eprintln!("100 matmul 256^3: {:?}", t.elapsed());
    let x = Tensor::randn([256, 16], (Kind::Float, Device::Cpu));
    let w = Tensor::randn([16, 2], (Kind::Float, Device::Cpu)) * 0.5;
    let z = x.matmul(&w);
    let y = Tensor::stack(&[z.select(1, 0).sin(), z.select(1, 1).tanh()], 1);
    eprintln!("y size {:?} mean {} std {}", y.size(), y.mean(Kind::Float).double_value(&[]), y.std(true).double_value(&[]));
    let vs = nn::VarStore::new(Device::Cpu);
    let p = vs.root();
    let net = nn::seq()
        .add(nn::linear(&p / "l1", 16, 256, Default::default())).add_fn(|x| x.relu())
        .add(nn::linear(&p / "l2", 256, 256, Default::default())).add_fn(|x| x.relu())
        .add(nn::linear(&p / "l3", 256, 2, Default::default()));
    let out = net.forward(&x);
    eprintln!("out std {}", out.std(true).double_value(&[]));
    let mut opt = nn::Adam::default().build(&vs, 1e-3).unwrap();
    let t = std::time::Instant::now();
    for i in 0..300 {
        let loss = net.forward(&x).mse_loss(&y, Reduction::Mean);
        opt.backward_step(&loss);
        if i % 50 == 0 || i == 299 { eprintln!("{i} {:.3e} {:?}", loss.double_value(&[]), t.elapsed()); }
    }
}
