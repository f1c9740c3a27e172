//! Gmsh MSH 4.1 reader, ASCII and binary (little-endian).
//!
//! Reads `$MeshFormat`, `$Nodes` and `$Elements`; every other section is
//! skipped to its `$End…` line. Node tags are mapped to indices through the
//! tags each block lists, so blocks may come in any order. Linear
//! tetrahedra (type 4) are kept, and quadratic ones (type 11) keep their four
//! corners; other element types are skipped. Every count read from the file
//! is checked against the bytes left before anything is reserved, and every
//! error names the section and the line (ASCII) or byte offset (binary).

use std::collections::HashMap;

use crate::error::{Result, SoftTissueError};
use crate::math::{Vec3, v3};

const F: &str = "Gmsh MSH 4.1";

/// Nodes per element of the Gmsh element types this reader can skip or read.
fn nodes_per_element(kind: i32) -> Option<usize> {
    Some(match kind {
        1 => 2,
        2 => 3,
        3 => 4,
        4 => 4,
        5 => 8,
        6 => 6,
        7 => 5,
        8 => 3,
        9 => 6,
        10 => 9,
        11 => 10,
        12 => 27,
        13 => 18,
        14 => 14,
        15 => 1,
        16 => 8,
        17 => 20,
        18 => 15,
        19 => 13,
        _ => return None,
    })
}

struct Reader<'a> {
    b: &'a [u8],
    pos: usize,
    binary: bool,
    size_bytes: usize,
    section: &'static str,
}

impl<'a> Reader<'a> {
    fn err(&self, what: impl std::fmt::Display) -> SoftTissueError {
        let at = if self.binary && self.section != "$MeshFormat" {
            format!("byte offset {}", self.pos)
        } else {
            let line = 1 + self.b[..self.pos.min(self.b.len())]
                .iter()
                .filter(|&&c| c == b'\n')
                .count();
            format!("line {line}")
        };
        SoftTissueError::Parse {
            format: F,
            reason: format!("{} ({at}): {what}", self.section),
        }
    }

    fn left(&self) -> usize {
        self.b.len().saturating_sub(self.pos)
    }

    fn skip_space(&mut self) {
        while self.pos < self.b.len() && self.b[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
    }

    /// The next line (without its end), or `None` at the end of the input.
    fn line(&mut self) -> Option<&'a str> {
        if self.pos >= self.b.len() {
            return None;
        }
        let start = self.pos;
        let end = self.b[start..]
            .iter()
            .position(|&c| c == b'\n')
            .map_or(self.b.len(), |i| start + i);
        self.pos = (end + 1).min(self.b.len());
        let raw = &self.b[start..end];
        let raw = raw.strip_suffix(b"\r").unwrap_or(raw);
        Some(std::str::from_utf8(raw).unwrap_or("\u{fffd}"))
    }

    /// The next whitespace-separated ASCII token.
    fn token(&mut self) -> Result<&'a str> {
        self.skip_space();
        let start = self.pos;
        while self.pos < self.b.len() && !self.b[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
        if start == self.pos {
            return Err(self.err("unexpected end of file"));
        }
        std::str::from_utf8(&self.b[start..self.pos]).map_err(|_| self.err("not ASCII text"))
    }

    fn parse<T: std::str::FromStr>(&mut self, what: &str) -> Result<T> {
        let t = self.token()?;
        t.parse()
            .map_err(|_| self.err(format!("expected {what}, found `{}`", truncate(t))))
    }

    fn bytes<const N: usize>(&mut self) -> Result<[u8; N]> {
        if self.left() < N {
            return Err(self.err("unexpected end of file"));
        }
        let mut out = [0u8; N];
        out.copy_from_slice(&self.b[self.pos..self.pos + N]);
        self.pos += N;
        Ok(out)
    }

    /// A `size_t` (count or tag).
    fn size(&mut self, what: &str) -> Result<u64> {
        if !self.binary {
            return self.parse(what);
        }
        Ok(match self.size_bytes {
            4 => u32::from_le_bytes(self.bytes()?) as u64,
            _ => u64::from_le_bytes(self.bytes()?),
        })
    }

    fn int(&mut self, what: &str) -> Result<i32> {
        if self.binary {
            Ok(i32::from_le_bytes(self.bytes()?))
        } else {
            self.parse(what)
        }
    }

