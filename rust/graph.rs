//! Radius graphs: validation, batching by `n_node`, the canonical distance every method shares,
//! the driver (find and sort each row in parallel tasks, then copy the rows into exact-size
//! output) and the brute-force oracle.
//!
//! Semantics (shared/design/neighbour-search.md): a directed edge j -> i for every pair of
//! particles of the same graph with |x_j - x_i| <= radius, self-edges decided by index,
//! senders and receivers sorted by (receiver, sender), the same for every method and thread
//! count. Nothing is ever truncated: more than `max_edges` edges is an error.

use crate::cells::Grid;
use crate::kdtree::KdTree;
use crate::{check_positive, first_non_finite, Error, Real, Result};
use rayon::prelude::*;
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// The default memory guard: 2^28 edges are 4 GiB of int64 output.
pub const DEFAULT_MAX_EDGES: u64 = 1 << 28;
/// Below this many particles one thread beats waking a pool. Measured from Python on the
/// 2-core machine (2D, ~14 neighbours): 2 threads took 0.79x the time of one at 512
/// particles, 1.13x at 768 and 1.21x at 1100.
const SERIAL_BELOW: usize = 640;
/// A periodic box at most 2^20 radii long: positions wrapped into [0, L) are then rounded by
/// at most 2^-32 radii (one ulp of L), far below any distance the search tells apart.
const MAX_PERIODIC_RADII: f64 = (1u64 << 20) as f64;
/// Queries per parallel task at most: small enough to balance clumps, large enough to
/// amortise; smaller inputs get smaller tasks, so that every thread has several.
const TASK: usize = 512;
const MIN_TASK: usize = 64;

/// How the neighbours are found; every method returns the same edges.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    /// Uniform grid of cell size >= radius (the default; falls back to the k-d tree when the
    /// bounding box would need far more cells than there are particles).
    Cells,
    /// k-d tree, for sparse or very non-uniform clouds.
    KdTree,
    /// All pairs: the slow oracle, O(N^2) per graph.
    Brute,
}

impl FromStr for Method {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "cells" => Ok(Method::Cells),
            "kdtree" => Ok(Method::KdTree),
            "brute" => Ok(Method::Brute),
            other => Err(Error::Value(format!(
                "method must be one of 'cells', 'kdtree', 'brute', got {other:?}"
            ))),
        }
    }
}

/// Everything about a search except the positions and the graph sizes.
#[derive(Clone, Debug)]
pub struct GraphOptions {
    pub radius: f64,
    pub self_edges: bool,
    /// Box length per axis; required when any axis is periodic.
    pub box_lengths: Option<Vec<f64>>,
    /// Periodic flag per axis (empty: none periodic).
    pub periodic: Vec<bool>,
    pub max_edges: u64,
    pub method: Method,
}

impl GraphOptions {
    pub fn new(radius: f64) -> Self {
        GraphOptions {
            radius,
            self_edges: true,
            box_lengths: None,
            periodic: Vec::new(),
            max_edges: DEFAULT_MAX_EDGES,
            method: Method::Cells,
        }
    }
}

/// An edge list: `senders[e] -> receivers[e]`; with periodic axes, `shifts[e * dim + d]` is the
/// image count so that x[s] - x[r] + shift * box is the minimum-image displacement.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Edges {
    pub senders: Vec<i64>,
    pub receivers: Vec<i64>,
    pub shifts: Vec<i32>,
}

/// The distance every method uses, so that they agree to the last bit: f64 throughout,
/// dx = x_j - x_i per axis, minimum image on periodic axes, summed over axes in order and
/// compared with radius^2 (inclusive).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Metric {
    pub r2: f64,
    /// Search reach for cells and tree pruning: a hair above the radius so that rounding in
    /// cell indices or box distances can never hide a pair that the exact test accepts.
    pub reach: f64,
    pub lengths: [f64; 3],
    pub periodic: [bool; 3],
    pub any_periodic: bool,
}

impl Metric {
    /// Minimum-image displacement along `axis` and the image count m subtracted (dx - m L).
    #[inline(always)]
    pub fn axis(&self, axis: usize, xi: f64, xj: f64) -> (f64, i32) {
        let dx = xj - xi;
        if self.periodic[axis] {
            let l = self.lengths[axis];
            let m = (dx / l).round();
            (dx - m * l, m as i32)
        } else {
            (dx, 0)
        }
    }

    #[inline(always)]
    pub fn d2<const D: usize>(&self, xi: &[f64; D], xj: &[f64; D]) -> f64 {
        let mut s = 0.0;
        for d in 0..D {
            let (dx, _) = self.axis(d, xi[d], xj[d]);
            s += dx * dx;
        }
        s
    }
}

/// Positions of one call, validated, in f64, periodic axes wrapped into [0, L).
pub(crate) struct Prepared {
    pub dim: usize,
    pub coords: Vec<f64>,
    /// Whole box lengths subtracted when wrapping, per particle and axis (empty if no periodic).
    pub wraps: Vec<i32>,
    pub metric: Metric,
    /// Graph boundaries: graph g holds particles bounds[g]..bounds[g + 1].
    pub bounds: Vec<usize>,
}

