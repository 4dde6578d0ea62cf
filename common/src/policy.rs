//! The actor network's forward pass in plain Rust, so actors and the evaluator run the policy without
//! libtorch. The learner's tch network exports its parameters in exactly [`PolicyLayout`]'s order and a
//! test in the learner holds the two forward passes equal within [`PolicyNet::rounding_bound`].
//!
//! Network (paper 4.2): hidden Linear layers with LeakyReLU (slope 0.01, torch's default), then two heads,
//! mean and log standard deviation; the action is tanh(mean + std * eps) (squashed Gaussian), and the
//! deterministic action is tanh(mean).
//!
//! Flat layout, torch's Linear convention (weight is [out, in], row-major): for each hidden layer its
//! weight then bias, then the mean head's weight and bias, then the log-std head's weight and bias.

use serde::{Deserialize, Serialize};

/// LeakyReLU negative slope (torch default).
pub const LEAKY_SLOPE: f32 = 0.01;
/// Clip of the log standard deviation (Han et al.'s LAC code).
pub const LOG_STD_MIN: f32 = -20.0;
pub const LOG_STD_MAX: f32 = 2.0;

/// Shape of the actor network.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PolicyLayout {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub hidden: Vec<usize>,
}

impl PolicyLayout {
    /// (in, out) of every Linear in flat order: hidden layers, mean head, log-std head.
    pub fn linears(&self) -> Vec<(usize, usize)> {
        let mut v = Vec::with_capacity(self.hidden.len() + 2);
        let mut input = self.obs_dim;
        for h in &self.hidden {
            v.push((input, *h));
            input = *h;
        }
        v.push((input, self.act_dim));
        v.push((input, self.act_dim));
        v
    }

    pub fn n_params(&self) -> usize {
        self.linears().iter().map(|(i, o)| i * o + o).sum()
    }

    /// A stable fingerprint of the shape, carried in weight messages so a mismatched peer is refused.
    pub fn fingerprint(&self) -> u64 {
        let bytes: Vec<u8> = [self.obs_dim, self.act_dim]
            .iter()
            .chain(self.hidden.iter())
            .flat_map(|v| (*v as u64).to_le_bytes())
            .collect();
        crate::hash::fnv1a64(&bytes)
    }

    pub fn max_width(&self) -> usize {
        self.hidden.iter().copied().chain([self.obs_dim, self.act_dim]).max().unwrap_or(1)
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PolicyError {
    #[error("policy weights have {got} parameters, the layout {layout:?} needs {want}")]
    WrongSize { got: usize, want: usize, layout: PolicyLayout },
    #[error("policy weights contain a non-finite value at index {index}")]
    NonFinite { index: usize },
}

/// The actor network with its flat parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct PolicyNet {
    layout: PolicyLayout,
    params: Vec<f32>,
    /// Offset of each Linear's weight in `params` (bias follows at offset + in * out).
    offsets: Vec<usize>,
    /// `params` with every weight transposed to [in, out] (same offsets): the wide layers run as
    /// column updates of all their outputs at once, which vectorise with no horizontal sums.
    transposed: Vec<f32>,
}

/// Reusable buffers for the forward pass (no allocation per call).
#[derive(Clone, Debug)]
pub struct Scratch {
    a: Vec<f32>,
    b: Vec<f32>,
}

impl Scratch {
    pub fn new(layout: &PolicyLayout) -> Self {
        let w = layout.max_width();
        Self { a: vec![0.0; w], b: vec![0.0; w] }
    }
}

impl PolicyNet {
    pub fn from_flat(layout: PolicyLayout, params: Vec<f32>) -> Result<Self, PolicyError> {
        let want = layout.n_params();
        if params.len() != want {
            return Err(PolicyError::WrongSize { got: params.len(), want, layout });
        }
        if let Some(index) = params.iter().position(|v| !v.is_finite()) {
            return Err(PolicyError::NonFinite { index });
        }
        let mut offsets = Vec::new();
        let mut o = 0;
        for (i, out) in layout.linears() {
            offsets.push(o);
            o += i * out + out;
        }
        let mut net = Self { transposed: params.clone(), layout, params, offsets };
        net.transpose();
        Ok(net)
    }

