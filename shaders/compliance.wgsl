// Contact compliance on the GPU: W = h² J (L D Lᵀ)⁻¹ Jᵀ for one body.
//
// Bindings are numbered across the module; each entry point uses its subset
// (pipelines use automatic layouts). Three kernels, dispatched in order:
//   forward   — one workgroup per contact node: the reach-restricted forward
//               solve Z_k = L⁻¹ E_k of the node's three unit columns, walking only
//               the node's elimination-tree path (3×3 node supernodes);
//               `forward_pieces` (the walk in workgroup memory, one step
//               per piece of a supernode) or `forward_shared` (the same,
//               one step per node) where every path has at most MAXP
//               nodes, `forward` (in global memory) else;
//   gram      — one workgroup per pair of contact nodes (a ≤ b): the Gram block
//               G_ab = Σ Z_aᵀ D⁻¹ Z_b over the common suffix of their paths;
//   contract  — one invocation per entry of W: W_rs = h² Σ j_raᵀ G_ab j_sb.
//
// 3×3 blocks are stored column-major (element (r, c) at 3c + r), like nalgebra.
// Paths: for contact node k, paths[k * stride] is the length, followed by the
// permuted node ids in ascending order (stride = longest path + 1).

struct Params {
    n: u32,        // nodes of the body
    k: u32,        // contact nodes
    stride: u32,   // path stride
    m: u32,        // rows of W handled by this body
    h2: f32,       // h²
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> col_ptr: array<u32>;
@group(0) @binding(2) var<storage, read> row_idx: array<u32>;
@group(0) @binding(3) var<storage, read> lvals: array<f32>;
@group(0) @binding(4) var<storage, read> ldiag: array<f32>;
@group(0) @binding(5) var<storage, read> paths: array<u32>;
@group(0) @binding(6) var<storage, read_write> zout: array<f32>;
@group(0) @binding(7) var<storage, read_write> work: array<f32>;

const WG: u32 = 64u;
// The walks in workgroup memory: one invocation per entry of a column of
// up to FWG entries in one pass.
const FWG: u32 = 256u;

var<workgroup> s_len: u32;
// The global walk's solved diagonal block, shared by the workgroup.
var<workgroup> s_z: mat3x3<f32>;

@compute @workgroup_size(FWG)
fn forward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let c = wid.x;
    let pbase = c * params.stride;
    let wbase = c * params.n * 9u;
    if (lid == 0u) {
        s_len = paths[pbase];
    }
    let len = workgroupUniformLoad(&s_len);
    // Clear the rows this solve touches (all on the path), set the unit columns.
    for (var t = lid; t < len; t += FWG) {
        let node = paths[pbase + 1u + t];
        for (var i = 0u; i < 9u; i++) {
            work[wbase + node * 9u + i] = select(0.0, 1.0, t == 0u && i % 4u == 0u);
        }
    }
    storageBarrier();
    workgroupBarrier();
    for (var t = 0u; t < len; t++) {
        let j = paths[pbase + 1u + t];
        if (lid == 0u) {
            // z_j = L_jj⁻¹ work_j, L_jj unit lower triangular (l10, l20, l21).
            let d = vec3<f32>(ldiag[j * 3u], ldiag[j * 3u + 1u], ldiag[j * 3u + 2u]);
            let q = wbase + j * 9u;
            let z = mat3x3<f32>(
                unit_lower_solve(vec3<f32>(work[q], work[q + 1u], work[q + 2u]), d),
                unit_lower_solve(vec3<f32>(work[q + 3u], work[q + 4u], work[q + 5u]), d),
                unit_lower_solve(vec3<f32>(work[q + 6u], work[q + 7u], work[q + 8u]), d),
            );
            s_z = z;
            store_z((c * params.stride + t) * 9u, z);
        }
        workgroupBarrier();
        // work_r -= L_rj z_j for the rows of column j (distinct rows: no conflicts).
        let z = s_z;
        let p0 = col_ptr[j];
        let p1 = col_ptr[j + 1u];
        for (var p = p0 + lid; p < p1; p += FWG) {
            let q = wbase + row_idx[p] * 9u;
            let m = l_block(p) * z;
            work[q] -= m[0].x;
            work[q + 1u] -= m[0].y;
            work[q + 2u] -= m[0].z;
            work[q + 3u] -= m[1].x;
            work[q + 4u] -= m[1].y;
            work[q + 5u] -= m[1].z;
            work[q + 6u] -= m[2].x;
            work[q + 7u] -= m[2].y;
            work[q + 8u] -= m[2].z;
        }
        storageBarrier();
        workgroupBarrier();
    }
}

