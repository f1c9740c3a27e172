//! A recorded contact problem: `W`, `δ₀`, the contact structure, `μ` and
//! the warm start, to replay through any solver (in the spirit of FCLIB).
//!
//! File format (little-endian): the 8 bytes `BSTLCP01`; `m` and the contact
//! count `nc` as `u64`; the `nc + 1` row offsets as `u64`; `μ` (`nc` ×
//! `f64`); `δ₀` and the warm start (`m` × `f64` each); the upper triangle of
//! `W` row by row (`m (m + 1) / 2` × `f64`).

use std::path::Path;

use super::solve::{LcpScratch, solve};
use super::types::{LcpReport, LcpSettings};
use crate::error::{Result, SoftTissueError};

const MAGIC: &[u8; 8] = b"BSTLCP01";

/// One contact LCP, as the contact phase solved it.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ContactProblem {
    /// `W`, dense, symmetric, `m × m`, row-major.
    pub w: Vec<f64>,
    /// The free violation `δ₀` (metres), one per row.
    pub delta0: Vec<f64>,
    /// Row offsets: contact `c` owns rows `rows[c]..rows[c + 1]` (1 or 3).
    pub rows: Vec<usize>,
    /// Friction coefficient per contact.
    pub mu: Vec<f64>,
    /// The forces the solve started from (the warm start), one per row.
    pub lambda0: Vec<f64>,
}

const FORMAT: &str = "contact problem";

fn bad(offset: usize, what: impl std::fmt::Display) -> SoftTissueError {
    SoftTissueError::Parse {
        format: FORMAT,
        reason: format!("byte {offset}: {what}"),
    }
}

impl ContactProblem {
    /// Rows of `W`.
    pub fn m(&self) -> usize {
        self.delta0.len()
    }

    /// Contacts.
    pub fn num_contacts(&self) -> usize {
        self.rows.len().saturating_sub(1)
    }

    /// Checks sizes, the row structure and that every number is finite.
    pub fn validate(&self) -> Result<()> {
        let m = self.m();
        let nc = self.num_contacts();
        let fail = |what: &str| {
            Err(SoftTissueError::Parse {
                format: FORMAT,
                reason: what.to_string(),
            })
        };
        if self.rows.first() != Some(&0) || self.rows.last() != Some(&m) {
            return fail("row offsets must run from 0 to m");
        }
        if self
            .rows
            .windows(2)
            .any(|p| !matches!(p[1].wrapping_sub(p[0]), 1 | 3))
        {
            return fail("every contact owns 1 or 3 rows");
        }
        if self.mu.len() != nc || self.lambda0.len() != m || self.w.len() != m * m {
            return fail("lengths of mu, lambda0 or W do not match the rows");
        }
        if self.mu.iter().any(|&u| !(u.is_finite() && u >= 0.0)) {
            return fail("a friction coefficient is negative or not finite");
        }
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        if !(finite(&self.w) && finite(&self.delta0) && finite(&self.lambda0)) {
            return fail("a number of W, delta0 or lambda0 is not finite");
        }
        Ok(())
    }

    /// Solves the problem from its warm start with `settings` (after
    /// [`Self::validate`]); returns the forces, `δ = W λ + δ₀` and the report.
    pub fn solve(&self, settings: &LcpSettings) -> Result<(Vec<f64>, Vec<f64>, LcpReport)> {
        self.validate()?;
        let mut lambda = self.lambda0.clone();
        let mut scratch = LcpScratch::default();
        let report = solve(
            &self.w,
            &self.delta0,
            &self.rows,
            &self.mu,
            &mut lambda,
            settings,
            &mut scratch,
        );
        Ok((lambda, scratch.delta().to_vec(), report))
    }

    /// The problem in the file format above.
    pub fn to_bytes(&self) -> Vec<u8> {
        let m = self.m();
        let mut out = Vec::with_capacity(24 + 8 * (self.rows.len() + m * (m + 7) / 2));
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(m as u64).to_le_bytes());
        out.extend_from_slice(&(self.num_contacts() as u64).to_le_bytes());
        for &r in &self.rows {
            out.extend_from_slice(&(r as u64).to_le_bytes());
        }
        for v in self.mu.iter().chain(&self.delta0).chain(&self.lambda0) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for i in 0..m {
            for v in &self.w[i * m + i..(i + 1) * m] {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        out
    }

    /// Reads a problem from the file format above; a malformed input gives
    /// an error naming the byte offset, never a panic, and nothing is
    /// allocated beyond what the input's length supports.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        if bytes.len() < 24 || &bytes[..8] != MAGIC {
            return Err(bad(0, "not a contact problem (magic BSTLCP01 missing)"));
        }
        let word = |i: usize| u64::from_le_bytes(bytes[i..i + 8].try_into().expect("8 bytes"));
        let (m, nc) = (word(8), word(16));
        // The length the header promises, in u64 arithmetic that cannot overflow
        // for any header whose counts fit the input.
        let len = bytes.len() as u128;
        let (m128, nc128) = (m as u128, nc as u128);
        // Each count needs at least 8 bytes per unit; past that the header lies
        // (and the sizes below stay far from overflow).
        if m128 > len / 8 || nc128 > len / 8 {
            return Err(bad(
                8,
                format!("m = {m} and {nc} contacts need more bytes than the file's {len}"),
            ));
        }
        let words = (nc128 + 1) + nc128 + 2 * m128 + m128 * (m128 + 1) / 2;
        if 24 + 8 * words != len {
            return Err(bad(
                24,
                format!(
                    "m = {m} and {nc} contacts need {} bytes, the file has {len}",
                    24 + 8 * words
                ),
            ));
        }
        // Both counts are now bounded by the input's length.
        let (m, nc) = (m as usize, nc as usize);
        let mut at = 24;
        let mut rows = Vec::with_capacity(nc + 1);
        for _ in 0..=nc {
            let r = word(at);
            if r > m as u64 {
                return Err(bad(at, format!("row offset {r} beyond m = {m}")));
            }
            rows.push(r as usize);
            at += 8;
        }
        let floats = |n: usize, at: &mut usize| -> Vec<f64> {
            let v = (0..n)
                .map(|i| {
                    f64::from_le_bytes(
                        bytes[*at + 8 * i..*at + 8 * i + 8]
                            .try_into()
                            .expect("8 bytes"),
                    )
                })
                .collect();
            *at += 8 * n;
            v
        };
        let mu = floats(nc, &mut at);
        let delta0 = floats(m, &mut at);
        let lambda0 = floats(m, &mut at);
        let mut w = vec![0.0; m * m];
        for i in 0..m {
            let row = floats(m - i, &mut at);
            for (k, v) in row.into_iter().enumerate() {
                w[i * m + i + k] = v;
                w[(i + k) * m + i] = v;
            }
        }
        let p = Self {
            w,
            delta0,
            rows,
            mu,
            lambda0,
        };
        p.validate()?;
        Ok(p)
    }

    /// Writes the problem to `path`.
    pub fn write(&self, path: &Path) -> Result<()> {
        std::fs::write(path, self.to_bytes()).map_err(|e| SoftTissueError::Io {
            path: path.display().to_string(),
            reason: e.to_string(),
        })
    }

    /// Reads a problem from `path`.
    pub fn read(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| SoftTissueError::Io {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        Self::from_bytes(&bytes).map_err(|e| SoftTissueError::Parse {
            format: FORMAT,
            reason: format!("{}: {e}", path.display()),
        })
    }
}