fn validate_options(dim: usize, opts: &GraphOptions) -> Result<Metric> {
    let r = opts.radius;
    check_positive("radius", r)?;
    if !(r * r).is_finite() {
        // Distances are compared squared: an infinite r^2 would accept every pair.
        return Err(Error::Value(format!(
            "radius = {r:e} is too large: its square overflows (at most about 1.3e154)"
        )));
    }
    let mut periodic = [false; 3];
    if !opts.periodic.is_empty() {
        if opts.periodic.len() != dim {
            return Err(Error::Shape(format!(
                "periodic must have one flag per axis ({dim}), got {} flags",
                opts.periodic.len()
            )));
        }
        periodic[..dim].copy_from_slice(&opts.periodic);
    }
    let any_periodic = periodic.iter().any(|&p| p);
    let mut lengths = [0.0; 3];
    match &opts.box_lengths {
        Some(b) => {
            if b.len() != dim {
                return Err(Error::Shape(format!(
                    "box must have one length per axis ({dim}), got {} values",
                    b.len()
                )));
            }
            for (d, &l) in b.iter().enumerate() {
                check_positive(&format!("box length on axis {d}"), l)?;
                if periodic[d] && l > MAX_PERIODIC_RADII * r {
                    return Err(Error::Value(format!(
                        "box length {l:e} on periodic axis {d} is more than {MAX_PERIODIC_RADII:e} \
                         radii ({r:e}); positions wrapped into it would be rounded by more \
                         than 2^-32 radii"
                    )));
                }
                if periodic[d] && l < 2.0 * r {
                    return Err(Error::Value(format!(
                        "box length {l} on periodic axis {d} is narrower than 2 * radius = {}; \
                         the minimum image would be ambiguous",
                        2.0 * r
                    )));
                }
                lengths[d] = l;
            }
        }
        None if any_periodic => {
            return Err(Error::Value(
                "periodic axes need a box (one length per axis)".into(),
            ))
        }
        None => {}
    }
    Ok(Metric {
        r2: r * r,
        reach: r,
        lengths,
        periodic,
        any_periodic,
    })
}

/// Validates and converts one call's input; `coords` is a buffer to reuse (a searcher's
/// last one), so that repeated calls do not fault in fresh pages for it.
pub(crate) fn prepare<T: Real>(
    positions: &[T],
    dim: usize,
    n_node: Option<&[i64]>,
    opts: &GraphOptions,
    mut coords: Vec<f64>,
) -> Result<Prepared> {
    if dim != 2 && dim != 3 {
        return Err(Error::Shape(format!(
            "positions must have 2 or 3 columns, got {dim}"
        )));
    }
    if positions.len() % dim != 0 {
        return Err(Error::Shape(format!(
            "positions has {} values, not a multiple of dim = {dim}",
            positions.len()
        )));
    }
    let n = positions.len() / dim;
    if n >= u32::MAX as usize {
        return Err(Error::Shape(format!(
            "at most {} particles per call, got {n}",
            u32::MAX - 1
        )));
    }
    let mut metric = validate_options(dim, opts)?;
    let bounds = graph_bounds(n, n_node)?;
    coords.clear();
    coords.extend(positions.iter().map(|v| v.to_f64()));
    let mut max_abs = largest_magnitude(&coords);
    if !max_abs.is_finite() {
        let (i, d) = first_non_finite(positions, dim).expect("a value is not finite");
        return Err(Error::NonFinite(format!(
            "positions[{i}, {d}] is {}; positions must be finite",
            positions[i * dim + d].to_f64()
        )));
    }
    let mut wraps = Vec::new();
    if metric.any_periodic {
        wraps = vec![0i32; coords.len()];
        for (k, (x, w)) in coords.iter_mut().zip(wraps.iter_mut()).enumerate() {
            let d = k % dim;
            if metric.periodic[d] {
                (*x, *w) = wrap(*x, metric.lengths[d], d)?;
            }
        }
        // Wrapped into the box, the coordinates are smaller.
        max_abs = largest_magnitude(&coords);
    }
    // A relative margin for the division in cell indices and an absolute one for coordinates
    // far from the origin, where one ulp of a coordinate is a sizeable part of the radius.
    metric.reach = opts.radius * (1.0 + 1e-9) + 16.0 * max_abs * f64::EPSILON;
    Ok(Prepared {
        dim,
        coords,
        wraps,
        metric,
        bounds,
    })
}

/// The largest |x|, or NaN when some x is not finite. Comparisons in 8 lanes rather than
/// f64::max, whose NaN rules keep it from vectorising; x * 0 is 0 exactly for finite x.
fn largest_magnitude(xs: &[f64]) -> f64 {
    with_simd(has_avx2(), || {
        let (mut top, mut bad) = ([0.0f64; 8], [0.0f64; 8]);
        let chunks = xs.chunks_exact(8);
        let tail = chunks.remainder();
        for c in chunks {
            for k in 0..8 {
                let a = c[k].abs();
                top[k] = if a > top[k] { a } else { top[k] };
                bad[k] += c[k] * 0.0;
            }
        }
        for (k, &x) in tail.iter().enumerate() {
            top[k] = top[k].max(x.abs());
            bad[k] += x * 0.0;
        }
        let largest = top.into_iter().fold(0.0, f64::max);
        // bad is 0 in every lane, or NaN in one.
        largest + bad.into_iter().sum::<f64>()
    })
}

/// x folded into [0, L), and how many box lengths were subtracted.
fn wrap(x: f64, l: f64, axis: usize) -> Result<(f64, i32)> {
    let mut k = (x / l).floor();
    if k.abs() > (i32::MAX / 4) as f64 {
        return Err(Error::Value(format!(
            "position {x} is {k} box lengths from the box on periodic axis {axis}; expected \
             positions within a few box lengths of the box"
        )));
    }
    let mut y = x - k * l;
    // Rounding can land exactly on L (or a hair below 0): fold it back.
    if y >= l {
        y -= l;
        k += 1.0;
    }
    if y < 0.0 {
        y += l;
        k -= 1.0;
    }
    Ok((y, k as i32))
}

