//! GPU contact compliance (feature `gpu`): batched reach-restricted triangular
//! solves in a wgpu compute pass on Bevy's own `RenderDevice` and `RenderQueue`.
//!
//! [`GpuCompliance`] implements [`ComplianceBackend`] for bodies in
//! [`ComplianceMode::Factorized`](crate::contact::ComplianceMode::Factorized):
//!
//! - the body's `L` factor (3×3 node blocks, unit diagonal blocks, `D⁻¹`) is
//!   converted to `f32` (or taken from the preconditioner's `f32` copy) and
//!   written once per factor version, not every step, into device buffers
//!   the body keeps across versions; the symbolic arrays are written again
//!   only when the symbolic factorization changes;
//! - every step the contact nodes' elimination-tree paths and the Jacobian
//!   entries `j = Qᵀ h` (already in the factor's frame) are uploaded;
//! - `shaders/compliance.wgsl` runs three dispatches: one workgroup per contact
//!   node for the forward solves `Z_k = L⁻¹ E_k` along the node's path (in
//!   workgroup memory where every path fits, by nodes or by pieces of
//!   supernodes, see [`ForwardWalk`]), one workgroup per node pair for the
//!   Gram blocks `Z_aᵀ D⁻¹ Z_b`, and one invocation per entry for
//!   `W = h² J G Jᵀ`;
//! - only `W` (rows of this body × rows of this body) is read back.
//!
//! The shader is embedded with `include_str!` (no asset loading needed, so
//! headless apps without an asset server work); it lives in `shaders/`.
//! Every GPU call runs inside a wgpu validation error scope: a validation
//! error becomes [`SoftTissueError::Gpu`] instead of a log line.
//!
//! Device buffers persist between steps and grow (to the next power of two)
//! only when a step needs more; the host-side staging vectors are kept too,
//! so a step allocates nothing once the largest contact set has been seen.
//! Which bodies use the GPU is [`GpuCompliance::min_rows`] (the plugin sets it
//! from its `GpuMode`).
//!
//! [`GpuCompliance::wait_seconds`] and its siblings count where the time goes;
//! where the device has timestamp queries, [`GpuCompliance::kernel_seconds`]
//! and [`GpuCompliance::span_seconds`] give the device's own time of each
//! kernel (one compute pass per kernel, a timestamp at each pass's start and
//! end, read back behind `W`). On an NVIDIA H200 a build of the 1 183-node
//! lens waits 0.5–1.0 ms for 30–260 contacts, about half of it the forward
//! kernel: a walk of up to 273 levels (the longest path), one barrier a
//! level (every invocation solves the level's diagonal block itself). The
//! kernels do their 3×3 block arithmetic on WGSL's `mat3x3` values: with
//! the blocks in arrays indexed in loops the forward and Gram kernels ran
//! two to three times slower (the arrays likely left registers for local
//! memory). The
//! driver lowers the clocks under the scene's light, steady load (see
//! [`GpuMode`](crate::plugin::GpuMode)), and the kernels then take two to
//! four times longer.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

use bevy::render::renderer::{RenderDevice, RenderQueue};

use crate::contact::{ComplianceBackend, FactorKey, JacEntry};
use crate::error::{Result, SoftTissueError};
use crate::solver::ldlt::{LdltFactor, LdltSymbolic, NONE};

/// The wgpu backends a render app tries: `backends`, or without it Bevy's
/// own choice (`WGPU_BACKEND` from the environment, else all).
fn render_backends(backends: Option<wgpu::Backends>) -> wgpu::Backends {
    backends
        .or(bevy::render::settings::WgpuSettings::default().backends)
        .unwrap_or(wgpu::Backends::all())
}

/// Whether this machine has any GPU adapter (hardware or software, such as
/// Mesa lavapipe) on `backends` (`None`: those Bevy's render plugin would
/// try). Bevy panics when it finds no adapter, so probe with this before
/// adding a render device to an app; [`add_headless_render`] does.
pub fn adapter_available(backends: Option<wgpu::Backends>) -> bool {
    let backends = render_backends(backends);
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = backends;
    let instance = wgpu::Instance::new(desc);
    !bevy::tasks::block_on(instance.enumerate_adapters(backends)).is_empty()
}

/// [`adapter_available`] as a result: [`SoftTissueError::Gpu`], saying which
/// backends were tried and where a software adapter comes from, when there
/// is none.
pub fn probe_adapter(backends: Option<wgpu::Backends>) -> Result<()> {
    if adapter_available(backends) {
        return Ok(());
    }
    Err(SoftTissueError::Gpu(format!(
        "no GPU adapter on this machine (backends {:?}); Mesa lavapipe \
         (Debian/Ubuntu: mesa-vulkan-drivers) gives a software Vulkan device",
        render_backends(backends)
    )))
}

/// Adds the plugins of a windowless app with a render device (no window, no
/// camera rendering): enough for `Res<RenderDevice>` / `Res<RenderQueue>` in
/// main-world systems. `backends` restricts the wgpu backends (`None`: automatic).
/// Call `app.finish()` and `app.cleanup()` after adding the rest of the app.
///
/// # Errors
/// [`SoftTissueError::Gpu`] when no adapter exists on those backends
/// ([`probe_adapter`]); the app is then left unchanged (Bevy itself would
/// panic).
pub fn add_headless_render(
    app: &mut bevy::app::App,
    backends: Option<wgpu::Backends>,
) -> Result<()> {
    use bevy::render::settings::{RenderCreation, WgpuSettings};
    probe_adapter(backends)?;
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
    Ok(())
}

