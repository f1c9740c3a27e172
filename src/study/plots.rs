//! The study's figures (PNG, plotters' bitmap backend). The font comes with
//! the build (`epaint_default_fonts`' Ubuntu Light), so no system font is
//! needed.
//!
//! - `fig3_error.png` (and `cataract_error.png`): RMS error over time, log scale;
//! - `pareto.png` (and `cataract_pareto.png`): mean RMS error against
//!   ms/step, log–log, points labelled, front highlighted;
//! - `fig4_compliance.png`: compliance build time against contacts;
//! - `growth.png`: step and factorization time against nodes, log–log.

use std::path::Path;
use std::sync::Once;

use plotters::coord::{CoordTranslate, Shift};
use plotters::prelude::*;

use super::full::{Fig4, StudyReport};
use super::{CaseResult, PARETO_MAX_PENETRATION, knee, pareto_front};
use crate::error::{Result, SoftTissueError};

/// Errors below this are drawn at this value on log scales (the `exact`
/// rerun's error is zero).
pub const LOG_FLOOR: f64 = 1e-16;

const SIZE: (u32, u32) = (1100, 700);

/// Width of the Pareto figure's key, pixels.
const KEY_WIDTH: u32 = 260;

fn pe(e: impl std::fmt::Display) -> SoftTissueError {
    SoftTissueError::Study(format!("drawing a figure: {e}"))
}

fn font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // Fails only on a malformed font, which the bundled one is not;
        // without it text is left out, and the figures are still drawn.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            epaint_default_fonts::UBUNTU_LIGHT,
        );
    });
}

fn area(path: &Path) -> Result<DrawingArea<BitMapBackend<'_>, Shift>> {
    let root = BitMapBackend::new(path, SIZE).into_drawing_area();
    root.fill(&WHITE).map_err(pe)?;
    Ok(root)
}

fn log_range(v: impl Iterator<Item = f64>) -> std::ops::Range<f64> {
    let (lo, hi) = v
        .filter(|x| x.is_finite())
        .map(|x| x.max(LOG_FLOOR))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
            (a.min(x), b.max(x))
        });
    if !lo.is_finite() {
        return 1e-12..1.0;
    }
    let lo = 10f64.powf(lo.log10().floor());
    let hi = 10f64.powf(hi.log10().ceil()).max(lo * 10.0);
    lo..hi
}

