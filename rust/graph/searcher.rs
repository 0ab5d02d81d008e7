//! The driver: [`Searcher`] validates a call (see `prepare`), builds one index per graph (cell
//! list, k-d tree or brute force), finds and sorts each row in parallel tasks (see `rows`),
//! then copies the rows in receiver order into exact-size output. [`radius_graph`] is the
//! same in one call.

use super::cells::Grid;
use super::kdtree::KdTree;
use super::prepare::{prepare, GraphOptions, Method, Prepared};
use super::query::{accept_at, point, Ctx, Found};
use super::rows::{RowSink, SharedMut, TaskRows};
use super::simd::{has_avx2, with_simd};
use crate::{Error, Real, Result};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// Below this many particles one thread beats waking a pool. Measured from Python on the
/// 2-core machine (2D, ~14 neighbours): 2 threads took 0.79x the time of one at 512
/// particles, 1.13x at 768 and 1.21x at 1100.
const SERIAL_BELOW: usize = 640;
/// Queries per parallel task at most: small enough to balance clumps, large enough to
/// amortise; smaller inputs get smaller tasks, so that every thread has several.
const TASK: usize = 512;
const MIN_TASK: usize = 64;

/// An edge list: `senders[e] -> receivers[e]`; with periodic axes, `shifts[e * dim + d]` is the
/// image count so that x[s] - x[r] + shift * box is the minimum-image displacement.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Edges {
    pub senders: Vec<i64>,
    pub receivers: Vec<i64>,
    pub shifts: Vec<i32>,
}

/// The spatial index of one graph.
pub(crate) enum GraphIndex {
    Cells2(Grid<2>),
    Cells3(Grid<3>),
    Tree2(KdTree<2>),
    Tree3(KdTree<3>),
    Brute { start: usize, end: usize },
}

impl GraphIndex {
    /// A lower bound on this graph's edges from tight clumps of particles (see
    /// [`tight`](super::query::tight)), worked out only when the particles could make more
    /// than `limit` edges at all; 0 otherwise. It lets a clump past max_edges fail at once
    /// instead of after collecting `limit` edges (a gigabyte at the default).
    fn sure_edges(&self, r2: f64, self_edges: bool, limit: u64) -> u64 {
        match self {
            GraphIndex::Cells2(g) => g.sure_edges(r2, self_edges, limit),
            GraphIndex::Cells3(g) => g.sure_edges(r2, self_edges, limit),
            GraphIndex::Tree2(t) => t.sure_edges(r2, self_edges, limit),
            GraphIndex::Tree3(t) => t.sure_edges(r2, self_edges, limit),
            GraphIndex::Brute { .. } => 0,
        }
    }

    fn len(&self) -> usize {
        match self {
            GraphIndex::Cells2(g) => g.len(),
            GraphIndex::Cells3(g) => g.len(),
            GraphIndex::Tree2(t) => t.len(),
            GraphIndex::Tree3(t) => t.len(),
            GraphIndex::Brute { start, end } => end - start,
        }
    }

    /// Collects the neighbours of queries lo..hi (in this index's locality-friendly order)
    /// into `sink`, i the global index. Stops early when the sink says so.
    #[inline(always)]
    fn collect_range(
        &self,
        lo: usize,
        hi: usize,
        ctx: &Ctx,
        found: &mut Found,
        sink: &mut RowSink,
    ) {
        match self {
            GraphIndex::Cells2(g) => g.collect_range(lo, hi, ctx, found, sink),
            GraphIndex::Cells3(g) => g.collect_range(lo, hi, ctx, found, sink),
            GraphIndex::Tree2(t) => {
                for p in lo..hi {
                    t.collect(p, ctx, found);
                    if !sink.push(t.original(p), &mut found.senders, &found.shifts) {
                        return;
                    }
                }
            }
            GraphIndex::Tree3(t) => {
                for p in lo..hi {
                    t.collect(p, ctx, found);
                    if !sink.push(t.original(p), &mut found.senders, &found.shifts) {
                        return;
                    }
                }
            }
            GraphIndex::Brute { start, end } => {
                for i in start + lo..start + hi {
                    found.senders.clear();
                    found.shifts.clear();
                    brute_collect(ctx, *start, *end, i, found);
                    if !sink.push(i, &mut found.senders, &found.shifts) {
                        return;
                    }
                }
            }
        }
    }
}

