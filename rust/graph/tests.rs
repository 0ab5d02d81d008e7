//! End-to-end tests of the search through its public entry points: every method and thread
//! count against a naive oracle, batches, periodic boxes, edge cases and bad inputs.

use super::{radius_graph, Edges, GraphOptions, Method, Searcher};
use crate::Error;

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
pub(super) fn naive(
    pts: &[f64],
    dim: usize,
    bounds: &[usize],
    opts: &GraphOptions,
) -> Vec<(i64, i64)> {
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
            let disp_b =
                moved[s as usize * 2 + d] - moved[r as usize * 2 + d] + b.shifts[k * 2 + d] as f64;
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