/// Error over time of every variant (first repeat), log scale.
pub fn error_over_time(case: &CaseResult, path: &Path) -> Result<()> {
    font();
    let root = area(path)?;
    let t_end = case.reference.steps.len() as f64 * case.timestep;
    let y = log_range(
        case.runs
            .iter()
            .flat_map(|r| r.steps.iter().map(|s| s.rms_error)),
    );
    let caption = format!(
        "{}: RMS node error against the exact reference (0 drawn at {LOG_FLOOR:.0e})",
        case.scene
    );
    let mut chart = frame(&root, caption, 24)
        .build_cartesian_2d(0.0..t_end.max(1e-9), y.log_scale())
        .map_err(pe)?;
    chart
        .configure_mesh()
        .x_desc("time (s)")
        .y_desc("RMS error (m)")
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .draw()
        .map_err(pe)?;
    for (i, r) in case.runs.iter().filter(|r| r.repeat == 0).enumerate() {
        let color = Palette99::pick(i).to_rgba();
        let pts: Vec<(f64, f64)> = r
            .steps
            .iter()
            .map(|s| {
                (
                    (s.step + 1) as f64 * case.timestep,
                    s.rms_error.max(LOG_FLOOR),
                )
            })
            .collect();
        chart
            .draw_series(LineSeries::new(pts, color.stroke_width(2)))
            .map_err(pe)?
            .label(r.variant.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
    }
    legend(&mut chart, SeriesLabelPosition::LowerRight, 13)?;
    root.present().map_err(pe)
}

/// Mean RMS error against ms/step, log–log, front highlighted. The `exact`
/// rerun (error zero by construction) is named in the caption, not drawn;
/// variants that leave more than [`PARETO_MAX_PENETRATION`] are hollow and
/// off the front. Labels that would overlap a drawn label are left out.
pub fn pareto(case: &CaseResult, path: &Path) -> Result<()> {
    font();
    let root = area(path)?;
    // The chart on the left, a key of every point on the right.
    let (plot, key) = root.split_horizontally(SIZE.0 - KEY_WIDTH);
    let all = case.summaries();
    let exact_ms = all
        .iter()
        .find(|s| s.variant == "exact")
        .map(|s| s.ms_per_step);
    let ok: Vec<_> = all
        .into_iter()
        .filter(|s| {
            s.variant != "exact"
                && s.failure.is_none()
                && s.rms_error_mean.is_finite()
                && s.ms_per_step > 0.0
        })
        .collect();
    let pts: Vec<(f64, f64)> = ok
        .iter()
        .map(|s| (s.ms_per_step, s.rms_error_mean.max(LOG_FLOOR)))
        .collect();
    let valid: Vec<usize> = (0..ok.len())
        .filter(|&i| ok[i].max_penetration <= PARETO_MAX_PENETRATION)
        .collect();
    let vpts: Vec<(f64, f64)> = valid.iter().map(|&i| pts[i]).collect();
    let front: Vec<usize> = pareto_front(&vpts).into_iter().map(|k| valid[k]).collect();
    let k = knee(&pts, &front);
    let x = log_range(pts.iter().map(|p| p.0));
    let y = log_range(pts.iter().map(|p| p.1));
    let caption = format!(
        "{}: accuracy against time (front in red{})",
        case.scene,
        exact_ms.map_or(String::new(), |m| format!(
            "; exact rerun: {m:.1} ms, error 0"
        ))
    );
    let mut chart = frame(&plot, caption, 20)
        .build_cartesian_2d(x.clone().log_scale(), y.clone().log_scale())
        .map_err(pe)?;
    chart
        .configure_mesh()
        .x_desc("ms per step")
        .y_desc("mean RMS error (m)")
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .draw()
        .map_err(pe)?;
    chart
        .draw_series(LineSeries::new(
            front.iter().map(|&i| pts[i]),
            RED.stroke_width(2),
        ))
        .map_err(pe)?;
    // Every point is numbered (short labels, so that a cluster stays
    // readable); the key names each number. Hollow: more penetration than
    // the front admits.
    for (i, &p) in pts.iter().enumerate() {
        let color = if front.contains(&i) { RED } else { BLUE };
        let dot = if ok[i].max_penetration <= PARETO_MAX_PENETRATION {
            Circle::new((0, 0), 5, color.filled())
        } else {
            Circle::new((0, 0), 5, color.stroke_width(2))
        };
        let label = Text::new(format!("{}", i + 1), (6, -14), ("sans-serif", 12));
        chart
            .draw_series(std::iter::once(EmptyElement::at(p) + dot + label))
            .map_err(pe)?;
    }
    let line = 15;
    let text = |s: String, row: i32, color: RGBColor| {
        Text::new(
            s,
            (8, 40 + row * line),
            ("sans-serif", 12).into_font().color(&color),
        )
    };
    key.draw(&text("key (red: on the front)".into(), 0, BLACK))
        .map_err(pe)?;
    for (i, s) in ok.iter().enumerate() {
        let color = if front.contains(&i) { RED } else { BLUE };
        let mut name = format!("{:>2} {}", i + 1, s.variant);
        if Some(i) == k {
            name.push_str(" (knee)");
        }
        if s.max_penetration > PARETO_MAX_PENETRATION {
            name.push_str(" (penetrates)");
        }
        key.draw(&text(name, i as i32 + 1, color)).map_err(pe)?;
    }
    root.present().map_err(pe)
}

fn frame<'a, 'b, DB: DrawingBackend>(
    root: &'a DrawingArea<DB, Shift>,
    caption: impl AsRef<str>,
    size: u32,
) -> ChartBuilder<'a, 'b, DB> {
    let mut b = ChartBuilder::on(root);
    b.caption(caption, ("sans-serif", size))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(80);
    b
}

/// The legend box at `pos` with labels of `size` points.
fn legend<'a, DB, CT>(
    chart: &mut ChartContext<'a, DB, CT>,
    pos: SeriesLabelPosition,
    size: u32,
) -> Result<()>
where
    DB: DrawingBackend + 'a,
    CT: CoordTranslate,
{
    chart
        .configure_series_labels()
        .position(pos)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", size))
        .draw()
        .map_err(pe)
}

/// Lines with dots and a legend entry each; empty series are left out.
fn draw_lines<'a, DB, CT>(
    chart: &mut ChartContext<'a, DB, CT>,
    series: Vec<(&str, Vec<(f64, f64)>)>,
) -> Result<()>
where
    DB: DrawingBackend + 'a,
    CT: CoordTranslate<From = (f64, f64)>,
{
    for (i, (name, pts)) in series.into_iter().enumerate() {
        if pts.is_empty() {
            continue;
        }
        let color = Palette99::pick(i).to_rgba();
        chart
            .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
            .map_err(pe)?
            .label(name)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
        chart
            .draw_series(pts.into_iter().map(|p| Circle::new(p, 4, color.filled())))
            .map_err(pe)?;
    }
    Ok(())
}

