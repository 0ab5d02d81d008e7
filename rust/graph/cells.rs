//! Cell-list search: a uniform grid of cell size >= radius, rebuilt each call by counting sort
//! from the graph's actual bounding box, with positions copied in cell order (structure of
//! arrays) so that each query scans a few contiguous runs instead of 9 or 27 scattered cells.

use super::prepare::Prepared;
use super::query::{accept_at, clump_edges, tight, Ctx, Found};
use super::rows::{RowSink, SharedMut};
use super::simd::{has_avx2, with_simd};
use rayon::prelude::*;

/// The grid declines (and the caller uses the k-d tree) when it would need more cells than
/// this many per particle: an outlier far away must not allocate billions of empty cells.
const MAX_CELLS_PER_PARTICLE: usize = 4;
const MIN_CELL_BUDGET: usize = 4096;
/// From this many particles the counting sort runs on every thread.
const PARALLEL_SORT_FROM: usize = 8_192;
/// Values past the end of the sorted arrays, so that [`Grid::gather`] may copy 16 values
/// from the start of the last run whatever its length.
const CHUNK_SLACK: usize = 16;
/// Slots past the padded width of each axis of a gathered block (see [`Grid::gather`]).
const BLOCK_SLACK: usize = 16;

pub(crate) struct Grid<const D: usize> {
    len: usize,
    /// Cells per axis; the last axis varies fastest in a cell id.
    n: [usize; D],
    lo: [f64; D],
    inv_cell: [f64; D],
    periodic: [bool; D],
    /// cell_start[c]..cell_start[c + 1] are the sorted positions of cell c.
    cell_start: Vec<u32>,
    /// The sum over cells of their particle count squared: no more edges can come from
    /// within cells (see [`Grid::sure_edges`]).
    pairs_in_cells: u64,
    /// Sorted position -> global particle index.
    order: Vec<u32>,
    /// Coordinates in sorted order, axis-major: sorted[d * len + p].
    sorted: Vec<f64>,
    /// Scratch for the counting sort: cell id by input order, and per-part histograms whose
    /// first n_cells values then become the cursors.
    cell_in: Vec<u32>,
    cursor: Vec<u32>,
}

impl<const D: usize> Default for Grid<D> {
    fn default() -> Self {
        Grid {
            len: 0,
            n: [1; D],
            lo: [0.0; D],
            inv_cell: [0.0; D],
            periodic: [false; D],
            cell_start: Vec::new(),
            pairs_in_cells: 0,
            order: Vec::new(),
            sorted: Vec::new(),
            cell_in: Vec::new(),
            cursor: Vec::new(),
        }
    }
}

/// Up to three distinct neighbouring cells along one axis (fewer at a wall, or on a periodic
/// axis of one or two cells where -1 and +1 are the same cell).
#[derive(Clone, Copy)]
struct AxisCells {
    cells: [usize; 3],
    len: usize,
}

impl AxisCells {
    fn new(c: usize, n: usize, periodic: bool) -> Self {
        let mut out = AxisCells {
            cells: [0; 3],
            len: 0,
        };
        if periodic {
            let mut cand = [(c + n - 1) % n, c, (c + 1) % n];
            cand.sort_unstable();
            for x in cand {
                if out.len == 0 || out.cells[out.len - 1] != x {
                    out.cells[out.len] = x;
                    out.len += 1;
                }
            }
        } else {
            for x in c.saturating_sub(1)..=(c + 1).min(n - 1) {
                out.cells[out.len] = x;
                out.len += 1;
            }
        }
        out
    }

    fn as_slice(&self) -> &[usize] {
        &self.cells[..self.len]
    }

    /// Runs of consecutive cells, as inclusive (first, last) pairs: contiguous in memory.
    fn runs(&self) -> ([(usize, usize); 3], usize) {
        let mut runs = [(0, 0); 3];
        let mut k = 0;
        for &c in self.as_slice() {
            if k > 0 && runs[k - 1].1 + 1 == c {
                runs[k - 1].1 = c;
            } else {
                runs[k] = (c, c);
                k += 1;
            }
        }
        (runs, k)
    }
}

impl<const D: usize> Grid<D> {
    pub fn len(&self) -> usize {
        self.len
    }

    /// Edges sure to exist: all pairs within each cell whose particles are tight (see
    /// [`tight`]), worked out only when the cells could hold more than `limit` pairs.
    pub fn sure_edges(&self, r2: f64, self_edges: bool, limit: u64) -> u64 {
        if self.pairs_in_cells <= limit {
            return 0;
        }
        let mut sure = 0;
        for w in self.cell_start.windows(2) {
            let (a, b) = (w[0] as usize, w[1] as usize);
            if b - a < 2 {
                continue;
            }
            let mut lo = [f64::INFINITY; D];
            let mut hi = [f64::NEG_INFINITY; D];
            for d in 0..D {
                for &x in &self.sorted[d * self.len + a..d * self.len + b] {
                    lo[d] = lo[d].min(x);
                    hi[d] = hi[d].max(x);
                }
            }
            if tight(&lo, &hi, r2) {
                sure += clump_edges(b - a, self_edges);
            }
        }
        sure
    }

