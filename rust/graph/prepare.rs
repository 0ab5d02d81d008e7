//! A call's input: the options ([`GraphOptions`], [`Method`]), their validation, the graph
//! boundaries from `n_node`, and the positions in f64 with periodic axes wrapped into the box
//! ([`Prepared`]), which every search structure is built from.

use super::query::Metric;
use super::simd::{has_avx2, with_simd};
use crate::{check_positive, first_non_finite, Error, Real, Result};
use std::str::FromStr;

/// The default memory guard: 2^28 edges are 4 GiB of int64 output.
pub const DEFAULT_MAX_EDGES: u64 = 1 << 28;
/// A periodic box at most 2^20 radii long: positions wrapped into [0, L) are then rounded by
/// at most 2^-32 radii (one ulp of L), far below any distance the search tells apart.
const MAX_PERIODIC_RADII: f64 = (1u64 << 20) as f64;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::tests::random_points;

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
}