/// Fig. 4: compliance build time against contacts.
pub fn compliance(fig4: &Fig4, path: &Path) -> Result<()> {
    font();
    let root = area(path)?;
    let t = &fig4.timings;
    let x_end = t.iter().map(|c| c.contacts).max().unwrap_or(1) as f64 * 1.05;
    let y = log_range(t.iter().flat_map(|c| {
        [c.dense_rows, c.factorized_cold, c.factorized_warm, c.exact]
            .into_iter()
            .chain(c.backend)
    }));
    let caption = match &fig4.backend {
        Ok(name) => format!("Compliance build, 1183-node lens, friction on (GPU: {name})"),
        Err(why) => {
            format!("Compliance build, 1183-node lens, friction on (GPU not measured: {why})")
        }
    };
    let mut chart = frame(&root, caption, 20)
        .build_cartesian_2d(0.0..x_end, y.log_scale())
        .map_err(pe)?;
    chart
        .configure_mesh()
        .x_desc("contacts")
        .y_desc("build time (ms)")
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .draw()
        .map_err(pe)?;
    type Get = fn(&super::compliance::ComplianceTiming) -> Option<f64>;
    let series: [(&str, Get); 5] = [
        ("DenseRows (paper CPU)", |c| Some(c.dense_rows)),
        ("Factorized, new factor", |c| Some(c.factorized_cold)),
        ("Factorized, cached columns", |c| Some(c.factorized_warm)),
        ("Exact (factorize + build)", |c| Some(c.exact)),
        ("GPU", |c| c.backend),
    ];
    let lines = series
        .iter()
        .map(|(name, get)| {
            let pts = t
                .iter()
                .filter_map(|c| get(c).map(|v| (c.contacts as f64, v.max(LOG_FLOOR))))
                .collect();
            (*name, pts)
        })
        .collect();
    draw_lines(&mut chart, lines)?;
    legend(&mut chart, SeriesLabelPosition::UpperLeft, 14)?;
    root.present().map_err(pe)
}

/// Step and factorization time against nodes, log–log.
pub fn growth(report: &StudyReport, path: &Path) -> Result<()> {
    font();
    let root = area(path)?;
    let g = &report.growth;
    let x = log_range(g.iter().map(|p| p.nodes as f64));
    let y = log_range(g.iter().flat_map(|p| [p.step_ms, p.factor_ms]));
    let caption = match report.growth_exponent {
        Some(e) => format!("Cost against mesh size (step time ~ nodes^{e:.2})"),
        None => "Cost against mesh size".to_string(),
    };
    let mut chart = frame(&root, caption, 24)
        .build_cartesian_2d(x.log_scale(), y.log_scale())
        .map_err(pe)?;
    chart
        .configure_mesh()
        .x_desc("nodes")
        .y_desc("milliseconds")
        .draw()
        .map_err(pe)?;
    type Get = fn(&super::growth::GrowthPoint) -> f64;
    let series: [(&str, Get); 2] = [
        ("step (Async, no contacts)", |p| p.step_ms),
        ("one LDLT factorization", |p| p.factor_ms),
    ];
    let lines = series
        .iter()
        .map(|(name, get)| {
            let pts = g
                .iter()
                .map(|p| (p.nodes as f64, get(p).max(LOG_FLOOR)))
                .collect();
            (*name, pts)
        })
        .collect();
    draw_lines(&mut chart, lines)?;
    legend(&mut chart, SeriesLabelPosition::UpperLeft, 14)?;
    root.present().map_err(pe)
}

/// Draws every figure into `dir`; returns the file names written.
pub fn write_all(report: &StudyReport, dir: &Path) -> Result<Vec<&'static str>> {
    let mut out = Vec::new();
    error_over_time(&report.lens, &dir.join("fig3_error.png"))?;
    pareto(&report.lens, &dir.join("pareto.png"))?;
    out.extend(["fig3_error.png", "pareto.png"]);
    if let Some(c) = &report.cataract {
        error_over_time(c, &dir.join("cataract_error.png"))?;
        pareto(c, &dir.join("cataract_pareto.png"))?;
        out.extend(["cataract_error.png", "cataract_pareto.png"]);
    }
    compliance(&report.fig4, &dir.join("fig4_compliance.png"))?;
    growth(report, &dir.join("growth.png"))?;
    out.extend(["fig4_compliance.png", "growth.png"]);
    Ok(out)
}