    /// Indexes particles start..end (the counting sort on every thread when `parallel` and
    /// large); false when the grid would be far too sparse.
    pub fn rebuild(
        &mut self,
        prepared: &Prepared,
        start: usize,
        end: usize,
        parallel: bool,
    ) -> bool {
        let metric = &prepared.metric;
        let coords = &prepared.coords[start * D..end * D];
        let len = end - start;
        self.len = len;
        let (lo, hi) = bounding_box::<D>(coords);
        let mut cells = 1.0f64;
        for d in 0..D {
            self.periodic[d] = metric.periodic[d];
            if metric.periodic[d] {
                // Whole cells that tile the box, each at least `reach` wide.
                let l = metric.lengths[d];
                let n = (l / metric.reach).floor().max(1.0);
                self.n[d] = n as usize;
                self.lo[d] = 0.0;
                self.inv_cell[d] = n / l;
            } else {
                let extent = if len == 0 { 0.0 } else { hi[d] - lo[d] };
                let n = (extent / metric.reach).floor() + 1.0;
                // An infinite extent (coordinates near f64::MAX) is caught by the budget below.
                self.n[d] = if n.is_finite() {
                    n.min(1e18) as usize
                } else {
                    usize::MAX
                };
                self.lo[d] = if len == 0 { 0.0 } else { lo[d] };
                self.inv_cell[d] = 1.0 / metric.reach;
            }
            cells *= if n_is_huge(self.n[d]) {
                f64::INFINITY
            } else {
                self.n[d] as f64
            };
        }
        // Also below 2^31 cells, so that every cell coordinate and id fits an i32.
        let budget = (MAX_CELLS_PER_PARTICLE * len)
            .max(MIN_CELL_BUDGET)
            .min(i32::MAX as usize);
        if cells > budget as f64 {
            return false;
        }
        let n_cells = cells as usize;

        // Counting sort by cell, stable: each cell lists its particles by index. On a large
        // input every thread counts one part of the input (cut in index order), then places
        // the particles of one run of cells.
        let parts = if parallel && len >= PARALLEL_SORT_FROM {
            rayon::current_num_threads().max(1)
        } else {
            1
        };
        let chunk = len.div_ceil(parts).max(1);
        let parts = len.div_ceil(chunk).max(1);
        let (n, lo, inv) = (self.n, self.lo, self.inv_cell);
        // Arrays that are overwritten in full are resized, not cleared: zeroing them first
        // would be a pass over memory for nothing.
        self.cell_in.resize(len, 0);
        self.cursor.clear();
        self.cursor.resize(parts * n_cells, 0);
        let avx2 = has_avx2();
        let histogram = |((ids, xs), hist): ((&mut [u32], &[f64]), &mut [u32])| {
            // Cell coordinates a block at a time (a multiple of 2 and 3 values, whole points).
            let mut axes = [0i32; 768];
            for (ids, xs) in ids.chunks_mut(axes.len() / D).zip(xs.chunks(axes.len())) {
                let axes = &mut axes[..xs.len()];
                with_simd(avx2, || axis_cells::<D>(&n, &lo, &inv, xs, axes));
                for (id, c) in ids.iter_mut().zip(axes.chunks_exact(D)) {
                    let mut cell = 0;
                    for d in 0..D {
                        cell = cell * n[d] + c[d] as usize;
                    }
                    *id = cell as u32;
                    hist[cell] += 1;
                }
            }
        };
        if parts == 1 {
            histogram(((&mut self.cell_in[..], coords), &mut self.cursor[..]));
        } else {
            self.cell_in
                .par_chunks_mut(chunk)
                .zip(coords.par_chunks(chunk * D))
                .zip(self.cursor.par_chunks_mut(n_cells))
                .for_each(histogram);
        }
        // Histograms to cell starts, and the first part's histogram to the cursors.
        self.cell_start.resize(n_cells + 1, 0);
        let mut acc = 0u32;
        self.pairs_in_cells = 0;
        for c in 0..n_cells {
            let m: u32 = (0..parts).map(|t| self.cursor[t * n_cells + c]).sum();
            self.cell_start[c] = acc;
            self.cursor[c] = acc;
            acc += m;
            self.pairs_in_cells += m as u64 * m as u64;
        }
        self.cell_start[n_cells] = acc;
        self.order.resize(len + CHUNK_SLACK, 0);
        self.sorted.resize(D * len + CHUNK_SLACK, 0.0);
        let (order, sorted, cursor) = (
            SharedMut(self.order.as_mut_ptr()),
            SharedMut(self.sorted.as_mut_ptr()),
            SharedMut(self.cursor.as_mut_ptr()),
        );
        // Each part places the particles of its own run of cells, reading all of cell_in:
        // parts cut by input index would write neighbouring slots of every cell, so nearly
        // every cache line of the output would pass between threads.
        let cell_start = &self.cell_start;
        let first_cell = |t: usize| cell_start.partition_point(|&s| (s as usize) < t * len / parts);
        let cell_in = &self.cell_in;
        let scatter = |t: usize| {
            // first_cell(parts) is past every non-empty cell: only empty ones start at len.
            let (c0, c1) = (first_cell(t), first_cell(t + 1));
            for (k, &c) in cell_in.iter().enumerate() {
                let c = c as usize;
                if c.wrapping_sub(c0) >= c1 - c0 {
                    continue;
                }
                // SAFETY: cursor[c] and the slots cell_start[c]..cell_start[c + 1] belong to
                // the one part that owns cell c; each slot is written once.
                unsafe {
                    let p = *cursor.ptr().add(c) as usize;
                    *cursor.ptr().add(c) += 1;
                    *order.ptr().add(p) = (start + k) as u32;
                }
            }
            // Then the coordinates of this part's sorted positions, in order: one scattered
            // write per particle above instead of 1 + D, and reads of whole points here.
            let (p0, p1) = (cell_start[c0] as usize, cell_start[c1] as usize);
            for p in p0..p1 {
                // SAFETY: as above, the slots p0..p1 belong to this part.
                unsafe {
                    let k = *order.ptr().add(p) as usize - start;
                    for d in 0..D {
                        *sorted.ptr().add(d * len + p) = coords[k * D + d];
                    }
                }
            }
        };
        if parts == 1 {
            scatter(0);
        } else {
            (0..parts).into_par_iter().for_each(scatter);
        }
        true
    }

