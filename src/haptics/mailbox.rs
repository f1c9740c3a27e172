//! A lock-free, allocation-free hand-over of the newest value between two
//! threads (a triple buffer made of two `crossbeam` queues of boxes).

use crossbeam::queue::ArrayQueue;

/// The newest value a writer posted, for a reader on another thread.
///
/// Neither side ever blocks: [`Self::post`] replaces a value the reader has
/// not taken yet, and [`Self::take`] returns `None` when nothing new came.
/// Boxes circulate between the two queues, so after the first few posts
/// nothing is allocated.
#[derive(Debug)]
pub struct Mailbox<T> {
    full: ArrayQueue<Box<T>>,
    free: ArrayQueue<Box<T>>,
}

impl<T: Default> Default for Mailbox<T> {
    fn default() -> Self {
        Self::new()
    }
}

impl<T: Default> Mailbox<T> {
    /// An empty mailbox with three boxes ready.
    pub fn new() -> Self {
        let free = ArrayQueue::new(4);
        for _ in 0..3 {
            let _ = free.push(Box::default());
        }
        Self {
            full: ArrayQueue::new(1),
            free,
        }
    }

    /// Fills a free box with `fill` and makes it the newest value, recycling
    /// the one it replaces.
    pub fn post(&self, fill: impl FnOnce(&mut T)) {
        let mut b = self.free.pop().unwrap_or_default();
        fill(&mut b);
        if let Some(old) = self.full.force_push(b) {
            let _ = self.free.push(old);
        }
    }

    /// The newest value, if one came since the last call. Give the box back
    /// with [`Self::recycle`] when done with it.
    pub fn take(&self) -> Option<Box<T>> {
        self.full.pop()
    }

    /// Returns a box taken with [`Self::take`] for reuse.
    pub fn recycle(&self, b: Box<T>) {
        let _ = self.free.push(b);
    }
}