// The forward solves with the walk in workgroup memory, for paths of at most
// MAXP nodes (the host uses `forward` for longer ones). Every row of column j
// of L is an ancestor of j, so on the path: the right-hand side lives in
// workgroup memory by path position, found by binary search over the sorted
// path. The path's column ranges are read once up front, and each level's
// column entries and diagonal block are loaded one level ahead, so a level
// waits on workgroup memory and barriers rather than on global loads.
// Workgroup memory: MAXP × 48 bytes + 4 (15 364 bytes, under WebGPU's
// 16 384 minimum limit); `forward_pieces` adds MAXPIECE × 36 + 16 bytes
// (15 956 in all).
const MAXP: u32 = 320u;

var<workgroup> f_path: array<u32, 320>;
var<workgroup> f_cp0: array<u32, 320>;
var<workgroup> f_cp1: array<u32, 320>;
var<workgroup> f_work: array<f32, 2880>;

// The position of `node` in f_path[0..len) (sorted ascending; node is on it).
fn path_pos(len: u32, node: u32) -> u32 {
    var lo = 0u;
    var hi = len;
    while (lo + 1u < hi) {
        let mid = (lo + hi) / 2u;
        if (f_path[mid] <= node) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return lo;
}

// z = L_jj⁻¹ w for one column, L_jj unit lower triangular (l10, l20, l21 in d).
fn unit_lower_solve(w: vec3<f32>, d: vec3<f32>) -> vec3<f32> {
    let x1 = w.y - d.x * w.x;
    return vec3<f32>(w.x, x1, w.z - d.y * w.x - d.z * x1);
}

// The 3×3 block of f_work at q (column-major), as a matrix.
fn work_block(q: u32) -> mat3x3<f32> {
    return mat3x3<f32>(
        f_work[q], f_work[q + 1u], f_work[q + 2u],
        f_work[q + 3u], f_work[q + 4u], f_work[q + 5u],
        f_work[q + 6u], f_work[q + 7u], f_work[q + 8u],
    );
}

// f_work's block at q −= m.
fn sub_work_block(q: u32, m: mat3x3<f32>) {
    f_work[q] -= m[0].x;
    f_work[q + 1u] -= m[0].y;
    f_work[q + 2u] -= m[0].z;
    f_work[q + 3u] -= m[1].x;
    f_work[q + 4u] -= m[1].y;
    f_work[q + 5u] -= m[1].z;
    f_work[q + 6u] -= m[2].x;
    f_work[q + 7u] -= m[2].y;
    f_work[q + 8u] -= m[2].z;
}

// zout's block at o (column-major) = z.
fn store_z(o: u32, z: mat3x3<f32>) {
    zout[o] = z[0].x;
    zout[o + 1u] = z[0].y;
    zout[o + 2u] = z[0].z;
    zout[o + 3u] = z[1].x;
    zout[o + 4u] = z[1].y;
    zout[o + 5u] = z[1].z;
    zout[o + 6u] = z[2].x;
    zout[o + 7u] = z[2].y;
    zout[o + 8u] = z[2].z;
}

// Block p of L (column-major), as a matrix.
fn l_block(p: u32) -> mat3x3<f32> {
    let b = p * 9u;
    return mat3x3<f32>(
        lvals[b], lvals[b + 1u], lvals[b + 2u],
        lvals[b + 3u], lvals[b + 4u], lvals[b + 5u],
        lvals[b + 6u], lvals[b + 7u], lvals[b + 8u],
    );
}

// Loads contact c's path into workgroup memory for the walks there: its
// nodes, their column ranges, and the right-hand side (the unit columns at
// the path's first node). Returns the path's length.
fn load_path(c: u32, lid: u32) -> u32 {
    let pbase = c * params.stride;
    if (lid == 0u) {
        s_len = min(paths[pbase], MAXP);
    }
    let len = workgroupUniformLoad(&s_len);
    for (var t = lid; t < len; t += FWG) {
        let j = paths[pbase + 1u + t];
        f_path[t] = j;
        f_cp0[t] = col_ptr[j];
        f_cp1[t] = col_ptr[j + 1u];
        for (var i = 0u; i < 9u; i++) {
            f_work[t * 9u + i] = select(0.0, 1.0, t == 0u && i % 4u == 0u);
        }
    }
    workgroupBarrier();
    return len;
}

@compute @workgroup_size(FWG)
fn forward_shared(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let c = wid.x;
    let len = load_path(c, lid);
    // Level 0's entry of this invocation and diagonal block.
    var nr = 0u;
    var nl = mat3x3<f32>();
    var nok = false;
    var nd = vec3<f32>(0.0, 0.0, 0.0);
    if (len > 0u) {
        let p = f_cp0[0] + lid;
        nok = p < f_cp1[0];
        if (nok) {
            nr = row_idx[p];
            nl = l_block(p);
        }
        let j = f_path[0];
        nd = vec3<f32>(ldiag[j * 3u], ldiag[j * 3u + 1u], ldiag[j * 3u + 2u]);
    }
    for (var t = 0u; t < len; t++) {
        let r0 = nr;
        let l0 = nl;
        let ok0 = nok;
        let d = nd;
        // Load the next level's entries while this one runs.
        if (t + 1u < len) {
            let p = f_cp0[t + 1u] + lid;
            nok = p < f_cp1[t + 1u];
            if (nok) {
                nr = row_idx[p];
                nl = l_block(p);
            }
            let j = f_path[t + 1u];
            nd = vec3<f32>(ldiag[j * 3u], ldiag[j * 3u + 1u], ldiag[j * 3u + 2u]);
        }
        // z_j = L_jj⁻¹ work_j, solved by every invocation: work_j is final
        // (this level writes only rows below j), so a level needs one barrier.
        let w = work_block(t * 9u);
        let z = mat3x3<f32>(
            unit_lower_solve(w[0], d),
            unit_lower_solve(w[1], d),
            unit_lower_solve(w[2], d),
        );
        if (lid == 0u) {
            store_z((c * params.stride + t) * 9u, z);
        }
        // work_r -= L_rj z_j for the rows of column j (distinct rows: no conflicts):
        // the first FWG entries from the loads above, any further ones directly.
        if (ok0) {
            sub_work_block(path_pos(len, r0) * 9u, l0 * z);
        }
        for (var p = f_cp0[t] + FWG + lid; p < f_cp1[t]; p += FWG) {
            sub_work_block(path_pos(len, row_idx[p]) * 9u, l_block(p) * z);
        }
        workgroupBarrier();
    }
}

// The forward solves by pieces of supernodes: the walk in workgroup memory
// (paths of at most MAXP nodes), one step per piece instead of per node.
// A piece is a run of nodes j, j+1, …, b of one chain of the elimination
// tree in which every column shares the structure of the last one below
// the piece (struct(j) = {j+1, …, b} ∪ struct(b)), at most MAXPIECE nodes.
// A path enters a piece at some node j and leaves it at b, through every
// node between. Per piece:
//   1. z of nodes j…b from the piece's inverted diagonal block: the trailing
//      part (from j) of the inverse of a unit lower triangular matrix is the
//      inverse of its trailing part, so one product with the piece's
//      precomputed inverse (`pinv`, row-major, q × q for q = 3 × nodes)
//      replaces 3·(b − j + 1) serial substitutions;
//   2. work_r −= Σ_{i=j..b} L_ri z_i for the rows r of column b below the
//      piece (the entry of row r in column i sits (b − i) entries after
//      the start of column i, past the piece's own rows).
// `pieces[3 j ..]` holds, per node j: the piece's first node, its last node
// and the offset of its inverse in `pinv`.
@group(0) @binding(14) var<storage, read> pieces: array<u32>;
@group(0) @binding(15) var<storage, read> pinv: array<f32>;

const MAXPIECE: u32 = 16u;

// (node entering the piece, the piece's last node, q, where the trailing
// block of the inverse starts).
var<workgroup> p_info: vec4<u32>;
var<workgroup> p_z: array<f32, 144>;

@compute @workgroup_size(FWG)
fn forward_pieces(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let c = wid.x;
    let len = load_path(c, lid);
    var t = 0u;
    loop {
        if (t >= len) {
            break;
        }
        if (lid == 0u) {
            let j = f_path[t];
            let a = pieces[3u * j];
            let b = pieces[3u * j + 1u];
            let q = 3u * (b - a + 1u);
            let o = 3u * (j - a);
            p_info = vec4<u32>(j, b, q, pieces[3u * j + 2u] + o * q + o);
        }
        let info = workgroupUniformLoad(&p_info);
        let j = info.x;
        let b = info.y;
        let q = info.z;
        let base = info.w;
        let m = b - j + 1u;
        // 1. z_(j..b) = (inverse's trailing block) work_(j..b), three columns.
        for (var idx = lid; idx < 9u * m; idx += FWG) {
            let x = idx / 3u;
            let col = idx % 3u;
            var acc = 0.0;
            for (var y = 0u; y <= x; y++) {
                acc += pinv[base + x * q + y] * f_work[(t + y / 3u) * 9u + col * 3u + y % 3u];
            }
            let o = (x / 3u) * 9u + col * 3u + x % 3u;
            p_z[o] = acc;
            zout[(c * params.stride + t) * 9u + o] = acc;
        }
        workgroupBarrier();
        // 2. The rows of column b below the piece (distinct rows: no conflicts).
        let tb = t + m - 1u;
        let p0 = f_cp0[tb];
        let cnt = f_cp1[tb] - p0;
        for (var e = lid; e < cnt; e += FWG) {
            let qpos = path_pos(len, row_idx[p0 + e]) * 9u;
            var acc = mat3x3<f32>();
            for (var i = 0u; i < m; i++) {
                let zi = i * 9u;
                let z = mat3x3<f32>(
                    p_z[zi], p_z[zi + 1u], p_z[zi + 2u],
                    p_z[zi + 3u], p_z[zi + 4u], p_z[zi + 5u],
                    p_z[zi + 6u], p_z[zi + 7u], p_z[zi + 8u],
                );
                acc += l_block(f_cp0[t + i] + (m - 1u - i) + e) * z;
            }
            sub_work_block(qpos, acc);
        }
        workgroupBarrier();
        t += m;
    }
}

@group(0) @binding(8) var<storage, read> dinv: array<f32>;
@group(0) @binding(9) var<storage, read_write> gram: array<f32>;

var<workgroup> s_common: u32;

// The 3×3 block of zout at o (column-major), as a matrix.
fn z_block(o: u32) -> mat3x3<f32> {
    return mat3x3<f32>(
        zout[o], zout[o + 1u], zout[o + 2u],
        zout[o + 3u], zout[o + 4u], zout[o + 5u],
        zout[o + 6u], zout[o + 7u], zout[o + 8u],
    );
}
var<workgroup> s_acc: array<mat3x3<f32>, 64>;

@compute @workgroup_size(64)
fn gram_blocks(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let a = wid.x;
    let b = wid.y;
    if (b < a) {
        return;
    }
    let pa = a * params.stride;
    let pb = b * params.stride;
    let la = paths[pa];
    let lb = paths[pb];
    if (lid == 0u) {
        // Paths end at the root of their tree: the shared part is a common suffix.
        var shared_len = 0u;
        loop {
            if (shared_len >= la || shared_len >= lb) {
                break;
            }
            if (paths[pa + la - shared_len] != paths[pb + lb - shared_len]) {
                break;
            }
            shared_len++;
        }
        s_common = shared_len;
    }
    let shared_len = workgroupUniformLoad(&s_common);
    var acc = mat3x3<f32>();
    for (var t = lid; t < shared_len; t += WG) {
        let ia = la - shared_len + t;
        let ib = lb - shared_len + t;
        let node = paths[pa + 1u + ia];
        let za = z_block((a * params.stride + ia) * 9u);
        let zb = z_block((b * params.stride + ib) * 9u);
        let dv = vec3<f32>(dinv[node * 3u], dinv[node * 3u + 1u], dinv[node * 3u + 2u]);
        // G += Z_aᵀ diag(dinv) Z_b
        acc += transpose(za) * mat3x3<f32>(zb[0] * dv, zb[1] * dv, zb[2] * dv);
    }
    s_acc[lid] = acc;
    workgroupBarrier();
    var stride = WG / 2u;
    loop {
        if (stride == 0u) {
            break;
        }
        if (lid < stride) {
            s_acc[lid] += s_acc[lid + stride];
        }
        workgroupBarrier();
        stride = stride / 2u;
    }
    if (lid == 0u) {
        let k = params.k;
        let g = s_acc[0];
        let gt = transpose(g);
        let ab = (a * k + b) * 9u;
        let ba = (b * k + a) * 9u;
        for (var col = 0u; col < 3u; col++) {
            gram[ab + col * 3u] = g[col].x;
            gram[ab + col * 3u + 1u] = g[col].y;
            gram[ab + col * 3u + 2u] = g[col].z;
            gram[ba + col * 3u] = gt[col].x;
            gram[ba + col * 3u + 1u] = gt[col].y;
            gram[ba + col * 3u + 2u] = gt[col].z;
        }
    }
}

@group(0) @binding(10) var<storage, read> row_ptr: array<u32>;
@group(0) @binding(11) var<storage, read> ent_node: array<u32>;
@group(0) @binding(12) var<storage, read> ent_j: array<f32>;
@group(0) @binding(13) var<storage, read_write> wout: array<f32>;

@compute @workgroup_size(64)
fn contract(@builtin(global_invocation_id) gid: vec3<u32>) {
    let m = params.m;
    let idx = gid.x;
    if (idx >= m * m) {
        return;
    }
    let r = idx / m;
    let s = idx % m;
    let k = params.k;
    var w = 0.0;
    for (var e = row_ptr[r]; e < row_ptr[r + 1u]; e++) {
        let a = ent_node[e];
        let ja = vec3<f32>(ent_j[e * 3u], ent_j[e * 3u + 1u], ent_j[e * 3u + 2u]);
        for (var f = row_ptr[s]; f < row_ptr[s + 1u]; f++) {
            let b = ent_node[f];
            let jb = vec3<f32>(ent_j[f * 3u], ent_j[f * 3u + 1u], ent_j[f * 3u + 2u]);
            let g = (a * k + b) * 9u;
            // jaᵀ G_ab jb, G column-major.
            for (var c = 0u; c < 3u; c++) {
                let gc = vec3<f32>(gram[g + c * 3u], gram[g + c * 3u + 1u], gram[g + c * 3u + 2u]);
                w += dot(ja, gc) * jb[c];
            }
        }
    }
    wout[idx] = params.h2 * w;
}