fn graph_bounds(n: usize, n_node: Option<&[i64]>) -> Result<Vec<usize>> {
    let Some(sizes) = n_node else {
        return Ok(vec![0, n]);
    };
    let mut bounds = Vec::with_capacity(sizes.len() + 1);
    bounds.push(0usize);
    let mut total: i64 = 0;
    for (g, &s) in sizes.iter().enumerate() {
        if s < 0 {
            return Err(Error::Value(format!(
                "n_node[{g}] = {s}; graph sizes must be >= 0"
            )));
        }
        total = total.saturating_add(s);
        bounds.push(total as usize);
    }
    if total != n as i64 {
        return Err(Error::Value(format!(
            "n_node sums to {total} but positions has {n} rows"
        )));
    }
    Ok(bounds)
}

/// The spatial index of one graph.
pub(crate) enum GraphIndex {
    Cells2(Grid<2>),
    Cells3(Grid<3>),
    Tree2(KdTree<2>),
    Tree3(KdTree<3>),
    Brute { start: usize, end: usize },
}

/// What a query needs besides its index: the prepared positions and the rules.
#[derive(Clone, Copy)]
pub(crate) struct Ctx<'a> {
    pub dim: usize,
    /// The CPU has AVX2 (checked at run time): the cell list's SIMD paths may run.
    pub avx2: bool,
    pub coords: &'a [f64],
    pub wraps: &'a [i32],
    pub metric: Metric,
    pub self_edges: bool,
    pub want_shifts: bool,
}

/// Neighbours of one query, as global indices (and shifts when wanted), unsorted.
#[derive(Default)]
pub(crate) struct Found {
    pub senders: Vec<u32>,
    pub shifts: Vec<[i32; 3]>,
    /// Traversal stack of the k-d tree, kept to avoid an allocation per query.
    pub stack: Vec<u32>,
    /// A cell's candidates gathered into one block (axis-major) and their indices.
    pub coords: Vec<f64>,
    pub ids: Vec<u32>,
}

/// Edges among `m` particles that are all within the radius of each other.
pub(crate) fn clump_edges(m: usize, self_edges: bool) -> u64 {
    let m = m as u64;
    m * m - if self_edges { 0 } else { m }
}

/// Whether a box of these extents is "tight": its diagonal is at most half the radius, so
/// every pair inside is an edge whatever the rounding of the exact test.
pub(crate) fn tight<const D: usize>(lo: &[f64; D], hi: &[f64; D], r2: f64) -> bool {
    let diag2: f64 = (0..D).map(|d| (hi[d] - lo[d]) * (hi[d] - lo[d])).sum();
    diag2 <= 0.25 * r2
}

