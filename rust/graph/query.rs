//! What a query needs and how it accepts a neighbour: the canonical distance ([`Metric`]), the
//! query's context ([`Ctx`]) and scratch ([`Found`]), the acceptance test every method ends in
//! (so they agree to the last bit), periodic shifts, and the clump bounds behind the
//! max_edges check. The vocabulary the search structures (cells, k-d tree, brute force) share;
//! it depends on nothing else of the search.

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
