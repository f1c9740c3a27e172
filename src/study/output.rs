//! The study's tables and report: CSV files and `report.md` in an output
//! folder (with the `study` feature, `study::plots` adds the figures that
//! the report embeds).
//!
//! Files:
//! - `results.csv`: one row per scene and variant ([`super::VariantSummary`]);
//! - `timeseries.csv`: one row per scene, variant, repeat and step ([`super::StepRecord`]);
//! - `compliance.csv`: Fig. 4's build times;
//! - `growth.csv`: step time, factorization time and `nnz(L)` per resolution;
//! - `validation.csv`: the cantilever and Hertz errors;
//! - `report.md`.

use std::fmt::Write as _;
use std::path::Path;

use super::full::{Fig4, Machine, StudyReport};
use super::{CaseResult, PARETO_MAX_PENETRATION, PHASES, VariantSummary, knee, pareto_front};
use crate::error::{Result, SoftTissueError};

/// Every file [`write()`] creates (figures only with the `study` feature).
pub const FILES: [&str; 6] = [
    "results.csv",
    "timeseries.csv",
    "compliance.csv",
    "growth.csv",
    "validation.csv",
    "report.md",
];

fn io(path: &Path, e: std::io::Error) -> SoftTissueError {
    SoftTissueError::Study(format!("writing {}: {e}", path.display()))
}

fn put(dir: &Path, name: &str, text: &str) -> Result<()> {
    let p = dir.join(name);
    std::fs::write(&p, text).map_err(|e| io(&p, e))
}

/// Writes the tables, the figures (with the `study` feature) and the report
/// into `dir` (created if missing).
pub fn write(report: &StudyReport, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
    let cases: Vec<&CaseResult> = std::iter::once(&report.lens)
        .chain(report.cataract.as_ref())
        .collect();
    let mut s = String::from(
        "scene,variant,runs,ms_per_step,ms_min,ms_max,rms_error_mean,rms_error_mean_min,\
         rms_error_mean_max,rms_error_max,max_node_error,max_penetration,cg_iterations,\
         cg_unconverged,final_energy",
    );
    for p in PHASES {
        let _ = write!(s, ",ms_{p}");
    }
    s.push_str(",failure,stopped\n");
    for c in &cases {
        for v in c.summaries() {
            let _ = write!(
                s,
                "{},{},{},{:.4},{:.4},{:.4},{:.6e},{:.6e},{:.6e},{:.6e},{:.6e},{:.6e},{:.2},{},{:.6e}",
                c.scene,
                v.variant,
                v.runs,
                v.ms_per_step,
                v.ms_range.0,
                v.ms_range.1,
                v.rms_error_mean,
                v.rms_error_range.0,
                v.rms_error_range.1,
                v.rms_error_max,
                v.max_node_error,
                v.max_penetration,
                v.cg_iterations,
                v.cg_unconverged,
                v.final_energy
            );
            for p in v.phase_ms {
                let _ = write!(s, ",{p:.4}");
            }
            let clean = |t: &Option<String>| t.as_deref().unwrap_or("").replace([',', '\n'], ";");
            let _ = writeln!(s, ",{},{}", clean(&v.failure), clean(&v.stopped));
        }
    }
    put(dir, "results.csv", &s)?;

    let mut s = String::from(
        "scene,variant,repeat,step,t,rms_error,max_error,ms,cg_iterations,contacts,max_penetration,energy\n",
    );
    for c in &cases {
        for r in std::iter::once(&c.reference).chain(&c.runs) {
            for x in &r.steps {
                let _ = writeln!(
                    s,
                    "{},{},{},{},{:.5},{:.6e},{:.6e},{:.4},{},{},{:.6e},{:.6e}",
                    c.scene,
                    r.variant,
                    r.repeat,
                    x.step,
                    (x.step + 1) as f64 * c.timestep,
                    x.rms_error,
                    x.max_error,
                    x.ms,
                    x.cg_iterations,
                    x.contacts,
                    x.max_penetration,
                    x.energy
                );
            }
        }
    }
    put(dir, "timeseries.csv", &s)?;

    put(dir, "compliance.csv", &compliance_csv(&report.fig4))?;

    let mut s = String::from("cells,nodes,tets,nnz_l,factor_ms,step_ms,cg_iterations,factor_age\n");
    for g in &report.growth {
        let _ = writeln!(
            s,
            "{},{},{},{},{:.3},{:.4},{:.2},{:.2}",
            g.cells,
            g.nodes,
            g.tets,
            g.nnz_l,
            g.factor_ms,
            g.step_ms,
            g.cg_iterations,
            g.factor_age
        );
    }
    put(dir, "growth.csv", &s)?;

    let mut s = String::from("test,parameter,nodes,model,analytic,relative_error\n");
    for c in &report.cantilever {
        let _ = writeln!(
            s,
            "cantilever,cells_across={},{},{:.6e},{:.6e},{:.5}",
            c.cells_across, c.nodes, c.deflection, c.analytic, c.relative_error
        );
    }
    for p in &report.hertz.points {
        let _ = writeln!(
            s,
            "hertz,depth={:.2e},{},{:.6e},{:.6e},{:.5}",
            p.depth, report.hertz.nodes, p.force, p.analytic, p.relative_error
        );
    }
    put(dir, "validation.csv", &s)?;

    #[cfg(feature = "study")]
    let figures = super::plots::write_all(report, dir)?;
    #[cfg(not(feature = "study"))]
    let figures: Vec<&str> = Vec::new();
    put(dir, "report.md", &markdown(report, &figures))
}