impl GraphIndex {
    /// A lower bound on this graph's edges from tight clumps of particles (see [`tight`]),
    /// worked out only when the particles could make more than `limit` edges at all; 0
    /// otherwise. It lets a clump past max_edges fail at once instead of after collecting
    /// `limit` edges (a gigabyte at the default).
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
pub(crate) fn point<const D: usize>(coords: &[f64], i: usize) -> [f64; D] {
    let mut p = [0.0; D];
    p.copy_from_slice(&coords[i * D..(i + 1) * D]);
    p
}

/// Accepts j (at xj) as a neighbour of i (at xi) under the canonical metric; records the
/// shift if asked. Every method ends here, so they agree to the last bit.
#[inline(always)]
pub(crate) fn accept_at<const D: usize>(
    ctx: &Ctx,
    i: usize,
    j: usize,
    xi: &[f64; D],
    xj: &[f64; D],
    found: &mut Found,
) {
    if j == i && !ctx.self_edges {
        return;
    }
    if ctx.metric.d2(xi, xj) <= ctx.metric.r2 {
        found.senders.push(j as u32);
        if ctx.want_shifts {
            found.shifts.push(shift::<D>(ctx, i, j));
        }
    }
}

#[inline(always)]
fn accept<const D: usize>(ctx: &Ctx, i: usize, j: usize, found: &mut Found) {
    let xi = point::<D>(ctx.coords, i);
    let xj = point::<D>(ctx.coords, j);
    accept_at(ctx, i, j, &xi, &xj, found);
}

/// Image count per axis such that x[j] - x[i] + shift * L is the minimum-image displacement
/// in the caller's (unwrapped) coordinates.
#[inline]
pub(crate) fn shift<const D: usize>(ctx: &Ctx, i: usize, j: usize) -> [i32; 3] {
    let mut s = [0i32; 3];
    if !ctx.metric.any_periodic {
        return s;
    }
    for (d, sd) in s.iter_mut().enumerate().take(D) {
        if ctx.metric.periodic[d] {
            let (_, m) = ctx
                .metric
                .axis(d, ctx.coords[i * D + d], ctx.coords[j * D + d]);
            // wrapped = x - k L, so x_j - x_i = (w_j - w_i) + (k_j - k_i) L.
            *sd = ctx.wraps[i * D + d] - ctx.wraps[j * D + d] - m;
        }
    }
    s
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
    senders: Vec<u32>,
    used: usize,
    /// (query, row length) in the order of the rows. Kept here, not written to arrays by
    /// query index: queries come in cell order, so two threads writing such arrays would
    /// share (and fight over) nearly every cache line.
    queries: Vec<(u32, u32)>,
    /// dim values per edge, only when shifts were asked for.
    shifts: Vec<i32>,
}

/// Values of room past every row: the in-place sort reads and writes 32 values from a row's
/// start, and [`Searcher::fill`] copies rows in whole chunks of 4 and at least 16.
const ROW_SLACK: usize = 32;

/// Where one task keeps its rows: a row is written straight into the task's buffer (by the
/// cell list's compaction, or copied from an unsorted list), sorted there, and recorded.
pub(crate) struct RowSink<'a> {
    rows: &'a mut TaskRows,
    avx2: bool,
    dim: usize,
    want_shifts: bool,
    order: Vec<usize>,
    pending: u64,
    total: &'a AtomicU64,
    over: &'a AtomicBool,
    max_edges: u64,
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
    fn flush(&mut self) -> bool {
        let edges = std::mem::take(&mut self.pending);
        if self.total.fetch_add(edges, Ordering::Relaxed) + edges > self.max_edges {
            self.over.store(true, Ordering::Relaxed);
        }
        !self.over.load(Ordering::Relaxed)
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

pub(crate) fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Runs `f` compiled for AVX2 when the CPU has it, so the loops inlined into it (distance
/// tests, the rank sort) vectorise 4 wide. Same arithmetic either way: no FMA contraction.
#[inline(always)]
pub(crate) fn with_simd<R>(avx2: bool, f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    if avx2 {
        #[target_feature(enable = "avx2")]
        unsafe fn wide<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        // SAFETY: avx2 is only true when the CPU has AVX2.
        return unsafe { wide(f) };
    }
    let _ = avx2;
    f()
}

/// Writes the distinct values `row` in ascending order to `out` (same length).
/// A typical row holds ~10-40 neighbours; for those, placing each value at its rank
/// (the count of smaller values) is branch-free and vectorises, where a comparison sort
/// pays a misprediction per element.
#[inline(always)]
fn sort_into(row: &mut [u32], out: &mut [u32]) {
    const SHORT: usize = 48;
    #[cfg(target_arch = "x86_64")]
    if row.len() <= SHORT && has_avx2() {
        // SAFETY: checked that the CPU has AVX2 (the check is a cached load).
        unsafe { rank_sort_avx2(row, out) };
        return;
    }
    if row.len() <= SHORT {
        // Padded to whole vectors with values no index can exceed, so the rank loop has no
        // scalar tail.
        let mut padded = [u32::MAX; SHORT];
        padded[..row.len()].copy_from_slice(row);
        let width = row.len().div_ceil(8) * 8;
        for &x in row.iter() {
            let rank: u32 = padded[..width].iter().map(|&y| (y < x) as u32).sum();
            out[rank as usize] = x;
        }
    } else {
        row.sort_unstable();
        out.copy_from_slice(row);
    }
}

/// Sorts the distinct values buf[..n] in place; buf holds at least 32 values past
/// buf[..n] (ROW_SLACK), which the networks may overwrite.
#[inline(always)]
fn sort_in_place(avx2: bool, buf: &mut [u32], n: usize) {
    #[cfg(target_arch = "x86_64")]
    if avx2 && n <= 32 {
        assert!(buf.len() >= 32);
        // SAFETY: avx2 is only true when the CPU has AVX2; buf holds 32 values.
        unsafe { network_sort_32(buf.as_mut_ptr(), n) };
        return;
    }
    let _ = avx2;
    if n <= 48 {
        let mut row = [0u32; 48];
        row[..n].copy_from_slice(&buf[..n]);
        sort_into(&mut row[..n], &mut buf[..n]);
    } else {
        buf[..n].sort_unstable();
    }
}

/// The usual row (at most 32 values; ~14 on average) sorted by a bitonic network on
/// 128-bit registers: the same steps whatever the values, so no branch for the predictor to
/// miss but the one on the width (16 or 32), and no 256-bit shuffles (slow on Zen 1). It beat
/// a rank sort (count of smaller values, 8 lanes at a time) by about 2x in instructions.
/// Lanes past n are padded with u32::MAX, so up to 32 values are written.
///
/// # Safety
/// p is valid for 32 values; the values p[..n] are distinct and below u32::MAX.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn network_sort_32(p: *mut u32, n: usize) {
    if n <= 16 {
        let mut r = load_padded::<4>(p, n);
        sort16(&mut r);
        store_regs(p, &r);
    } else {
        let mut r = load_padded::<8>(p, n);
        let (lo, hi) = r.split_at_mut(4);
        sort16(lo.try_into().unwrap());
        sort16(hi.try_into().unwrap());
        merge_sorted::<8>(&mut r);
        store_regs(p, &r);
    }
}

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::__m128i;

/// M registers of 4 values from p, lanes from n on set to u32::MAX.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn load_padded<const M: usize>(p: *const u32, n: usize) -> [__m128i; M] {
    use std::arch::x86_64::*;
    let last = _mm_set1_epi32(n as i32 - 1);
    let lane = _mm_setr_epi32(0, 1, 2, 3);
    let mut r = [_mm_setzero_si128(); M];
    for (k, rk) in r.iter_mut().enumerate() {
        let past = _mm_cmpgt_epi32(_mm_add_epi32(lane, _mm_set1_epi32(4 * k as i32)), last);
        *rk = _mm_or_si128(_mm_loadu_si128(p.add(4 * k) as *const __m128i), past);
    }
    r
}

#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn store_regs<const M: usize>(p: *mut u32, r: &[__m128i; M]) {
    use std::arch::x86_64::*;
    for (k, rk) in r.iter().enumerate() {
        _mm_storeu_si128(p.add(4 * k) as *mut __m128i, *rk);
    }
}

/// Compare-exchange, lane by lane: a gets the smaller values, b the larger.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn cmp_swap(r: &mut [__m128i], a: usize, b: usize) {
    use std::arch::x86_64::*;
    let lo = _mm_min_epu32(r[a], r[b]);
    r[b] = _mm_max_epu32(r[a], r[b]);
    r[a] = lo;
}

