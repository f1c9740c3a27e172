//! The reference and the standard list of variants.
//!
//! Every variant starts from the scene's own settings
//! ([`super::StudyScene::body_settings`], [`super::StudyScene::contact_settings`])
//! and changes only the knobs it is named after. Names are the `variant`
//! column of the study's tables:
//!
//! | name | preconditioner | compliance | other |
//! |---|---|---|---|
//! | `exact` | `Exact` (every step) | `Exact` | CG and LCP to 1e-10: the reference rerun |
//! | `diagonal` | `Async` | `Diagonal` | |
//! | `rest_precomputed` | `Async` | `RestPrecomputed` | the paper's "no update" |
//! | `periodic1`, `periodic4`, `periodic16` | `Periodic` | `Factorized` | |
//! | `async` | `Async` | `Factorized` | back to back, repeated |
//! | `async_realtime` | `Async` | `Factorized` | paced at `h` per step, repeated |
//! | `async_lag2` | `AsyncLagged { lag: 2 }` | `Factorized` | deterministic |
//! | `async_cg1e-4`, `…1e-6`, `…1e-8` | `Async` | `Factorized` | CG tolerance |
//! | `async_lcp1e-4`, `async_lcp1e-6` | `Async` | `Factorized` | LCP residual tolerance |
//! | `async_lcp_pgs` | `Async` | `Factorized` | projected Gauss–Seidel LCP (≤ 500 sweeps) |
//! | `async_lcp_reference` | `Async` | `Factorized` | the reference's LCP: 1e-10, up to 5000 sweeps |
//! | `async_passes1` | `Async` | `Factorized` | one contact pass |
//! | `async_no_predict` | `Async` | `Factorized` | contacts detected at the free motion |
//! | `async_no_consistency` | `Async` | `Factorized` | no consistency refresh (`consistency_tolerance = ∞`) |
//! | `async_reuse4`, `async_reuse8` | `Async` | `Factorized` | `factor_reuse` |

use super::{Pacing, Variant};
use crate::body::BodySettings;
use crate::contact::{ComplianceMode, ContactSettings, LcpSolver};
use crate::solver::PreconditionerKind;

/// Tolerance of the reference's CG and LCP.
pub const REFERENCE_TOLERANCE: f64 = 1e-10;

/// The reference: an exact `LDLᵀ` every step, `Exact` compliance, CG and
/// LCP to [`REFERENCE_TOLERANCE`], from the scene's settings.
pub fn reference(body: BodySettings, contact: ContactSettings) -> Variant {
    let mut b = body;
    b.preconditioner = PreconditionerKind::Exact;
    b.cg.tolerance = REFERENCE_TOLERANCE;
    b.cg.max_iterations = b.cg.max_iterations.max(1000);
    let mut c = contact;
    c.compliance = ComplianceMode::Exact;
    c.lcp.tolerance = REFERENCE_TOLERANCE;
    c.lcp.residual_tolerance = REFERENCE_TOLERANCE;
    c.lcp.max_iterations = c.lcp.max_iterations.max(5000);
    Variant::new("reference", b, c)
}

/// Which variants [`standard`] lists.
#[derive(Debug, Clone, PartialEq)]
pub struct Options {
    /// Runs of each `async` variant whose result depends on thread timing (≥ 1).
    pub async_repeats: usize,
    /// Include the knob sweeps on `async` (CG and LCP tolerance, passes,
    /// prediction, factor reuse).
    pub sweeps: bool,
    /// Include `rest_precomputed` (its dense inverse needs the body to have
    /// at most [`crate::contact::compliance::REST_PRECOMPUTED_MAX_NODES`] nodes).
    pub rest_precomputed: bool,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            async_repeats: 3,
            sweeps: true,
            rest_precomputed: true,
        }
    }
}

/// The standard variants from the scene's settings `body` and `contact`.
pub fn standard(body: BodySettings, contact: ContactSettings, opts: &Options) -> Vec<Variant> {
    let with = |name: &str,
                kind: PreconditionerKind,
                mode: ComplianceMode,
                edit: &dyn Fn(&mut BodySettings, &mut ContactSettings)| {
        let (mut b, mut c) = (body, contact);
        b.preconditioner = kind;
        c.compliance = mode;
        edit(&mut b, &mut c);
        Variant::new(name, b, c)
    };
    let none = |_: &mut BodySettings, _: &mut ContactSettings| {};
    let asy = PreconditionerKind::Async;
    let fac = ComplianceMode::Factorized;
    let mut exact = reference(body, contact);
    exact.name = "exact".into();
    let mut out = vec![
        exact,
        with("diagonal", asy, ComplianceMode::Diagonal, &none),
    ];
    if opts.rest_precomputed {
        out.push(with(
            "rest_precomputed",
            asy,
            ComplianceMode::RestPrecomputed,
            &none,
        ));
    }
    for every in [1, 4, 16] {
        out.push(with(
            &format!("periodic{every}"),
            PreconditionerKind::Periodic { every },
            fac,
            &none,
        ));
    }
    let repeats = opts.async_repeats.max(1);
    let mut a = with("async", asy, fac, &none);
    a.repeats = repeats;
    out.push(a.clone());
    a.name = "async_realtime".into();
    a.pacing = Pacing::RealTime;
    out.push(a);
    out.push(with(
        "async_lag2",
        PreconditionerKind::AsyncLagged { lag: 2 },
        fac,
        &none,
    ));
    if opts.sweeps {
        for (name, tol) in [
            ("async_cg1e-4", 1e-4),
            ("async_cg1e-6", 1e-6),
            ("async_cg1e-8", 1e-8),
        ] {
            out.push(with(name, asy, fac, &|b, _| b.cg.tolerance = tol));
        }
        for (name, tol) in [("async_lcp1e-4", 1e-4), ("async_lcp1e-6", 1e-6)] {
            out.push(with(name, asy, fac, &|_, c| c.lcp.residual_tolerance = tol));
        }
        // The projected Gauss–Seidel LCP of earlier releases, capped at 500 sweeps.
        out.push(with("async_lcp_pgs", asy, fac, &|_, c| {
            c.lcp.solver = LcpSolver::ProjectedGaussSeidel
        }));
        // The reference's LCP (tolerance and sweep cap) with the default
        // factor: what the LCP's own convergence costs in accuracy.
        out.push(with("async_lcp_reference", asy, fac, &|_, c| {
            c.lcp.tolerance = REFERENCE_TOLERANCE;
            c.lcp.residual_tolerance = REFERENCE_TOLERANCE;
            c.lcp.max_iterations = c.lcp.max_iterations.max(5000);
        }));
        out.push(with("async_passes1", asy, fac, &|_, c| c.max_passes = 1));
        out.push(with("async_no_predict", asy, fac, &|_, c| {
            c.predict = false
        }));
        out.push(with("async_no_consistency", asy, fac, &|_, c| {
            c.consistency_tolerance = f64::INFINITY
        }));
        for reuse in [4, 8] {
            out.push(with(&format!("async_reuse{reuse}"), asy, fac, &|_, c| {
                c.factor_reuse = reuse
            }));
        }
    }
    out
}