/// WGSL source of the compliance kernels.
pub const SHADER: &str = include_str!("../../shaders/compliance.wgsl");

/// The longest elimination-tree path the walks in workgroup memory
/// (`forward_pieces`, `forward_shared`) take (the shader's `MAXP`); builds
/// with a longer path use `forward`, in global memory.
pub const SHARED_FORWARD_MAX_PATH: usize = 320;

/// The most nodes in one piece of a supernode for
/// [`ForwardWalk::Pieces`] (the shader's `MAXPIECE`).
pub const MAX_PIECE_NODES: usize = 16;

/// How the forward kernel walks each contact node's elimination-tree path
/// (all three give the same `W`; paths longer than
/// [`SHARED_FORWARD_MAX_PATH`] nodes always take [`ForwardWalk::Global`]).
///
/// On an NVIDIA H200 (`gpu_bench`, the 1 183-node lens, one factor for every
/// build, 30–260 contacts) the forward kernel took 0.24–0.30 ms by nodes and
/// 0.16–0.19 ms by pieces, but writing a new factor cost the stepping thread
/// 0.33–0.36 ms by nodes and 0.94–1.15 ms by pieces (their inverses). In
/// the cataract scene nearly every build brings a new factor, so nodes is
/// the default; pieces pays where a factor serves about ten builds or more
/// (a `Periodic` preconditioner, or `W` built from scratch several times
/// per factor).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ForwardWalk {
    /// In workgroup memory, one step per node (the default).
    #[default]
    Nodes,
    /// In workgroup memory, one step per piece of a supernode (a chain of
    /// nodes whose columns of `L` share their structure below the chain, at
    /// most [`GpuCompliance::piece_nodes`] nodes): the piece's unknowns come
    /// from one product with its inverted diagonal block, which the host
    /// computes and writes with each new factor. The lens's paths of
    /// 247–273 nodes take 27–40 such steps with pieces of 16 nodes.
    Pieces,
    /// In global memory, one step per node (needs a `k × n` work buffer).
    Global,
}

// `forward_shared`'s workgroup memory (three `u32` and nine `f32` per path
// node, `s_len` beside them) within WebGPU's minimum limit, and
// `forward_pieces`' (the same per path node, `s_len`, nine `f32` per piece
// node and `p_info`).
const _: () = assert!(SHARED_FORWARD_MAX_PATH * 4 * (3 + 9) + 4 <= 16_384);
const _: () =
    assert!(SHARED_FORWARD_MAX_PATH * 4 * (3 + 9) + 4 + MAX_PIECE_NODES * 36 + 16 <= 16_384);

struct Pipelines {
    forward: wgpu::ComputePipeline,
    forward_shared: wgpu::ComputePipeline,
    forward_pieces: wgpu::ComputePipeline,
    gram: wgpu::ComputePipeline,
    contract: wgpu::ComputePipeline,
}

/// A body's factor on the device. The buffers persist across factor versions
/// and grow only when a factor needs more; the symbolic arrays are written
/// again only when the symbolic factorization changes.
#[derive(Default)]
struct UploadedFactor {
    /// The factor version on the device (`None`: nothing written yet).
    key: Option<FactorKey>,
    symbolic: Option<Arc<LdltSymbolic>>,
    n: u32,
    col_ptr: GrowBuffer,
    row_idx: GrowBuffer,
    lvals: GrowBuffer,
    ldiag: GrowBuffer,
    dinv: GrowBuffer,
    /// Per node: its piece's first and last node and the offset of the
    /// piece's inverse (see [`piece_table`]), for `piece_nodes` nodes a
    /// piece at most.
    pieces: GrowBuffer,
    piece_table: Vec<u32>,
    piece_nodes: usize,
    /// The pieces' inverted diagonal blocks (see [`invert_pieces`]), and the
    /// factor version they were made from (`None`: none yet for this one).
    pinv: GrowBuffer,
    pinv_key: Option<FactorKey>,
    host_pinv: Vec<f32>,
    /// Host staging of the `f32` conversions, kept between versions.
    host_u32: Vec<u32>,
    host_f32: Vec<f32>,
    /// Scratch of the inversions (one piece's diagonal block).
    host_f64: Vec<f64>,
}

/// Splits the elimination tree's chains into pieces for
/// [`ForwardWalk::Pieces`]: node `j` continues the piece of `j − 1` when
/// column `j − 1`'s rows are `j` and then column `j`'s
/// ([`LdltSymbolic::joins_next`]) and the piece has fewer than `max_nodes`
/// nodes. Writes three entries per node into `table` (the
/// piece's first node, its last node, the offset of its inverse, `q²`
/// entries for `q = 3 ×` nodes) and returns the inverses' total length.
fn piece_table(s: &LdltSymbolic, max_nodes: usize, table: &mut Vec<u32>) -> usize {
    let n = s.n;
    table.clear();
    table.resize(3 * n, 0);
    let (mut start, mut offset) = (0, 0);
    for j in 0..n {
        let continues = s.joins_next(j) && j + 1 - start < max_nodes.max(1);
        if !continues {
            let q = 3 * (j + 1 - start);
            for t in &mut table[3 * start..3 * (j + 1)].chunks_exact_mut(3) {
                t.copy_from_slice(&[start as u32, j as u32, offset as u32]);
            }
            offset += q * q;
            start = j + 1;
        }
    }
    offset
}