    fn float(&mut self) -> Result<f64> {
        if self.binary {
            Ok(f64::from_le_bytes(self.bytes()?))
        } else {
            self.parse("a coordinate")
        }
    }

    /// A count of items of at least `min_bytes` each, checked against the input left.
    fn count(&mut self, what: &str, min_bytes: usize) -> Result<usize> {
        let n = self.size(what)?;
        if n > (self.left() / min_bytes.max(1)) as u64 {
            return Err(self.err(format!(
                "{what} {n} cannot fit in the {} bytes left",
                self.left()
            )));
        }
        Ok(n as usize)
    }

    fn expect_end(&mut self, name: &str) -> Result<()> {
        self.skip_space();
        match self.line() {
            Some(l) if l.trim_end() == name => Ok(()),
            Some(l) => Err(self.err(format!("expected `{name}`, found `{}`", truncate(l)))),
            None => Err(self.err(format!("missing `{name}`"))),
        }
    }

    /// Enters section `name` (after `$MeshFormat`, once) and reads its header:
    /// the block count and the total count of `what` (items of at least
    /// `per_item` bytes), then the smallest and largest tags.
    fn section_header(
        &mut self,
        name: &'static str,
        format_seen: bool,
        seen_before: bool,
        what: &str,
        per_item: usize,
    ) -> Result<(usize, usize)> {
        self.section = name;
        if !format_seen {
            return Err(self.err(format!("`{name}` before `$MeshFormat`")));
        }
        if seen_before {
            return Err(self.err(format!("a second `{name}` section")));
        }
        let per_block = if self.binary { 12 + self.size_bytes } else { 8 };
        let blocks = self.count("block count", per_block)?;
        let total = self.count(&format!("{what} count"), per_item)?;
        let _min_tag = self.size("the smallest tag")?;
        let _max_tag = self.size("the largest tag")?;
        Ok((blocks, total))
    }

    /// Skips an unread section to the line after `$End<name>`.
    fn skip_section(&mut self, name: &str) -> Result<()> {
        let end = format!("\n$End{name}");
        let hay = &self.b[self.pos.saturating_sub(1)..];
        match hay.windows(end.len()).position(|w| w == end.as_bytes()) {
            Some(i) => {
                self.pos = self.pos.saturating_sub(1) + i + 1;
                self.line();
                Ok(())
            }
            None => Err(self.err(format!("section `${name}` has no `$End{name}`"))),
        }
    }
}

fn truncate(s: &str) -> String {
    let mut t: String = s.chars().take(40).collect();
    if t.len() < s.len() {
        t.push('…');
    }
    t
}

