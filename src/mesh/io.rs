//! Mesh file formats: Gmsh MSH 4.1 (ASCII and binary, read and write) and
//! TetGen `.node` / `.ele` (read).
//!
//! Linear tetrahedra (Gmsh type 4) are read from MSH files, and quadratic ones
//! (type 11, TetGen's 10-node elements) keep their four corners; other
//! element blocks (surface triangles, lines, points) are skipped. Malformed
//! files give [`SoftTissueError::Parse`] naming the section and the line or
//! byte offset, never a panic; no count read from a file reserves more memory
//! than the file's size can justify.

use std::path::Path;

use crate::error::{Result, SoftTissueError};
use crate::math::{Vec3, v3};
use crate::mesh::{TetMesh, ValidateOptions};

fn parse_err(format: &'static str, reason: impl Into<String>) -> SoftTissueError {
    SoftTissueError::Parse {
        format,
        reason: reason.into(),
    }
}

fn read(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| SoftTissueError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    })
}

/// Loads a Gmsh MSH 4.1 file (ASCII or binary).
pub fn load_msh(path: impl AsRef<Path>, options: ValidateOptions) -> Result<TetMesh> {
    parse_msh(&read(path.as_ref())?, options)
}

/// Parses the bytes of a Gmsh MSH 4.1 file (ASCII or binary; see
/// `mesh/msh.rs` for what is read). Nodes that no tetrahedron uses (those of
/// surface, line and point elements, or the midside nodes of quadratic
/// tetrahedra) are dropped.
pub fn parse_msh(bytes: &[u8], options: ValidateOptions) -> Result<TetMesh> {
    let (positions, tets) = super::msh::parse(bytes)?;
    compact_and_build(positions, tets, options)
}

fn compact_and_build(
    positions: Vec<Vec3>,
    mut tets: Vec<[usize; 4]>,
    options: ValidateOptions,
) -> Result<TetMesh> {
    if tets.iter().flatten().any(|&v| v >= positions.len()) {
        // Let validation name the bad index.
        return TetMesh::with_options(positions, tets, options);
    }
    let mut used = vec![false; positions.len()];
    for t in &tets {
        for &v in t {
            used[v] = true;
        }
    }
    if used.iter().all(|&u| u) {
        return TetMesh::with_options(positions, tets, options);
    }
    // Keep the file's node order, dropping nodes no tetrahedron uses.
    let mut remap = vec![usize::MAX; positions.len()];
    let mut kept = Vec::new();
    for (i, p) in positions.iter().enumerate() {
        if used[i] {
            remap[i] = kept.len();
            kept.push(*p);
        }
    }
    for t in &mut tets {
        for v in t.iter_mut() {
            *v = remap[*v];
        }
    }
    TetMesh::with_options(kept, tets, options)
}

