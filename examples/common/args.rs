//! Command-line values shared by the examples (parsers for clap).

use bevy_soft_tissue::contact::LcpSolver;
use bevy_soft_tissue::solver::PreconditionerKind;

/// `none`, `jacobi`, `exact`, `async`, `lagN` (`AsyncLagged`: the factor
/// arrives exactly N steps after it was requested) or `periodicN`.
pub fn preconditioner(v: &str) -> Result<PreconditionerKind, String> {
    let whole = |s: &str| s.parse().map_err(|_| format!("bad preconditioner `{v}`"));
    Ok(match v {
        "none" => PreconditionerKind::None,
        "jacobi" => PreconditionerKind::Jacobi,
        "exact" => PreconditionerKind::Exact,
        "async" => PreconditionerKind::Async,
        p if p.starts_with("lag") => PreconditionerKind::AsyncLagged {
            lag: whole(&p[3..])?,
        },
        p if p.starts_with("periodic") => PreconditionerKind::Periodic {
            every: whole(&p[8..])?,
        },
        _ => return Err(format!("unknown preconditioner `{v}`")),
    })
}

/// The contact solver: `pgs`, `block`, `nncg` or `subspace` (`LcpSolver`).
pub fn lcp_solver(v: &str) -> Result<LcpSolver, String> {
    Ok(match v {
        "pgs" => LcpSolver::ProjectedGaussSeidel,
        "block" => LcpSolver::BlockGaussSeidel,
        "nncg" => LcpSolver::Nncg,
        "subspace" => LcpSolver::Subspace,
        _ => return Err(format!("unknown LCP solver `{v}`")),
    })
}

/// How the haptic thread runs, for the examples' output
/// (`HapticStats::realtime`).
pub fn priority(realtime: bool) -> &'static str {
    if realtime {
        "real-time priority"
    } else {
        "normal priority"
    }
}