#[inline(always)]
fn accept<const D: usize>(ctx: &Ctx, i: usize, j: usize, found: &mut Found) {
    let xi = point::<D>(ctx.coords, i);
    let xj = point::<D>(ctx.coords, j);
    accept_at(ctx, i, j, &xi, &xj, found);
}

/// The oracle: every particle of the graph tested with the canonical metric.
fn brute_collect(ctx: &Ctx, start: usize, end: usize, i: usize, found: &mut Found) {
    for j in start..end {
        if ctx.dim == 2 {
            accept::<2>(ctx, i, j, found);
        } else {
            accept::<3>(ctx, i, j, found);
        }
    }
}

/// A reusable radius-graph searcher: keeps its buffers (and optionally its own thread pool)
/// between calls, so repeated searches of similar size allocate nothing but the output.
#[derive(Default)]
pub struct Searcher {
    /// The searcher's own pool, or None for the global one (or for one thread).
    pool: Option<rayon::ThreadPool>,
    one_thread: bool,
    prepared: Option<Prepared>,
    indices: Vec<GraphIndex>,
    tasks: Vec<(usize, usize, usize)>,
    rows: Vec<TaskRows>,
    /// Where each particle's row is, by original index.
    row_of: Vec<RowAt>,
    /// Row offsets by original index (len N + 1): receiver i owns offsets[i]..offsets[i + 1].
    offsets: Vec<u64>,
    want_shifts: bool,
}

impl Searcher {
    /// A searcher on the global rayon pool (`num_threads = None`), on a pool of its own, or
    /// on the caller's thread alone (`Some(1)`).
    pub fn new(num_threads: Option<usize>) -> Result<Self> {
        let pool = match num_threads {
            None => None,
            Some(0) => {
                return Err(Error::Value(
                    "num_threads must be >= 1 (or None for the default pool), got 0".into(),
                ))
            }
            // One thread: every call runs on the caller's, so no pool to hand it to.
            Some(1) => None,
            Some(t) => Some(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build()
                    .map_err(|e| Error::Value(format!("cannot start {t} threads: {e}")))?,
            ),
        };
        Ok(Searcher {
            pool,
            one_thread: num_threads == Some(1),
            ..Default::default()
        })
    }

    /// Whether a call on n particles uses several threads: not below SERIAL_BELOW, and not
    /// with one thread (or a global pool of one).
    fn parallel(&self, n: usize) -> bool {
        let threads = self
            .pool
            .as_ref()
            .map_or_else(rayon::current_num_threads, |p| p.current_num_threads());
        !self.one_thread && n >= SERIAL_BELOW && threads > 1
    }

    /// Runs f on this searcher's pool when the call is parallel, else right here (where f
    /// must not start parallel work: it would run on the global pool).
    fn install<R: Send>(&self, parallel: bool, f: impl FnOnce() -> R + Send) -> R {
        match &self.pool {
            Some(p) if parallel => p.install(f),
            _ => f(),
        }
    }

