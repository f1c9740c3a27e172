//! A global allocator for the test binaries that include this file: it
//! forwards every call to the system allocator and notes, per thread, the
//! largest single allocation (the loader tests) and the number of
//! allocations (the steady-state tests). Each binary uses what it needs.
#![allow(dead_code)]

use bevy_soft_tissue::solver::PreconditionerKind;

pub struct TrackingAlloc;

thread_local! {
    static MAX_ALLOC: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
    static ALLOCS: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

fn note_alloc(size: usize) {
    let _ = MAX_ALLOC.try_with(|m| m.set(m.get().max(size)));
    let _ = ALLOCS.try_with(|n| n.set(n.get() + 1));
}

// SAFETY: every call is forwarded to the system allocator unchanged.
unsafe impl std::alloc::GlobalAlloc for TrackingAlloc {
    unsafe fn alloc(&self, l: std::alloc::Layout) -> *mut u8 {
        note_alloc(l.size());
        unsafe { std::alloc::System.alloc(l) }
    }
    unsafe fn alloc_zeroed(&self, l: std::alloc::Layout) -> *mut u8 {
        note_alloc(l.size());
        unsafe { std::alloc::System.alloc_zeroed(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: std::alloc::Layout) {
        unsafe { std::alloc::System.dealloc(p, l) }
    }
    unsafe fn realloc(&self, p: *mut u8, l: std::alloc::Layout, size: usize) -> *mut u8 {
        note_alloc(size);
        unsafe { std::alloc::System.realloc(p, l, size) }
    }
}

#[global_allocator]
static ALLOC: TrackingAlloc = TrackingAlloc;

/// Allocations (and reallocations) made by the current thread so far.
pub fn allocations() -> usize {
    ALLOCS.with(|n| n.get())
}

/// Forgets the current thread's largest allocation.
pub fn reset_max_alloc() {
    MAX_ALLOC.with(|m| m.set(0));
}

/// The current thread's largest allocation since [`reset_max_alloc`].
pub fn max_alloc() -> usize {
    MAX_ALLOC.with(|m| m.get())
}

/// Asserts that the steps after the first ten of `counts` (allocations per
/// step) allocated nothing. The first time a lagged step waits for its
/// factor, crossbeam makes the waiting thread's context and the channel's
/// waiter slot (once per thread and channel, kept after): for
/// `AsyncLagged` one step may show up to four. A per-step allocation would
/// show in every counted step.
pub fn assert_steady(kind: PreconditionerKind, counts: &[usize], what: &str) {
    let warm = &counts[10..];
    let (steps, once) = if matches!(kind, PreconditionerKind::AsyncLagged { .. }) {
        (1, 4)
    } else {
        (0, 0)
    };
    assert!(
        warm.iter().filter(|&&n| n > 0).count() <= steps && warm.iter().all(|&n| n <= once),
        "{what}: allocations per step {counts:?}"
    );
}