    /// Fills `transposed` from `params`.
    fn transpose(&mut self) {
        for ((n_in, n_out), &o) in self.layout.linears().into_iter().zip(&self.offsets) {
            for j in 0..n_out {
                for i in 0..n_in {
                    self.transposed[o + i * n_out + j] = self.params[o + j * n_in + i];
                }
            }
            self.transposed[o + n_in * n_out..o + n_in * n_out + n_out]
                .copy_from_slice(&self.params[o + n_in * n_out..o + n_in * n_out + n_out]);
        }
    }

    pub fn layout(&self) -> &PolicyLayout {
        &self.layout
    }

    pub fn params(&self) -> &[f32] {
        &self.params
    }

    /// Replaces the parameters in place (same layout), e.g. when new weights arrive.
    pub fn set_params(&mut self, params: &[f32]) -> Result<(), PolicyError> {
        if params.len() != self.params.len() {
            return Err(PolicyError::WrongSize {
                got: params.len(),
                want: self.params.len(),
                layout: self.layout.clone(),
            });
        }
        if let Some(index) = params.iter().position(|v| !v.is_finite()) {
            return Err(PolicyError::NonFinite { index });
        }
        self.params.copy_from_slice(params);
        self.transpose();
        Ok(())
    }

    /// Mean and (clipped) log standard deviation of the Gaussian before the tanh squash.
    pub fn forward(&self, obs: &[f32], s: &mut Scratch, mean: &mut [f32], log_std: &mut [f32]) {
        debug_assert_eq!(obs.len(), self.layout.obs_dim);
        #[cfg(target_arch = "x86_64")]
        {
            if simd::avx2_fma() {
                // SAFETY: the CPU supports AVX2 and FMA (checked at run time).
                unsafe { self.forward_avx2(obs, s, mean, log_std) };
                return;
            }
        }
        self.forward_body::<false>(obs, s, mean, log_std);
    }

    /// The same code compiled for AVX2 + FMA: 8-wide fused multiply-adds in the dot products.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn forward_avx2(&self, obs: &[f32], s: &mut Scratch, mean: &mut [f32], log_std: &mut [f32]) {
        self.forward_body::<true>(obs, s, mean, log_std);
    }

    #[inline(always)]
    fn forward_body<const FMA: bool>(&self, obs: &[f32], s: &mut Scratch, mean: &mut [f32], log_std: &mut [f32]) {
        let l = &self.layout;
        let n_hidden = l.hidden.len();
        s.a[..l.obs_dim].copy_from_slice(obs);
        let mut width = l.obs_dim;
        for (k, h) in l.hidden.iter().enumerate() {
            let (src, dst) = (&s.a[..width], &mut s.b[..*h]);
            self.linear::<FMA>(k, src, dst);
            for v in dst.iter_mut() {
                if *v < 0.0 {
                    *v *= LEAKY_SLOPE;
                }
            }
            std::mem::swap(&mut s.a, &mut s.b);
            width = *h;
        }
        self.linear::<FMA>(n_hidden, &s.a[..width], mean);
        self.linear::<FMA>(n_hidden + 1, &s.a[..width], log_std);
        for v in log_std.iter_mut() {
            *v = v.clamp(LOG_STD_MIN, LOG_STD_MAX);
        }
    }

    #[inline(always)]
    fn linear<const FMA: bool>(&self, k: usize, input: &[f32], out: &mut [f32]) {
        let (n_in, n_out) = (input.len(), out.len());
        let o = self.offsets[k];
        if n_out < 8 {
            // The heads: a few long dot products.
            let w = &self.params[o..o + n_in * n_out];
            let b = &self.params[o + n_in * n_out..o + n_in * n_out + n_out];
            for j in 0..n_out {
                out[j] = b[j] + dot::<FMA>(&w[j * n_in..(j + 1) * n_in], input);
            }
            return;
        }
        // Wide layers: out = b + sum_i W[:, i] x_i, one input at a time over a block of outputs held in
        // registers (BLOCK lanes), then the rest of the outputs the same way one at a time.
        const BLOCK: usize = 32;
        let w = &self.transposed[o..o + n_in * n_out];
        out.copy_from_slice(&self.transposed[o + n_in * n_out..o + n_in * n_out + n_out]);
        let blocks = n_out / BLOCK;
        for blk in 0..blocks {
            let mut acc = [0f32; BLOCK];
            acc.copy_from_slice(&out[blk * BLOCK..(blk + 1) * BLOCK]);
            for (i, &x) in input.iter().enumerate() {
                let col = &w[i * n_out + blk * BLOCK..i * n_out + (blk + 1) * BLOCK];
                for l in 0..BLOCK {
                    acc[l] = if FMA { col[l].mul_add(x, acc[l]) } else { acc[l] + col[l] * x };
                }
            }
            out[blk * BLOCK..(blk + 1) * BLOCK].copy_from_slice(&acc);
        }
        for (i, &x) in input.iter().enumerate() {
            let col = &w[i * n_out..(i + 1) * n_out];
            for j in blocks * BLOCK..n_out {
                out[j] = if FMA { col[j].mul_add(x, out[j]) } else { out[j] + col[j] * x };
            }
        }
    }