    /// The contiguous runs of sorted positions (a, b) that can hold neighbours of the
    /// particles of cell c: up to 3 (2D) or 9 (3D) rows, split in two where a periodic row wraps.
    /// Written into `runs`, not returned: copying the array out costs more than filling it.
    fn runs_of_cell(&self, mut id: usize, runs: &mut [(usize, usize); 18]) -> usize {
        if !self.periodic.iter().any(|&p| p) {
            return self.runs_of_open_cell(id, runs);
        }
        let mut c = [0usize; D];
        for d in (0..D).rev() {
            c[d] = id % self.n[d];
            id /= self.n[d];
        }
        let (inner, n_inner) = AxisCells::new(c[D - 1], self.n[D - 1], self.periodic[D - 1]).runs();
        let mut k = 0;
        let mut visit_row = |row: usize| {
            let base = row * self.n[D - 1];
            for &(a, b) in &inner[..n_inner] {
                let (lo, hi) = (self.cell_start[base + a], self.cell_start[base + b + 1]);
                if lo < hi {
                    runs[k] = (lo as usize, hi as usize);
                    k += 1;
                }
            }
        };
        let a0 = AxisCells::new(c[0], self.n[0], self.periodic[0]);
        if D == 2 {
            a0.as_slice().iter().for_each(|&c0| visit_row(c0));
        } else {
            let a1 = AxisCells::new(c[1], self.n[1], self.periodic[1]);
            for &c0 in a0.as_slice() {
                for &c1 in a1.as_slice() {
                    visit_row(c0 * self.n[1] + c1);
                }
            }
        }
        k
    }

    /// [`Grid::runs_of_cell`] without periodic axes: each row of the stencil is one run,
    /// clipped at the walls, found from the cell id by offsets (no per-axis cell lists).
    #[inline(always)]
    fn runs_of_open_cell(&self, id: usize, runs: &mut [(usize, usize); 18]) -> usize {
        let n_last = self.n[D - 1];
        let (row, c_last) = (id / n_last, id % n_last);
        // The run of a row: the cells c - 1 ..= c + 1 of the last axis, within the grid.
        let (left, right) = ((c_last > 0) as usize, (c_last + 1 < n_last) as usize);
        let mut k = 0;
        let mut visit = |same_column: usize| {
            let a = self.cell_start[same_column - left] as usize;
            let b = self.cell_start[same_column + right + 1] as usize;
            runs[k] = (a, b);
            k += (a < b) as usize;
        };
        let rows = |c: usize, n: usize| (c.saturating_sub(1), (c + 1).min(n - 1));
        if D == 2 {
            let (r0, r1) = rows(row, self.n[0]);
            for r in r0..=r1 {
                visit(r * n_last + c_last);
            }
        } else {
            let (c0, c1) = (row / self.n[1], row % self.n[1]);
            let (a0, b0) = rows(c0, self.n[0]);
            let (a1, b1) = rows(c1, self.n[1]);
            for r0 in a0..=b0 {
                for r1 in a1..=b1 {
                    visit((r0 * self.n[1] + r1) * n_last + c_last);
                }
            }
        }
        k
    }

