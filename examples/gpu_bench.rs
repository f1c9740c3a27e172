//! GPU against CPU compliance build time on the paper-size lens (1183 nodes),
//! with friction, for 30 … 260 contacts. Runs on Bevy's render device.
//!
//! ```text
//! cargo run --release --features gpu --example gpu_bench
//! cargo run --release --features gpu --example gpu_bench -- --walk pieces
//! cargo run --release --features gpu --example gpu_bench -- --idle-ms 300
//! ```
//! `--walk nodes|pieces|global` picks the forward kernel's walk (by nodes
//! in workgroup memory, the default; by pieces of supernodes in workgroup
//! memory; by nodes in global memory, the kernel for paths too long for
//! workgroup memory), `--piece-nodes N` the size of a piece;
//! `--upload-each` writes the factor to the device again before every GPU
//! build, as when each step brings a new factor; `--idle-ms N` lets the
//! device idle N ms before each GPU build, as between a scene's steps
//! (`--help` lists them).
//! On Mesa lavapipe (a CPU rasterizer) the numbers only show that the path
//! works; GPU timings need a real GPU.

use std::time::Instant;

use bevy::prelude::*;
use bevy::render::renderer::{RenderAdapterInfo, RenderDevice, RenderQueue};
use bevy_soft_tissue::contact::ComplianceBackend;
use bevy_soft_tissue::gpu::{ForwardWalk, GpuCompliance};
use bevy_soft_tissue::prelude::*;
mod common;
use bevy_soft_tissue::study::compliance::lens_with_factor;
use clap::Parser;
use common::bench::pole_contacts;

#[derive(Parser, Debug)]
#[command(about = "GPU against CPU compliance build time on the paper-size lens")]
struct Args {
    /// How the forward kernel walks the paths.
    #[arg(long, value_enum, default_value_t = Walk::Nodes)]
    walk: Walk,
    /// The most nodes in a piece (`--walk pieces`).
    #[arg(long, default_value_t = bevy_soft_tissue::gpu::MAX_PIECE_NODES)]
    piece_nodes: usize,
    /// Write the factor to the device again before every GPU build.
    #[arg(long)]
    upload_each: bool,
    /// Let the device idle this many milliseconds before each GPU build.
    #[arg(long, default_value_t = 0)]
    idle_ms: u64,
    /// After each row, this many more GPU builds back to back (no CPU build or
    /// idling between them), reported on a row of their own: the device's
    /// time when it is kept busy.
    #[arg(long, default_value_t = 0)]
    back_to_back: usize,
}

/// [`ForwardWalk`] on the command line.
#[derive(clap::ValueEnum, Clone, Copy, Debug)]
enum Walk {
    /// By nodes, in workgroup memory.
    Nodes,
    /// By pieces of supernodes, in workgroup memory.
    Pieces,
    /// By nodes, in global memory.
    Global,
}

/// The GPU builder's counters before a row's builds.
struct Counters {
    wait: f64,
    built: u64,
    paths: u64,
    depth: u64,
    span: f64,
    kernels: [f64; 3],
    timed: u64,
}

impl Counters {
    fn of(gpu: &GpuCompliance) -> Self {
        Self {
            wait: gpu.wait_seconds,
            built: gpu.built,
            paths: gpu.path_sum,
            depth: gpu.depth_sum,
            span: gpu.span_seconds,
            kernels: gpu.kernel_seconds,
            timed: gpu.timed,
        }
    }