/// Fig. 4's table as CSV (`compliance.csv`).
pub fn compliance_csv(fig4: &Fig4) -> String {
    let mut s = String::from(
        "contacts,rows,dense_rows_ms,factorized_cold_ms,factorized_warm_ms,exact_ms,backend_ms,\
         backend_built,backend_timed\n",
    );
    for t in &fig4.timings {
        let _ = writeln!(
            s,
            "{},{},{:.4},{:.4},{:.4},{:.4},{},{},{}",
            t.contacts,
            3 * t.contacts,
            t.dense_rows,
            t.factorized_cold,
            t.factorized_warm,
            t.exact,
            t.backend.map_or(String::new(), |b| format!("{b:.4}")),
            t.backend_builds.0,
            t.backend_builds.1
        );
    }
    s
}

/// Every file [`write_fig4`] creates (the figure only with the `study` feature).
pub const FIG4_FILES: [&str; 2] = ["compliance.csv", "fig4.md"];

/// Fig. 4 alone (`accuracy_study --fig4-only`), measured on `machine`:
/// `compliance.csv`, `fig4_compliance.png` (with the `study` feature) and
/// `fig4.md` into `dir` (created if missing).
pub fn write_fig4(fig4: &Fig4, machine: &Machine, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
    put(dir, "compliance.csv", &compliance_csv(fig4))?;
    #[cfg(feature = "study")]
    let figure = {
        super::plots::compliance(fig4, &dir.join("fig4_compliance.png"))?;
        true
    };
    #[cfg(not(feature = "study"))]
    let figure = false;
    let mut out = format!(
        "# Fig. 4 alone\n\nOn {} ({} cores).\n\n",
        machine.cpu, machine.cores
    );
    fig4_markdown(&mut out, fig4, figure);
    put(dir, "fig4.md", &out)
}

/// Fig. 4's table in Markdown (milliseconds; `–` where no backend was timed).
pub fn fig4_table(fig4: &Fig4) -> String {
    let mut out = String::from(
        "| contacts | DenseRows | Factorized (new factor) | Factorized (cached) | Exact | backend |\n\
         |---|---|---|---|---|---|\n",
    );
    for t in &fig4.timings {
        let _ = writeln!(
            out,
            "| {} | {:.3} | {:.3} | {:.3} | {:.3} | {} |",
            t.contacts,
            t.dense_rows,
            t.factorized_cold,
            t.factorized_warm,
            t.exact,
            t.backend.map_or("–".into(), |b| format!("{b:.3}"))
        );
    }
    out
}

