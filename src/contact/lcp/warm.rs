//! Warm start: the forces of the last step's first pass, by contact identity.

/// Identity of a contact across steps: (body id, its nodes, other side), where
/// the nodes are a vertex's (`[v, 0, 0]`) or a surface triangle's (a tool
/// inside a face, [`crate::contact::ContactSettings::tool_faces`]) and the
/// other side is a tool index or a body id.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ContactKey {
    /// Id of the vertex's body ([`crate::body::DeformableBody::id`]).
    pub body: u64,
    /// The contact's nodes on that body: `[v, 0, 0]` for a vertex, the
    /// triangle's three for a face.
    pub nodes: [u32; 3],
    /// What the vertex or face touches.
    pub other: OtherKey,
}

/// The other side of a [`ContactKey`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum OtherKey {
    /// A tool, by index.
    Tool(usize),
    /// A body, by id.
    Body(u64),
}

/// Forces of the last step's first pass by contact, to start the next solve from.
#[derive(Debug, Default)]
pub struct WarmStart {
    previous: std::collections::HashMap<ContactKey, [f64; 3]>,
}

impl WarmStart {
    /// Copies the remembered forces of the contacts `keys` into `lambda`
    /// (`rows[c]..rows[c+1]` are the rows of contact `c`).
    pub fn apply(
        &self,
        keys: impl Iterator<Item = ContactKey>,
        rows: &[usize],
        lambda: &mut [f64],
    ) {
        for (ci, key) in keys.enumerate() {
            if let Some(prev) = self.previous.get(&key) {
                let r = rows[ci];
                let k = rows[ci + 1] - r;
                lambda[r..r + k].copy_from_slice(&prev[..k]);
            }
        }
    }

    /// Forgets every remembered force.
    pub fn clear(&mut self) {
        self.previous.clear();
    }

    /// Remembers the force `f` of contact `key`.
    pub fn remember(&mut self, key: ContactKey, f: [f64; 3]) {
        self.previous.insert(key, f);
    }
}