    /// Calls `f(p0, p1, runs)` for each stretch p0..p1 of the queries lo..hi that share a
    /// cell: the stencil is worked out once per cell, not once per query.
    #[inline(always)]
    fn for_each_cell(
        &self,
        lo: usize,
        hi: usize,
        mut f: impl FnMut(usize, usize, &[(usize, usize)]) -> bool,
    ) {
        let mut p = lo;
        let mut runs = [(0, 0); 18];
        // The cell of p: the last one that starts at or before it (empty cells start there too).
        let mut c = self
            .cell_start
            .partition_point(|&s| s as usize <= p)
            .saturating_sub(1);
        while p < hi {
            while self.cell_start[c + 1] as usize <= p {
                c += 1;
            }
            let end = (self.cell_start[c + 1] as usize).min(hi);
            let k = self.runs_of_cell(c, &mut runs);
            if !f(p, end, &runs[..k]) {
                return;
            }
            p = end;
        }
    }

    #[inline(always)]
    fn query_point(&self, p: usize) -> [f64; D] {
        let mut q = [0.0; D];
        for (d, qd) in q.iter_mut().enumerate() {
            *qd = self.sorted[d * self.len + p];
        }
        q
    }

    /// Copies the candidates of `runs` into one contiguous axis-major block, padded to a
    /// multiple of 4 with points at infinity (never within any radius), so that one SIMD loop
    /// without a scalar tail serves every query of the cell. Returns the padded width w; axis
    /// d of the block starts at d * (w + BLOCK_SLACK).
    fn gather(&self, runs: &[(usize, usize)], coords: &mut Vec<f64>, ids: &mut Vec<u32>) -> usize {
        let n: usize = runs.iter().map(|&(a, b)| b - a).sum();
        let width = n.div_ceil(4) * 4;
        // Runs are copied 16 values at a time at least, then in chunks of 4, which may
        // overshoot a run's end by 15: the next run or the padding overwrites that, and the
        // BLOCK_SLACK extra slots per axis keep the overshoot of one axis out of the next.
        // A fixed first copy covers most runs (~13 values in 2D) without a branch on their
        // length, which the predictor kept missing.
        let stride = width + BLOCK_SLACK;
        if coords.len() < D * stride {
            coords.resize(D * stride, 0.0);
        }
        if ids.len() < stride {
            ids.resize(stride, 0);
        }
        let mut k = 0;
        for &(a, b) in runs {
            let m = b - a;
            // SAFETY: reads stay below a + max(m + 3, 16) <= len + 16 of an axis, and
            // `sorted` and `order` carry CHUNK_SLACK values past the last axis; writes stay
            // below k + max(m + 3, 16) <= n + 16 <= stride of each axis, as k + m <= n.
            unsafe {
                for d in 0..D {
                    let src = self.sorted.as_ptr().add(d * self.len + a);
                    copy_chunks(src, coords.as_mut_ptr().add(d * stride + k), m);
                }
                copy_chunks(self.order.as_ptr().add(a), ids.as_mut_ptr().add(k), m);
            }
            k += m;
        }
        // Padding: n..width, written as 4 values (stride has room for them).
        for d in 0..D {
            coords[d * stride + n..d * stride + n + 4].fill(f64::INFINITY);
        }
        ids[n..n + 4].fill(u32::MAX);
        width
    }

    #[inline(always)]
    pub fn collect_range(
        &self,
        lo: usize,
        hi: usize,
        ctx: &Ctx,
        found: &mut Found,
        sink: &mut RowSink,
    ) {
        self.for_each_cell(lo, hi, |p0, p1, runs| {
            if ctx.metric.any_periodic {
                for p in p0..p1 {
                    let q = self.query_point(p);
                    let i = self.order[p] as usize;
                    found.senders.clear();
                    found.shifts.clear();
                    for k in runs.iter().flat_map(|&(a, b)| a..b) {
                        let j = self.order[k] as usize;
                        accept_at(ctx, i, j, &q, &self.query_point(k), found);
                    }
                    if !sink.push(i, &mut found.senders, &found.shifts) {
                        return false;
                    }
                }
                return true;
            }
            let w = self.gather(runs, &mut found.coords, &mut found.ids);
            #[cfg(target_arch = "x86_64")]
            if ctx.avx2 {
                // SAFETY: avx2 is only set when the CPU has AVX2.
                return unsafe { self.cell_avx2(p0, p1, w, ctx, found, sink) };
            }
            let r2 = ctx.metric.r2;
            for p in p0..p1 {
                let q = self.query_point(p);
                let i = self.order[p] as usize;
                // Compacted straight into the task's rows (the SIMD compaction stores whole
                // vectors of 4 indices: w + 4 slots), sorted there by the sink.
                let row = sink.room(w + 4);
                let stride = w + BLOCK_SLACK;
                let mut n =
                    collect_block::<D>(ctx.avx2, &found.coords, &found.ids, stride, w, &q, r2, row);
                if !ctx.self_edges {
                    n = without_self(row, n, i);
                }
                if !sink.keep(i, n) {
                    return false;
                }
            }
            true
        });
    }
}