/// Inverts each piece's diagonal block of the unit lower triangular `L`
/// (3×3 unit diagonal blocks, the piece's own off-diagonal blocks) into
/// `out` (row-major, `q × q` per piece at the offsets of `table`), in `f64`
/// then rounded. `scratch` holds one block.
fn invert_pieces(f: &LdltFactor, table: &[u32], out: &mut [f32], scratch: &mut Vec<f64>) {
    let s = &*f.symbolic;
    let mut a = 0;
    while a < s.n {
        let b = table[3 * a + 1] as usize;
        let off = table[3 * a + 2] as usize;
        let q = 3 * (b - a + 1);
        // T, the piece's block of L, row-major.
        scratch.clear();
        scratch.resize(2 * q * q, 0.0);
        let (t, x) = scratch.split_at_mut(q * q);
        for j in a..=b {
            let c0 = 3 * (j - a);
            let [l10, l20, l21] = f.ldiag[j];
            t[c0 * q + c0] = 1.0;
            t[(c0 + 1) * q + c0] = l10;
            t[(c0 + 1) * q + c0 + 1] = 1.0;
            t[(c0 + 2) * q + c0] = l20;
            t[(c0 + 2) * q + c0 + 1] = l21;
            t[(c0 + 2) * q + c0 + 2] = 1.0;
            // Column j's first entries are the piece's later nodes, in order.
            for i in j + 1..=b {
                let slot = s.col_ptr[j] + (i - j - 1);
                debug_assert_eq!(s.row_idx[slot], i);
                let l = &f.l[slot];
                let r0 = 3 * (i - a);
                for r in 0..3 {
                    for c in 0..3 {
                        t[(r0 + r) * q + c0 + c] = l[(r, c)];
                    }
                }
            }
        }
        // X = T⁻¹ row by row: X_r = e_r − Σ_{k<r} T_rk X_k (X unit lower).
        for r in 0..q {
            let (done, rest) = x.split_at_mut(r * q);
            let row = &mut rest[..q];
            row[r] = 1.0;
            for k in 0..r {
                let tk = t[r * q + k];
                if tk != 0.0 {
                    for (v, w) in row[..=k].iter_mut().zip(&done[k * q..=k * q + k]) {
                        *v -= tk * w;
                    }
                }
            }
        }
        for (o, v) in out[off..off + q * q].iter_mut().zip(x.iter()) {
            *o = *v as f32;
        }
        a = b + 1;
    }
}

/// A device buffer kept between steps, grown when a step needs more.
#[derive(Default)]
struct GrowBuffer {
    buf: Option<wgpu::Buffer>,
    size: u64,
}

impl GrowBuffer {
    /// The buffer, at least `bytes` long (at least 4: wgpu rejects empty bindings).
    fn ensure(
        &mut self,
        device: &wgpu::Device,
        label: &'static str,
        usage: wgpu::BufferUsages,
        bytes: u64,
    ) -> &wgpu::Buffer {
        let bytes = bytes.max(4);
        if self.buf.is_none() || self.size < bytes {
            let size = bytes.next_power_of_two();
            self.buf = Some(device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            }));
            self.size = size;
        }
        self.buf.as_ref().expect("created above")
    }

    /// The buffer, once created.
    fn get(&self) -> Result<&wgpu::Buffer> {
        self.buf
            .as_ref()
            .ok_or(SoftTissueError::Gpu("buffer not uploaded".into()))
    }
}

/// The per-step buffers, host and device.
#[derive(Default)]
struct StepBuffers {
    nodes: Vec<u32>,
    path: Vec<u32>,
    path_offsets: Vec<usize>,
    paths: Vec<u32>,
    rows: Vec<usize>,
    by_row: Vec<(usize, u32, [f32; 3])>,
    row_ptr: Vec<u32>,
    ent_node: Vec<u32>,
    ent_j: Vec<f32>,
    out: Vec<f32>,
    params: GrowBuffer,
    paths_buf: GrowBuffer,
    z: GrowBuffer,
    work: GrowBuffer,
    gram: GrowBuffer,
    w: GrowBuffer,
    row_ptr_buf: GrowBuffer,
    ent_node_buf: GrowBuffer,
    ent_j_buf: GrowBuffer,
    readback: GrowBuffer,
}

impl StepBuffers {
    /// The distinct constraint rows of `entries`, sorted, into `rows`.
    fn fill_rows(&mut self, entries: &[JacEntry]) {
        self.rows.clear();
        self.rows.extend(entries.iter().map(|e| e.row as usize));
        self.rows.sort_unstable();
        self.rows.dedup();
    }
}