    /// Deterministic action tanh(mean), in [-1, 1].
    pub fn act_deterministic(&self, obs: &[f32], s: &mut Scratch, action: &mut [f32]) {
        let mut log_std = [0f32; 8];
        let n = action.len();
        self.forward(obs, s, action, &mut log_std[..n]);
        for a in action.iter_mut() {
            *a = a.tanh();
        }
    }

    /// A bound on how far two correct f32 forward passes of this network (any summation order, with or
    /// without fused multiply-adds: this one and libtorch's CPU kernels of any level) may differ on `obs`,
    /// per output: (mean bound, log-std bound).
    ///
    /// Why a bound and not a constant: the difference grows with the dot-product length n and with the
    /// magnitudes summed. A Linear output computed in any order is within lambda sqrt(n + 1) u M of the
    /// exact value, M = sum |w x| + |b|, u = 2^-24, except with probability <= 2 exp(-lambda^2 / 2)
    /// (Higham & Mary 2019, probabilistic rounding error analysis; the worst-case bound n u M is
    /// thousands of times looser than any real difference once propagated through 256-wide layers).
    /// Two implementations differ by at most twice that, plus the input difference carried through W,
    /// added in quadrature (independent rounding errors); LeakyReLU and the log-std clip are 1-Lipschitz.
    /// lambda = 8: a spurious failure is rarer than 1e-13 per output. Computed in f64.
    pub fn rounding_bound(&self, obs: &[f32]) -> (Vec<f64>, Vec<f64>) {
        const LAMBDA: f64 = 8.0;
        let u = f64::from(f32::EPSILON) / 2.0;
        let l = &self.layout;
        let mut h: Vec<f64> = obs.iter().map(|v| f64::from(*v)).collect();
        let mut err = vec![0.0f64; h.len()];
        // One Linear in f64: (exact output, bound on the two implementations' difference).
        let linear = |k: usize, h: &[f64], err: &[f64], n_out: usize| -> (Vec<f64>, Vec<f64>) {
            let n_in = h.len();
            let w = &self.params[self.offsets[k]..self.offsets[k] + n_in * n_out];
            let b = &self.params[self.offsets[k] + n_in * n_out..self.offsets[k] + n_in * n_out + n_out];
            let local = 2.0 * LAMBDA * ((n_in + 1) as f64).sqrt() * u;
            let (mut out, mut bound) = (vec![0.0; n_out], vec![0.0; n_out]);
            for j in 0..n_out {
                let row = &w[j * n_in..(j + 1) * n_in];
                let (mut s, mut mag, mut carried_sq) = (f64::from(b[j]), f64::from(b[j]).abs(), 0.0);
                for i in 0..n_in {
                    let wi = f64::from(row[i]);
                    s += wi * h[i];
                    mag += wi.abs() * (h[i].abs() + err[i]);
                    carried_sq += (wi * err[i]).powi(2);
                }
                out[j] = s;
                bound[j] = carried_sq.sqrt() + local * mag;
            }
            (out, bound)
        };
        for (k, width) in l.hidden.iter().enumerate() {
            let (out, bound) = linear(k, &h, &err, *width);
            h = out.into_iter().map(|v| if v < 0.0 { v * f64::from(LEAKY_SLOPE) } else { v }).collect();
            err = bound;
        }
        let (_, mean_bound) = linear(l.hidden.len(), &h, &err, l.act_dim);
        let (_, log_std_bound) = linear(l.hidden.len() + 1, &h, &err, l.act_dim);
        (mean_bound, log_std_bound)
    }