/// Sorts a bitonic sequence of 4 held in one register.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn bitonic4(x: __m128i) -> __m128i {
    use std::arch::x86_64::*;
    // Lanes (0, 2), (1, 3), then (0, 1), (2, 3).
    let t = _mm_shuffle_epi32::<0x4E>(x);
    let x = _mm_blend_epi32::<0b1100>(_mm_min_epu32(x, t), _mm_max_epu32(x, t));
    let t = _mm_shuffle_epi32::<0xB1>(x);
    _mm_blend_epi32::<0b1010>(_mm_min_epu32(x, t), _mm_max_epu32(x, t))
}

/// Sorts a bitonic sequence held in M registers (M a power of two), in place.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn bitonic_merge(r: &mut [__m128i]) {
    let m = r.len();
    let mut s = m / 2;
    while s >= 1 {
        for i in 0..m {
            if i & s == 0 {
                cmp_swap(r, i, i + s);
            }
        }
        s /= 2;
    }
    for x in r.iter_mut() {
        *x = bitonic4(*x);
    }
}

/// Merges the sorted halves r[..M/2] and r[M/2..] into one sorted sequence.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn merge_sorted<const M: usize>(r: &mut [__m128i; M]) {
    use std::arch::x86_64::*;
    let h = M / 2;
    // The first half ascending and the second reversed form a bitonic sequence; one
    // compare-exchange of opposite lanes splits it into a lower and an upper bitonic half.
    let second: [__m128i; M] = std::array::from_fn(|i| {
        if i < h {
            _mm_shuffle_epi32::<0x1B>(r[M - 1 - i])
        } else {
            _mm_setzero_si128()
        }
    });
    for i in 0..h {
        let (a, b) = (r[i], second[i]);
        r[i] = _mm_min_epu32(a, b);
        r[h + i] = _mm_max_epu32(a, b);
    }
    let (lo, hi) = r.split_at_mut(h);
    bitonic_merge(lo);
    bitonic_merge(hi);
}

/// Sorts 16 values in 4 registers: each lane's column by a 4-input network, a transpose
/// (each register then holds a sorted run of 4), and two rounds of merges.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn sort16(r: &mut [__m128i; 4]) {
    use std::arch::x86_64::*;
    for (a, b) in [(0, 1), (2, 3), (0, 2), (1, 3), (1, 2)] {
        cmp_swap(r, a, b);
    }
    let t0 = _mm_unpacklo_epi32(r[0], r[1]);
    let t1 = _mm_unpackhi_epi32(r[0], r[1]);
    let t2 = _mm_unpacklo_epi32(r[2], r[3]);
    let t3 = _mm_unpackhi_epi32(r[2], r[3]);
    r[0] = _mm_unpacklo_epi64(t0, t2);
    r[1] = _mm_unpackhi_epi64(t0, t2);
    r[2] = _mm_unpacklo_epi64(t1, t3);
    r[3] = _mm_unpackhi_epi64(t1, t3);
    let (lo, hi) = r.split_at_mut(2);
    merge_sorted::<2>(lo.try_into().unwrap());
    merge_sorted::<2>(hi.try_into().unwrap());
    merge_sorted::<4>(r);
}

