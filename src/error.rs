//! Errors returned by the numerical core.
//!
//! Every fallible entry point of the core returns [`Result<T>`]. Errors name
//! the offending element, vertex, node or parameter so that a malformed mesh
//! or an impossible setting can be fixed without a debugger. The core never
//! panics on bad input and never lets a NaN through silently.

use thiserror::Error;

/// Result alias used across the crate.
pub type Result<T> = std::result::Result<T, SoftTissueError>;

/// Everything that can go wrong when building or stepping a soft body.
#[derive(Debug, Clone, Error, PartialEq)]
pub enum SoftTissueError {
    /// The mesh has no vertices or no tetrahedra.
    #[error("empty mesh: {0}")]
    EmptyMesh(&'static str),
    /// A vertex coordinate is NaN or infinite.
    #[error("vertex {vertex} has a non-finite coordinate {value:?}")]
    NonFiniteVertex {
        /// Vertex index.
        vertex: usize,
        /// The offending position.
        value: [f64; 3],
    },
    /// A tetrahedron references a vertex that does not exist.
    #[error("tetrahedron {tet} references vertex {index}, but the mesh has {len} vertices")]
    IndexOutOfRange {
        /// Tetrahedron index.
        tet: usize,
        /// The bad vertex index.
        index: usize,
        /// Number of vertices.
        len: usize,
    },
    /// A tetrahedron uses the same vertex twice.
    #[error("tetrahedron {tet} repeats vertex {vertex}")]
    RepeatedVertex {
        /// Tetrahedron index.
        tet: usize,
        /// The repeated vertex.
        vertex: usize,
    },
    /// A vertex is not used by any tetrahedron (it would carry no mass).
    #[error("vertex {vertex} is not used by any tetrahedron")]
    UnusedVertex {
        /// Vertex index.
        vertex: usize,
    },
    /// A tetrahedron has (near) zero volume.
    #[error("tetrahedron {tet} is degenerate (volume {volume:e})")]
    DegenerateTet {
        /// Tetrahedron index.
        tet: usize,
        /// Its signed volume.
        volume: f64,
    },
    /// A tetrahedron has negative orientation and re-orientation was not requested.
    #[error(
        "tetrahedron {tet} is inverted (signed volume {volume:e}); enable re-orientation to fix it"
    )]
    InvertedTet {
        /// Tetrahedron index.
        tet: usize,
        /// Its signed volume.
        volume: f64,
    },
    /// A physical or numerical parameter is outside its valid range.
    #[error("invalid parameter `{name}` = {value}: {reason}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// The value given.
        value: f64,
        /// What the valid range is.
        reason: &'static str,
    },
    /// A per-element or per-node array has the wrong length.
    #[error("`{name}` has length {got}, expected {expected}")]
    LengthMismatch {
        /// Which array.
        name: &'static str,
        /// Its length.
        got: usize,
        /// The expected length.
        expected: usize,
    },
    /// A node index given by the caller does not exist.
    #[error("node {node} out of range: the body has {len} nodes")]
    NodeOutOfRange {
        /// The bad node.
        node: usize,
        /// Number of nodes.
        len: usize,
    },
    /// A mesh file could not be parsed.
    #[error("malformed {format} file: {reason}")]
    Parse {
        /// File format.
        format: &'static str,
        /// What is wrong, with the line when known.
        reason: String,
    },
    /// Reading a file failed.
    #[error("i/o error on {path}: {reason}")]
    Io {
        /// The path.
        path: String,
        /// The OS error text.
        reason: String,
    },
    /// The factorization met a non-positive pivot: the matrix is not SPD.
    #[error(
        "LDLᵀ factorization failed: pivot {pivot:e} at node {node} (matrix not positive definite)"
    )]
    NotPositiveDefinite {
        /// Node (in original numbering) where the pivot failed.
        node: usize,
        /// The pivot value.
        pivot: f64,
    },
    /// A non-finite value appeared in the state or the right-hand side.
    #[error("non-finite value in {0}")]
    NonFinite(&'static str),
    /// A contact tool shape is invalid.
    #[error("invalid tool shape: {0}")]
    InvalidShape(String),
    /// The background factorization panicked; its slot was released and the
    /// body keeps its previous factor.
    #[error("the background factorization panicked: {0}")]
    WorkerPanic(String),
    /// A step could not finish what it started (for example, a body or tool
    /// the contact phases listed was removed part way through the step).
    #[error("step interrupted: {0}")]
    Interrupted(&'static str),
    /// The accuracy study could not run or write its outputs.
    #[error("accuracy study: {0}")]
    Study(String),
    /// The GPU path failed (device, shader or validation error).
    #[error("GPU compliance: {0}")]
    Gpu(String),
    /// A request is larger than a mode supports.
    #[error("{what}: size {size} exceeds the limit {limit}")]
    TooLarge {
        /// What was requested.
        what: &'static str,
        /// Requested size.
        size: usize,
        /// Maximum size.
        limit: usize,
    },
}

/// Checks that `value` is finite and inside `[min, max]`.
pub(crate) fn check_range(name: &'static str, value: f64, min: f64, max: f64) -> Result<()> {
    if !value.is_finite() || value < min || value > max {
        return Err(SoftTissueError::InvalidParameter {
            name,
            value,
            reason: "out of range or not finite",
        });
    }
    Ok(())
}

/// The time steps the solver accepts, seconds: 1 ns to 10⁵ s. Below, `h²`
/// terms underflow against the mass; steps of minutes or hours are a
/// quasi-static solve (the implicit step goes to equilibrium); above, the
/// `h²` terms head for overflow.
pub const TIMESTEP_RANGE: (f64, f64) = (1e-9, 1e5);

/// Checks a time step against [`TIMESTEP_RANGE`].
pub fn check_timestep(h: f64) -> Result<()> {
    if !(h.is_finite() && h >= TIMESTEP_RANGE.0 && h <= TIMESTEP_RANGE.1) {
        return Err(SoftTissueError::InvalidParameter {
            name: "h (time step)",
            value: h,
            reason: "must be finite and between 1 ns and 1e5 s",
        });
    }
    Ok(())
}

/// Checks that a vector's squared norm is finite (its components alone can
/// be finite while `|v|²` overflows, which CG would then misread).
pub(crate) fn check_vector(name: &'static str, v: &crate::math::Vec3) -> Result<()> {
    if !v.norm_squared().is_finite() {
        return Err(SoftTissueError::InvalidParameter {
            name,
            value: v.amax(),
            reason: "not finite, or its squared norm overflows",
        });
    }
    Ok(())
}

/// Checks that `value` is finite and strictly positive.
pub(crate) fn check_positive(name: &'static str, value: f64) -> Result<()> {
    if !value.is_finite() || value <= 0.0 {
        return Err(SoftTissueError::InvalidParameter {
            name,
            value,
            reason: "must be finite and > 0",
        });
    }
    Ok(())
}