    /// First pass: validates, indexes, finds and sorts every row. Returns the number of
    /// edges, so the caller can allocate the output for [`Searcher::fill`].
    pub fn count<T: Real>(
        &mut self,
        positions: &[T],
        dim: usize,
        n_node: Option<&[i64]>,
        opts: &GraphOptions,
        want_shifts: bool,
    ) -> Result<usize> {
        let coords = self.prepared.take().map(|p| p.coords).unwrap_or_default();
        let prepared = prepare(positions, dim, n_node, opts, coords)?;
        let mut indices = std::mem::take(&mut self.indices);
        let mut rows = std::mem::take(&mut self.rows);
        let mut row_of = std::mem::take(&mut self.row_of);
        let mut offsets = std::mem::take(&mut self.offsets);
        let n = prepared.coords.len() / prepared.dim;
        let parallel = self.parallel(n);
        let result = self.install(parallel, || {
            build_indices(&prepared, opts.method, &mut indices, parallel);
            let (r2, max_edges) = (prepared.metric.r2, opts.max_edges);
            let sure: u64 = indices
                .iter()
                .map(|index| index.sure_edges(r2, opts.self_edges, max_edges))
                .sum();
            if sure > max_edges {
                return Err(Error::TooManyEdges {
                    at_least: sure,
                    max_edges,
                });
            }
            let tasks = tasks(&indices);
            let found = Collect {
                prepared: &prepared,
                indices: &indices,
                tasks: &tasks,
                opts,
                want_shifts,
                parallel,
            }
            .run(&mut rows, &mut row_of, &mut offsets);
            found.map(|total| (total, tasks))
        });
        self.indices = indices;
        self.rows = rows;
        self.row_of = row_of;
        self.offsets = offsets;
        let (total, tasks) = match result {
            Ok(ok) => ok,
            Err(e) => {
                // Give back what a runaway search (a clump past max_edges) collected.
                self.rows = Vec::new();
                return Err(e);
            }
        };
        self.tasks = tasks;
        self.prepared = Some(prepared);
        self.want_shifts = want_shifts;
        Ok(total)
    }

    /// Second pass: copies the rows found by the last [`Searcher::count`] into exact-size
    /// slices; `shifts` (len E * dim) is required exactly when count was asked for shifts.
    pub fn fill(
        &self,
        senders: &mut [i64],
        receivers: &mut [i64],
        shifts: Option<&mut [i32]>,
    ) -> Result<()> {
        let prepared = self
            .prepared
            .as_ref()
            .ok_or_else(|| Error::Value("fill called before a successful count".into()))?;
        let total = *self.offsets.last().unwrap_or(&0) as usize;
        let dim = prepared.dim;
        let n = prepared.coords.len() / dim;
        if senders.len() != total || receivers.len() != total {
            return Err(Error::Shape(format!(
                "output needs {total} senders and receivers, got {} and {}",
                senders.len(),
                receivers.len()
            )));
        }
        match (&shifts, self.want_shifts) {
            (Some(s), true) if s.len() == total * dim => {}
            (None, false) => {}
            _ => {
                return Err(Error::Shape(format!(
                    "shifts must be given (len {}) exactly when count was asked for them",
                    total * dim
                )))
            }
        }
        let rows = &self.rows[..self.tasks.len()];
        let place = RowPlace {
            rows,
            row_of: &self.row_of,
            offsets: &self.offsets,
            dim,
        };
        let out = (
            SharedMut(senders.as_mut_ptr()),
            SharedMut(receivers.as_mut_ptr()),
            shifts.map(|s| SharedMut(s.as_mut_ptr())),
        );
        let avx2 = has_avx2();
        // Rows are written in receiver order, senders and receivers together: sequential
        // writes, where the rows themselves are read from the tasks' buffers.
        let write = |i0: usize| {
            let i1 = (i0 + FILL_CHUNK).min(n);
            // SAFETY: particles i0..i1 own offsets[i0]..offsets[i1], written by this call only.
            with_simd(avx2, || unsafe { place.write(avx2, i0, i1, out) });
        };
        let parallel = self.parallel(n);
        self.install(parallel, || {
            if !parallel {
                (0..n).step_by(FILL_CHUNK).for_each(write);
            } else {
                (0..n).into_par_iter().step_by(FILL_CHUNK).for_each(write);
            }
        });
        Ok(())
    }

