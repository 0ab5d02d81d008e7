//! Per-task row storage: each task writes a query's row straight into its own buffer, sorts
//! it there and records it ([`RowSink`]); the driver later copies the rows to their offsets.
//! Also the max_edges guard's running count, and [`SharedMut`], the pointer through which
//! threads write disjoint parts of one array.

use super::sort::sort_in_place;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// A raw pointer that several threads write through, each to rows no other thread touches.
#[derive(Clone, Copy)]
pub(crate) struct SharedMut<T>(pub(crate) *mut T);
unsafe impl<T> Send for SharedMut<T> {}
unsafe impl<T> Sync for SharedMut<T> {}

impl<T> SharedMut<T> {
    /// A method, not a field access, so closures capture the Sync wrapper, not the pointer.
    #[inline(always)]
    pub(crate) fn ptr(self) -> *mut T {
        self.0
    }
}

/// What one task found: its queries' sorted rows back to back, ready to be copied to their
/// offsets.
#[derive(Default)]
pub(crate) struct TaskRows {
    /// senders[..used] are this call's rows; the rest is room kept from earlier calls, so
    /// that a row is written once rather than zeroed first. At least ROW_SLACK values always
    /// follow the last row.
    pub(super) senders: Vec<u32>,
    pub(super) used: usize,
    /// (query, row length) in the order of the rows. Kept here, not written to arrays by
    /// query index: queries come in cell order, so two threads writing such arrays would
    /// share (and fight over) nearly every cache line.
    pub(super) queries: Vec<(u32, u32)>,
    /// dim values per edge, only when shifts were asked for.
    pub(super) shifts: Vec<i32>,
}

/// Values of room past every row: the in-place sort reads and writes 32 values from a row's
/// start, and [`Searcher::fill`](super::Searcher::fill) copies rows in whole chunks of 4 and
/// at least 16.
const ROW_SLACK: usize = 32;

/// Edges a task keeps between two looks at the shared total (the max_edges guard).
const CHECK_EVERY: u64 = 1 << 20;

/// Where one task keeps its rows: a row is written straight into the task's buffer (by the
/// cell list's compaction, or copied from an unsorted list), sorted there, and recorded.
pub(crate) struct RowSink<'a> {
    pub(super) rows: &'a mut TaskRows,
    pub(super) avx2: bool,
    pub(super) dim: usize,
    pub(super) want_shifts: bool,
    pub(super) order: Vec<usize>,
    pub(super) pending: u64,
    pub(super) total: &'a AtomicU64,
    pub(super) over: &'a AtomicBool,
    pub(super) max_edges: u64,
}

impl RowSink<'_> {
    /// Room for a row of up to `len` values at the end of the task's buffer (and ROW_SLACK more).
    #[inline(always)]
    pub(crate) fn room(&mut self, len: usize) -> &mut [u32] {
        let rows = &mut *self.rows;
        let need = rows.used + len + ROW_SLACK;
        if rows.senders.len() < need {
            rows.senders.resize(need.max(2 * rows.senders.len()), 0);
        }
        &mut rows.senders[rows.used..]
    }

    /// Sorts the first n values of the last [`RowSink::room`] and keeps them as the row of
    /// query i. False when the search must stop (past max_edges).
    #[inline(always)]
    pub(crate) fn keep(&mut self, i: usize, n: usize) -> bool {
        let used = self.rows.used;
        sort_in_place(self.avx2, &mut self.rows.senders[used..], n);
        if self.want_shifts {
            // No periodic axis: the shifts are all zero.
            let len = self.rows.shifts.len();
            self.rows.shifts.resize(len + n * self.dim, 0);
        }
        self.record(i, n)
    }

    /// Keeps an unsorted row (and its shifts when asked for) as the row of query i.
    pub(crate) fn push(&mut self, i: usize, senders: &mut [u32], shifts: &[[i32; 3]]) -> bool {
        let len = senders.len();
        if !self.want_shifts {
            self.room(len)[..len].copy_from_slice(senders);
            return self.keep(i, len);
        }
        let used = self.rows.used;
        self.room(len);
        self.order.clear();
        self.order.extend(0..len);
        self.order.sort_unstable_by_key(|&k| senders[k]);
        for (e, &k) in self.order.iter().enumerate() {
            self.rows.senders[used + e] = senders[k];
            // No periodic axis: the shifts are all zero.
            let sh = shifts.get(k).copied().unwrap_or_default();
            self.rows.shifts.extend_from_slice(&sh[..self.dim]);
        }
        self.record(i, len)
    }

    #[inline(always)]
    fn record(&mut self, i: usize, n: usize) -> bool {
        self.rows.queries.push((i as u32, n as u32));
        self.rows.used += n;
        self.pending += n as u64;
        if self.pending >= CHECK_EVERY {
            return self.flush();
        }
        true
    }

    /// Adds the pending edges to the shared total; false when it is past max_edges.
    pub(super) fn flush(&mut self) -> bool {
        let edges = std::mem::take(&mut self.pending);
        if self.total.fetch_add(edges, Ordering::Relaxed) + edges > self.max_edges {
            self.over.store(true, Ordering::Relaxed);
        }
        !self.over.load(Ordering::Relaxed)
    }
}