impl<const D: usize> Grid<D> {
    /// The queries p0..p1 of one cell against its gathered block of width w, compiled for
    /// AVX2 as a whole so that the compaction and the sort inline into the query loop.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn cell_avx2(
        &self,
        p0: usize,
        p1: usize,
        w: usize,
        ctx: &Ctx,
        found: &Found,
        sink: &mut RowSink,
    ) -> bool {
        let r2 = ctx.metric.r2;
        let stride = w + BLOCK_SLACK;
        assert!(found.coords.len() >= D * stride && found.ids.len() >= w);
        let (coords, ids) = (found.coords.as_ptr(), found.ids.as_ptr());
        let mut p = p0;
        // Two queries per pass over the block: each load of the block serves both, and the
        // loop's exit (a branch the predictor misses about once per pass) is paid once.
        while p + 2 <= p1 {
            let (qa, qb) = (self.query_point(p), self.query_point(p + 1));
            let (ia, ib) = (self.order[p] as usize, self.order[p + 1] as usize);
            // Row a at 0, row b at `at_b` until row a is kept; then b moves down next to it.
            // Row a's compaction writes below w + 4, its sort below 32 (or na + 32).
            let at_b = (w + 4).max(32);
            let row = sink.room(at_b + w + 4);
            let out = row.as_mut_ptr();
            let (mut na, mut nb) =
                compact2_avx2::<D>(coords, ids, stride, w, [&qa, &qb], r2, out, out.add(at_b));
            if !ctx.self_edges {
                na = without_self(row, na, ia);
                nb = without_self(&mut row[at_b..], nb, ib);
            }
            if !sink.keep(ia, na) {
                return false;
            }
            // Row a's sort writes below 32 if na <= 32, else in place below na <= w: row b
            // is intact.
            let row = sink.room(0);
            let src = row.as_ptr().add(at_b - na);
            if nb <= 24 {
                copy_24_down(src, row.as_mut_ptr());
            } else {
                std::ptr::copy(src, row.as_mut_ptr(), nb);
            }
            if !sink.keep(ib, nb) {
                return false;
            }
            p += 2;
        }
        if p < p1 {
            let q = self.query_point(p);
            let i = self.order[p] as usize;
            let row = sink.room(w + 4);
            let mut n = compact_avx2::<D>(coords, ids, stride, w, &q, r2, row.as_mut_ptr());
            if !ctx.self_edges {
                n = without_self(row, n, i);
            }
            if !sink.keep(i, n) {
                return false;
            }
        }
        true
    }
}

/// The row row[..n] without query i itself, its new length: self-edges are decided by index,
/// so coincident other particles stay.
#[inline(always)]
fn without_self(row: &mut [u32], n: usize, i: usize) -> usize {
    match row[..n].iter().position(|&j| j as usize == i) {
        Some(k) => {
            row.swap(k, n - 1);
            n - 1
        }
        None => n,
    }
}

/// Copies 24 u32 from src to dst <= src - 4 (the ranges may overlap): all loads first.
///
/// # Safety
/// Both valid for 24 values; called in AVX2 code only.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn copy_24_down(src: *const u32, dst: *mut u32) {
    use std::arch::x86_64::*;
    let a = _mm256_loadu_si256(src as *const __m256i);
    let b = _mm256_loadu_si256(src.add(8) as *const __m256i);
    let c = _mm256_loadu_si256(src.add(16) as *const __m256i);
    _mm256_storeu_si256(dst as *mut __m256i, a);
    _mm256_storeu_si256(dst.add(8) as *mut __m256i, b);
    _mm256_storeu_si256(dst.add(16) as *mut __m256i, c);
}

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::{__m128i, __m256d};

/// A query point broadcast to every lane, axis by axis (in 2D the last entry repeats y and
/// is not used).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn broadcast<const D: usize>(q: &[f64; D]) -> [__m256d; 3] {
    use std::arch::x86_64::*;
    [
        _mm256_set1_pd(q[0]),
        _mm256_set1_pd(q[1]),
        _mm256_set1_pd(q[D - 1]),
    ]
}