/// Fig. 4's section of a report (`figure`: whether `fig4_compliance.png` was drawn).
fn fig4_markdown(out: &mut String, fig4: &Fig4, figure: bool) {
    let _ = write!(
        out,
        "## Fig. 4: compliance build time against contacts\n\nThe 1183-node lens, friction on \
         (3 rows per contact), median of repeats, milliseconds.\n\n{}",
        fig4_table(fig4)
    );
    match &fig4.backend {
        Ok(name) => {
            let _ = writeln!(
                out,
                "\nBackend: {name}, timed back to back after untimed builds (a device left idle \
                 lowers its clocks).\n"
            );
            for t in fig4
                .timings
                .iter()
                .filter(|t| t.backend_builds.0 < t.backend_builds.1)
            {
                let _ = writeln!(
                    out,
                    "At {} contacts the backend left {} of its {} timed builds to the CPU.\n",
                    t.contacts,
                    t.backend_builds.1 - t.backend_builds.0,
                    t.backend_builds.1
                );
            }
        }
        Err(why) => {
            let _ = writeln!(out, "\nGPU: not measured ({why}).\n");
        }
    }
    if let (Some(a), Some(b)) = (fig4.timings.first(), fig4.timings.last()) {
        let _ = writeln!(
            out,
            "`DenseRows` grows from {:.2} to {:.2} ms, `Factorized` with a new factor from {:.2} to {:.2} ms \
             and with cached columns from {:.3} to {:.3} ms between {} and {} contacts.\n",
            a.dense_rows,
            b.dense_rows,
            a.factorized_cold,
            b.factorized_cold,
            a.factorized_warm,
            b.factorized_warm,
            a.contacts,
            b.contacts
        );
    }
    if figure {
        let _ = writeln!(out, "![fig4](fig4_compliance.png)\n");
    }
}

fn summaries_ok(c: &CaseResult) -> Vec<VariantSummary> {
    c.summaries()
        .into_iter()
        .filter(|s| s.failure.is_none() && s.rms_error_mean.is_finite())
        .collect()
}

fn case_section(
    out: &mut String,
    c: &CaseResult,
    fig_error: &str,
    fig_pareto: &str,
    figures: &[&str],
) {
    let l = c.length_scale;
    let _ = writeln!(
        out,
        "{} nodes, h = {:.4} s, {} steps; errors are RMS node distances to the \
         reference (exact `LDLᵀ` every step, `Exact` compliance, CG and LCP to 1e-10), \
         also given relative to the length scale {:.2} mm.\n",
        c.nodes,
        c.timestep,
        c.reference.steps.len(),
        l * 1e3
    );
    let _ = writeln!(
        out,
        "| variant | runs | ms/step (range) | mean RMS error | relative | max RMS | max penetration | CG its | failure or stop |\n|---|---|---|---|---|---|---|---|---|"
    );
    let r =
        c.reference.steps.iter().map(|x| x.ms).sum::<f64>() / c.reference.steps.len().max(1) as f64;
    let _ = writeln!(out, "| reference | 1 | {r:.2} | 0 | 0 | 0 | | | |");
    for s in c.summaries() {
        let _ = writeln!(
            out,
            "| {} | {} | {:.2} ({:.2}–{:.2}) | {:.3e} m | {:.2e} | {:.3e} m | {:.2} µm | {:.1} | {} |",
            s.variant,
            s.runs,
            s.ms_per_step,
            s.ms_range.0,
            s.ms_range.1,
            s.rms_error_mean,
            s.rms_error_mean / l,
            s.rms_error_max,
            s.max_penetration * 1e6,
            s.cg_iterations,
            s.failure.as_deref().or(s.stopped.as_deref()).unwrap_or("")
        );
    }
    let ok = summaries_ok(c);
    let mut order: Vec<&VariantSummary> = ok.iter().collect();
    order.sort_by(|a, b| b.rms_error_mean.total_cmp(&a.rms_error_mean));
    let names: Vec<String> = order
        .iter()
        .map(|s| format!("`{}` {:.2e}", s.variant, s.rms_error_mean))
        .collect();
    let _ = writeln!(
        out,
        "\nMeasured ordering of mean RMS error, largest first: {}.\n",
        names.join(" > ")
    );
    let get = |n: &str| ok.iter().find(|s| s.variant == n);
    if let (Some(a), Some(e)) = (get("async"), get("exact")) {
        let rest = get("rest_precomputed");
        let _ = writeln!(
            out,
            "`async`: {:.3} ms/step ({:.2}× less time than `exact`'s {:.3}), mean RMS error {:.3e} m \
             ({:.3} % of the length scale){}.\n",
            a.ms_per_step,
            e.ms_per_step / a.ms_per_step,
            e.ms_per_step,
            a.rms_error_mean,
            100.0 * a.rms_error_mean / l,
            rest.map_or(String::new(), |r| format!(
                ", {:.1}× below `rest_precomputed`'s {:.3e} m",
                r.rms_error_mean / a.rms_error_mean.max(1e-300),
                r.rms_error_mean
            ))
        );
    }
    // The front as `pareto.png` draws it: without the `exact` rerun and
    // without variants that leave more than 10 µm of penetration.
    let ok: Vec<VariantSummary> = ok
        .into_iter()
        .filter(|s| s.variant != "exact" && s.max_penetration <= PARETO_MAX_PENETRATION)
        .collect();
    let pts: Vec<(f64, f64)> = ok
        .iter()
        .map(|s| (s.ms_per_step, s.rms_error_mean.max(1e-16)))
        .collect();
    let front = pareto_front(&pts);
    let front_names: Vec<&str> = front.iter().map(|&i| ok[i].variant.as_str()).collect();
    let _ = writeln!(
        out,
        "Pareto front (cheapest first; the `exact` rerun and variants leaving more than 10 µm \
         of penetration left out): {}.",
        front_names.join(", ")
    );
    if let Some(k) = knee(&pts, &front) {
        let _ = writeln!(
            out,
            "Its knee is `{}` ({:.2} ms/step, {:.2e} m): past it, each further cut in error costs \
             the most time.\n",
            ok[k].variant, ok[k].ms_per_step, ok[k].rms_error_mean
        );
    }
    for f in [fig_error, fig_pareto] {
        if figures.contains(&f) {
            let _ = writeln!(out, "![{f}]({f})\n");
        }
    }
}

