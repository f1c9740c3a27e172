//! Phase 2a, the constraint Jacobian `H`: one normal row per contact, plus two
//! tangent rows when `μ > 0`; the friction `μ` and free gap `δ₀` of each row.
//!
//! Entries are kept per body ([`JacEntry`], sorted by node then row), only for
//! free nodes (fixed and driven nodes do not move in response to a contact).

use super::bodies::Bodies;
use super::compliance::JacEntry;
use super::types::{Contact, ContactOther, ContactSide};
use crate::body::NodeConstraint;
use crate::math::Vec3;

/// The Jacobian of one pass.
#[derive(Debug, Default)]
pub struct Jacobian {
    /// Row offsets per contact: rows of contact `c` are `rows[c]..rows[c+1]`.
    pub rows: Vec<usize>,
    /// Friction coefficient per contact.
    pub mu: Vec<f64>,
    /// Free gap (normal) and slip (tangents) per row.
    pub delta0: Vec<f64>,
    /// Entries per body index.
    pub entries: Vec<Vec<JacEntry>>,
    /// Contacts that have friction rows.
    pub friction_contacts: usize,
}

impl Jacobian {
    /// Number of rows.
    pub fn m(&self) -> usize {
        self.delta0.len()
    }

    /// Builds `H`, `μ` and `δ₀` of `contacts`.
    pub fn build<B: Bodies + ?Sized>(&mut self, contacts: &[Contact], bodies: &B) {
        self.rows.clear();
        self.mu.clear();
        self.delta0.clear();
        self.entries.resize_with(bodies.len(), Vec::new);
        for e in &mut self.entries {
            e.clear();
        }
        self.friction_contacts = 0;
        for c in contacts {
            self.rows.push(self.delta0.len());
            self.mu.push(c.mu);
            self.delta0.push(c.gap);
            if c.mu > 0.0 {
                self.delta0.push(c.slip[0]);
                self.delta0.push(c.slip[1]);
                self.friction_contacts += 1;
            }
        }
        self.rows.push(self.delta0.len());
        for (ci, c) in contacts.iter().enumerate() {
            let r0 = self.rows[ci];
            let dirs = [c.normal, c.tangents[0], c.tangents[1]];
            let nrows = self.rows[ci + 1] - r0;
            let mut push = |side: &ContactSide, sign: f64| {
                let body = bodies.body(side.body);
                for k in 0..3 {
                    let (node, wgt) = (side.nodes[k] as usize, side.weights[k]);
                    if wgt == 0.0 || body.constraints()[node] != NodeConstraint::Free {
                        continue;
                    }
                    for (r, d) in dirs.iter().enumerate().take(nrows) {
                        self.entries[side.body].push(JacEntry {
                            node: node as u32,
                            row: (r0 + r) as u32,
                            h: d * (sign * wgt),
                            j: Vec3::zeros(),
                        });
                    }
                }
            };
            push(&c.a, 1.0);
            if let ContactOther::Body(b) = &c.other {
                push(b, -1.0);
            }
        }
        for e in &mut self.entries {
            e.sort_unstable_by_key(|e| (e.node, e.row));
        }
    }
}