/// Which of the 4 points (x, y, z) are within r2 of q: bit l for lane l. z is read in 3D only.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn near_mask<const D: usize>(
    x: __m256d,
    y: __m256d,
    z: __m256d,
    q: &[__m256d; 3],
    r2: __m256d,
) -> usize {
    use std::arch::x86_64::*;
    let dx = _mm256_sub_pd(x, q[0]);
    let dy = _mm256_sub_pd(y, q[1]);
    let mut d2 = _mm256_add_pd(_mm256_mul_pd(dx, dx), _mm256_mul_pd(dy, dy));
    if D == 3 {
        let dz = _mm256_sub_pd(z, q[2]);
        d2 = _mm256_add_pd(d2, _mm256_mul_pd(dz, dz));
    }
    _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LE_OQ>(d2, r2)) as usize
}

/// Stores the ids of idv that `mask` selects at out (a whole vector of 4) and returns how many.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn pack(idv: __m128i, mask: usize, out: *mut u32) -> usize {
    use std::arch::x86_64::*;
    let shuffle = _mm_loadu_si128(PACK[mask].as_ptr() as *const __m128i);
    _mm_storeu_si128(out as *mut __m128i, _mm_shuffle_epi8(idv, shuffle));
    // Counts from a table: `count_ones` (no POPCNT in this context) was turned into a
    // vector popcount whose results crossed back to the integer registers every pass.
    LANES[mask] as usize
}

/// [`compact_avx2`] for two queries at once, into out_a and out_b (w + 4 slots each): each
/// load of the block serves both.
///
/// # Safety
/// As for [`compact_avx2`].
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn compact2_avx2<const D: usize>(
    coords: *const f64,
    ids: *const u32,
    stride: usize,
    w: usize,
    q: [&[f64; D]; 2],
    r2: f64,
    out_a: *mut u32,
    out_b: *mut u32,
) -> (usize, usize) {
    use std::arch::x86_64::*;
    let (xs, ys, zs) = (coords, coords.add(stride), coords.add((D - 1) * stride));
    let (qa, qb) = (broadcast(q[0]), broadcast(q[1]));
    let r2v = _mm256_set1_pd(r2);
    let (mut na, mut nb) = (0, 0);
    let mut k = 0;
    while k < w {
        let x = _mm256_loadu_pd(xs.add(k));
        let y = _mm256_loadu_pd(ys.add(k));
        let z = if D == 3 {
            _mm256_loadu_pd(zs.add(k))
        } else {
            x
        };
        let idv = _mm_loadu_si128(ids.add(k) as *const __m128i);
        na += pack(idv, near_mask::<D>(x, y, z, &qa, r2v), out_a.add(na));
        nb += pack(idv, near_mask::<D>(x, y, z, &qb, r2v), out_b.add(nb));
        k += 4;
    }
    (na, nb)
}

/// The compaction of [`collect_run_avx2`] over a whole gathered block (w a multiple of 4),
/// without a tail; inlined into AVX2 code only.
///
/// # Safety
/// coords holds D axes of w values at stride, ids w values, out w + 4 slots.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn compact_avx2<const D: usize>(
    coords: *const f64,
    ids: *const u32,
    stride: usize,
    w: usize,
    q: &[f64; D],
    r2: f64,
    out: *mut u32,
) -> usize {
    use std::arch::x86_64::*;
    let (xs, ys, zs) = (coords, coords.add(stride), coords.add((D - 1) * stride));
    let q = broadcast(q);
    let r2v = _mm256_set1_pd(r2);
    let mut n = 0;
    let mut k = 0;
    while k < w {
        let x = _mm256_loadu_pd(xs.add(k));
        let y = _mm256_loadu_pd(ys.add(k));
        let z = if D == 3 {
            _mm256_loadu_pd(zs.add(k))
        } else {
            x
        };
        let idv = _mm_loadu_si128(ids.add(k) as *const __m128i);
        n += pack(idv, near_mask::<D>(x, y, z, &q, r2v), out.add(n));
        k += 4;
    }
    n
}

/// Writes the ids of the neighbours of q among the first w points of a gathered block (axis d
/// at d * stride) to the front of `out` (which needs 4 slots of slack) and returns how many.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn collect_block<const D: usize>(
    avx2: bool,
    coords: &[f64],
    ids: &[u32],
    stride: usize,
    w: usize,
    q: &[f64; D],
    r2: f64,
    out: &mut [u32],
) -> usize {
    #[cfg(target_arch = "x86_64")]
    if avx2 {
        // SAFETY: avx2 is only set when the CPU has AVX2.
        return unsafe { collect_run_avx2::<D>(coords, ids, stride, 0, w, q, r2, out) };
    }
    let _ = avx2;
    collect_run::<D>(coords, ids, stride, 0, w, q, r2, out)
}

