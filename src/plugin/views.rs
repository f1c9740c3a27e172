//! The contact phases' [`Bodies`] / [`Tools`] over ECS queries: body `i` is
//! the entity at index `i` of the solver's sorted entity list. No per-step
//! collection; the systems check that every listed entity exists before
//! they build a view.

use bevy::prelude::*;

use super::components::{SoftBody, Tool};
use crate::body::DeformableBody;
use crate::contact::{Bodies, BodiesMut, RigidTool, Tools, ToolsMut};

const LISTED: &str = "the system checked that every listed entity exists";

/// Bodies, read-only.
pub(super) struct BodyView<'a, 'w, 's> {
    pub(super) q: &'a Query<'w, 's, &'static SoftBody>,
    pub(super) e: &'a [Entity],
}

impl Bodies for BodyView<'_, '_, '_> {
    fn len(&self) -> usize {
        self.e.len()
    }
    fn body(&self, i: usize) -> &DeformableBody {
        &self.q.get(self.e[i]).expect(LISTED).0
    }
}

/// Bodies, mutable.
pub(super) struct BodyViewMut<'a, 'w, 's> {
    pub(super) q: &'a mut Query<'w, 's, &'static mut SoftBody>,
    pub(super) e: &'a [Entity],
}

impl Bodies for BodyViewMut<'_, '_, '_> {
    fn len(&self) -> usize {
        self.e.len()
    }
    fn body(&self, i: usize) -> &DeformableBody {
        &self.q.get(self.e[i]).expect(LISTED).0
    }
}

impl BodiesMut for BodyViewMut<'_, '_, '_> {
    fn body_mut(&mut self, i: usize) -> &mut DeformableBody {
        &mut self.q.get_mut(self.e[i]).expect(LISTED).into_inner().0
    }
}

/// Tools, read-only.
pub(super) struct ToolView<'a, 'w, 's> {
    pub(super) q: &'a Query<'w, 's, &'static Tool>,
    pub(super) e: &'a [Entity],
}

impl Tools for ToolView<'_, '_, '_> {
    fn len(&self) -> usize {
        self.e.len()
    }
    fn tool(&self, i: usize) -> &RigidTool {
        &self.q.get(self.e[i]).expect(LISTED).0
    }
}

/// Tools, mutable.
pub(super) struct ToolViewMut<'a, 'w, 's> {
    pub(super) q: &'a mut Query<'w, 's, &'static mut Tool>,
    pub(super) e: &'a [Entity],
}

impl Tools for ToolViewMut<'_, '_, '_> {
    fn len(&self) -> usize {
        self.e.len()
    }
    fn tool(&self, i: usize) -> &RigidTool {
        &self.q.get(self.e[i]).expect(LISTED).0
    }
}

impl ToolsMut for ToolViewMut<'_, '_, '_> {
    fn tool_mut(&mut self, i: usize) -> &mut RigidTool {
        &mut self.q.get_mut(self.e[i]).expect(LISTED).into_inner().0
    }
}

/// Whether every entity of `list` is matched by `q`.
pub(super) fn all_present<D: bevy::ecs::query::QueryData, F: bevy::ecs::query::QueryFilter>(
    q: &Query<'_, '_, D, F>,
    list: &[Entity],
) -> bool {
    list.iter().all(|e| q.contains(*e))
}