/// The GPU compliance builder (a [`ComplianceBackend`]).
pub struct GpuCompliance {
    device: RenderDevice,
    queue: RenderQueue,
    pipelines: Option<Pipelines>,
    factors: HashMap<u64, UploadedFactor>,
    step: StepBuffers,
    /// The fewest constraint rows a body needs for its `W` to be built here;
    /// bodies with fewer are left to the CPU (0: every body).
    pub min_rows: usize,
    /// Compute dispatches issued so far.
    pub dispatches: u64,
    /// Factor uploads so far.
    pub uploads: u64,
    /// Bodies' `W` blocks built on the GPU so far (through
    /// [`ComplianceBackend::accumulate`]).
    pub built: u64,
    /// Seconds spent writing factors to the device (the `f32` conversion
    /// and the queue writes; the copy itself runs with the next submit).
    pub upload_seconds: f64,
    /// Seconds from submitting a build's dispatches until its `W` was mapped
    /// on the host: the GPU's work and the transfers, as the stepping thread
    /// waits for them.
    pub wait_seconds: f64,
    /// Seconds in [`Self::compute`] in all (host preparation, upload, wait and
    /// read-back).
    pub compute_seconds: f64,
    /// GPU time of the three kernels (forward, Gram blocks, contraction),
    /// seconds summed over the builds that were timed, from timestamps the
    /// device writes at each kernel's start and end. Zero where the device
    /// lacks `TIMESTAMP_QUERY` (see [`Self::timestamps`]).
    pub kernel_seconds: [f64; 3],
    /// GPU time from the first kernel's start to the last one's end, summed
    /// over the timed builds: the device's busy span. What
    /// [`Self::wait_seconds`] has beyond it is submission, scheduling, the
    /// read-back copy, the fence wait and the mapping.
    pub span_seconds: f64,
    /// Builds timed by the device's timestamps.
    pub timed: u64,
    /// How the forward kernel walks the paths (default
    /// [`ForwardWalk::Nodes`]; builds with a path longer than
    /// [`SHARED_FORWARD_MAX_PATH`] nodes walk in global memory whatever it says).
    pub forward_walk: ForwardWalk,
    /// The most nodes in a piece for [`ForwardWalk::Pieces`], 1 to
    /// [`MAX_PIECE_NODES`] (the default): a larger piece means fewer steps
    /// and a larger inverse to write with each factor (`q³/6` operations on
    /// the host for `q = 3 ×` nodes).
    pub piece_nodes: usize,
    /// Builds whose forward solves ran in workgroup memory (either walk).
    pub shared_forwards: u64,
    /// Builds whose forward solves walked by pieces.
    pub piece_forwards: u64,
    /// Each build's serial depth (the most steps any of its forward solves
    /// took: pieces for [`ForwardWalk::Pieces`], nodes otherwise), summed
    /// over the builds.
    pub depth_sum: u64,
    /// The longest elimination-tree path of any build so far (nodes): the
    /// forward kernel's serial depth.
    pub longest_path: usize,
    /// Each build's longest path (nodes), summed over the builds.
    pub path_sum: u64,
    timer: Option<Timer>,
}

/// The device's timestamp queries around each kernel of a build: six
/// timestamps (start and end of each kernel's pass) resolved into a buffer
/// that is copied behind `W` in the read-back.
struct Timer {
    queries: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    /// Nanoseconds per timestamp tick.
    period_ns: f64,
}

/// Timestamps per build (start and end of three kernels).
const TIMESTAMPS: u32 = 6;

impl std::fmt::Debug for GpuCompliance {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuCompliance")
            .field("min_rows", &self.min_rows)
            .field("dispatches", &self.dispatches)
            .field("uploads", &self.uploads)
            .field("upload_seconds", &self.upload_seconds)
            .field("wait_seconds", &self.wait_seconds)
            .field("compute_seconds", &self.compute_seconds)
            .field("kernel_seconds", &self.kernel_seconds)
            .field("span_seconds", &self.span_seconds)
            .field("timed", &self.timed)
            .field("forward_walk", &self.forward_walk)
            .field("shared_forwards", &self.shared_forwards)
            .field("piece_forwards", &self.piece_forwards)
            .finish()
    }
}

fn gpu_err(e: impl std::fmt::Display) -> SoftTissueError {
    SoftTissueError::Gpu(e.to_string())
}

const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_SRC)
    .union(wgpu::BufferUsages::COPY_DST);

/// Writes `data` into `buf` (grown as needed) and returns it.
fn upload<'a, T: bytemuck::Pod>(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    buf: &'a mut GrowBuffer,
    label: &'static str,
    usage: wgpu::BufferUsages,
    data: &[T],
) -> &'a wgpu::Buffer {
    let bytes: &[u8] = bytemuck::cast_slice(data);
    let b = buf.ensure(device, label, usage, bytes.len() as u64);
    if !bytes.is_empty() {
        queue.write_buffer(b, 0, bytes);
    }
    b
}

impl GpuCompliance {
    /// A builder on Bevy's render device and queue for bodies with at least
    /// `min_rows` constraint rows.
    pub fn new(device: RenderDevice, queue: RenderQueue, min_rows: usize) -> Self {
        let timer = device
            .features()
            .contains(wgpu::Features::TIMESTAMP_QUERY)
            .then(|| {
                let d = device.wgpu_device();
                Timer {
                    queries: d.create_query_set(&wgpu::QuerySetDescriptor {
                        label: Some("soft_tissue_compliance_timestamps"),
                        ty: wgpu::QueryType::Timestamp,
                        count: TIMESTAMPS,
                    }),
                    resolve: d.create_buffer(&wgpu::BufferDescriptor {
                        label: Some("soft_tissue_compliance_timestamps"),
                        size: u64::from(TIMESTAMPS) * 8,
                        usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                        mapped_at_creation: false,
                    }),
                    period_ns: f64::from(queue.get_timestamp_period()),
                }
            });
        Self {
            device,
            queue,
            timer,
            pipelines: None,
            factors: HashMap::new(),
            step: StepBuffers::default(),
            min_rows,
            dispatches: 0,
            uploads: 0,
            built: 0,
            upload_seconds: 0.0,
            wait_seconds: 0.0,
            compute_seconds: 0.0,
            kernel_seconds: [0.0; 3],
            span_seconds: 0.0,
            timed: 0,
            forward_walk: ForwardWalk::Nodes,
            piece_nodes: MAX_PIECE_NODES,
            shared_forwards: 0,
            piece_forwards: 0,
            depth_sum: 0,
            longest_path: 0,
            path_sum: 0,
        }
    }

