//! GPU contact compliance (feature `gpu`): batched reach-restricted triangular
//! solves in a wgpu compute pass on Bevy's own `RenderDevice` and `RenderQueue`.
//!
//! [`GpuCompliance`] implements [`ComplianceBackend`] for bodies in
//! [`ComplianceMode::Factorized`](crate::contact::ComplianceMode::Factorized):
//!
//! - the body's `L` factor (3×3 node blocks, unit diagonal blocks, `D⁻¹`) is
//!   converted to `f32` and uploaded once per factor version, not every step;
//! - every step the contact nodes' elimination-tree paths and the Jacobian
//!   entries `j = Qᵀ h` (already in the factor's frame) are uploaded;
//! - `shaders/compliance.wgsl` runs three dispatches: one workgroup per contact
//!   node for the forward solves `Z_k = L⁻¹ E_k` along the node's path, one
//!   workgroup per node pair for the Gram blocks `Z_aᵀ D⁻¹ Z_b`, and one
//!   invocation per entry for `W = h² J G Jᵀ`;
//! - only `W` (rows of this body × rows of this body) is read back.
//!
//! The shader is embedded with `include_str!` (no asset loading needed, so
//! headless apps without an asset server work); it lives in `shaders/`.
//! Every GPU call runs inside a wgpu validation error scope: a validation
//! error becomes [`SoftTissueError::Gpu`] instead of a log line.
//!
//! [`GpuMode`] selects the path: off, always on, or automatic above a contact
//! count.

use std::collections::HashMap;

use bevy::render::renderer::{RenderDevice, RenderQueue};
use wgpu::util::DeviceExt;

use crate::contact::{ComplianceBackend, JacEntry};
use crate::error::{Result, SoftTissueError};
use crate::solver::ldlt::{LdltFactor, NONE};

pub use crate::plugin::GpuMode;

/// Adds the plugins of a windowless app with a render device (no window, no
/// camera rendering): enough for `Res<RenderDevice>` / `Res<RenderQueue>` in
/// main-world systems. `backends` restricts the wgpu backends (`None`: automatic).
/// Call `app.finish()` and `app.cleanup()` after adding the rest of the app.
pub fn add_headless_render(app: &mut bevy::app::App, backends: Option<wgpu::Backends>) {
    use bevy::render::settings::{RenderCreation, WgpuSettings};
    let mut settings = WgpuSettings::default();
    if backends.is_some() {
        settings.backends = backends;
    }
    app.add_plugins((
        bevy::MinimalPlugins,
        bevy::asset::AssetPlugin::default(),
        bevy::image::ImagePlugin::default(),
        bevy::mesh::MeshPlugin,
        bevy::camera::CameraPlugin,
        bevy::window::WindowPlugin {
            primary_window: None,
            exit_condition: bevy::window::ExitCondition::DontExit,
            ..Default::default()
        },
        bevy::render::RenderPlugin {
            render_creation: RenderCreation::Automatic(Box::new(settings)),
            synchronous_pipeline_compilation: true,
            ..Default::default()
        },
    ));
}

/// WGSL source of the compliance kernels.
pub const SHADER: &str = include_str!("../../shaders/compliance.wgsl");

struct Pipelines {
    forward: wgpu::ComputePipeline,
    gram: wgpu::ComputePipeline,
    contract: wgpu::ComputePipeline,
}

struct UploadedFactor {
    version: u64,
    n: u32,
    col_ptr: wgpu::Buffer,
    row_idx: wgpu::Buffer,
    lvals: wgpu::Buffer,
    ldiag: wgpu::Buffer,
    dinv: wgpu::Buffer,
}

/// The GPU compliance builder (a [`ComplianceBackend`]).
pub struct GpuCompliance {
    device: RenderDevice,
    queue: RenderQueue,
    pipelines: Option<Pipelines>,
    factors: HashMap<u64, UploadedFactor>,
    /// Which bodies and steps use the GPU.
    pub mode: GpuMode,
    /// Compute dispatches issued so far.
    pub dispatches: u64,
    /// Factor uploads so far.
    pub uploads: u64,
    /// Bodies whose `W` was built on the GPU in the last call.
    pub built: u64,
}

