//! One math vocabulary for the battery model, the MDP and the UKF: fixed-size nalgebra types only.
//!
//! The model state is stored as eight numbers (the paper's seven plus the bulk temperature) so the
//! thermal option costs nothing when it is off; the calibration MDP sees only the first seven.

use nalgebra::SVector;

/// Number of electrochemical states of the paper's Eq. (1).
pub const N_STATE: usize = 7;

/// Full model state: `[qpS, qpB, qnB, qnS (C), Vo, Vsn, Vsp (V), tb (K)]`.
pub type ModelState = SVector<f64, 8>;

/// The paper's seven-state vector `[qpS, qpB, qnB, qnS, Vo, Vsn, Vsp]`.
pub type StateVec = SVector<f64, N_STATE>;

/// Index of each entry of [`ModelState`]; one place so no code writes a bare `x[4]`.
pub mod idx {
    pub const QP_S: usize = 0;
    pub const QP_B: usize = 1;
    pub const QN_B: usize = 2;
    pub const QN_S: usize = 3;
    pub const V_O: usize = 4;
    pub const V_SN: usize = 5;
    pub const V_SP: usize = 6;
    pub const T_B: usize = 7;
}

/// Names of the seven MDP states, in order (CSV headers, reports).
pub const STATE_NAMES: [&str; N_STATE] = ["qpS", "qpB", "qnB", "qnS", "Vo", "Vsn", "Vsp"];

/// The seven electrochemical states of a full model state.
#[inline]
pub fn electro(x: &ModelState) -> StateVec {
    x.fixed_rows::<N_STATE>(0).into_owned()
}