/// Positions and tetrahedra (indices into the positions) of an MSH 4.1 file.
pub(crate) fn parse(bytes: &[u8]) -> Result<(Vec<Vec3>, Vec<[usize; 4]>)> {
    let mut r = Reader {
        b: bytes,
        pos: 0,
        binary: false,
        size_bytes: 8,
        section: "header",
    };
    let mut format = false;
    let mut positions: Option<Vec<Vec3>> = None;
    let mut tag_to_index: HashMap<u64, usize> = HashMap::new();
    let mut tet_tags: Option<Vec<[u64; 4]>> = None;
    loop {
        r.skip_space();
        let Some(line) = r.line() else { break };
        let name = line.trim_end();
        match name {
            "$MeshFormat" => {
                r.section = "$MeshFormat";
                let version: String = r.parse("a version")?;
                if version != "4.1" {
                    return Err(r.err(format!("version {}, only 4.1 is read", truncate(&version))));
                }
                let kind: u32 = r.parse("a file type")?;
                let size: u64 = r.parse("a data size")?;
                if kind > 1 {
                    return Err(r.err(format!(
                        "file type {kind}, expected 0 (ASCII) or 1 (binary)"
                    )));
                }
                if size != 4 && size != 8 {
                    return Err(r.err(format!("data size {size}, expected 8 (or 4)")));
                }
                r.size_bytes = size as usize;
                if kind == 1 {
                    // A binary one (4 bytes) follows on its own line: the byte order.
                    r.line();
                    let one = i32::from_le_bytes(r.bytes()?);
                    if one != 1 {
                        return Err(r.err("big-endian binary files are not read"));
                    }
                    r.binary = true;
                }
                r.expect_end("$EndMeshFormat")?;
                format = true;
            }
            "$Nodes" => {
                let per_node = if r.binary { r.size_bytes + 24 } else { 8 };
                let (blocks, total) =
                    r.section_header("$Nodes", format, positions.is_some(), "node", per_node)?;
                let mut x = Vec::with_capacity(total);
                tag_to_index.reserve(total);
                for _ in 0..blocks {
                    let dim = r.int("an entity dimension")?;
                    let _entity = r.int("an entity tag")?;
                    let parametric = r.int("the parametric flag")?;
                    if !(0..=3).contains(&dim) || !(0..=1).contains(&parametric) {
                        return Err(r.err(format!(
                            "block header: dimension {dim}, parametric flag {parametric}"
                        )));
                    }
                    let n = r.count("block node count", per_node)?;
                    if x.len() + n > total {
                        return Err(r.err(format!(
                            "the blocks hold more than the {total} nodes announced"
                        )));
                    }
                    let base = x.len();
                    for i in 0..n {
                        let tag = r.size("a node tag")?;
                        if tag_to_index.insert(tag, base + i).is_some() {
                            return Err(r.err(format!("node tag {tag} appears twice")));
                        }
                    }
                    let extra = if parametric == 1 { dim as usize } else { 0 };
                    for _ in 0..n {
                        let p = v3(r.float()?, r.float()?, r.float()?);
                        for _ in 0..extra {
                            r.float()?;
                        }
                        x.push(p);
                    }
                }
                if x.len() != total {
                    return Err(r.err(format!(
                        "{} nodes in the blocks, {total} announced",
                        x.len()
                    )));
                }
                r.expect_end("$EndNodes")?;
                positions = Some(x);
            }
            "$Elements" => {
                let per_elem = if r.binary { 2 * r.size_bytes } else { 4 };
                let (blocks, total) =
                    r.section_header("$Elements", format, tet_tags.is_some(), "element", per_elem)?;
                let mut tets = Vec::new();
                let mut seen = 0usize;
                for _ in 0..blocks {
                    let _dim = r.int("an entity dimension")?;
                    let _entity = r.int("an entity tag")?;
                    let kind = r.int("an element type")?;
                    let per = nodes_per_element(kind)
                        .ok_or_else(|| r.err(format!("unsupported element type {kind}")))?;
                    let n = r.count("block element count", per_elem)?;
                    seen += n;
                    if seen > total {
                        return Err(r.err(format!(
                            "the blocks hold more than the {total} elements announced"
                        )));
                    }
                    let keep = kind == 4 || kind == 11;
                    if keep {
                        tets.reserve(n);
                    }
                    for _ in 0..n {
                        let _tag = r.size("an element tag")?;
                        let mut t = [0u64; 4];
                        for k in 0..per {
                            let v = r.size("a node tag")?;
                            if k < 4 {
                                t[k] = v;
                            }
                        }
                        if keep {
                            tets.push(t);
                        }
                    }
                }
                if seen != total {
                    return Err(r.err(format!("{seen} elements in the blocks, {total} announced")));
                }
                r.expect_end("$EndElements")?;
                tet_tags = Some(tets);
            }
            other if other.starts_with('$') && !other.starts_with("$End") => {
                r.section = "section";
                r.skip_section(&other[1..])?;
            }
            other => {
                return Err(r.err(format!("unexpected line `{}`", truncate(other))));
            }
        }
    }
    r.section = "file";
    if !format {
        return Err(r.err("no `$MeshFormat` section"));
    }
    let positions = positions.ok_or_else(|| r.err("no `$Nodes` section"))?;
    let tet_tags = tet_tags.ok_or_else(|| r.err("no `$Elements` section"))?;
    let mut tets = Vec::with_capacity(tet_tags.len());
    for (e, t) in tet_tags.iter().enumerate() {
        let mut tet = [0usize; 4];
        for k in 0..4 {
            tet[k] = *tag_to_index.get(&t[k]).ok_or_else(|| SoftTissueError::Parse {
                format: F,
                reason: format!(
                    "$Elements: tetrahedron {} references node tag {}, which no node block lists",
                    e + 1,
                    t[k]
                ),
            })?;
        }
        tets.push(tet);
    }
    if tets.is_empty() {
        return Err(SoftTissueError::Parse {
            format: F,
            reason: "no tetrahedra (element type 4 or 11)".into(),
        });
    }
    Ok((positions, tets))
}
