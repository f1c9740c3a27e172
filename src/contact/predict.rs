//! Prediction: where the first pass of a step detects
//! ([`super::ContactSettings::predict`]).
//!
//! Each body's corrections of a step (all passes) are summed; the next step's
//! first pass detects at the free motion plus that sum, where held contacts
//! will be, and [`Prediction::linearize_back`] takes the gaps back to the free
//! motion (`δ₀ = gap − H·shift`). Only the step just before counts: a body that
//! was left alone for a step, or a pipeline that skipped a step, predicts
//! nothing. Refinement passes ([`super::PassKind::Refine`]) always detect at
//! the current positions.

use super::compliance::JacEntry;
use super::detect::DetectBody;
use super::types::PassKind;
use crate::body::DeformableBody;
use crate::math::Vec3;

/// Prediction state of one body, kept between steps.
#[derive(Debug, Default)]
pub struct Prediction {
    /// The previous step's total correction, the prediction of this step's.
    shift: Vec<Vec3>,
    /// Whether this step's first pass detects at predicted positions.
    shifted: bool,
    /// This step's corrections so far (all passes).
    acc: Vec<Vec3>,
    /// Whether `acc` holds a correction.
    has_acc: bool,
    /// The step count at which `acc` was started.
    acc_step: u64,
}

impl Prediction {
    /// Starts step number `step` (counted by the caller, one per first pass):
    /// the last step's correction becomes this step's shift.
    pub fn begin_step(&mut self, n: usize, step: u64, predict: bool) {
        std::mem::swap(&mut self.shift, &mut self.acc);
        self.shifted =
            predict && self.has_acc && self.acc_step + 1 == step && self.shift.len() == n;
        self.has_acc = false;
        self.acc_step = step;
        self.acc.clear();
        self.acc.resize(n, Vec3::zeros());
    }

    /// Whether this pass detects at shifted positions.
    pub fn shifted(&self, pass: PassKind) -> bool {
        self.shifted && pass == PassKind::First
    }

    /// Fills the positions detection reads in this pass (and how much farther
    /// each vertex searches), and their bounds.
    pub fn fill(&self, body: &DeformableBody, pass: PassKind, out: &mut DetectBody) {
        let x = body.positions();
        out.x.clear();
        out.extra.clear();
        if self.shifted(pass) {
            out.x.extend(x.iter().zip(&self.shift).map(|(p, s)| p + s));
            // A vertex whose shift overshoots would leave the alarm band of
            // a contact it still has at the free motion: search as much
            // farther as it was shifted.
            out.extra.extend(self.shift.iter().map(|s| s.norm()));
        } else {
            out.x.extend_from_slice(x);
            out.extra.resize(x.len(), 0.0);
        }
        out.max_extra = out.extra.iter().copied().fold(0.0, f64::max);
        out.update_bounds(&body.surface().vertices);
    }

    /// Detected at `x + shift`: the gaps `δ₀` at the free motion.
    pub fn linearize_back(&self, pass: PassKind, entries: &[JacEntry], delta0: &mut [f64]) {
        if self.shifted(pass) {
            for e in entries {
                delta0[e.row as usize] -= e.h.dot(&self.shift[e.node as usize]);
            }
        }
    }

    /// Adds a pass's correction to this step's total.
    pub fn record(&mut self, dx: &[Vec3]) {
        if self.acc.len() == dx.len() {
            for (a, d) in self.acc.iter_mut().zip(dx) {
                *a += d;
            }
            self.has_acc = true;
        }
    }

    /// A step without contact: nothing to predict from.
    pub fn forget(&mut self) {
        self.has_acc = false;
    }
}