impl std::fmt::Debug for GpuCompliance {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuCompliance")
            .field("mode", &self.mode)
            .field("dispatches", &self.dispatches)
            .field("uploads", &self.uploads)
            .finish()
    }
}

fn gpu_err(e: impl std::fmt::Display) -> SoftTissueError {
    SoftTissueError::Gpu(e.to_string())
}

fn storage(device: &wgpu::Device, label: &str, bytes: &[u8]) -> wgpu::Buffer {
    // wgpu rejects zero-sized bindings: pad empty arrays to one word.
    let padded;
    let contents = if bytes.is_empty() {
        padded = [0u8; 4];
        &padded[..]
    } else {
        bytes
    };
    device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
    })
}

fn as_bytes<T: Copy>(v: &[T]) -> &[u8] {
    // SAFETY: only called with u32 / f32 slices (plain old data, no padding).
    unsafe { std::slice::from_raw_parts(v.as_ptr() as *const u8, std::mem::size_of_val(v)) }
}

impl GpuCompliance {
    /// A builder on Bevy's render device and queue.
    pub fn new(device: RenderDevice, queue: RenderQueue, mode: GpuMode) -> Self {
        Self {
            device,
            queue,
            pipelines: None,
            factors: HashMap::new(),
            mode,
            dispatches: 0,
            uploads: 0,
            built: 0,
        }
    }