    /// Prints a row: `label`, the CPU and GPU build times (ms; no CPU time
    /// and ratio for back-to-back rows), then per GPU build since `self`
    /// the device wait, path, depth and, where the device has timestamps,
    /// its busy span and kernel times.
    fn print_row(&self, gpu: &GpuCompliance, label: &str, cpu: Option<f64>, g: f64) {
        let builds = (gpu.built - self.built).max(1);
        let wait = (gpu.wait_seconds - self.wait) * 1e3 / builds as f64;
        let (c, ratio) = match cpu {
            Some(c) => (format!("{c:.3}"), format!("{:.2}", g / c)),
            None => ("-".into(), "-".into()),
        };
        print!(
            "{label:>8} {c:>14} {g:>10.3} {ratio:>10} {wait:>10.3} {:>10} {:>10}",
            (gpu.path_sum - self.paths) / builds,
            (gpu.depth_sum - self.depth) / builds
        );
        // The device's own timing of the same builds, where it has timestamps.
        let timed = (gpu.timed - self.timed) as f64;
        if timed > 0.0 {
            let per = |now: f64, then: f64| (now - then) * 1e3 / timed;
            print!(" {:>10.3}", per(gpu.span_seconds, self.span));
            for (now, then) in gpu.kernel_seconds.iter().zip(self.kernels) {
                print!(" {:>10.3}", per(*now, then));
            }
        }
        println!();
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> bevy_soft_tissue::error::Result<()> {
    let args = Args::parse();
    let mut app = App::new();
    if let Err(e) = bevy_soft_tissue::gpu::add_headless_render(&mut app, None) {
        eprintln!("gpu_bench: not measured: {e}");
        return Ok(());
    }
    app.finish();
    app.cleanup();
    let (Some(device), Some(queue)) = (
        app.world().get_resource::<RenderDevice>(),
        app.world().get_resource::<RenderQueue>(),
    ) else {
        eprintln!("no render device");
        return Ok(());
    };
    if let Some(info) = app.world().get_resource::<RenderAdapterInfo>() {
        println!("adapter: {} ({:?})", info.name, info.device_type);
    }
    let mut gpu = GpuCompliance::new(device.clone(), queue.clone(), 0);
    gpu.forward_walk = match args.walk {
        Walk::Pieces => ForwardWalk::Pieces,
        Walk::Nodes => ForwardWalk::Nodes,
        Walk::Global => ForwardWalk::Global,
    };
    gpu.piece_nodes = args.piece_nodes;
    let (upload_each, idle_ms) = (args.upload_each, args.idle_ms);
    if idle_ms > 0 {
        println!("the device idles {idle_ms} ms before each GPU build");
    }
    if upload_each {
        println!("the factor is written to the device again before every GPU build");
    }
    println!(
        "forward solves walked by {:?}{}",
        gpu.forward_walk,
        if gpu.forward_walk == ForwardWalk::Pieces {
            format!(" ({} nodes a piece at most)", gpu.piece_nodes)
        } else {
            String::new()
        }
    );
    // The paper-size lens; its factor is never refreshed, so every build uses the same one.
    let mut body = lens_with_factor(12)?;
    println!("compliance build time (ms, median of 5), friction on");
    if gpu.timestamps() {
        println!(
            "per GPU build, mean (ms): `wait` from submit to W mapped on the host; `busy` from the \
             first kernel's start to the last one's end on the device (timestamps); the kernels; `path` the longest path (nodes), `depth` the forward kernel's steps (pieces or nodes) along the deepest path, means over the builds; `upload` host time writing each factor (ms, mean per upload)"
        );
    } else {
        println!("(this device has no timestamp queries: no busy and kernel columns)");
    }
    println!(
        "{:>8} {:>14} {:>10} {:>10} {:>10} {:>10} {:>10} {:>10} {:>10} {:>10} {:>10}",
        "contacts",
        "CPU Factorized",
        "GPU",
        "GPU/CPU",
        "wait",
        "path",
        "depth",
        "busy",
        "forward",
        "gram",
        "contract"
    );
    for n in [30, 60, 90, 130, 260] {
        let cs = pole_contacts(&body, n, v3(0.0, 0.0, -1.0), 0.3);
        let (mut cpu_t, mut gpu_t) = (Vec::new(), Vec::new());
        let before = Counters::of(&gpu);
        for _ in 0..5 {
            // A new solver each time: no cached columns, W from the body's current factor.
            let build = |body: &mut DeformableBody,
                         gpu: Option<&mut GpuCompliance>|
             -> bevy_soft_tissue::error::Result<f64> {
                let mut s = ContactSolver::new(ContactSettings {
                    factor_reuse: 0,
                    ..Default::default()
                })?;
                s.set_contacts(&cs, &[&*body], 0.02)?;
                let t0 = Instant::now();
                let backend = gpu.map(|g| g as &mut dyn ComplianceBackend);
                s.build_compliance(&mut [body], PassKind::First, backend)?;
                Ok(t0.elapsed().as_secs_f64() * 1e3)
            };
            cpu_t.push(build(&mut body, None)?);
            if upload_each {
                gpu.invalidate_factors();
            }
            std::thread::sleep(std::time::Duration::from_millis(idle_ms));
            gpu_t.push(build(&mut body, Some(&mut gpu))?);
        }
        before.print_row(&gpu, &n.to_string(), Some(median(cpu_t)), median(gpu_t));
        if args.back_to_back > 0 {
            let before = Counters::of(&gpu);
            let mut s = ContactSolver::new(ContactSettings {
                factor_reuse: 0,
                ..Default::default()
            })?;
            s.set_contacts(&cs, &[&body], 0.02)?;
            let t0 = Instant::now();
            for _ in 0..args.back_to_back {
                s.build_compliance(&mut [&mut body], PassKind::First, Some(&mut gpu))?;
            }
            let g = t0.elapsed().as_secs_f64() * 1e3 / args.back_to_back as f64;
            before.print_row(&gpu, &format!("{n} b2b"), None, g);
        }
    }
    if gpu.uploads > 0 {
        println!(
            "factor uploads: {}, {:.3} ms each on the host{}",
            gpu.uploads,
            gpu.upload_seconds * 1e3 / gpu.uploads as f64,
            if gpu.forward_walk == ForwardWalk::Pieces {
                " (the pieces' inverses included)"
            } else {
                ""
            }
        );
    }
    Ok(())
}