    /// Whether the device times each build's kernels
    /// ([`Self::kernel_seconds`], [`Self::span_seconds`]): it has
    /// `TIMESTAMP_QUERY`, which Bevy's default settings enable where the
    /// adapter offers it.
    pub fn timestamps(&self) -> bool {
        self.timer.is_some()
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
                forward_shared: make("forward_shared"),
                forward_pieces: make("forward_pieces"),
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

    /// Writes the factor in `f32` to the device (once per factor key), into
    /// the body's persistent buffers.
    fn upload_factor(&mut self, body_id: u64, f: &LdltFactor, key: FactorKey) {
        if self
            .factors
            .get(&body_id)
            .is_some_and(|u| u.key == Some(key))
        {
            return;
        }
        let t0 = Instant::now();
        let s = &*f.symbolic;
        let device = self.device.wgpu_device();
        let queue: &wgpu::Queue = &self.queue;
        let up = self.factors.entry(body_id).or_default();
        up.key = Some(key);
        up.n = s.n as u32;
        // Each array through the kept host staging vector into its buffer.
        let (h32, f32s) = (&mut up.host_u32, &mut up.host_f32);
        let mut put = |buf: &mut GrowBuffer, label, values: &mut dyn Iterator<Item = f32>| {
            f32s.clear();
            f32s.extend(values);
            upload(device, queue, buf, label, STORAGE, f32s);
        };
        if !up
            .symbolic
            .as_ref()
            .is_some_and(|old| Arc::ptr_eq(old, &f.symbolic))
        {
            for (buf, label, values) in [
                (&mut up.col_ptr, "col_ptr", &s.col_ptr),
                (&mut up.row_idx, "row_idx", &s.row_idx),
            ] {
                h32.clear();
                h32.extend(values.iter().map(|&x| x as u32));
                upload(device, queue, buf, label, STORAGE, h32);
            }
            up.symbolic = Some(f.symbolic.clone());
            up.piece_nodes = 0;
        }
        // The preconditioner's single-precision copy where the factor has one.
        match f.l_single() {
            Some(l) => {
                upload(device, queue, &mut up.lvals, "lvals", STORAGE, l);
            }
            None => put(
                &mut up.lvals,
                "lvals",
                &mut f.l.iter().flat_map(|m| m.iter().map(|&x| x as f32)),
            ),
        }
        put(
            &mut up.ldiag,
            "ldiag",
            &mut f.ldiag.iter().flat_map(|d| d.map(|x| x as f32)),
        );
        put(
            &mut up.dinv,
            "dinv",
            &mut f
                .d
                .iter()
                .flat_map(|d| [1.0 / d.x, 1.0 / d.y, 1.0 / d.z].map(|x| x as f32)),
        );
        up.pinv_key = None;
        self.uploads += 1;
        self.upload_seconds += t0.elapsed().as_secs_f64();
    }

    /// Writes the piece table and the pieces' inverses of the uploaded
    /// factor `f` for [`ForwardWalk::Pieces`] (once per factor version and
    /// piece size; counted in [`Self::upload_seconds`]).
    fn upload_pieces(&mut self, body_id: u64, f: &LdltFactor) -> Result<()> {
        let piece_nodes = self.piece_nodes.clamp(1, MAX_PIECE_NODES);
        let up = self
            .factors
            .get_mut(&body_id)
            .ok_or(SoftTissueError::Gpu("factor not uploaded".into()))?;
        if up.pinv_key.is_some() && up.piece_nodes == piece_nodes {
            return Ok(());
        }
        let t0 = Instant::now();
        let device = self.device.wgpu_device();
        let queue: &wgpu::Queue = &self.queue;
        if up.piece_nodes != piece_nodes {
            let len = piece_table(&f.symbolic, piece_nodes, &mut up.piece_table);
            upload(
                device,
                queue,
                &mut up.pieces,
                "pieces",
                STORAGE,
                &up.piece_table,
            );
            up.piece_nodes = piece_nodes;
            up.host_pinv.clear();
            up.host_pinv.resize(len, 0.0);
        }
        invert_pieces(f, &up.piece_table, &mut up.host_pinv, &mut up.host_f64);
        upload(device, queue, &mut up.pinv, "pinv", STORAGE, &up.host_pinv);
        up.pinv_key = up.key;
        self.upload_seconds += t0.elapsed().as_secs_f64();
        Ok(())
    }

    /// Marks every uploaded factor stale: the next build of each body writes
    /// its factor again, into the same device buffers, as after a new factor
    /// from the worker (`gpu_bench --upload-each` times builds this way).
    pub fn invalidate_factors(&mut self) {
        for up in self.factors.values_mut() {
            up.key = None;
        }
    }

    /// Forgets uploaded factors of bodies not in `alive`.
    pub fn retain_bodies(&mut self, alive: &[u64]) {
        self.factors.retain(|id, _| alive.contains(id));
    }

    /// Computes this body's `W` block on the GPU; returns `(rows, w)` with
    /// `w` row-major over the listed global rows (both borrowed from the
    /// builder's persistent buffers, valid until the next call).
    pub fn compute(
        &mut self,
        body_id: u64,
        factor: &LdltFactor,
        key: FactorKey,
        h: f64,
        entries: &[JacEntry],
    ) -> Result<(&[usize], &[f32])> {
        self.step.fill_rows(entries);
        self.compute_rows_filled(body_id, factor, key, h, entries)
    }

    /// [`Self::compute`] with `self.step.rows` already filled from `entries`.
    fn compute_rows_filled(
        &mut self,
        body_id: u64,
        factor: &LdltFactor,
        key: FactorKey,
        h: f64,
        entries: &[JacEntry],
    ) -> Result<(&[usize], &[f32])> {
        let t0 = Instant::now();
        self.pipelines()?;
        self.upload_factor(body_id, factor, key);
        let s = &*factor.symbolic;
        let st = &mut self.step;
        // Contact nodes (entries are sorted by node) and their paths.
        st.nodes.clear();
        st.nodes.extend(entries.iter().map(|e| e.node));
        st.nodes.dedup();
        let k = st.nodes.len();
        st.path.clear();
        st.path_offsets.clear();
        let mut longest = 0;
        for &node in &st.nodes {
            let start = st.path.len();
            st.path_offsets.push(start);
            let mut j = s.iperm[node as usize];
            while j != NONE {
                st.path.push(j as u32);
                j = s.parent[j];
            }
            longest = longest.max(st.path.len() - start);
        }
        st.path_offsets.push(st.path.len());
        // The walk: by pieces or by nodes in workgroup memory where every
        // path fits, else in global memory; its serial depth.
        let walk = match self.forward_walk {
            _ if longest > SHARED_FORWARD_MAX_PATH => ForwardWalk::Global,
            w => w,
        };
        let depth = if walk == ForwardWalk::Pieces {
            self.upload_pieces(body_id, factor)?;
            let table = &self
                .factors
                .get(&body_id)
                .ok_or(SoftTissueError::Gpu("factor not uploaded".into()))?
                .piece_table;
            let st = &self.step;
            // A step per piece entered: at a path's first node or a piece's first.
            st.path_offsets
                .windows(2)
                .map(|w| {
                    let p = &st.path[w[0]..w[1]];
                    p.iter()
                        .enumerate()
                        .filter(|&(i, &j)| i == 0 || table[3 * j as usize] == j)
                        .count()
                })
                .max()
                .unwrap_or(0)
        } else {
            longest
        };
        let st = &mut self.step;
        let stride = longest + 1;
        st.paths.clear();
        st.paths.resize(k * stride, 0);
        for c in 0..k {
            let p = &st.path[st.path_offsets[c]..st.path_offsets[c + 1]];
            st.paths[c * stride] = p.len() as u32;
            st.paths[c * stride + 1..c * stride + 1 + p.len()].copy_from_slice(p);
        }
        // Local rows (filled by the caller) and their entries (contact-node index + j).
        let m = st.rows.len();
        st.by_row.clear();
        for e in entries {
            let local_row = st.rows.binary_search(&(e.row as usize)).unwrap_or(0);
            let c = st.nodes.binary_search(&e.node).unwrap_or(0) as u32;
            st.by_row
                .push((local_row, c, [e.j.x as f32, e.j.y as f32, e.j.z as f32]));
        }
        st.by_row.sort_by_key(|e| e.0);
        st.row_ptr.clear();
        st.row_ptr.resize(m + 1, 0);
        for e in &st.by_row {
            st.row_ptr[e.0 + 1] += 1;
        }
        for r in 0..m {
            st.row_ptr[r + 1] += st.row_ptr[r];
        }
        st.ent_node.clear();
        st.ent_node.extend(st.by_row.iter().map(|e| e.1));
        st.ent_j.clear();
        st.ent_j.extend(st.by_row.iter().flat_map(|e| e.2));

        let up = self
            .factors
            .get(&body_id)
            .ok_or(SoftTissueError::Gpu("factor not uploaded".into()))?;
        let n = up.n;
        let (col_ptr, row_idx, lvals, ldiag, dinv) = (
            up.col_ptr.get()?,
            up.row_idx.get()?,
            up.lvals.get()?,
            up.ldiag.get()?,
            up.dinv.get()?,
        );
        let device = self.device.wgpu_device();
        let queue: &wgpu::Queue = &self.queue;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let mut params = [0u32; 8];
        params[0] = n;
        params[1] = k as u32;
        params[2] = stride as u32;
        params[3] = m as u32;
        params[4] = ((h * h) as f32).to_bits();
        let uniform = wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST;
        let params = upload(device, queue, &mut st.params, "params", uniform, &params);
        let paths_buf = upload(
            device,
            queue,
            &mut st.paths_buf,
            "paths",
            STORAGE,
            &st.paths,
        );
        let z =
            st.z.ensure(device, "z", STORAGE, (k * stride * 9 * 4) as u64);
        // The walks in workgroup memory need no `work` buffer (k × n blocks).
        let shared = walk != ForwardWalk::Global;
        let work = if shared {
            None
        } else {
            Some(
                st.work
                    .ensure(device, "work", STORAGE, (k * n as usize * 9 * 4) as u64),
            )
        };
        let gram = st
            .gram
            .ensure(device, "gram", STORAGE, (k * k * 9 * 4) as u64);
        let w_bytes = (m * m * 4) as u64;
        let w = st.w.ensure(device, "w", STORAGE, w_bytes);
        let row_ptr_buf = upload(
            device,
            queue,
            &mut st.row_ptr_buf,
            "row_ptr",
            STORAGE,
            &st.row_ptr,
        );
        let ent_node_buf = upload(
            device,
            queue,
            &mut st.ent_node_buf,
            "ent_node",
            STORAGE,
            &st.ent_node,
        );
        let ent_j_buf = upload(
            device,
            queue,
            &mut st.ent_j_buf,
            "ent_j",
            STORAGE,
            &st.ent_j,
        );
        // `W`, then (8-byte aligned) the timestamps where the device has them.
        let copy = w_bytes.max(4);
        let stamps_at = copy.next_multiple_of(8);
        let stamps_bytes = if self.timer.is_some() {
            u64::from(TIMESTAMPS) * 8
        } else {
            0
        };
        let readback = st.readback.ensure(
            device,
            "w_readback",
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            stamps_at + stamps_bytes,
        );
        let pl = self
            .pipelines
            .as_ref()
            .ok_or(SoftTissueError::Gpu("no pipelines".into()))?;
        let bind = |pipeline: &wgpu::ComputePipeline, entries: &[wgpu::BindGroupEntry]| {
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &pipeline.get_bind_group_layout(0),
                entries,
            })
        };
        fn e(binding: u32, buf: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
            wgpu::BindGroupEntry {
                binding,
                resource: buf.as_entire_binding(),
            }
        }
        let forward_entries = [
            e(0, params),
            e(1, col_ptr),
            e(2, row_idx),
            e(3, lvals),
            e(4, ldiag),
            e(5, paths_buf),
            e(6, z),
        ];
        let (forward, bg_forward) = match (walk, work) {
            (ForwardWalk::Pieces, _) => {
                let entries = [
                    e(0, params),
                    e(1, col_ptr),
                    e(2, row_idx),
                    e(3, lvals),
                    e(5, paths_buf),
                    e(6, z),
                    e(14, up.pieces.get()?),
                    e(15, up.pinv.get()?),
                ];
                (&pl.forward_pieces, bind(&pl.forward_pieces, &entries))
            }
            (_, None) => (
                &pl.forward_shared,
                bind(&pl.forward_shared, &forward_entries),
            ),
            (_, Some(work)) => {
                let [a, b, c, d, f, g, h] = forward_entries;
                let entries = [a, b, c, d, f, g, h, e(7, work)];
                (&pl.forward, bind(&pl.forward, &entries))
            }
        };
        let bg_gram = bind(
            &pl.gram,
            &[
                e(0, params),
                e(5, paths_buf),
                e(6, z),
                e(8, dinv),
                e(9, gram),
            ],
        );
        let bg_contract = bind(
            &pl.contract,
            &[
                e(0, params),
                e(9, gram),
                e(10, row_ptr_buf),
                e(11, ent_node_buf),
                e(12, ent_j_buf),
                e(13, w),
            ],
        );
        let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("soft_tissue_compliance"),
        });
        // One pass per kernel, so that each can carry its own timestamps.
        let timer = self.timer.as_ref();
        let writes = |i: u32| {
            timer.map(|t| wgpu::ComputePassTimestampWrites {
                query_set: &t.queries,
                beginning_of_pass_write_index: Some(2 * i),
                end_of_pass_write_index: Some(2 * i + 1),
            })
        };
        let m_groups = ((m * m) as u32).div_ceil(64);
        let kernels: [(&wgpu::ComputePipeline, &wgpu::BindGroup, [u32; 2]); 3] = [
            (forward, &bg_forward, [k as u32, 1]),
            (&pl.gram, &bg_gram, [k as u32, k as u32]),
            (&pl.contract, &bg_contract, [m_groups, 1]),
        ];
        for (i, (pipeline, bg, [x, y])) in kernels.into_iter().enumerate() {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("soft_tissue_compliance"),
                timestamp_writes: writes(i as u32),
            });
            // An empty pass still writes its timestamps.
            if x > 0 && y > 0 {
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        enc.copy_buffer_to_buffer(w, 0, readback, 0, copy);
        if let Some(t) = timer {
            enc.resolve_query_set(&t.queries, 0..TIMESTAMPS, &t.resolve, 0);
            enc.copy_buffer_to_buffer(&t.resolve, 0, readback, stamps_at, stamps_bytes);
        }
        let submitted = Instant::now();
        self.queue.submit([enc.finish()]);
        self.dispatches += 3;
        self.shared_forwards += u64::from(shared);
        self.piece_forwards += u64::from(walk == ForwardWalk::Pieces);
        self.depth_sum += depth as u64;
        self.longest_path = self.longest_path.max(longest);
        self.path_sum += longest as u64;
        let slice = readback.slice(..stamps_at + stamps_bytes);
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
        self.wait_seconds += submitted.elapsed().as_secs_f64();
        st.out.clear();
        {
            let data = slice.get_mapped_range();
            st.out.extend_from_slice(
                &bytemuck::cast_slice::<u8, f32>(&data[..copy as usize])[..m * m],
            );
            if let Some(t) = timer {
                let at = stamps_at as usize;
                let mut ticks = [0u64; TIMESTAMPS as usize];
                for (tick, b) in ticks
                    .iter_mut()
                    .zip(data[at..at + stamps_bytes as usize].chunks_exact(8))
                {
                    *tick = u64::from_le_bytes(b.try_into().unwrap_or([0; 8]));
                }
                let secs = |a: u64, b: u64| b.saturating_sub(a) as f64 * t.period_ns * 1e-9;
                for (i, kt) in self.kernel_seconds.iter_mut().enumerate() {
                    *kt += secs(ticks[2 * i], ticks[2 * i + 1]);
                }
                self.span_seconds += secs(ticks[0], ticks[5]);
                self.timed += 1;
            }
        }
        readback.unmap();
        self.compute_seconds += t0.elapsed().as_secs_f64();
        Ok((&st.rows, &st.out))
    }
}

