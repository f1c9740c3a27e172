//! The whole study in one call: the paper's experiment and the cataract
//! push with every standard variant, Fig. 4, growth and validation.

use std::time::Instant;

use super::cases::{CataractPush, LensThroughHole};
use super::compliance::{self, CONTACT_COUNTS, ComplianceTiming};
use super::growth::{self, GrowthPoint};
use super::validation::{self, CantileverPoint, HertzResult};
use super::{CaseResult, Progress, StudyScene, fit_power_law, run_case_within, variants};
use crate::contact::ComplianceBackend;
use crate::error::Result;

/// What to run.
#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    /// Coarse meshes and few steps (minutes on 2 cores) instead of the full study.
    pub quick: bool,
    /// Runs of the timing-dependent `async` variants.
    pub async_repeats: usize,
    /// Run the cataract push too.
    pub cataract: bool,
    /// Each variant run's time budget, as a multiple of its scene's
    /// reference run ([`super::run_case_within`]; `f64::INFINITY`: none).
    pub time_factor: f64,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            quick: false,
            async_repeats: 3,
            cataract: true,
            time_factor: super::DEFAULT_TIME_FACTOR,
        }
    }
}

impl Config {
    /// The paper's experiment at this config's size.
    pub fn lens_case(&self) -> LensThroughHole {
        if self.quick {
            LensThroughHole {
                cells: 8,
                steps: 60,
                ..Default::default()
            }
        } else {
            LensThroughHole::default()
        }
    }

    /// The cataract push at this config's size.
    pub fn cataract_case(&self) -> CataractPush {
        if self.quick {
            CataractPush {
                steps: 150,
                ..CataractPush::coarse()
            }
        } else {
            CataractPush::default()
        }
    }
}

/// The machine the study ran on.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Machine {
    /// CPU model (from `/proc/cpuinfo` where there is one).
    pub cpu: String,
    /// Logical cores available to the process.
    pub cores: usize,
}

impl Machine {
    /// This machine.
    pub fn detect() -> Self {
        let cpu = std::fs::read_to_string("/proc/cpuinfo")
            .ok()
            .and_then(|s| {
                s.lines()
                    .find(|l| l.starts_with("model name"))
                    .and_then(|l| l.split(':').nth(1))
                    .map(|m| m.trim().to_string())
            })
            .unwrap_or_else(|| "unknown".into());
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        Self { cpu, cores }
    }
}

/// Fig. 4: the compliance build time against contacts.
#[derive(Debug, Clone, PartialEq)]
pub struct Fig4 {
    /// Build times per contact count.
    pub timings: Vec<ComplianceTiming>,
    /// Name of the compliance backend (the GPU) timed beside the CPU modes,
    /// or why none was.
    pub backend: std::result::Result<String, String>,
}

/// Everything the study measured.
#[derive(Debug, Clone, PartialEq)]
pub struct StudyReport {
    /// The configuration.
    pub config: Config,
    /// The machine.
    pub machine: Machine,
    /// The paper's experiment.
    pub lens: CaseResult,
    /// The cataract push.
    pub cataract: Option<CaseResult>,
    /// Fig. 4.
    pub fig4: Fig4,
    /// Growth with the mesh.
    pub growth: Vec<GrowthPoint>,
    /// Fitted exponent of step time against nodes.
    pub growth_exponent: Option<f64>,
    /// Cantilever against Euler–Bernoulli.
    pub cantilever: Vec<CantileverPoint>,
    /// Hertz contact.
    pub hertz: HertzResult,
    /// Wall time of the whole study, seconds.
    pub seconds: f64,
}

/// Fig. 4 alone: the compliance build time against contacts for every CPU
/// mode and `backend` (the GPU, with its name, or why there is none), at
/// this config's size.
/// [`run`] calls it; `accuracy_study --fig4-only` runs only this (the part
/// worth running on a machine with a GPU).
pub fn fig4(
    config: &Config,
    backend: std::result::Result<(String, &mut dyn ComplianceBackend), String>,
    progress: &mut dyn FnMut(Progress),
) -> Result<Fig4> {
    let (counts, repeats): (&[usize], usize) = if config.quick {
        (&[30, 60, 90], 3)
    } else {
        (&CONTACT_COUNTS, 7)
    };
    progress(Progress::Start {
        label: "fig4 compliance",
        repeat: 0,
        steps: counts.len(),
    });
    let mut body = compliance::lens_with_factor(12)?;
    let (name, be) = match backend {
        Ok((n, b)) => (Ok(n), Some(b)),
        Err(why) => (Err(why), None),
    };
    let timings = compliance::timings(&mut body, counts, repeats, be, &mut |_| {
        progress(Progress::Step)
    })?;
    Ok(Fig4 {
        timings,
        backend: name,
    })
}

/// Runs the whole study. `backend` is the GPU (or other) compliance path to
/// time in Fig. 4 with its name, or why there is none.
pub fn run(
    config: &Config,
    backend: std::result::Result<(String, &mut dyn ComplianceBackend), String>,
    progress: &mut dyn FnMut(Progress),
) -> Result<StudyReport> {
    let t0 = Instant::now();
    let machine = Machine::detect();
    let opts = variants::Options {
        async_repeats: config.async_repeats,
        ..Default::default()
    };
    let case = |scene: &dyn StudyScene, progress: &mut dyn FnMut(Progress)| {
        let (b, c) = (scene.body_settings(), scene.contact_settings());
        run_case_within(
            scene,
            &variants::reference(b, c),
            &variants::standard(b, c, &opts),
            config.time_factor,
            progress,
        )
    };
    let lens = case(&config.lens_case(), progress)?;
    let cataract = if config.cataract {
        Some(case(&config.cataract_case(), progress)?)
    } else {
        None
    };

    let fig4 = fig4(config, backend, progress)?;

    let (cells, steps): (&[usize], usize) = if config.quick {
        (&[6, 8, 10, 12], 10)
    } else {
        (&[10, 14, 20, 26, 31], 30)
    };
    progress(Progress::Start {
        label: "growth",
        repeat: 0,
        steps: cells.len(),
    });
    let growth = growth::measure(cells, steps, &mut |_| progress(Progress::Step))?;
    let growth_exponent = fit_power_law(
        &growth
            .iter()
            .map(|g| (g.nodes as f64, g.step_ms))
            .collect::<Vec<_>>(),
    )
    .map(|f| f.0);

    progress(Progress::Start {
        label: "validation",
        repeat: 0,
        steps: 2,
    });
    let cantilever = validation::cantilever(if config.quick { &[1, 2, 3] } else { &[2, 4, 8] })?;
    progress(Progress::Step);
    let hertz = validation::hertz(if config.quick { 12 } else { 32 })?;
    progress(Progress::Step);
    Ok(StudyReport {
        config: config.clone(),
        machine,
        lens,
        cataract,
        fig4,
        growth,
        growth_exponent,
        cantilever,
        hertz,
        seconds: t0.elapsed().as_secs_f64(),
    })
}