    /// Stochastic action tanh(mean + std * eps) with eps ~ N(0, 1) drawn from `normal`.
    pub fn act_stochastic(&self, obs: &[f32], s: &mut Scratch, mut normal: impl FnMut() -> f64, action: &mut [f32]) {
        let mut log_std = [0f32; 8];
        let n = action.len();
        self.forward(obs, s, action, &mut log_std[..n]);
        for (a, ls) in action.iter_mut().zip(&log_std[..n]) {
            *a = (*a + ls.exp() * normal() as f32).tanh();
        }
    }
}

/// Dot product in 32 independent lanes (four 8-wide vectors) so the compiler vectorises it and the
/// multiply-add latency is hidden. `FMA` selects fused multiply-adds, only where the CPU has them (elsewhere
/// `mul_add` would be a slow software call).
#[inline(always)]
fn dot<const FMA: bool>(w: &[f32], x: &[f32]) -> f32 {
    const LANES: usize = 32;
    let mut acc = [0f32; LANES];
    let chunks = w.len() / LANES;
    for c in 0..chunks {
        let (wc, xc) = (&w[c * LANES..c * LANES + LANES], &x[c * LANES..c * LANES + LANES]);
        for l in 0..LANES {
            acc[l] = if FMA { wc[l].mul_add(xc[l], acc[l]) } else { acc[l] + wc[l] * xc[l] };
        }
    }
    // Pairwise (vectorised) sum of the lanes: a serial one would cost a chain of 32 dependent adds.
    let mut width = LANES;
    while width > 1 {
        width /= 2;
        for l in 0..width {
            acc[l] += acc[l + width];
        }
    }
    let mut s = acc[0];
    for k in chunks * LANES..w.len() {
        s = if FMA { w[k].mul_add(x[k], s) } else { s + w[k] * x[k] };
    }
    s
}

#[cfg(target_arch = "x86_64")]
mod simd {
    use std::sync::OnceLock;

