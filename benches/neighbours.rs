//! Neighbour-search benchmark of the Rust core alone (no Python):
//!     cargo bench --bench neighbours [-- --quick]
//! Prints time per call and ns per edge for the cases of shared/design/neighbour-search.md,
//! for the cell list and the k-d tree, on the global pool and on one thread. Peers are measured
//! from Python in the same run by benches/neighbours.py.

use gns::{GraphOptions, Method, Searcher};
use std::time::Instant;

/// A small deterministic generator (xorshift64*), so the benchmark needs no dependency.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545F4914F6CDD1D) >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Uniform points in the unit box and the radius that gives about `k` neighbours (self included).
fn uniform(n: usize, dim: usize, k: f64, seed: u64) -> (Vec<f64>, f64) {
    let mut rng = Rng(seed.wrapping_mul(0x9E3779B97F4A7C15) | 1);
    let pts = (0..n * dim).map(|_| rng.next()).collect();
    let vol = k / n as f64;
    let r = if dim == 2 {
        (vol / std::f64::consts::PI).sqrt()
    } else {
        (vol * 3.0 / (4.0 * std::f64::consts::PI)).cbrt()
    };
    (pts, r)
}

/// Half the particles packed into a box 1/8 as wide per axis (much denser), same radius.
fn clumped(n: usize, dim: usize, k: f64, seed: u64) -> (Vec<f64>, f64) {
    let (mut pts, r) = uniform(n, dim, k, seed);
    for v in pts[..n / 2 * dim].iter_mut() {
        *v = 0.4 + *v / 8.0;
    }
    (pts, r)
}

/// Median seconds per call of count + fill into warm output buffers, and the edge count.
fn time(
    searcher: &mut Searcher,
    pts: &[f64],
    dim: usize,
    opts: &GraphOptions,
    reps: usize,
) -> (f64, usize) {
    let e = searcher.count(pts, dim, None, opts, false).unwrap();
    let (mut s, mut r) = (vec![0i64; e], vec![0i64; e]);
    let mut times: Vec<f64> = (0..reps)
        .map(|_| {
            let t = Instant::now();
            searcher.count(pts, dim, None, opts, false).unwrap();
            searcher.fill(&mut s, &mut r, None).unwrap();
            t.elapsed().as_secs_f64()
        })
        .collect();
    times.sort_by(f64::total_cmp);
    (times[reps / 2], e)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let quick = args.iter().any(|a| a == "--quick");
    // `--cells` measures only the cell list (for profiling it).
    let cells_only = args.iter().any(|a| a == "--cells");
    // `--only TEXT` keeps only the case named TEXT (for profiling one case).
    let only = args
        .iter()
        .position(|a| a == "--only")
        .and_then(|k| args.get(k + 1).cloned());
    let mut cases: Vec<(&str, usize, usize, bool)> = vec![
        ("2D 1.1k", 1100, 2, false),
        ("2D 10k", 10_000, 2, false),
        ("3D 20k", 20_000, 3, false),
        ("2D 10k clumped", 10_000, 2, true),
        ("3D 20k clumped", 20_000, 3, true),
    ];
    if !quick {
        cases.push(("3D 1M", 1_000_000, 3, false));
    }
    let threads = rayon::current_num_threads();
    println!(
        "| case | edges | method | threads | ms per call | ns per edge |\n|---|---|---|---|---|---|"
    );
    for (name, n, dim, clump) in cases {
        if only.as_ref().is_some_and(|o| name != o.as_str()) {
            continue;
        }
        let (pts, r) = if clump {
            clumped(n, dim, 14.0, 1)
        } else {
            uniform(n, dim, 14.0, 1)
        };
        let reps = if n >= 1_000_000 {
            3
        } else if quick {
            20
        } else {
            200
        };
        let methods: &[Method] = if cells_only {
            &[Method::Cells]
        } else {
            &[Method::Cells, Method::KdTree]
        };
        for &method in methods {
            let opts = GraphOptions {
                method,
                ..GraphOptions::new(r)
            };
            for t in [threads, 1] {
                let mut s = if t == threads {
                    Searcher::default()
                } else {
                    Searcher::new(Some(1)).unwrap()
                };
                let (secs, e) = time(&mut s, &pts, dim, &opts, reps);
                println!(
                    "| {name} | {e} | {method:?} | {t} | {:.3} | {:.2} |",
                    secs * 1e3,
                    secs * 1e9 / e as f64
                );
                if t == 1 {
                    break;
                }
            }
        }
    }
}
