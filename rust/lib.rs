//! Rust core of `gns`: the work done at every step of a learned particle simulator.
//!
//! Pure functions over slices; only `python.rs` (behind the `python` feature) names pyo3/numpy.
//! - [`graph`]: radius graphs (dispatch, batching by `n_node`, canonical distance, brute force),
//!   with the cell-list search used by default (`graph/cells.rs`) and a k-d tree search for
//!   sparse or very non-uniform clouds (`graph/kdtree.rs`)
//! - [`walls`]: clipped distances to box walls and to obstacle shapes (parry)
//! - [`integrate`]: the semi-implicit Euler update
//! - [`mpm`]: the reference simulator (MLS-MPM in 2D and 3D, rigid bodies) that makes ground truth

// Per-axis loops index several per-axis arrays at once; an index reads clearer than zips.
#![allow(clippy::needless_range_loop)]

pub mod graph;
pub mod integrate;
pub mod mpm;
pub mod walls;

#[cfg(feature = "python")]
mod python;

pub use graph::{radius_graph, Edges, GraphOptions, Method, Searcher, DEFAULT_MAX_EDGES};
pub use integrate::euler_step;
pub use walls::{nearest_obstacle_features, obstacle_features, wall_features, Obstacle};

use std::fmt;

/// Every way an input can be rejected. Each message names the bad value and what was expected;
/// the Python binding turns every variant into `ValueError`.
#[derive(Debug, Clone, PartialEq)]
pub enum Error {
    /// A shape, dimension or length that does not fit.
    Shape(String),
    /// A NaN or infinite value where finite numbers are required.
    NonFinite(String),
    /// A parameter outside its allowed range (radius, box, n_node, clip, dt...).
    Value(String),
    /// The graph would hold more edges than allowed; nothing is truncated.
    TooManyEdges { at_least: u64, max_edges: u64 },
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::Shape(m) | Error::NonFinite(m) | Error::Value(m) => f.write_str(m),
            Error::TooManyEdges {
                at_least,
                max_edges,
            } => write!(
                f,
                "the radius graph would have at least {at_least} edges, more than max_edges = \
                 {max_edges}; pass a larger max_edges if this is intended (each edge costs 16 \
                 bytes), or check the radius and the positions (clumped or duplicated particles?)"
            ),
        }
    }
}

impl std::error::Error for Error {}

pub type Result<T> = std::result::Result<T, Error>;

/// Scalars accepted as positions. Every computation is done in f64 so that float32 and float64
/// inputs with the same values give the same graph (and agree with scipy, which also uses f64).
pub trait Real: Copy + Send + Sync + 'static {
    fn to_f64(self) -> f64;
    fn from_f64(v: f64) -> Self;
}

impl Real for f32 {
    #[inline]
    fn to_f64(self) -> f64 {
        self as f64
    }
    #[inline]
    fn from_f64(v: f64) -> Self {
        v as f32
    }
}

impl Real for f64 {
    #[inline]
    fn to_f64(self) -> f64 {
        self
    }
    #[inline]
    fn from_f64(v: f64) -> Self {
        v
    }
}

/// Ok for a finite value > 0; otherwise the error every parameter check of the crate gives.
pub(crate) fn check_positive(name: &str, value: f64) -> Result<()> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(Error::Value(format!(
            "{name} must be a finite number > 0, got {value}"
        )))
    }
}

/// The first non-finite value of a row-major `(n, dim)` array, as (row, column).
pub(crate) fn first_non_finite<T: Real>(values: &[T], dim: usize) -> Option<(usize, usize)> {
    values
        .iter()
        .position(|v| !v.to_f64().is_finite())
        .map(|k| (k / dim, k % dim))
}