/// Copies m values: 16 whatever m, then whole chunks of 4 (up to 15 past m): a few vector
/// moves, where a memcpy call for a dozen values costs more than the copy.
///
/// # Safety
/// src and dst must be valid for max(16, m rounded up to a multiple of 4) values.
#[inline(always)]
unsafe fn copy_chunks<T: Copy>(src: *const T, dst: *mut T, m: usize) {
    std::ptr::copy_nonoverlapping(src, dst, 16);
    let mut t = 16;
    while t < m {
        std::ptr::copy_nonoverlapping(src.add(t), dst.add(t), 4);
        t += 4;
    }
}

/// The smallest and largest coordinate on each axis of finite points (lo > hi when there are
/// none). Comparisons rather than f64::min and max, whose NaN rules keep them from vectorising;
/// 12 lanes hold 6 (2D) or 4 (3D) whole points.
fn bounding_box<const D: usize>(coords: &[f64]) -> ([f64; D], [f64; D]) {
    let mut lo = [f64::INFINITY; 12];
    let mut hi = [f64::NEG_INFINITY; 12];
    let chunks = coords.chunks_exact(12);
    let tail = chunks.remainder();
    for c in chunks {
        for k in 0..12 {
            lo[k] = if c[k] < lo[k] { c[k] } else { lo[k] };
            hi[k] = if c[k] > hi[k] { c[k] } else { hi[k] };
        }
    }
    for (k, &x) in tail.iter().enumerate() {
        lo[k] = lo[k].min(x);
        hi[k] = hi[k].max(x);
    }
    let (mut lo_d, mut hi_d) = ([f64::INFINITY; D], [f64::NEG_INFINITY; D]);
    for k in 0..12 {
        lo_d[k % D] = lo_d[k % D].min(lo[k]);
        hi_d[k % D] = hi_d[k % D].max(hi[k]);
    }
    (lo_d, hi_d)
}

/// The cell coordinate of every value of coords (axis k % D for value k), clamped to the
/// grid: 12 lanes at a time, 4 to a vector conversion, where the saturating `as` casts of a
/// point at a time cost several times more.
#[inline(always)]
fn axis_cells<const D: usize>(
    n: &[usize; D],
    lo: &[f64; D],
    inv_cell: &[f64; D],
    coords: &[f64],
    out: &mut [i32],
) {
    let lane = |k: usize| (lo[k % D], inv_cell[k % D], (n[k % D] - 1) as i32);
    let cell = |x: f64, (lo, inv, last): (f64, f64, i32)| {
        let v = (x - lo) * inv;
        // x >= lo (lo is the least coordinate, or 0 with positions wrapped into the box), so
        // v >= 0; v is at most about n - 1 < 2^31 (the grid's budget): in range of i32.
        debug_assert!((0.0..i32::MAX as f64).contains(&v));
        // SAFETY: v is finite and within the range of i32 (above).
        unsafe { v.to_int_unchecked::<i32>() }.min(last)
    };
    let lanes: [(f64, f64, i32); 12] = std::array::from_fn(lane);
    let mut outs = out.chunks_exact_mut(12);
    let mut ins = coords.chunks_exact(12);
    for (o, c) in (&mut outs).zip(&mut ins) {
        for k in 0..12 {
            o[k] = cell(c[k], lanes[k]);
        }
    }
    for (k, (o, &x)) in outs
        .into_remainder()
        .iter_mut()
        .zip(ins.remainder())
        .enumerate()
    {
        *o = cell(x, lanes[k]);
    }
}

fn n_is_huge(n: usize) -> bool {
    n > (1usize << 52)
}

/// Writes the indices of the points of a..b within the radius of q to the front of `out` and
/// returns how many: a branchless compaction. The arithmetic is exactly the canonical one,
/// (0 + dx^2) + dy^2 (+ dz^2) with dx = x_j - x_i, so every method agrees to the last bit.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn collect_run<const D: usize>(
    sorted: &[f64],
    order: &[u32],
    len: usize,
    a: usize,
    b: usize,
    q: &[f64; D],
    r2: f64,
    out: &mut [u32],
) -> usize {
    let xs = &sorted[a..b];
    let ys = &sorted[len + a..len + b];
    let ids = &order[a..b];
    let out = &mut out[..xs.len()];
    let mut n = 0;
    if D == 2 {
        for k in 0..xs.len() {
            let dx = xs[k] - q[0];
            let dy = ys[k] - q[1];
            out[n] = ids[k];
            n += (dx * dx + dy * dy <= r2) as usize;
        }
    } else {
        let zs = &sorted[2 * len + a..2 * len + b];
        for k in 0..xs.len() {
            let dx = xs[k] - q[0];
            let dy = ys[k] - q[1];
            let dz = zs[k] - q[D - 1];
            out[n] = ids[k];
            n += (dx * dx + dy * dy + dz * dz <= r2) as usize;
        }
    }
    n
}

