//! k-d tree search (the paper's choice): median splits on the widest axis, small leaves, box
//! pruning. Slower than the grid at simulation densities, but indifferent to how the points are
//! spread, so it serves sparse clouds, far outliers, and as a second opinion in tests.

use super::prepare::Prepared;
use super::query::{accept_at, clump_edges, tight, Ctx, Found};

const LEAF: usize = 12;
const NO_CHILD: u32 = u32::MAX;

struct Node<const D: usize> {
    lo: [f64; D],
    hi: [f64; D],
    start: u32,
    end: u32,
    left: u32,
    right: u32,
}

pub(crate) struct KdTree<const D: usize> {
    /// (global index, coordinates) in tree order: every node owns a contiguous range.
    items: Vec<(u32, [f64; D])>,
    nodes: Vec<Node<D>>,
}

impl<const D: usize> KdTree<D> {
    pub fn build(prepared: &Prepared, start: usize, end: usize) -> Self {
        let items = (start..end)
            .map(|i| {
                let mut x = [0.0; D];
                x.copy_from_slice(&prepared.coords[i * D..(i + 1) * D]);
                (i as u32, x)
            })
            .collect();
        let mut tree = KdTree {
            items,
            nodes: Vec::new(),
        };
        if !tree.items.is_empty() {
            tree.split(0, tree.items.len());
        }
        tree
    }

    fn split(&mut self, start: usize, end: usize) -> u32 {
        let mut lo = [f64::INFINITY; D];
        let mut hi = [f64::NEG_INFINITY; D];
        for (_, x) in &self.items[start..end] {
            for d in 0..D {
                lo[d] = lo[d].min(x[d]);
                hi[d] = hi[d].max(x[d]);
            }
        }
        let id = self.nodes.len() as u32;
        self.nodes.push(Node {
            lo,
            hi,
            start: start as u32,
            end: end as u32,
            left: NO_CHILD,
            right: NO_CHILD,
        });
        let widest = (0..D)
            .max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b])))
            .unwrap_or(0);
        // A leaf when small, or when every point coincides (no split can separate them).
        if end - start <= LEAF || hi[widest] - lo[widest] <= 0.0 {
            return id;
        }
        let mid = (start + end) / 2;
        self.items[start..end]
            .select_nth_unstable_by(mid - start, |a, b| a.1[widest].total_cmp(&b.1[widest]));
        let left = self.split(start, mid);
        let right = self.split(mid, end);
        let node = &mut self.nodes[id as usize];
        node.left = left;
        node.right = right;
        id
    }

    pub fn len(&self) -> usize {
        self.items.len()
    }

    /// Edges sure to exist: all pairs within each largest tight node (see [`tight`]),
    /// worked out only when the particles could make more than `limit` edges.
    pub fn sure_edges(&self, r2: f64, self_edges: bool, limit: u64) -> u64 {
        let n = self.items.len() as u64;
        if n * n <= limit || self.nodes.is_empty() {
            return 0;
        }
        let (mut sure, mut stack) = (0, vec![0u32]);
        while let Some(id) = stack.pop() {
            let node = &self.nodes[id as usize];
            if tight(&node.lo, &node.hi, r2) {
                sure += clump_edges((node.end - node.start) as usize, self_edges);
            } else if node.left != NO_CHILD {
                stack.push(node.left);
                stack.push(node.right);
            }
        }
        sure
    }

    pub fn original(&self, p: usize) -> usize {
        self.items[p].0 as usize
    }

    pub fn collect(&self, p: usize, ctx: &Ctx, found: &mut Found) {
        found.senders.clear();
        found.shifts.clear();
        let (i, q) = self.items[p];
        let i = i as usize;
        let m = &ctx.metric;
        // On a periodic axis a neighbour can sit across either face: search the images of the
        // query one box length either way.
        let mut images = [q; 27];
        let mut n_images = 1;
        for d in 0..D {
            if m.periodic[d] {
                let base = n_images;
                for s in [-1.0, 1.0] {
                    for k in 0..base {
                        images[n_images] = images[k];
                        images[n_images][d] += s * m.lengths[d];
                        n_images += 1;
                    }
                }
            }
        }
        let reach2 = m.reach * m.reach;
        let mut stack = std::mem::take(&mut found.stack);
        for qs in &images[..n_images] {
            stack.clear();
            stack.push(0);
            while let Some(id) = stack.pop() {
                let node = &self.nodes[id as usize];
                let mut gap2 = 0.0;
                for d in 0..D {
                    let g = (node.lo[d] - qs[d]).max(qs[d] - node.hi[d]).max(0.0);
                    gap2 += g * g;
                }
                if gap2 > reach2 {
                    continue;
                }
                if node.left == NO_CHILD {
                    for (j, x) in &self.items[node.start as usize..node.end as usize] {
                        accept_at(ctx, i, *j as usize, &q, x, found);
                    }
                } else {
                    stack.push(node.right);
                    stack.push(node.left);
                }
            }
        }
        found.stack = stack;
        if n_images > 1 {
            // A small periodic box lets two images reach the same particle: keep one.
            let mut pairs: Vec<(u32, [i32; 3])> = found
                .senders
                .iter()
                .enumerate()
                .map(|(k, &j)| (j, found.shifts.get(k).copied().unwrap_or_default()))
                .collect();
            pairs.sort_unstable_by_key(|x| x.0);
            pairs.dedup_by_key(|x| x.0);
            found.senders.clear();
            found.senders.extend(pairs.iter().map(|x| x.0));
            if ctx.want_shifts {
                found.shifts.clear();
                found.shifts.extend(pairs.iter().map(|x| x.1));
            }
        }
    }
}
