//! Compliance build time against the number of contacts (the paper's
//! Fig. 4), on the paper-size lens with friction (three rows per contact).
//!
//! Modes timed, each on the same contacts and the same factor:
//! - `DenseRows`: the paper's CPU method, two full triangular solves per row;
//! - `Factorized` with a new factor (`factorized_cold`: every node column solved);
//! - `Factorized` with the columns cached (`factorized_warm`: the same factor
//!   and nodes as the previous build, as in a step where the factor did not change);
//! - `Exact`: a fresh factorization of the current matrix, then `Factorized`'s build;
//! - a [`ComplianceBackend`] (the GPU) when one is given, its builds back to
//!   back after untimed ones for [`BACKEND_WARMUP_SECONDS`],
//!   so that the device runs at the clocks a steady load gives it.

use std::time::Instant;

use super::cases::lens_material;
use crate::body::{BodySettings, DeformableBody};
use crate::contact::{
    ComplianceBackend, ComplianceMode, Contact, ContactOther, ContactSettings, ContactSide,
    ContactSolver, PassKind, tangent_basis,
};
use crate::error::Result;
use crate::math::{Vec3, v3};
use crate::mesh::generate::{self, LENS_RADII};
use crate::solver::PreconditionerKind;

/// Seconds of untimed back-to-back backend builds (at least one) before the
/// timed ones at each contact count. A GPU left idle for a few seconds (the
/// CPU modes' builds at high contact counts) lowers its clocks, and five
/// builds (about 50 ms) did not bring them back on an NVIDIA H200.
pub const BACKEND_WARMUP_SECONDS: f64 = 1.0;

/// Contact counts of the paper's Fig. 4 range.
pub const CONTACT_COUNTS: [usize; 6] = [30, 60, 90, 130, 190, 260];

/// `n` contacts of body 0 with tool 0 at the surface vertices nearest to the
/// body's highest point, with the given normal and friction.
pub fn pole_contacts(body: &DeformableBody, n: usize, normal: Vec3, mu: f64) -> Vec<Contact> {
    let x = body.positions();
    let top = body.surface().vertices.iter().map(|&v| x[v]).fold(
        v3(0.0, 0.0, f64::NEG_INFINITY),
        |a, p| {
            if p.z > a.z { p } else { a }
        },
    );
    let mut verts: Vec<usize> = body.surface().vertices.clone();
    verts.sort_by(|&a, &b| (x[a] - top).norm().total_cmp(&(x[b] - top).norm()));
    let normal = normal.normalize();
    verts
        .iter()
        .take(n)
        .map(|&v| Contact {
            a: ContactSide {
                body: 0,
                nodes: [v as u32, 0, 0],
                weights: [1.0, 0.0, 0.0],
            },
            other: ContactOther::Tool(0),
            normal,
            tangents: tangent_basis(&normal),
            gap: -1e-5,
            slip: [0.0, 0.0],
            mu,
            point: x[v],
            force: Vec3::zeros(),
        })
        .collect()
}

/// The lens of `cells` resolution with a factor that is never refreshed
/// (every build uses the same one), clamped at its bottom, after one step.
pub fn lens_with_factor(cells: usize) -> Result<DeformableBody> {
    let mesh = generate::ellipsoid(LENS_RADII, cells)?;
    let settings = BodySettings {
        preconditioner: PreconditionerKind::Periodic { every: u32::MAX },
        ..Default::default()
    };
    let mut body = DeformableBody::new(mesh, lens_material(5.0), settings)?;
    body.fix_where(|p| p.z < -2.0e-3);
    body.step(0.02)?;
    Ok(body)
}

/// Build times at one contact count, milliseconds (median of the repeats).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ComplianceTiming {
    /// Contacts (three rows each).
    pub contacts: usize,
    /// `DenseRows`.
    pub dense_rows: f64,
    /// `Factorized`, new factor.
    pub factorized_cold: f64,
    /// `Factorized`, columns cached.
    pub factorized_warm: f64,
    /// `Exact`.
    pub exact: f64,
    /// The backend (GPU), `None` when none was given.
    pub backend: Option<f64>,
    /// Of the backend's timed builds, how many it built itself (the rest it
    /// left to the CPU, so [`Self::backend`] timed the CPU for those).
    pub backend_builds: (usize, usize),
}