    /// Whether this CPU has AVX2 and FMA, detected once.
    pub fn avx2_fma() -> bool {
        static HAS: OnceLock<bool> = OnceLock::new();
        *HAS.get_or_init(|| std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout() -> PolicyLayout {
        PolicyLayout { obs_dim: 3, act_dim: 2, hidden: vec![4, 5] }
    }

    #[test]
    fn sizes_and_fingerprint() {
        let l = layout();
        assert_eq!(l.n_params(), (3 * 4 + 4) + (4 * 5 + 5) + 2 * (5 * 2 + 2));
        let paper = PolicyLayout { obs_dim: 15, act_dim: 2, hidden: vec![256; 3] };
        assert_eq!(paper.n_params(), 15 * 256 + 256 + 2 * (256 * 256 + 256) + 2 * (256 * 2 + 2));
        assert_ne!(l.fingerprint(), paper.fingerprint());
        let err = PolicyNet::from_flat(l.clone(), vec![0.0; 3]).unwrap_err();
        assert!(err.to_string().contains("needs"));
        let mut bad = vec![0.0; l.n_params()];
        bad[7] = f32::NAN;
        assert_eq!(PolicyNet::from_flat(l, bad).unwrap_err(), PolicyError::NonFinite { index: 7 });
    }

    #[test]
    fn forward_matches_a_hand_computation() {
        // One hidden layer of width 2 on a 2-d input, one action.
        let l = PolicyLayout { obs_dim: 2, act_dim: 1, hidden: vec![2] };
        #[rustfmt::skip]
        let p = vec![
            1.0, -1.0,   0.5, 2.0,   0.0, -1.0, // hidden W (2x2) row-major, bias
            3.0, 1.0,    0.25,                  // mean head W (1x2), bias
            0.0, 0.0,    5.0,                   // log-std head: constant 5 -> clipped to 2
        ];
        let net = PolicyNet::from_flat(l.clone(), p).unwrap();
        let mut s = Scratch::new(&l);
        let (mut mean, mut log_std) = ([0f32], [0f32]);
        net.forward(&[2.0, 1.0], &mut s, &mut mean, &mut log_std);
        // h = leaky([2-1+0, 1+2-1]) = [1, 2]; mean = 3 + 2 + 0.25.
        assert_eq!(mean[0], 5.25);
        assert_eq!(log_std[0], LOG_STD_MAX);
        net.forward(&[-2.0, 0.0], &mut s, &mut mean, &mut log_std);
        // h = leaky([-2, -1 - 1]) = [-0.02, -0.02]; mean = -0.06 - 0.02 + 0.25.
        assert!((mean[0] - 0.17).abs() < 1e-6);
        let mut a = [0f32];
        net.act_deterministic(&[2.0, 1.0], &mut s, &mut a);
        assert_eq!(a[0], 5.25f32.tanh());
        net.act_stochastic(&[2.0, 1.0], &mut s, || 0.0, &mut a);
        assert_eq!(a[0], 5.25f32.tanh());
    }

    /// The rounding bound holds for a forward pass summed in another order, grows with the dot-product
    /// length, and is far below the difference a real mistake (one weight changed) makes.
    #[test]
    fn rounding_bound_covers_another_summation_order_and_not_a_wrong_weight() {
        let l = PolicyLayout { obs_dim: 15, act_dim: 2, hidden: vec![256, 256, 256] };
        let mut seed = 0x1234_5678u64;
        let mut next = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.2
        };
        let params: Vec<f32> = (0..l.n_params()).map(|_| next()).collect();
        let net = PolicyNet::from_flat(l.clone(), params.clone()).unwrap();
        let obs: Vec<f32> = (0..15).map(|k| (k as f32 - 7.0) * 0.8).collect();
        let (mean_bound, _) = net.rounding_bound(&obs);
        // A plain f32 forward pass summing each dot product backwards: another legal order.
        let reversed = |p: &[f32]| {
            let mut h: Vec<f32> = obs.clone();
            let mut off = 0;
            for (k, (n_in, n_out)) in l.linears().into_iter().take(l.hidden.len() + 1).enumerate() {
                let mut out = vec![0f32; n_out];
                for (j, o) in out.iter_mut().enumerate() {
                    let mut s = 0f32;
                    for i in (0..n_in).rev() {
                        s += p[off + j * n_in + i] * h[i];
                    }
                    *o = s + p[off + n_in * n_out + j];
                }
                off += n_in * n_out + n_out;
                let hidden = k < l.hidden.len();
                h = out.iter().map(|v| if hidden && *v < 0.0 { v * LEAKY_SLOPE } else { *v }).collect();
            }
            h
        };
        let mut s = Scratch::new(&l);
        let (mut mean, mut log_std) = ([0f32; 2], [0f32; 2]);
        net.forward(&obs, &mut s, &mut mean, &mut log_std);
        let other = reversed(&params);
        for j in 0..2 {
            let d = f64::from((mean[j] - other[j]).abs());
            assert!(d <= mean_bound[j], "output {j}: differ by {d:e}, bound {:e}", mean_bound[j]);
            assert!(mean_bound[j] < 1e-3 * (1.0 + f64::from(mean[j].abs())), "bound {:e} is useless", mean_bound[j]);
        }
        // A mean-head bias off by 0.01 moves the output by far more than the bound: real mistakes show.
        let mut wrong = params.clone();
        let mean_bias = 15 * 256 + 256 + 2 * (256 * 256 + 256) + 2 * 256;
        wrong[mean_bias] += 0.01;
        let moved = reversed(&wrong);
        let moved_by: Vec<f32> = (0..2).map(|j| (moved[j] - other[j]).abs()).collect();
        assert!(
            (0..2).any(|j| f64::from(moved_by[j]) > 10.0 * mean_bound[j]),
            "a wrong weight moved the outputs by {moved_by:?}, bounds {mean_bound:?}"
        );
        // Longer dot products get a larger bound on the same magnitude (sum |w x| = 1 in both).
        let one_layer = |n: usize| {
            let l = PolicyLayout { obs_dim: n, act_dim: 1, hidden: vec![] };
            let mut p = vec![1.0 / n as f32; l.n_params()];
            p[n] = 0.0; // the mean head's bias
            PolicyNet::from_flat(l, p).unwrap().rounding_bound(&vec![1.0; n]).0[0]
        };
        assert!(one_layer(1024) > 4.0 * one_layer(16), "{} vs {}", one_layer(1024), one_layer(16));
    }
}

/// What a trained calibrator is, apart from libtorch: the actor's flat weights with the MDP they were
/// trained on (scales travel with the weights). The learner writes one beside every checkpoint; actors and
/// the evaluator read it without libtorch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PolicyFile {
    pub layout: PolicyLayout,
    /// The task the policy was trained on (its observation, scales and action map travel with it).
    pub task: crate::task::Task,
    pub experiment: crate::dataset::Experiment,
    /// Learner update counter when the weights were taken.
    pub update_step: u64,
    pub params: Vec<f32>,
}

