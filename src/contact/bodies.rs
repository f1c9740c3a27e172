//! How the contact phases reach bodies and tools: by index, through
//! [`Bodies`] / [`BodiesMut`] and [`Tools`] / [`ToolsMut`].
//!
//! A contact names its bodies by index ([`super::ContactSide::body`]) and its
//! tool by index ([`super::ContactOther::Tool`]). The phases only ever ask
//! "body `i`" or "tool `i`", so any container that can answer that works, and
//! no caller has to collect a `Vec` of references each step: a slice or array
//! of bodies, of `&` or `&mut` references ([`AsBody`]), a `Vec`, or a view
//! over ECS entities (the plugin's query views).

use super::tool::RigidTool;
use crate::body::DeformableBody;

/// A value that is, or refers to, a body.
pub trait AsBody {
    /// The body.
    fn as_body(&self) -> &DeformableBody;
}

/// A value that is, or refers mutably to, a body.
pub trait AsBodyMut: AsBody {
    /// The body, mutably.
    fn as_body_mut(&mut self) -> &mut DeformableBody;
}

/// A value that is, or refers to, a tool.
pub trait AsTool {
    /// The tool.
    fn as_tool(&self) -> &RigidTool;
}

/// A value that is, or refers mutably to, a tool.
pub trait AsToolMut: AsTool {
    /// The tool, mutably.
    fn as_tool_mut(&mut self) -> &mut RigidTool;
}

macro_rules! as_impls {
    ($t:ty, $as:ident, $f:ident, $as_mut:ident, $fm:ident) => {
        impl $as for $t {
            fn $f(&self) -> &$t {
                self
            }
        }
        impl $as_mut for $t {
            fn $fm(&mut self) -> &mut $t {
                self
            }
        }
        impl $as for &$t {
            fn $f(&self) -> &$t {
                self
            }
        }
        impl $as for &mut $t {
            fn $f(&self) -> &$t {
                self
            }
        }
        impl $as_mut for &mut $t {
            fn $fm(&mut self) -> &mut $t {
                self
            }
        }
    };
}
as_impls!(DeformableBody, AsBody, as_body, AsBodyMut, as_body_mut);
as_impls!(RigidTool, AsTool, as_tool, AsToolMut, as_tool_mut);

/// Bodies by index (see the module docs).
pub trait Bodies {
    /// Number of bodies.
    fn len(&self) -> usize;
    /// Body `i` (`i < len()`).
    fn body(&self, i: usize) -> &DeformableBody;
    /// Whether there is no body.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Bodies by index, mutably.
pub trait BodiesMut: Bodies {
    /// Body `i` (`i < len()`), mutably.
    fn body_mut(&mut self, i: usize) -> &mut DeformableBody;
}

/// Tools by index (see the module docs).
pub trait Tools {
    /// Number of tools.
    fn len(&self) -> usize;
    /// Tool `i` (`i < len()`).
    fn tool(&self, i: usize) -> &RigidTool;
    /// Whether there is no tool.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Tools by index, mutably.
pub trait ToolsMut: Tools {
    /// Tool `i` (`i < len()`), mutably.
    fn tool_mut(&mut self, i: usize) -> &mut RigidTool;
}

macro_rules! container_impls {
    ($as:ident, $f:ident, $as_mut:ident, $fm:ident, $tr:ident, $get:ident, $tr_mut:ident, $get_mut:ident, $ret:ty) => {
        impl<B: $as> $tr for [B] {
            fn len(&self) -> usize {
                <[B]>::len(self)
            }
            fn $get(&self, i: usize) -> &$ret {
                self[i].$f()
            }
        }
        impl<B: $as_mut> $tr_mut for [B] {
            fn $get_mut(&mut self, i: usize) -> &mut $ret {
                self[i].$fm()
            }
        }
        impl<B: $as, const N: usize> $tr for [B; N] {
            fn len(&self) -> usize {
                N
            }
            fn $get(&self, i: usize) -> &$ret {
                self[i].$f()
            }
        }
        impl<B: $as_mut, const N: usize> $tr_mut for [B; N] {
            fn $get_mut(&mut self, i: usize) -> &mut $ret {
                self[i].$fm()
            }
        }
        impl<B: $as> $tr for Vec<B> {
            fn len(&self) -> usize {
                Vec::len(self)
            }
            fn $get(&self, i: usize) -> &$ret {
                self[i].$f()
            }
        }
        impl<B: $as_mut> $tr_mut for Vec<B> {
            fn $get_mut(&mut self, i: usize) -> &mut $ret {
                self[i].$fm()
            }
        }
    };
}
container_impls!(
    AsBody,
    as_body,
    AsBodyMut,
    as_body_mut,
    Bodies,
    body,
    BodiesMut,
    body_mut,
    DeformableBody
);
container_impls!(
    AsTool,
    as_tool,
    AsToolMut,
    as_tool_mut,
    Tools,
    tool,
    ToolsMut,
    tool_mut,
    RigidTool
);

/// No tools, for scenes of bodies alone: `solver.detect(&bodies, &NO_TOOLS, h, pass)`.
pub const NO_TOOLS: [&RigidTool; 0] = [];