impl ComplianceBackend for GpuCompliance {
    fn accumulate(
        &mut self,
        body_id: u64,
        factor: &LdltFactor,
        key: FactorKey,
        h: f64,
        entries: &[JacEntry],
        w: &mut [f64],
        m: usize,
    ) -> Result<bool> {
        self.step.fill_rows(entries);
        if self.step.rows.len() < self.min_rows {
            return Ok(false);
        }
        let (rows, block) = self.compute_rows_filled(body_id, factor, key, h, entries)?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::{BodySettings, DeformableBody};
    use crate::material::TissueMaterial;
    use crate::math::Mat3;
    use crate::mesh::generate;
    use crate::solver::PreconditionerKind;

    /// A factor of the paper-size lens.
    fn lens_factor() -> LdltFactor {
        let mesh = generate::ellipsoid(generate::LENS_RADII, 12).unwrap();
        let settings = BodySettings {
            preconditioner: PreconditionerKind::Periodic { every: 1000 },
            ..Default::default()
        };
        let mut body =
            DeformableBody::new(mesh, TissueMaterial::new(1000.0, 5e3, 0.45), settings).unwrap();
        body.step(0.02).unwrap();
        body.preconditioner().factor_state().unwrap().factor.clone()
    }

    /// The host side of `forward_pieces`, step for step on the CPU: the
    /// piece table and inverses give the same `L⁻¹ E_node` as the factor's
    /// own forward solve, for every piece size, and a piece's columns share
    /// the structure of its last column below it.
    #[test]
    fn a_walk_by_pieces_solves_like_the_factor() {
        let f = lens_factor();
        let s = &*f.symbolic;
        let (mut table, mut scratch) = (Vec::new(), Vec::new());
        let mut work = vec![Mat3::zeros(); s.n];
        for max_nodes in [1, 4, MAX_PIECE_NODES] {
            let len = piece_table(s, max_nodes, &mut table);
            let mut inv = vec![0.0f32; len];
            invert_pieces(&f, &table, &mut inv, &mut scratch);
            let mut widest = 0;
            for j in 0..s.n {
                let (a, b) = (table[3 * j] as usize, table[3 * j + 1] as usize);
                assert!(a <= j && j <= b && b - a < max_nodes);
                widest = widest.max(b - a + 1);
                let own: Vec<usize> = (j + 1..=b).collect();
                assert_eq!(&rows_of(s, j)[..b - j], &own[..]);
                assert_eq!(&rows_of(s, j)[b - j..], rows_of(s, b));
            }
            if max_nodes > 1 {
                assert!(widest > 1, "no piece of more than one node");
            }
            for node in (0..s.n).step_by(97) {
                let (mut path, mut blocks) = (Vec::new(), Vec::new());
                f.node_forward_solve(node, &mut work, &mut path, &mut blocks);
                // The walk by pieces, in f64 over the f32 inverses.
                let mut w: Vec<[f64; 9]> = vec![[0.0; 9]; path.len()];
                for c in 0..3 {
                    w[0][4 * c] = 1.0;
                }
                let pos = |r: usize| path.binary_search(&r).unwrap();
                let mut t = 0;
                while t < path.len() {
                    let j = path[t];
                    let (a, b, off) = (
                        table[3 * j] as usize,
                        table[3 * j + 1] as usize,
                        table[3 * j + 2] as usize,
                    );
                    let (q, o, m) = (3 * (b - a + 1), 3 * (j - a), b - j + 1);
                    assert_eq!(&path[t..t + m], &(j..=b).collect::<Vec<_>>()[..]);
                    let mut z = vec![[0.0f64; 9]; m];
                    for x in 0..3 * m {
                        for col in 0..3 {
                            let mut acc = 0.0;
                            for y in 0..=x {
                                acc += inv[off + (o + x) * q + o + y] as f64
                                    * w[t + y / 3][3 * col + y % 3];
                            }
                            z[x / 3][3 * col + x % 3] = acc;
                        }
                    }
                    for (e, &r) in rows_of(s, b).iter().enumerate() {
                        for i in j..=b {
                            let l = &f.l[s.col_ptr[i] + (b - i) + e];
                            let zi = Mat3::from_column_slice(&z[i - j]);
                            let d = l * zi;
                            for (v, dv) in w[pos(r)].iter_mut().zip(d.iter()) {
                                *v -= dv;
                            }
                        }
                    }
                    for (i, zi) in z.iter().enumerate() {
                        let want = &blocks[t + i];
                        let got = Mat3::from_column_slice(zi);
                        let err = (got - want).abs().max();
                        assert!(
                            err <= 1e-4 * want.abs().max().max(1.0),
                            "node {node}, pieces of {max_nodes}: {err:e}"
                        );
                    }
                    t += m;
                }
            }
        }
    }

    fn rows_of(s: &LdltSymbolic, c: usize) -> &[usize] {
        &s.row_idx[s.col_ptr[c]..s.col_ptr[c + 1]]
    }

    /// The host's limit for the walk in workgroup memory is the shader's
    /// `MAXP`, and the shader's workgroup arrays are sized by it.
    #[test]
    fn shared_forward_limit_matches_the_shader() {
        let maxp = format!("const MAXP: u32 = {SHARED_FORWARD_MAX_PATH}u;");
        assert!(SHADER.contains(&maxp), "shader lacks `{maxp}`");
        for decl in [
            format!("f_path: array<u32, {SHARED_FORWARD_MAX_PATH}>"),
            format!("f_cp0: array<u32, {SHARED_FORWARD_MAX_PATH}>"),
            format!("f_cp1: array<u32, {SHARED_FORWARD_MAX_PATH}>"),
            format!("f_work: array<f32, {}>", 9 * SHARED_FORWARD_MAX_PATH),
            format!("const MAXPIECE: u32 = {MAX_PIECE_NODES}u;"),
            format!("p_z: array<f32, {}>", 9 * MAX_PIECE_NODES),
        ] {
            assert!(SHADER.contains(&decl), "shader lacks `{decl}`");
        }
    }
}