// Version 3: the task travels as JSON inside the payload, so a task field added later (with its serde
// default, as every config field has) leaves earlier files readable, and a file from a newer bcal names the
// field this one does not know. Version 2 (task in bincode, readable only while the task format stands
// still) still loads.
const POLICY_MAGIC: &[u8; 8] = b"BCALPOL3";
const POLICY_MAGIC_V2: &[u8; 8] = b"BCALPOL2";

/// A policy file's payload (version 3): [`PolicyFile`] with its task as JSON.
#[derive(Serialize, Deserialize)]
struct Stored {
    layout: PolicyLayout,
    task_json: String,
    experiment: crate::dataset::Experiment,
    update_step: u64,
    params: Vec<f32>,
}

/// A run folder's policy files: the latest weights (written at every checkpoint) ...
pub const POLICY_LAST: &str = "policy.bcalpol";
/// ... and the delivered one, the best by the run's `learner.select_by` validation score.
pub const POLICY_BEST: &str = "policy.best.bcalpol";

/// The file of the best policy by one validation score.
pub fn best_policy_file(select: crate::config::SelectBy) -> String {
    format!("policy.best-{}.bcalpol", select.name())
}

#[derive(Debug, thiserror::Error)]
pub enum PolicyFileError {
    #[error("cannot {action} policy file {path}: {source}")]
    Io { action: &'static str, path: std::path::PathBuf, source: std::io::Error },
    #[error("policy file {path} is not usable: {why}")]
    Corrupt { path: std::path::PathBuf, why: String },
    #[error("policy file {path}: {source}")]
    Policy { path: std::path::PathBuf, source: PolicyError },
}

impl PolicyFile {
    /// Atomic write ([`crate::fsutil`]): magic + CRC32 + bincode payload (the task inside it as JSON).
    pub fn save(&self, path: &std::path::Path) -> Result<(), PolicyFileError> {
        use std::io::Write;
        let stored = Stored {
            layout: self.layout.clone(),
            task_json: serde_json::to_string(&self.task).expect("tasks serialise"),
            experiment: self.experiment,
            update_step: self.update_step,
            params: self.params.clone(),
        };
        let payload = bincode::serde::encode_to_vec(&stored, bincode::config::standard()).expect("policies serialise");
        crate::fsutil::write_atomic_with(path, |f| {
            f.write_all(POLICY_MAGIC)?;
            f.write_all(&crc32fast::hash(&payload).to_le_bytes())?;
            f.write_all(&payload)
        })
        .map_err(|source| PolicyFileError::Io { action: "write", path: path.to_path_buf(), source })
    }

    /// Reads and verifies a policy file (magic, checksum, shape, finite weights).
    pub fn load(path: &std::path::Path) -> Result<Self, PolicyFileError> {
        let corrupt = |why: String| PolicyFileError::Corrupt { path: path.to_path_buf(), why };
        let bytes = std::fs::read(path).map_err(|source| PolicyFileError::Io {
            action: "read",
            path: path.to_path_buf(),
            source,
        })?;
        if bytes.len() >= 8 && &bytes[..8] == b"BCALPOL1" {
            return Err(corrupt("a policy file of an older bcal (no task recorded); retrain the run".into()));
        }
        let version = match bytes.get(..8) {
            Some(m) if m == POLICY_MAGIC => 3,
            Some(m) if m == POLICY_MAGIC_V2 => 2,
            _ => return Err(corrupt("not a bcal policy file (bad magic or too short)".into())),
        };
        if bytes.len() < 12 {
            return Err(corrupt("not a bcal policy file (too short)".into()));
        }
        let crc = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
        if crc32fast::hash(&bytes[12..]) != crc {
            return Err(corrupt("checksum mismatch (truncated or damaged)".into()));
        }
        let pf = if version == 3 {
            let (st, _): (Stored, usize) = bincode::serde::decode_from_slice(&bytes[12..], bincode::config::standard())
                .map_err(|e| corrupt(format!("undecodable ({e}): damaged")))?;
            let task = serde_json::from_str(&st.task_json).map_err(|e| {
                corrupt(format!(
                    "its task does not read here ({e}): written by a newer bcal (a field this one does not know); \
                     run it with that bcal"
                ))
            })?;
            PolicyFile {
                layout: st.layout,
                task,
                experiment: st.experiment,
                update_step: st.update_step,
                params: st.params,
            }
        } else {
            let (pf, _): (PolicyFile, usize) =
                bincode::serde::decode_from_slice(&bytes[12..], bincode::config::standard()).map_err(|e| {
                    corrupt(format!(
                        "undecodable ({e}): a version-2 policy file (its task in a fixed binary layout) written by a \
                         bcal whose task format differs from this one's, or damaged; run it with the bcal that \
                         trained it, or retrain (policies written since carry their task as JSON and stay readable)"
                    ))
                })?;
            pf
        };
        if pf.layout.obs_dim != pf.task.obs_dim() || pf.layout.act_dim != pf.task.act_dim() {
            return Err(corrupt(format!(
                "network shape {}->{} does not match its task {}->{}",
                pf.layout.obs_dim,
                pf.layout.act_dim,
                pf.task.obs_dim(),
                pf.task.act_dim()
            )));
        }
        Ok(pf)
    }