/// The report's Markdown.
pub fn markdown(r: &StudyReport, figures: &[&str]) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "# Accuracy against time\n\n{} study, {:.0} s on {} ({} cores).\n",
        if r.config.quick { "Quick" } else { "Full" },
        r.seconds,
        r.machine.cpu,
        r.machine.cores
    );
    let _ = writeln!(
        out,
        "Times are wall-clock on a shared machine: compare variants within one run. \
         `async` variants depend on thread timing and ran {} times (range in brackets); \
         `async_lag2` is the deterministic `AsyncLagged {{ lag: 2 }}`.\n",
        r.config.async_repeats
    );
    let _ = writeln!(out, "## Fig. 3: the lens pushed through a hole\n");
    case_section(&mut out, &r.lens, "fig3_error.png", "pareto.png", figures);
    if let Some(c) = &r.cataract {
        let _ = writeln!(out, "## The cataract push\n");
        case_section(
            &mut out,
            c,
            "cataract_error.png",
            "cataract_pareto.png",
            figures,
        );
    }
    fig4_markdown(&mut out, &r.fig4, figures.contains(&"fig4_compliance.png"));
    let _ = writeln!(
        out,
        "## Growth with the mesh\n\n| cells | nodes | nnz(L) | factorization ms | step ms | CG its | factor age |\n|---|---|---|---|---|---|---|"
    );
    for g in &r.growth {
        let _ = writeln!(
            out,
            "| {} | {} | {} | {:.1} | {:.2} | {:.1} | {:.1} |",
            g.cells, g.nodes, g.nnz_l, g.factor_ms, g.step_ms, g.cg_iterations, g.factor_age
        );
    }
    if let Some(p) = r.growth_exponent {
        let _ = writeln!(
            out,
            "\nStep time grows as nodes^{p:.2} (least squares on log–log).\n"
        );
    }
    if figures.contains(&"growth.png") {
        let _ = writeln!(out, "![growth](growth.png)\n");
    }
    let _ = writeln!(
        out,
        "## Validation\n\nCantilever (20 × 2 × 2 mm, E = 1 MPa, ν = 0.3, own weight) against \
         Euler–Bernoulli:\n\n| cells across | nodes | tip deflection | analytic | error |\n|---|---|---|---|---|"
    );
    for c in &r.cantilever {
        let _ = writeln!(
            out,
            "| {} | {} | {:.4e} m | {:.4e} m | {:.1} % |",
            c.cells_across,
            c.nodes,
            c.deflection,
            c.analytic,
            100.0 * c.relative_error
        );
    }
    let _ = writeln!(
        out,
        "\nHertz (rigid sphere R = 5 mm into a 20 × 20 × 10 mm block, E = 10 kPa, ν = 0.3; {} nodes, \
         cells {:.3} mm):\n\n| depth | force | Hertz | error |\n|---|---|---|---|",
        r.hertz.nodes,
        r.hertz.cell_size * 1e3
    );
    for p in &r.hertz.points {
        let _ = writeln!(
            out,
            "| {:.2} mm | {:.4e} N | {:.4e} N | {:.1} % |",
            p.depth * 1e3,
            p.force,
            p.analytic,
            100.0 * p.relative_error
        );
    }
    out
}