    /// Count and fill into fresh vectors.
    pub fn search<T: Real>(
        &mut self,
        positions: &[T],
        dim: usize,
        n_node: Option<&[i64]>,
        opts: &GraphOptions,
        want_shifts: bool,
    ) -> Result<Edges> {
        let e = self.count(positions, dim, n_node, opts, want_shifts)?;
        let mut edges = Edges {
            senders: vec![0; e],
            receivers: vec![0; e],
            shifts: if want_shifts {
                vec![0; e * dim]
            } else {
                Vec::new()
            },
        };
        let sh = want_shifts.then_some(edges.shifts.as_mut_slice());
        self.fill(&mut edges.senders, &mut edges.receivers, sh)?;
        Ok(edges)
    }
}

/// Receivers per parallel part of [`Searcher::fill`].
const FILL_CHUNK: usize = TASK * 8;

/// Where one particle's row is: which task found it, and where in that task's senders.
#[derive(Clone, Copy, Default)]
struct RowAt {
    at: u64,
    task: u32,
    len: u32,
}

/// Where the rows of the last count are, for [`Searcher::fill`].
struct RowPlace<'a> {
    rows: &'a [TaskRows],
    row_of: &'a [RowAt],
    offsets: &'a [u64],
    dim: usize,
}

type OutPtrs = (SharedMut<i64>, SharedMut<i64>, Option<SharedMut<i32>>);

impl RowPlace<'_> {
    /// Writes the rows of receivers i0..i1 to offsets[i0]..offsets[i1] of the outputs.
    ///
    /// # Safety
    /// The outputs must hold offsets[n] values (dim times that for shifts), and no one else
    /// may write offsets[i0]..offsets[i1] meanwhile.
    #[inline(always)]
    unsafe fn write(&self, avx2: bool, i0: usize, i1: usize, out: OutPtrs) {
        let (out_s, out_r, out_sh) = out;
        let end = self.offsets[i1] as usize;
        for i in i0..i1 {
            let o = self.offsets[i] as usize;
            let len = self.offsets[i + 1] as usize - o;
            let row = self.row_of[i];
            let rows = &self.rows[row.task as usize];
            let at = row.at as usize;
            let src = rows.senders.as_ptr().add(at);
            let (ds, dr) = (out_s.ptr().add(o), out_r.ptr().add(o));
            // Whole chunks, up to 15 values past the row, where that stays inside this part:
            // the next rows overwrite them, and the rows' buffers hold ROW_SLACK values past
            // every row.
            let chunked = avx2 && o + len.next_multiple_of(4).max(16) <= end;
            #[cfg(target_arch = "x86_64")]
            if chunked {
                write_row_avx2(src, ds, dr, i as i64, len);
            }
            if !cfg!(target_arch = "x86_64") || !chunked {
                for k in 0..len {
                    *ds.add(k) = *src.add(k) as i64;
                    *dr.add(k) = i as i64;
                }
            }
            if let Some(sh) = out_sh {
                let d = self.dim;
                std::ptr::copy_nonoverlapping(
                    rows.shifts.as_ptr().add(at * d),
                    sh.ptr().add(o * d),
                    len * d,
                );
            }
        }
    }
}

/// Writes a row of `len` senders (widened to i64) and as many receivers `i`, in chunks of 4
/// and at least 16 values: a fixed number of stores covers most rows without a branch that
/// depends on the row's length.
///
/// # Safety
/// src must be readable, and ds and dr writable, for max(16, len rounded up to 4) values.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn write_row_avx2(src: *const u32, ds: *mut i64, dr: *mut i64, i: i64, len: usize) {
    use std::arch::x86_64::*;
    let rv = _mm256_set1_epi64x(i);
    let chunk = |k: usize| {
        let s = _mm256_cvtepu32_epi64(_mm_loadu_si128(src.add(k) as *const __m128i));
        _mm256_storeu_si256(ds.add(k) as *mut __m256i, s);
        _mm256_storeu_si256(dr.add(k) as *mut __m256i, rv);
    };
    chunk(0);
    chunk(4);
    chunk(8);
    chunk(12);
    let mut k = 16;
    while k < len {
        chunk(k);
        k += 4;
    }
}