/// [`sort_into`] for rows of at most 48: the rank of each value is the count of smaller
/// values, worked out for 8 values at once: each value in turn is broadcast and compared with
/// every vector of the row (indices are biased by 2^31 for the signed compare).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn rank_sort_avx2(row: &[u32], out: &mut [u32]) {
    assert!(row.len() <= 48 && out.len() == row.len());
    // A fixed vector count keeps the row and its ranks in registers.
    match row.len().div_ceil(8) {
        0 => {}
        1 => rank_sort_vectors::<1>(row, out),
        2 => rank_sort_vectors::<2>(row, out),
        3 => rank_sort_vectors::<3>(row, out),
        4 => rank_sort_vectors::<4>(row, out),
        5 => rank_sort_vectors::<5>(row, out),
        _ => rank_sort_vectors::<6>(row, out),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn rank_sort_vectors<const NV: usize>(row: &[u32], out: &mut [u32]) {
    use std::arch::x86_64::*;
    // Lanes 0..r of a masked load are MASK_WINDOW[8 - r..16 - r].
    static MASK_WINDOW: [i32; 16] = [-1, -1, -1, -1, -1, -1, -1, -1, 0, 0, 0, 0, 0, 0, 0, 0];
    let m = row.len();
    debug_assert!(m.div_ceil(8) == NV && out.len() == m);
    let bias = _mm256_set1_epi32(i32::MIN);
    let mut v = [_mm256_setzero_si256(); NV];
    for (k, vk) in v.iter_mut().enumerate() {
        // A masked load reads only the lanes of the row, never past its end; the padding
        // lanes get ranks too, which are never read.
        let lanes = (m - 8 * k).min(8);
        let mask = _mm256_loadu_si256(MASK_WINDOW.as_ptr().add(8 - lanes) as *const __m256i);
        let x = _mm256_maskload_epi32(row.as_ptr().add(8 * k) as *const i32, mask);
        *vk = _mm256_xor_si256(x, bias);
    }
    let mut rank = [_mm256_setzero_si256(); NV];
    for &x in row {
        let xb = _mm256_set1_epi32((x ^ 0x8000_0000) as i32);
        for k in 0..NV {
            // -1 in the lanes whose value is greater than x: x counts as smaller there.
            rank[k] = _mm256_sub_epi32(rank[k], _mm256_cmpgt_epi32(v[k], xb));
        }
    }
    let mut ranks = [[0u32; 8]; NV];
    for k in 0..NV {
        _mm256_storeu_si256(ranks[k].as_mut_ptr() as *mut __m256i, rank[k]);
    }
    for (&x, &r) in row.iter().zip(ranks.as_flattened()) {
        // The values are distinct indices, so the ranks are a permutation of 0..m.
        *out.get_unchecked_mut(r as usize) = x;
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

const CHECK_EVERY: u64 = 1 << 20;

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
pub(crate) mod tests {
    use super::*;

    /// Deterministic points (xorshift64*), so the tests need no dependency.
    pub(crate) fn random_points(n: usize, dim: usize, seed: u64, scale: f64) -> Vec<f64> {
        let mut s = seed.wrapping_mul(0x9E3779B97F4A7C15) | 1;
        (0..n * dim)
            .map(|_| {
                s ^= s >> 12;
                s ^= s << 25;
                s ^= s >> 27;
                scale * ((s.wrapping_mul(0x2545F4914F6CDD1D) >> 11) as f64 / (1u64 << 53) as f64)
            })
            .collect()
    }

    /// The plainest possible oracle, independent of Metric: all pairs, f64, minimum image by
    /// trying every image within one box length.
    fn naive(pts: &[f64], dim: usize, bounds: &[usize], opts: &GraphOptions) -> Vec<(i64, i64)> {
        let mut out = Vec::new();
        for g in 0..bounds.len() - 1 {
            for i in bounds[g]..bounds[g + 1] {
                for j in bounds[g]..bounds[g + 1] {
                    if i == j && !opts.self_edges {
                        continue;
                    }
                    let mut d2 = 0.0;
                    for d in 0..dim {
                        let mut dx: f64 = pts[j * dim + d] - pts[i * dim + d];
                        if opts.periodic.get(d).copied().unwrap_or(false) {
                            let l = opts.box_lengths.as_ref().unwrap()[d];
                            dx = dx.rem_euclid(l);
                            dx = dx.min(l - dx);
                        }
                        d2 += dx * dx;
                    }
                    if d2 <= opts.radius * opts.radius {
                        out.push((i as i64, j as i64));
                    }
                }
            }
        }
        out
    }

    fn as_pairs(e: &Edges) -> Vec<(i64, i64)> {
        e.receivers
            .iter()
            .zip(&e.senders)
            .map(|(&r, &s)| (r, s))
            .collect()
    }

    fn all_methods(pts: &[f64], dim: usize, n_node: Option<&[i64]>, opts: &GraphOptions) -> Edges {
        let mut first: Option<Edges> = None;
        for method in [Method::Brute, Method::Cells, Method::KdTree] {
            for threads in [None, Some(1), Some(3)] {
                let o = GraphOptions {
                    method,
                    ..opts.clone()
                };
                let e = Searcher::new(threads)
                    .unwrap()
                    .search(pts, dim, n_node, &o, o.box_lengths.is_some())
                    .unwrap();
                match &first {
                    None => first = Some(e),
                    Some(f) => assert_eq!(f, &e, "{method:?} with {threads:?} threads differs"),
                }
            }
        }
        first.unwrap()
    }

    #[test]
    fn every_method_matches_the_naive_oracle() {
        for dim in [2, 3] {
            for (n, radius) in [(0, 0.1), (1, 0.1), (2, 5.0), (300, 0.08), (5000, 0.03)] {
                let pts = random_points(n, dim, 7 + n as u64, 1.0);
                let opts = GraphOptions::new(radius);
                let e = all_methods(&pts, dim, None, &opts);
                assert_eq!(
                    as_pairs(&e),
                    naive(&pts, dim, &[0, n], &opts),
                    "dim {dim} n {n}"
                );
            }
        }
    }

    #[test]
    fn largest_magnitude_is_the_largest_absolute_value_or_nan() {
        // Every length up to a few chunks of 8 lanes, the extreme in every position.
        for len in 1..30 {
            for at in 0..len {
                let mut xs = random_points(len, 1, len as u64, 2.0);
                xs[at] = -3.5;
                assert_eq!(largest_magnitude(&xs), 3.5, "len {len}, at {at}");
                for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                    xs[at] = bad;
                    assert!(largest_magnitude(&xs).is_nan(), "len {len}, at {at}");
                }
            }
        }
        assert_eq!(largest_magnitude(&[]), 0.0);
    }

    #[test]
    fn rank_sort_and_comparison_sort_agree() {
        let row: Vec<u32> = (0..47u32)
            .map(|k| k.wrapping_mul(2_654_435_761) ^ 0x8000_0003)
            .collect();
        for len in [0, 1, 7, 8, 9, 31, 47] {
            let mut want = row[..len].to_vec();
            want.sort_unstable();
            let mut got = vec![0u32; len];
            sort_into(&mut row[..len].to_vec(), &mut got);
            assert_eq!(got, want);
            #[cfg(target_arch = "x86_64")]
            if has_avx2() {
                let mut wide = vec![0u32; len];
                unsafe { rank_sort_avx2(&row[..len], &mut wide) };
                assert_eq!(wide, want);
            }
        }
    }

    #[test]
    fn in_place_sorts_agree_with_the_standard_sort() {
        // Every width path (network 16 and 32, rank sort, comparison sort), values spanning
        // the whole unsigned range (the networks compare unsigned), garbage past the row.
        let mut s = 0x9E37_79B9_7F4A_7C15u64;
        for n in (0..=70).chain([100, 300]) {
            for avx2 in [false, has_avx2()] {
                for round in 0..20 {
                    let mut set = std::collections::BTreeSet::new();
                    while set.len() < n {
                        s ^= s << 13;
                        s ^= s >> 7;
                        s ^= s << 17;
                        let v = match round % 3 {
                            0 if n <= 64 => s as u32 % 64,
                            1 if n <= 64 => u32::MAX - 1 - (s as u32 % 100),
                            _ => (s as u32).min(u32::MAX - 1),
                        };
                        set.insert(v);
                    }
                    let want: Vec<u32> = set.iter().copied().collect();
                    let mut row: Vec<u32> = want.iter().rev().copied().collect();
                    row.rotate_left(n / 3);
                    row.extend(std::iter::repeat_n(7, ROW_SLACK));
                    sort_in_place(avx2, &mut row, n);
                    assert_eq!(&row[..n], &want[..], "n {n} avx2 {avx2} round {round}");
                }
            }
        }
    }

    #[test]
    fn rows_are_sorted_by_receiver_then_sender() {
        let pts = random_points(6000, 2, 3, 1.0);
        let e = radius_graph(&pts, 2, None, &GraphOptions::new(0.04), false).unwrap();
        let pairs = as_pairs(&e);
        assert!(pairs.windows(2).all(|w| w[0] < w[1]));
        // Long rows (a dense clump) take the comparison-sort path: still sorted.
        let mut dense = random_points(3000, 2, 4, 0.01);
        dense.extend(random_points(3000, 2, 5, 1.0));
        let e = radius_graph(&dense, 2, None, &GraphOptions::new(0.02), false).unwrap();
        assert!(as_pairs(&e).windows(2).all(|w| w[0] < w[1]));
        assert!(e.senders.len() > 3000 * 100);
    }

    #[test]
    fn large_inputs_sort_in_parallel_and_agree_with_the_tree_and_one_thread() {
        // Above PARALLEL_SORT_FROM the counting sort is split per thread; the result must not
        // depend on the thread count, and must match the independent k-d tree.
        for dim in [2, 3] {
            let mut pts = random_points(50_000, dim, 21, 1.0);
            pts.extend(random_points(20_000, dim, 22, 0.3)); // denser region: uneven parts
            let opts = GraphOptions::new(if dim == 2 { 0.01 } else { 0.03 });
            let one = Searcher::new(Some(1))
                .unwrap()
                .search(&pts, dim, None, &opts, false)
                .unwrap();
            let three = Searcher::new(Some(3))
                .unwrap()
                .search(&pts, dim, None, &opts, false)
                .unwrap();
            let tree = GraphOptions {
                method: Method::KdTree,
                ..opts.clone()
            };
            let by_tree = radius_graph(&pts, dim, None, &tree, false).unwrap();
            assert_eq!(one, three);
            assert_eq!(one, by_tree);
            assert!(one.senders.len() > 70_000 * 5);
        }
    }

    #[test]
    fn batches_never_cross_graphs() {
        let pts = random_points(900, 3, 11, 1.0);
        let sizes = [0i64, 400, 0, 499, 1];
        let bounds = [0, 0, 400, 400, 899, 900];
        let opts = GraphOptions::new(0.2);
        let e = all_methods(&pts, 3, Some(&sizes), &opts);
        assert_eq!(as_pairs(&e), naive(&pts, 3, &bounds, &opts));
    }

    #[test]
    fn periodic_boxes_use_the_minimum_image() {
        for (dim, periodic, lengths) in [
            (2, vec![true, true], vec![1.0, 0.5]),
            (3, vec![true, false, true], vec![1.0, 1.0, 0.3]),
            // Exactly 2 * radius wide: one or two cells per axis.
            (2, vec![true, true], vec![0.2, 0.3]),
        ] {
            let mut pts = random_points(700, dim, 5, 1.0);
            for (k, x) in pts.iter_mut().enumerate() {
                *x *= lengths[k % dim];
            }
            let opts = GraphOptions {
                box_lengths: Some(lengths.clone()),
                periodic: periodic.clone(),
                ..GraphOptions::new(0.1)
            };
            let e = all_methods(&pts, dim, None, &opts);
            assert_eq!(as_pairs(&e), naive(&pts, dim, &[0, 700], &opts));
            // The shifts reproduce the minimum-image displacement.
            for (k, (&r, &s)) in e.receivers.iter().zip(&e.senders).enumerate() {
                let mut d2 = 0.0;
                for d in 0..dim {
                    let sh = e.shifts[k * dim + d] as f64 * lengths[d];
                    let dx = pts[s as usize * dim + d] - pts[r as usize * dim + d] + sh;
                    assert!(dx.abs() <= lengths[d] / 2.0 + 1e-12);
                    d2 += dx * dx;
                }
                assert!(d2 <= 0.01 + 1e-12);
            }
        }
    }

    #[test]
    fn wrapped_positions_keep_their_shifts() {
        // The same particles, some moved by whole box lengths: same pairs, and the shifts
        // absorb the moves.
        let pts = random_points(200, 2, 9, 1.0);
        let mut moved = pts.clone();
        for (k, x) in moved.iter_mut().enumerate() {
            *x += ((k % 5) as f64 - 2.0) * 1.0;
        }
        let opts = GraphOptions {
            box_lengths: Some(vec![1.0, 1.0]),
            periodic: vec![true, true],
            ..GraphOptions::new(0.15)
        };
        let a = radius_graph(&pts, 2, None, &opts, true).unwrap();
        let b = radius_graph(&moved, 2, None, &opts, true).unwrap();
        assert_eq!(a.senders, b.senders);
        for (k, (&r, &s)) in b.receivers.iter().zip(&b.senders).enumerate() {
            for d in 0..2 {
                let disp_a =
                    pts[s as usize * 2 + d] - pts[r as usize * 2 + d] + a.shifts[k * 2 + d] as f64;
                let disp_b = moved[s as usize * 2 + d] - moved[r as usize * 2 + d]
                    + b.shifts[k * 2 + d] as f64;
                assert!((disp_a - disp_b).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn exactly_at_the_radius_is_inside_and_a_hair_beyond_is_not() {
        // 3-4-5 triangle: exactly representable, distance exactly 5.
        let pts = [0.0, 0.0, 3.0, 4.0, 3.0, 4.0 + 4.0 * f64::EPSILON];
        let e = all_methods(&pts, 2, None, &GraphOptions::new(5.0));
        assert_eq!(
            as_pairs(&e),
            vec![(0, 0), (0, 1), (1, 0), (1, 1), (1, 2), (2, 1), (2, 2)]
        );
        // float32 inputs with the same values give the same graph.
        let p32: Vec<f32> = [0.0f32, 0.0, 0.5, 0.0, 0.0, 0.5].to_vec();
        let e = radius_graph(&p32, 2, None, &GraphOptions::new(0.5), false).unwrap();
        assert_eq!(e.senders.len(), 3 + 4);
    }

    #[test]
    fn coincident_particles_are_neighbours_and_self_edges_go_by_index() {
        let pts = [1.0, 1.0, 1.0, 1.0, 1.0, 1.0];
        let opts = GraphOptions {
            self_edges: false,
            ..GraphOptions::new(0.5)
        };
        let e = all_methods(&pts, 2, None, &opts);
        assert_eq!(
            as_pairs(&e),
            vec![(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)]
        );
    }

    #[test]
    fn far_outliers_neither_blow_up_the_grid_nor_get_lost() {
        let mut pts = random_points(2000, 3, 2, 1.0);
        pts.extend_from_slice(&[1e6, 1e6, 1e6, 1e6 + 0.01, 1e6, 1e6, -1e300, 0.0, 0.0]);
        let opts = GraphOptions::new(0.1);
        let e = all_methods(&pts, 3, None, &opts);
        assert_eq!(as_pairs(&e), naive(&pts, 3, &[0, 2003], &opts));
    }

    #[test]
    fn too_many_edges_is_an_error_naming_the_count() {
        let pts = vec![0.5; 2 * 20_000];
        let opts = GraphOptions {
            max_edges: 1_000_000,
            ..GraphOptions::new(0.1)
        };
        match radius_graph(&pts, 2, None, &opts, false) {
            Err(Error::TooManyEdges {
                at_least,
                max_edges,
            }) => {
                assert!(at_least > 1_000_000 && max_edges == 1_000_000);
            }
            other => panic!("expected TooManyEdges, got {other:?}"),
        }
    }

    #[test]
    fn a_tight_clump_past_max_edges_fails_before_the_search() {
        // 20k coincident particles: the check counts all 4e8 pairs up front, where the
        // search's own guard would stop a little past max_edges.
        let pts = vec![0.5; 2 * 20_000];
        for (method, self_edges) in [(Method::Cells, true), (Method::KdTree, false)] {
            let opts = GraphOptions {
                max_edges: 1_000_000,
                method,
                self_edges,
                ..GraphOptions::new(0.1)
            };
            let expected = 20_000u64 * 20_000 - if self_edges { 0 } else { 20_000 };
            match radius_graph(&pts, 2, None, &opts, false) {
                Err(Error::TooManyEdges { at_least, .. }) => assert_eq!(at_least, expected),
                other => panic!("expected TooManyEdges, got {other:?}"),
            }
        }
    }

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

    #[test]
    fn bad_inputs_are_rejected_with_their_value() {
        let ok = [0.0, 0.0, 1.0, 1.0];
        let err = |pts: &[f64], dim: usize, n_node: Option<&[i64]>, o: GraphOptions| {
            radius_graph(pts, dim, n_node, &o, false)
                .unwrap_err()
                .to_string()
        };
        assert!(err(&[0.0, f64::NAN], 2, None, GraphOptions::new(1.0)).contains("NaN"));
        assert!(err(&[0.0, f64::INFINITY], 2, None, GraphOptions::new(1.0)).contains("inf"));
        assert!(err(&ok, 4, None, GraphOptions::new(1.0)).contains("2 or 3"));
        assert!(err(&ok[..3], 2, None, GraphOptions::new(1.0)).contains("multiple"));
        for r in [0.0, -1.0, f64::NAN, f64::INFINITY, 1.4e154] {
            assert!(err(&ok, 2, None, GraphOptions::new(r)).contains("radius"));
        }
        assert!(err(&ok, 2, Some(&[1, 2]), GraphOptions::new(1.0)).contains("sums to 3"));
        assert!(err(&ok, 2, Some(&[3, -1]), GraphOptions::new(1.0)).contains("-1"));
        let periodic = |b: Option<Vec<f64>>| GraphOptions {
            box_lengths: b,
            periodic: vec![true, false],
            ..GraphOptions::new(1.0)
        };
        assert!(err(&ok, 2, None, periodic(None)).contains("need a box"));
        assert!(err(&ok, 2, None, periodic(Some(vec![1.5, 1.0]))).contains("narrower"));
        // Found by fuzzing: -1.5 wrapped into a box of 1.8e16 rounded onto 0, one radius away.
        assert!(err(&ok, 2, None, periodic(Some(vec![1.8e16, 1.0]))).contains("2^-32 radii"));
        assert!(err(&ok, 2, None, periodic(Some(vec![2.0]))).contains("one length per axis"));
        assert!("octree"
            .parse::<Method>()
            .unwrap_err()
            .to_string()
            .contains("octree"));
    }
}