/// [`collect_run`] four candidates at a time: compare, then pack the accepted indices to the
/// front with one byte shuffle. Same arithmetic, same result; `out` needs 4 slots of slack.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn collect_run_avx2<const D: usize>(
    sorted: &[f64],
    order: &[u32],
    len: usize,
    a: usize,
    b: usize,
    q: &[f64; D],
    r2: f64,
    out: &mut [u32],
) -> usize {
    let m = b - a;
    assert!(out.len() >= m + 4 && b <= len && order.len() >= b && sorted.len() >= D * len);
    // Whole chunks of 4 by the shared kernel (axes of `sorted` are len apart), the rest here.
    let k = m & !3;
    let n = compact_avx2::<D>(
        sorted.as_ptr().add(a),
        order.as_ptr().add(a),
        len,
        k,
        q,
        r2,
        out.as_mut_ptr(),
    );
    let tail = &mut out[n..];
    n + collect_run::<D>(sorted, order, len, a + k, b, q, r2, tail)
}

/// LANES[mask]: how many of 4 lanes `mask` selects.
#[cfg(target_arch = "x86_64")]
static LANES: [u8; 16] = [0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4];

/// PACK[mask]: byte shuffle that moves the 32-bit lanes selected by `mask` to the front.
#[cfg(target_arch = "x86_64")]
static PACK: [[u8; 16]; 16] = {
    let mut table = [[0x80u8; 16]; 16];
    let mut mask = 0;
    while mask < 16 {
        let mut out = 0;
        let mut lane = 0;
        while lane < 4 {
            if mask & (1 << lane) != 0 {
                let mut byte = 0;
                while byte < 4 {
                    table[mask][out * 4 + byte] = (lane * 4 + byte) as u8;
                    byte += 1;
                }
                out += 1;
            }
            lane += 1;
        }
        mask += 1;
    }
    table
};

#[cfg(test)]
mod tests {
    use super::*;

    /// The box and the cell coordinates against the plain per-point formulas, for lengths
    /// that fill the 12 lanes exactly, partly, or leave a tail.
    fn box_and_cells_agree_with_plain_loops<const D: usize>() {
        for n_pts in 0..30 {
            let pts = crate::graph::tests::random_points(n_pts, D, n_pts as u64 + 7, 3.0);
            let (lo, hi) = bounding_box::<D>(&pts);
            for d in 0..D {
                let axis = pts.iter().skip(d).step_by(D);
                assert_eq!(lo[d], axis.clone().fold(f64::INFINITY, |a, &x| a.min(x)));
                assert_eq!(hi[d], axis.fold(f64::NEG_INFINITY, |a, &x| a.max(x)));
            }
            if n_pts == 0 {
                continue;
            }
            let inv = [1.0 / 0.37; D];
            let n: [usize; D] = std::array::from_fn(|d| ((hi[d] - lo[d]) * inv[d]) as usize + 1);
            let mut out = vec![-1; pts.len()];
            axis_cells::<D>(&n, &lo, &inv, &pts, &mut out);
            for (k, &x) in pts.iter().enumerate() {
                let d = k % D;
                let want = (((x - lo[d]) * inv[d]).floor() as i32).min(n[d] as i32 - 1);
                assert_eq!(out[k], want, "{n_pts} points, value {k}");
            }
        }
    }

    #[test]
    fn bounding_box_and_axis_cells_agree_with_plain_loops() {
        box_and_cells_agree_with_plain_loops::<2>();
        box_and_cells_agree_with_plain_loops::<3>();
    }

    #[test]
    fn simd_and_portable_compaction_agree() {
        // Distances on a dyadic grid, many of them exactly at the radius.
        let w = 64;
        let mut coords = vec![0.0; 3 * w];
        for (k, c) in coords.iter_mut().enumerate() {
            *c = ((k * 37) % 11) as f64 * 0.125;
        }
        let ids: Vec<u32> = (0..w as u32).map(|k| k * 3 + 1).collect();
        for (q, r2) in [
            ([0.5, 0.25, 0.75], 0.25),
            ([0.0, 0.0, 0.0], 1.0),
            ([1.0, 1.0, 1.0], 0.0),
        ] {
            let mut portable = vec![0u32; w + 4];
            let n = collect_block::<3>(false, &coords, &ids, w, w, &q, r2, &mut portable);
            let want: Vec<u32> = (0..w)
                .filter(|&k| {
                    let d: Vec<f64> = (0..3).map(|a| coords[a * w + k] - q[a]).collect();
                    d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= r2
                })
                .map(|k| ids[k])
                .collect();
            assert_eq!(&portable[..n], &want[..]);
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                let mut wide = vec![0u32; w + 4];
                let m = collect_block::<3>(true, &coords, &ids, w, w, &q, r2, &mut wide);
                assert_eq!(&wide[..m], &want[..]);
            }
        }
    }
}