/// (graph, first query, end) slices of every graph's query order.
fn tasks(indices: &[GraphIndex]) -> Vec<(usize, usize, usize)> {
    let total: usize = indices.iter().map(|i| i.len()).sum();
    let size = (total / (8 * rayon::current_num_threads())).clamp(MIN_TASK, TASK);
    let mut t = Vec::new();
    for (g, index) in indices.iter().enumerate() {
        let n = index.len();
        let mut lo = 0;
        while lo < n {
            let hi = (lo + size).min(n);
            t.push((g, lo, hi));
            lo = hi;
        }
    }
    t
}

fn build_indices(
    prepared: &Prepared,
    method: Method,
    indices: &mut Vec<GraphIndex>,
    parallel: bool,
) {
    let n_graphs = prepared.bounds.len() - 1;
    // Old indices keep their buffers where the variant matches (a searcher called every step).
    indices.truncate(n_graphs);
    indices.resize_with(n_graphs, || GraphIndex::Brute { start: 0, end: 0 });
    let build =
        |(g, slot): (usize, &mut GraphIndex)| build_one(prepared, method, g, slot, parallel);
    if !parallel || n_graphs == 1 {
        indices.iter_mut().enumerate().for_each(build);
    } else {
        indices.par_iter_mut().enumerate().for_each(build);
    }
}

fn build_one(prepared: &Prepared, method: Method, g: usize, slot: &mut GraphIndex, parallel: bool) {
    let (start, end) = (prepared.bounds[g], prepared.bounds[g + 1]);
    let tree = || match prepared.dim {
        2 => GraphIndex::Tree2(KdTree::build(prepared, start, end)),
        _ => GraphIndex::Tree3(KdTree::build(prepared, start, end)),
    };
    match method {
        Method::Brute => *slot = GraphIndex::Brute { start, end },
        Method::KdTree => *slot = tree(),
        Method::Cells => {
            let fits = match (prepared.dim, &mut *slot) {
                (2, GraphIndex::Cells2(grid)) => grid.rebuild(prepared, start, end, parallel),
                (3, GraphIndex::Cells3(grid)) => grid.rebuild(prepared, start, end, parallel),
                (2, _) => {
                    let mut grid = Grid::default();
                    let fits = grid.rebuild(prepared, start, end, parallel);
                    *slot = GraphIndex::Cells2(grid);
                    fits
                }
                _ => {
                    let mut grid = Grid::default();
                    let fits = grid.rebuild(prepared, start, end, parallel);
                    *slot = GraphIndex::Cells3(grid);
                    fits
                }
            };
            // The grid declines when the bounding box would need far more cells than there
            // are particles (outliers far away): a tree handles any spread.
            if !fits {
                *slot = tree();
            }
        }
    }
}

/// The first pass over every task: find each query's neighbours, sort the row, keep it in
/// the task's buffer. Checks the max_edges guard every CHECK_EVERY edges, so a clump stops
/// soon after passing it rather than after collecting everything.
struct Collect<'a> {
    prepared: &'a Prepared,
    indices: &'a [GraphIndex],
    tasks: &'a [(usize, usize, usize)],
    opts: &'a GraphOptions,
    want_shifts: bool,
    parallel: bool,
}

