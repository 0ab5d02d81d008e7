//! Radius graphs: validation, batching by `n_node`, the canonical distance every method shares,
//! the search structures, the driver (find and sort each row in parallel tasks, then copy the
//! rows into exact-size output) and the brute-force oracle.
//!
//! Semantics: a directed edge j -> i for every pair of
//! particles of the same graph with |x_j - x_i| <= radius, self-edges decided by index,
//! senders and receivers sorted by (receiver, sender), the same for every method and thread
//! count. Nothing is ever truncated: more than `max_edges` edges is an error.
//!
//! One job per file, each using only files listed above it:
//! - `simd`: the run-time AVX2 check and the trampoline into AVX2-compiled code
//! - `query`: the vocabulary of one query that every search method shares: the canonical
//!   distance, the query's context and scratch, the acceptance test, periodic shifts
//! - `prepare`: the options, their validation, graph boundaries from `n_node`, positions in
//!   f64 with periodic axes wrapped
//! - `sort`: sorting one row of neighbour indices (bitonic networks, rank sort)
//! - `rows`: per-task row storage: each row written, sorted and kept in its task's buffer
//! - `cells`: the cell-list search used by default
//! - `kdtree`: a k-d tree search for sparse or very non-uniform clouds
//! - `searcher`: the driver: one index per graph, parallel tasks, output placement;
//!   [`Searcher`] and [`radius_graph`]

mod cells;
mod kdtree;
mod prepare;
mod query;
mod rows;
mod searcher;
mod simd;
mod sort;

#[cfg(test)]
mod tests;

pub use prepare::{GraphOptions, Method, DEFAULT_MAX_EDGES};
pub use searcher::{radius_graph, Edges, Searcher};