    /// The runnable network.
    pub fn net(&self) -> Result<PolicyNet, PolicyError> {
        PolicyNet::from_flat(self.layout.clone(), self.params.clone())
    }
}

#[cfg(test)]
mod file_tests {
    use super::*;

    fn measured_file() -> PolicyFile {
        let task = crate::task::Task::Measured(crate::measured::env::MeasuredSpec::default());
        let layout = PolicyLayout { obs_dim: task.obs_dim(), act_dim: task.act_dim(), hidden: vec![4] };
        let params = (0..layout.n_params()).map(|k| (k as f32 * 0.37).sin() * 0.1).collect();
        PolicyFile { layout, task, experiment: crate::dataset::Experiment::Multi, update_step: 42, params }
    }

    /// Writes a version-3 file whose task JSON went through `edit` (as another bcal would have written it).
    fn write_v3(path: &std::path::Path, pf: &PolicyFile, edit: impl Fn(&mut serde_json::Value)) {
        let mut task = serde_json::to_value(&pf.task).unwrap();
        edit(&mut task);
        let stored = Stored {
            layout: pf.layout.clone(),
            task_json: task.to_string(),
            experiment: pf.experiment,
            update_step: pf.update_step,
            params: pf.params.clone(),
        };
        let payload = bincode::serde::encode_to_vec(&stored, bincode::config::standard()).unwrap();
        let bytes = [&POLICY_MAGIC[..], &crc32fast::hash(&payload).to_le_bytes(), &payload].concat();
        std::fs::write(path, bytes).unwrap();
    }

    /// A policy file keeps its task through save and load; one written before a task field existed loads
    /// with that field's default; one naming a field this bcal does not know is refused, naming it; a
    /// version-2 file (task in bincode) still loads.
    #[test]
    fn policy_files_carry_their_task_across_versions() {
        let dir = tempfile::tempdir().unwrap();
        let pf = measured_file();
        let path = dir.path().join("p.bcalpol");
        pf.save(&path).unwrap();
        assert_eq!(PolicyFile::load(&path).unwrap(), pf);

        // An older bcal's file: no `correction` in its task (the field came later).
        let mut changed = pf.clone();
        if let crate::task::Task::Measured(m) = &mut changed.task {
            m.correction.shift_max_sd = 3.0;
        }
        write_v3(&path, &changed, |t| {
            t["Measured"].as_object_mut().unwrap().remove("correction");
        });
        assert_eq!(PolicyFile::load(&path).unwrap(), pf, "the missing field takes its default");

        // A newer bcal's file: a field this one does not know.
        write_v3(&path, &pf, |t| {
            t["Measured"]["correction"]["a_later_option"] = serde_json::json!(0.5);
        });
        let err = PolicyFile::load(&path).unwrap_err().to_string();
        assert!(err.contains("a_later_option") && err.contains("newer bcal"), "{err}");

        // Version 2: the whole file in bincode.
        let payload = bincode::serde::encode_to_vec(&pf, bincode::config::standard()).unwrap();
        let bytes = [&POLICY_MAGIC_V2[..], &crc32fast::hash(&payload).to_le_bytes(), &payload].concat();
        std::fs::write(&path, bytes).unwrap();
        assert_eq!(PolicyFile::load(&path).unwrap(), pf);
    }
}