/// Writes a mesh as Gmsh MSH 4.1, ASCII or binary (little-endian).
pub fn write_msh(mesh: &TetMesh, binary: bool) -> Vec<u8> {
    let n = mesh.num_vertices() as u64;
    let m = mesh.num_tets() as u64;
    let mut out = Vec::new();
    if binary {
        out.extend_from_slice(b"$MeshFormat\n4.1 1 8\n");
        out.extend_from_slice(&1i32.to_le_bytes());
        out.extend_from_slice(b"\n$EndMeshFormat\n$Nodes\n");
        for x in [1u64, n, 1, n] {
            out.extend_from_slice(&x.to_le_bytes());
        }
        for x in [3i32, 1, 0] {
            out.extend_from_slice(&x.to_le_bytes());
        }
        out.extend_from_slice(&n.to_le_bytes());
        for i in 1..=n {
            out.extend_from_slice(&i.to_le_bytes());
        }
        for p in mesh.positions() {
            for c in p.iter() {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        out.extend_from_slice(b"\n$EndNodes\n$Elements\n");
        for x in [1u64, m, 1, m] {
            out.extend_from_slice(&x.to_le_bytes());
        }
        for x in [3i32, 1, 4] {
            out.extend_from_slice(&x.to_le_bytes());
        }
        out.extend_from_slice(&m.to_le_bytes());
        for (i, t) in mesh.tets().iter().enumerate() {
            out.extend_from_slice(&(i as u64 + 1).to_le_bytes());
            for &v in t {
                out.extend_from_slice(&(v as u64 + 1).to_le_bytes());
            }
        }
        out.extend_from_slice(b"\n$EndElements\n");
    } else {
        use std::fmt::Write;
        let mut s = String::new();
        let _ = writeln!(
            s,
            "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 {n} 1 {n}\n3 1 0 {n}"
        );
        for i in 1..=n {
            let _ = writeln!(s, "{i}");
        }
        for p in mesh.positions() {
            let _ = writeln!(s, "{:e} {:e} {:e}", p.x, p.y, p.z);
        }
        let _ = writeln!(s, "$EndNodes\n$Elements\n1 {m} 1 {m}\n3 1 4 {m}");
        for (i, t) in mesh.tets().iter().enumerate() {
            let _ = writeln!(
                s,
                "{} {} {} {} {}",
                i + 1,
                t[0] + 1,
                t[1] + 1,
                t[2] + 1,
                t[3] + 1
            );
        }
        s.push_str("$EndElements\n");
        out = s.into_bytes();
    }
    out
}

/// Loads TetGen `<base>.node` and `<base>.ele`.
pub fn load_tetgen(base: impl AsRef<Path>, options: ValidateOptions) -> Result<TetMesh> {
    let base = base.as_ref();
    let node = read(&base.with_extension("node"))?;
    let ele = read(&base.with_extension("ele"))?;
    parse_tetgen(
        &String::from_utf8_lossy(&node),
        &String::from_utf8_lossy(&ele),
        options,
    )
}

/// Non-empty, comment-stripped lines with their 1-based line numbers.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, Vec<&str>)> {
    text.lines().enumerate().filter_map(|(i, l)| {
        let l = l.split('#').next().unwrap_or("");
        let toks: Vec<&str> = l.split_whitespace().collect();
        (!toks.is_empty()).then_some((i + 1, toks))
    })
}

fn num<T: std::str::FromStr>(f: &'static str, line: usize, tok: Option<&&str>) -> Result<T> {
    let tok = tok.ok_or_else(|| parse_err(f, format!("line {line}: missing value")))?;
    tok.parse()
        .map_err(|_| parse_err(f, format!("line {line}: cannot parse `{tok}`")))
}

/// Parses the texts of a TetGen `.node` and `.ele` pair. Indices may start
/// at 0 or 1 (the first point's index decides, as in TetGen). Quadratic
/// (10-node) elements keep their four corners.
pub fn parse_tetgen(node: &str, ele: &str, options: ValidateOptions) -> Result<TetMesh> {
    const FN: &str = "TetGen .node";
    const FE: &str = "TetGen .ele";
    let mut lines = data_lines(node);
    let (l, head) = lines.next().ok_or_else(|| parse_err(FN, "empty file"))?;
    let count: usize = num(FN, l, head.first())?;
    let dim: usize = num(FN, l, head.get(1))?;
    if dim != 3 {
        return Err(parse_err(
            FN,
            format!("line {l}: dimension {dim}, expected 3"),
        ));
    }
    // A point takes a line of at least 8 bytes ("1 0 0 0\n"): reserve no more.
    let mut positions = Vec::with_capacity(count.min(node.len() / 8));
    let mut first_index = 0usize;
    for (i, (l, toks)) in lines.take(count).enumerate() {
        let idx: usize = num(FN, l, toks.first())?;
        if i == 0 {
            first_index = idx;
            if idx > 1 {
                return Err(parse_err(
                    FN,
                    format!("line {l}: first index {idx}, expected 0 or 1"),
                ));
            }
        }
        if idx != first_index + i {
            return Err(parse_err(
                FN,
                format!("line {l}: point index {idx} out of sequence"),
            ));
        }
        let x: f64 = num(FN, l, toks.get(1))?;
        let y: f64 = num(FN, l, toks.get(2))?;
        let z: f64 = num(FN, l, toks.get(3))?;
        positions.push(v3(x, y, z));
    }
    if positions.len() != count {
        return Err(parse_err(
            FN,
            format!(
                "header announces {count} points, file has {}",
                positions.len()
            ),
        ));
    }
    let mut lines = data_lines(ele);
    let (l, head) = lines.next().ok_or_else(|| parse_err(FE, "empty file"))?;
    let count: usize = num(FE, l, head.first())?;
    let per: usize = num(FE, l, head.get(1))?;
    if per != 4 && per != 10 {
        return Err(parse_err(
            FE,
            format!("line {l}: {per} nodes per element, expected 4 or 10"),
        ));
    }
    let mut tets = Vec::with_capacity(count.min(ele.len() / 10));
    for (l, toks) in lines.take(count) {
        let mut t = [0usize; 4];
        for (k, v) in t.iter_mut().enumerate() {
            let raw: usize = num(FE, l, toks.get(k + 1))?;
            *v = raw.checked_sub(first_index).ok_or_else(|| {
                parse_err(
                    FE,
                    format!("line {l}: node index {raw} below the first index {first_index}"),
                )
            })?;
        }
        tets.push(t);
    }
    if tets.len() != count {
        return Err(parse_err(
            FE,
            format!(
                "header announces {count} tetrahedra, file has {}",
                tets.len()
            ),
        ));
    }
    // 10-node elements: the midside nodes (used by no corner) are dropped.
    compact_and_build(positions, tets, options)
}