/// A backend that counts the builds it accepted.
struct Counted<'a> {
    inner: &'a mut dyn ComplianceBackend,
    took: usize,
}

impl ComplianceBackend for Counted<'_> {
    fn accumulate(
        &mut self,
        body_id: u64,
        factor: &crate::solver::ldlt::LdltFactor,
        key: crate::contact::FactorKey,
        h: f64,
        entries: &[crate::contact::JacEntry],
        w: &mut [f64],
        m: usize,
    ) -> Result<bool> {
        let took = self
            .inner
            .accumulate(body_id, factor, key, h, entries, w, m)?;
        self.took += usize::from(took);
        Ok(took)
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// Times the compliance build on `body` for each of `counts` contacts,
/// `repeats` times each (the median is kept), with `backend` if given.
pub fn timings(
    body: &mut DeformableBody,
    counts: &[usize],
    repeats: usize,
    mut backend: Option<&mut dyn ComplianceBackend>,
    progress: &mut dyn FnMut(usize),
) -> Result<Vec<ComplianceTiming>> {
    let h = 0.02;
    let solver = |mode| {
        ContactSolver::new(ContactSettings {
            compliance: mode,
            factor_reuse: 0,
            ..Default::default()
        })
    };
    let mut dense_s = solver(ComplianceMode::DenseRows)?;
    let mut fact_s = solver(ComplianceMode::Factorized)?;
    let mut exact_s = solver(ComplianceMode::Exact)?;
    let mut back_s = solver(ComplianceMode::Factorized)?;
    let mut out = Vec::with_capacity(counts.len());
    for &n in counts {
        let cs = pole_contacts(body, n, v3(0.0, 0.0, -1.0), 0.3);
        let (mut d, mut c, mut w, mut e, mut g) = (vec![], vec![], vec![], vec![], vec![]);
        let time = |s: &mut ContactSolver,
                    body: &mut DeformableBody,
                    forget: bool,
                    b: Option<&mut dyn ComplianceBackend>|
         -> Result<f64> {
            s.set_contacts(&cs, &[&*body], h)?;
            if forget {
                s.forget_columns();
            }
            let t0 = Instant::now();
            s.build_compliance(&mut [body], PassKind::First, b)?;
            Ok(t0.elapsed().as_secs_f64() * 1e3)
        };
        for _ in 0..repeats.max(1) {
            d.push(time(&mut dense_s, body, false, None)?);
            c.push(time(&mut fact_s, body, true, None)?);
            w.push(time(&mut fact_s, body, false, None)?);
            e.push(time(&mut exact_s, body, false, None)?);
        }
        // The backend's builds back to back, after untimed ones: a GPU left
        // idle through the CPU modes' builds (hundreds of ms at high counts)
        // lowers its clocks, and its kernels then run several times slower
        // (`gpu_bench --idle-ms`).
        let mut took = 0;
        if let Some(b) = backend.as_deref_mut() {
            let warm = Instant::now();
            loop {
                time(&mut back_s, body, true, Some(&mut *b))?;
                if warm.elapsed().as_secs_f64() >= BACKEND_WARMUP_SECONDS {
                    break;
                }
            }
            for _ in 0..repeats.max(1) {
                let mut counted = Counted { inner: b, took: 0 };
                g.push(time(&mut back_s, body, true, Some(&mut counted))?);
                took += counted.took;
            }
        }
        out.push(ComplianceTiming {
            contacts: n,
            dense_rows: median(d),
            factorized_cold: median(c),
            factorized_warm: median(w),
            exact: median(e),
            backend_builds: (took, g.len()),
            backend: (!g.is_empty()).then(|| median(g)),
        });
        progress(n);
    }
    Ok(out)
}
