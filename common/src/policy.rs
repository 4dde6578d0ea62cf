//! The actor network's forward pass in plain Rust, so actors and the evaluator run the policy without
//! libtorch. The learner's tch network exports its parameters in exactly [`PolicyLayout`]'s order and a
//! test in the learner holds the two forward passes equal to 1e-5.
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
        let mut h: u64 = 0xcbf29ce484222325;
        for v in [self.obs_dim, self.act_dim].iter().chain(self.hidden.iter()) {
            for b in (*v as u64).to_le_bytes() {
                h ^= u64::from(b);
                h = h.wrapping_mul(0x100000001b3);
            }
        }
        h
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
        Ok(Self { layout, params, offsets })
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
        let w = &self.params[self.offsets[k]..self.offsets[k] + n_in * n_out];
        let b = &self.params[self.offsets[k] + n_in * n_out..self.offsets[k] + n_in * n_out + n_out];
        for j in 0..n_out {
            out[j] = b[j] + dot::<FMA>(&w[j * n_in..(j + 1) * n_in], input);
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
    let mut s = 0.0;
    for a in acc {
        s += a;
    }
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
}

/// What a trained calibrator is, apart from libtorch: the actor's flat weights with the MDP they were
/// trained on (scales travel with the weights). The learner writes one beside every checkpoint; actors and
/// the evaluator read it without libtorch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PolicyFile {
    pub layout: PolicyLayout,
    pub mdp: crate::mdp::MdpSpec,
    pub experiment: crate::dataset::Experiment,
    /// Learner update counter when the weights were taken.
    pub update_step: u64,
    pub params: Vec<f32>,
}

const POLICY_MAGIC: &[u8; 8] = b"BCALPOL1";

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
    /// Atomic write: temporary file, fsync, rename. Magic + CRC32 + bincode payload.
    pub fn save(&self, path: &std::path::Path) -> Result<(), PolicyFileError> {
        use std::io::Write;
        let io = |action, source| PolicyFileError::Io { action, path: path.to_path_buf(), source };
        let payload = bincode::serde::encode_to_vec(self, bincode::config::standard()).expect("policies serialise");
        let tmp = path.with_extension(format!("tmp{}", std::process::id()));
        let write = || -> std::io::Result<()> {
            let mut f = std::fs::File::create(&tmp)?;
            f.write_all(POLICY_MAGIC)?;
            f.write_all(&crc32fast::hash(&payload).to_le_bytes())?;
            f.write_all(&payload)?;
            f.sync_all()?;
            std::fs::rename(&tmp, path)
        };
        write().map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            io("write", e)
        })
    }

    /// Reads and verifies a policy file (magic, checksum, shape, finite weights).
    pub fn load(path: &std::path::Path) -> Result<Self, PolicyFileError> {
        let corrupt = |why: String| PolicyFileError::Corrupt { path: path.to_path_buf(), why };
        let bytes = std::fs::read(path).map_err(|source| PolicyFileError::Io {
            action: "read",
            path: path.to_path_buf(),
            source,
        })?;
        if bytes.len() < 12 || &bytes[..8] != POLICY_MAGIC {
            return Err(corrupt("not a bcal policy file (bad magic or too short)".into()));
        }
        let crc = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
        if crc32fast::hash(&bytes[12..]) != crc {
            return Err(corrupt("checksum mismatch (truncated or damaged)".into()));
        }
        let (pf, _): (PolicyFile, usize) = bincode::serde::decode_from_slice(&bytes[12..], bincode::config::standard())
            .map_err(|e| corrupt(format!("undecodable: {e}")))?;
        if pf.layout.obs_dim != pf.mdp.obs_dim() || pf.layout.act_dim != pf.mdp.act_dim() {
            return Err(corrupt(format!(
                "network shape {}->{} does not match its MDP {}->{}",
                pf.layout.obs_dim,
                pf.layout.act_dim,
                pf.mdp.obs_dim(),
                pf.mdp.act_dim()
            )));
        }
        Ok(pf)
    }

    /// The runnable network.
    pub fn net(&self) -> Result<PolicyNet, PolicyError> {
        PolicyNet::from_flat(self.layout.clone(), self.params.clone())
    }
}