    fn pipelines(&mut self) -> Result<&Pipelines> {
        if self.pipelines.is_none() {
            let device = self.device.wgpu_device();
            let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("soft_tissue_compliance"),
                source: wgpu::ShaderSource::Wgsl(SHADER.into()),
            });
            let make = |entry: &str| {
                device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(entry),
                    layout: None,
                    module: &module,
                    entry_point: Some(entry),
                    compilation_options: Default::default(),
                    cache: None,
                })
            };
            let p = Pipelines {
                forward: make("forward"),
                gram: make("gram_blocks"),
                contract: make("contract"),
            };
            if let Some(e) = bevy::tasks::block_on(scope.pop()) {
                return Err(gpu_err(format!("compliance shader: {e}")));
            }
            self.pipelines = Some(p);
        }
        self.pipelines
            .as_ref()
            .ok_or(SoftTissueError::Gpu("no pipelines".into()))
    }

    fn upload(&mut self, body_id: u64, f: &LdltFactor, version: u64) {
        if self
            .factors
            .get(&body_id)
            .is_some_and(|u| u.version == version)
        {
            return;
        }
        let s = &*f.symbolic;
        let device = self.device.wgpu_device();
        let col_ptr: Vec<u32> = s.col_ptr.iter().map(|&x| x as u32).collect();
        let row_idx: Vec<u32> = s.row_idx.iter().map(|&x| x as u32).collect();
        let lvals: Vec<f32> =
            f.l.iter()
                .flat_map(|m| m.iter().map(|&x| x as f32))
                .collect();
        let ldiag: Vec<f32> = f.ldiag.iter().flat_map(|d| d.map(|x| x as f32)).collect();
        let dinv: Vec<f32> =
            f.d.iter()
                .flat_map(|d| [1.0 / d.x, 1.0 / d.y, 1.0 / d.z].map(|x| x as f32))
                .collect();
        let up = UploadedFactor {
            version,
            n: s.n as u32,
            col_ptr: storage(device, "col_ptr", as_bytes(&col_ptr)),
            row_idx: storage(device, "row_idx", as_bytes(&row_idx)),
            lvals: storage(device, "lvals", as_bytes(&lvals)),
            ldiag: storage(device, "ldiag", as_bytes(&ldiag)),
            dinv: storage(device, "dinv", as_bytes(&dinv)),
        };
        self.factors.insert(body_id, up);
        self.uploads += 1;
    }

    /// Forgets uploaded factors of bodies not in `alive`.
    pub fn retain_bodies(&mut self, alive: &[u64]) {
        self.factors.retain(|id, _| alive.contains(id));
    }

    /// Computes this body's `W` block on the GPU; returns `(rows, w)` with
    /// `w` row-major over the listed global rows.
    pub fn compute(
        &mut self,
        body_id: u64,
        factor: &LdltFactor,
        version: u64,
        h: f64,
        entries: &[JacEntry],
    ) -> Result<(Vec<usize>, Vec<f32>)> {
        self.pipelines()?;
        self.upload(body_id, factor, version);
        let s = &*factor.symbolic;
        // Contact nodes (entries are sorted by node) and their paths.
        let mut nodes: Vec<u32> = entries.iter().map(|e| e.node).collect();
        nodes.dedup();
        let k = nodes.len();
        let mut path_lists = Vec::with_capacity(k);
        let mut longest = 0;
        for &node in &nodes {
            let mut p = Vec::new();
            let mut j = s.iperm[node as usize];
            while j != NONE {
                p.push(j as u32);
                j = s.parent[j];
            }
            longest = longest.max(p.len());
            path_lists.push(p);
        }
        let stride = longest + 1;
        let mut paths = vec![0u32; k * stride];
        for (c, p) in path_lists.iter().enumerate() {
            paths[c * stride] = p.len() as u32;
            paths[c * stride + 1..c * stride + 1 + p.len()].copy_from_slice(p);
        }
        // Local rows and their entries (contact-node index + j).
        let mut rows: Vec<usize> = entries.iter().map(|e| e.row as usize).collect();
        rows.sort_unstable();
        rows.dedup();
        let m = rows.len();
        let mut by_row: Vec<(usize, u32, [f32; 3])> = entries
            .iter()
            .map(|e| {
                let local_row = rows.binary_search(&(e.row as usize)).unwrap_or(0);
                let c = nodes.binary_search(&e.node).unwrap_or(0) as u32;
                (local_row, c, [e.j.x as f32, e.j.y as f32, e.j.z as f32])
            })
            .collect();
        by_row.sort_by_key(|e| e.0);
        let mut row_ptr = vec![0u32; m + 1];
        for e in &by_row {
            row_ptr[e.0 + 1] += 1;
        }
        for r in 0..m {
            row_ptr[r + 1] += row_ptr[r];
        }
        let ent_node: Vec<u32> = by_row.iter().map(|e| e.1).collect();
        let ent_j: Vec<f32> = by_row.iter().flat_map(|e| e.2).collect();

        let up = self
            .factors
            .get(&body_id)
            .ok_or(SoftTissueError::Gpu("factor not uploaded".into()))?;
        let n = up.n;
        let device = self.device.wgpu_device();
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let mut params = [0u32; 8];
        params[0] = n;
        params[1] = k as u32;
        params[2] = stride as u32;
        params[3] = m as u32;
        params[4] = ((h * h) as f32).to_bits();
        let params = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("params"),
            contents: as_bytes(&params),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let paths_buf = storage(device, "paths", as_bytes(&paths));
        let zeros = |label: &str, floats: usize| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: (floats.max(1) * 4) as u64,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            })
        };
        let z = zeros("z", k * stride * 9);
        let work = zeros("work", k * n as usize * 9);
        let gram = zeros("gram", k * k * 9);
        let w = zeros("w", m * m);
        let row_ptr_buf = storage(device, "row_ptr", as_bytes(&row_ptr));
        let ent_node_buf = storage(device, "ent_node", as_bytes(&ent_node));
        let ent_j_buf = storage(device, "ent_j", as_bytes(&ent_j));
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("w_readback"),
            size: (m.max(1) * m.max(1) * 4) as u64,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let pl = self
            .pipelines
            .as_ref()
            .ok_or(SoftTissueError::Gpu("no pipelines".into()))?;
        let bind = |pipeline: &wgpu::ComputePipeline, entries: &[(u32, &wgpu::Buffer)]| {
            let e: Vec<wgpu::BindGroupEntry> = entries
                .iter()
                .map(|(b, buf)| wgpu::BindGroupEntry {
                    binding: *b,
                    resource: buf.as_entire_binding(),
                })
                .collect();
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &pipeline.get_bind_group_layout(0),
                entries: &e,
            })
        };
        let bg_forward = bind(
            &pl.forward,
            &[
                (0, &params),
                (1, &up.col_ptr),
                (2, &up.row_idx),
                (3, &up.lvals),
                (4, &up.ldiag),
                (5, &paths_buf),
                (6, &z),
                (7, &work),
            ],
        );
        let bg_gram = bind(
            &pl.gram,
            &[
                (0, &params),
                (5, &paths_buf),
                (6, &z),
                (8, &up.dinv),
                (9, &gram),
            ],
        );
        let bg_contract = bind(
            &pl.contract,
            &[
                (0, &params),
                (9, &gram),
                (10, &row_ptr_buf),
                (11, &ent_node_buf),
                (12, &ent_j_buf),
                (13, &w),
            ],
        );
        let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("soft_tissue_compliance"),
        });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("soft_tissue_compliance"),
                timestamp_writes: None,
            });
            if k > 0 {
                pass.set_pipeline(&pl.forward);
                pass.set_bind_group(0, &bg_forward, &[]);
                pass.dispatch_workgroups(k as u32, 1, 1);
                pass.set_pipeline(&pl.gram);
                pass.set_bind_group(0, &bg_gram, &[]);
                pass.dispatch_workgroups(k as u32, k as u32, 1);
            }
            if m > 0 {
                pass.set_pipeline(&pl.contract);
                pass.set_bind_group(0, &bg_contract, &[]);
                pass.dispatch_workgroups(((m * m) as u32).div_ceil(64), 1, 1);
            }
        }
        enc.copy_buffer_to_buffer(&w, 0, &readback, 0, (m.max(1) * m.max(1) * 4) as u64);
        self.queue.submit([enc.finish()]);
        self.dispatches += 3;
        let slice = readback.slice(..);
        let (tx, rx) = crossbeam::channel::bounded(1);
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(gpu_err)?;
        if let Some(e) = bevy::tasks::block_on(scope.pop()) {
            return Err(gpu_err(format!("compliance dispatch: {e}")));
        }
        rx.recv().map_err(gpu_err)?.map_err(gpu_err)?;
        let out: Vec<f32> = {
            let data = slice.get_mapped_range();
            data.chunks_exact(4)
                .take(m * m)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect()
        };
        readback.unmap();
        Ok((rows, out))
    }
}

impl ComplianceBackend for GpuCompliance {
    fn accumulate(
        &mut self,
        body_id: u64,
        factor: &LdltFactor,
        factor_version: u64,
        h: f64,
        entries: &[JacEntry],
        w: &mut [f64],
        m: usize,
    ) -> Result<bool> {
        let contacts = entries
            .iter()
            .map(|e| e.row)
            .collect::<std::collections::BTreeSet<_>>()
            .len();
        let on = match self.mode {
            GpuMode::Off => false,
            GpuMode::On => true,
            GpuMode::Auto { min_rows } => contacts >= min_rows,
        };
        if !on {
            return Ok(false);
        }
        let (rows, block) = self.compute(body_id, factor, factor_version, h, entries)?;
        let k = rows.len();
        for (a, &ra) in rows.iter().enumerate() {
            for (b, &rb) in rows.iter().enumerate() {
                w[ra * m + rb] += block[a * k + b] as f64;
            }
        }
        self.built += 1;
        Ok(true)
    }
}