impl Collect<'_> {
    fn run(
        &self,
        rows: &mut Vec<TaskRows>,
        row_of: &mut Vec<RowAt>,
        offsets: &mut Vec<u64>,
    ) -> Result<usize> {
        let prepared = self.prepared;
        let (n, dim) = (prepared.coords.len() / prepared.dim, prepared.dim);
        let ctx = Ctx {
            dim,
            avx2: has_avx2(),
            coords: &prepared.coords,
            wraps: &prepared.wraps,
            metric: prepared.metric,
            self_edges: self.opts.self_edges,
            want_shifts: self.want_shifts,
        };
        // Keep the buffers of earlier calls: a searcher called every step reuses them.
        rows.resize_with(self.tasks.len().max(rows.len()), TaskRows::default);
        let total = AtomicU64::new(0);
        let over = AtomicBool::new(false);
        let max_edges = self.opts.max_edges;
        let run_task = |(task_rows, &(g, lo, hi)): (&mut TaskRows, &(usize, usize, usize))| {
            task_rows.used = 0;
            task_rows.queries.clear();
            task_rows.shifts.clear();
            if over.load(Ordering::Relaxed) {
                return;
            }
            let mut found = Found::default();
            let mut sink = RowSink {
                rows: task_rows,
                avx2: ctx.avx2,
                dim,
                want_shifts: self.want_shifts,
                order: Vec::new(),
                pending: 0,
                total: &total,
                over: &over,
                max_edges,
            };
            with_simd(ctx.avx2, || {
                self.indices[g].collect_range(lo, hi, &ctx, &mut found, &mut sink)
            });
            sink.flush();
        };
        if !self.parallel {
            rows.iter_mut().zip(self.tasks.iter()).for_each(run_task);
        } else {
            rows.par_iter_mut()
                .zip(self.tasks.par_iter())
                .for_each(run_task);
        }
        if over.load(Ordering::Relaxed) {
            return Err(Error::TooManyEdges {
                at_least: total.load(Ordering::Relaxed),
                max_edges,
            });
        }
        // Where each particle's row is, by particle: one thread, so no cache line is shared.
        row_of.resize(n, RowAt::default()); // overwritten in full: every particle is a query
        for (t, task) in rows[..self.tasks.len()].iter().enumerate() {
            let mut at = 0u64;
            for &(i, len) in &task.queries {
                row_of[i as usize] = RowAt {
                    at,
                    task: t as u32,
                    len,
                };
                at += len as u64;
            }
        }
        offsets.clear();
        offsets.reserve(n + 1);
        let mut acc = 0u64;
        offsets.push(0);
        for row in row_of.iter() {
            acc += row.len as u64;
            offsets.push(acc);
        }
        Ok(acc as usize)
    }
}

/// Radius graph in one call (a fresh [`Searcher`] on the global pool).
pub fn radius_graph<T: Real>(
    positions: &[T],
    dim: usize,
    n_node: Option<&[i64]>,
    opts: &GraphOptions,
    want_shifts: bool,
) -> Result<Edges> {
    Searcher::default().search(positions, dim, n_node, opts, want_shifts)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::tests::{naive, random_points};

    #[test]
    fn the_clump_check_never_counts_more_than_the_real_edges() {
        // Clumps of 40-400 particles (some tight, some wider than the radius) in a sparse
        // cloud; each index's sure count (asked for whatever the limit) against brute force.
        for (dim, seed) in [(2, 1), (3, 2), (2, 3)] {
            let mut pts = random_points(100, dim, seed, 1.0);
            for (k, spread) in [(40, 0.0), (400, 1e-3), (120, 0.04), (300, 0.2)] {
                let centre = random_points(1, dim, seed + k as u64, 1.0);
                let jitter = random_points(k, dim, seed + 7 * k as u64, spread);
                pts.extend(jitter.iter().enumerate().map(|(i, x)| centre[i % dim] + x));
            }
            let n = pts.len() / dim;
            for method in [Method::Cells, Method::KdTree] {
                for self_edges in [true, false] {
                    let opts = GraphOptions {
                        method,
                        self_edges,
                        ..GraphOptions::new(0.05)
                    };
                    let exact = naive(&pts, dim, &[0, n], &opts).len() as u64;
                    let prepared = prepare(&pts, dim, None, &opts, Vec::new()).unwrap();
                    let mut indices = Vec::new();
                    build_indices(&prepared, method, &mut indices, false);
                    let sure = indices[0].sure_edges(prepared.metric.r2, self_edges, 0);
                    assert!(sure > 0 && sure <= exact, "{method:?}: {sure} vs {exact}");
                    // Below the limit nothing is worked out.
                    assert_eq!(
                        indices[0].sure_edges(prepared.metric.r2, self_edges, 1 << 40),
                        0
                    );
                }
            }
        }
    }
}
