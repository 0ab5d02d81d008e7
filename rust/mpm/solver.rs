//! The MLS-MPM grid and transfers in D dimensions: particles to grid, grid update (gravity,
//! walls, obstacles), grid to particles, and the substep loop with its CFL bound.

use super::constitutive::{deform, drucker_prager, kirchhoff_stress, project, trace, von_mises};
use super::rigid::Body;
use super::{inside_grid, Dim, Material, Matrix, Model, Settings, Space, Vector, Wall};
use crate::{Error, Result};
use rayon::prelude::*;

/// The P2G scatter of a run with at least SPLIT_AT particles is split into PARTS fixed ranges of
/// particles, each into its own grid, summed in order: fixed (not per thread) so the
/// summation order, and so the result, never depends on the thread count.
const PARTS: usize = 4;
pub(super) const SPLIT_AT: usize = 1024;

/// A grid node: momentum and mass after the scatter; update_grid turns momentum into velocity
/// (the mass is kept for the weights' normalisation).
#[derive(Clone, Copy)]
struct Node<const D: usize> {
    momentum: Vector<D>,
    mass: f64,
}

impl<const D: usize> Node<D> {
    const ZERO: Self = Node {
        momentum: [0.0; D],
        mass: 0.0,
    };
}

pub(super) struct Mpm<'a, const D: usize> {
    s: &'a Settings<D>,
    materials: &'a [Material],
    lame: Vec<(f64, f64)>,
    dx: f64,
    /// Nodes per axis (grid + 1); node (i, j, k) is at index (i nodes + j) nodes + k.
    nodes: usize,
    pub(super) x: Vec<Vector<D>>,
    pub(super) v: Vec<Vector<D>>,
    c: Vec<Matrix<D>>,
    f: Vec<Matrix<D>>,
    /// Water: the volume ratio J (F is not kept for a fluid). Sand: the log of the volume
    /// gained by separating (Tampubolon et al. 2017), which must be recompressed before the
    /// grains carry stress again, as Taichi-Elements does.
    j: Vec<f64>,
    material: Vec<u32>,
    volume: f64,
    wave_speed: f64,
    /// Grid nodes covered by obstacle particles (sticky), fixed for the run.
    solid: Vec<bool>,
    grid: Vec<Node<D>>,
    /// The PARTS grids of a split scatter (empty below SPLIT_AT particles), kept between substeps.
    parts: Vec<Vec<Node<D>>>,
    /// One per material of the Rigid model that has particles, in material order.
    bodies: Vec<Body<D>>,
}

/// A particle's quadratic B-spline stencil: the base node, the particle's offset from it in
/// cells, and the weights per axis.
struct Stencil<const D: usize> {
    base: [usize; D],
    fx: Vector<D>,
    w: [[f64; 3]; D],
}

impl<const D: usize> Stencil<D> {
    #[inline]
    fn new(p: &Vector<D>, inv_dx: f64) -> Self {
        let mut base = [0usize; D];
        let mut fx = [0.0; D];
        let mut w = [[0.0; 3]; D];
        for a in 0..D {
            let g = p[a] * inv_dx;
            let b = (g - 0.5).floor();
            base[a] = b as usize;
            let f = g - b;
            fx[a] = f;
            w[a] = [
                0.5 * (1.5 - f) * (1.5 - f),
                0.75 - (f - 1.0) * (f - 1.0),
                0.5 * (f - 0.5) * (f - 0.5),
            ];
        }
        Stencil { base, fx, w }
    }

    /// Calls `visit(node index, weight, node - particle in cells)` for the 3^D nodes, the last
    /// axis fastest (a fixed order, so the sums over a stencil are reproducible).
    #[inline(always)]
    fn for_each(&self, nodes: usize, mut visit: impl FnMut(usize, f64, Vector<D>)) {
        // Nested loops (D is 2 or 3) rather than one loop over the 3^D offsets, which the
        // compiler did not unroll: a 2D water run took 1.3x the instructions (callgrind).
        let (w, base, fx) = (&self.w, &self.base, &self.fx);
        let mut offset = [0usize; D];
        let mut node = |offset: &[usize; D]| {
            let mut weight = w[0][offset[0]];
            let mut index = base[0] + offset[0];
            for a in 1..D {
                weight *= w[a][offset[a]];
                index = index * nodes + base[a] + offset[a];
            }
            visit(
                index,
                weight,
                std::array::from_fn(|a| offset[a] as f64 - fx[a]),
            );
        };
        for i in 0..3 {
            offset[0] = i;
            for j in 0..3 {
                offset[1] = j;
                if D == 2 {
                    node(&offset);
                    continue;
                }
                for k in 0..3 {
                    offset[2] = k;
                    node(&offset);
                }
            }
        }
    }
}

impl<'a, const D: usize> Mpm<'a, D>
where
    Dim<D>: Space<D>,
{
    /// The initial state of checked inputs (mod.rs, check_inputs).
    pub(super) fn new(
        s: &'a Settings<D>,
        materials: &'a [Material],
        positions: &[f64],
        velocities: &[f64],
        material: &[u32],
        volume: f64,
    ) -> Self {
        let n = material.len();
        let nodes = s.grid + 1;
        let size = nodes.pow(D as u32);
        let dx = 1.0 / s.grid as f64;
        let point = |a: &[f64], i: usize| -> Vector<D> { std::array::from_fn(|k| a[D * i + k]) };
        let x: Vec<Vector<D>> = (0..n).map(|i| point(positions, i)).collect();
        let wave_speed = material
            .iter()
            .map(|&m| materials[m as usize].wave_speed())
            .fold(0.0, f64::max);
        let mut solid = vec![false; size];
        for i in 0..n {
            if matches!(materials[material[i] as usize].model, Model::Obstacle) {
                Stencil::new(&x[i], s.grid as f64).for_each(nodes, |node, _, _| solid[node] = true);
            }
        }
        let bodies = Body::all(materials, material, &x);
        let mut sim = Mpm {
            s,
            materials,
            lame: materials.iter().map(Material::lame).collect(),
            dx,
            nodes,
            v: (0..n).map(|i| point(velocities, i)).collect(),
            x,
            c: vec![[[0.0; D]; D]; n],
            f: vec![super::constitutive::identity(); n],
            j: material
                .iter()
                .map(|&m| match materials[m as usize].model {
                    Model::Water { .. } => 1.0,
                    _ => 0.0,
                })
                .collect(),
            material: material.to_vec(),
            volume,
            wave_speed,
            solid,
            grid: vec![Node::ZERO; size],
            parts: if n >= SPLIT_AT {
                vec![vec![Node::ZERO; size]; PARTS]
            } else {
                vec![]
            },
            bodies,
        };
        for body in &sim.bodies {
            body.start(&mut sim.v, &mut sim.c);
        }
        sim
    }

    pub(super) fn record(&self, out: &mut Vec<f32>) {
        for p in &self.x {
            out.extend(p.iter().map(|&c| c as f32));
        }
    }

    /// Advances one frame under `gravity` (held over the frame's substeps); returns the number
    /// of substeps it took.
    pub(super) fn advance_frame(&mut self, gravity: Vector<D>) -> Result<u32> {
        let mut t = 0.0;
        let mut substeps = 0u32;
        while t < self.s.frame_dt * (1.0 - 1e-12) {
            if substeps as usize >= self.s.max_substeps {
                return Err(Error::Value(format!(
                    "more than max_substeps = {} substeps needed (fastest particle {:.3e}); \
                     the run is unstable or needs a larger max_substeps",
                    self.s.max_substeps,
                    self.max_speed()
                )));
            }
            let bound = self.s.cfl * self.dx / (self.wave_speed + self.max_speed());
            let dt = bound.min(self.s.frame_dt - t);
            self.substep(dt, &gravity)?;
            t += dt;
            substeps += 1;
        }
        Ok(substeps)
    }

    fn max_speed(&self) -> f64 {
        self.v
            .par_iter()
            .map(|v| super::constitutive::sum::<D>(|a| v[a] * v[a]).sqrt())
            .reduce(|| 0.0, f64::max)
    }

    fn substep(&mut self, dt: f64, gravity: &Vector<D>) -> Result<()> {
        self.particles_to_grid(dt);
        self.update_grid(dt, gravity);
        self.grid_to_particles(dt)?;
        self.move_bodies(dt)
    }

    fn particles_to_grid(&mut self, dt: f64) {
        let inv_dx = 1.0 / self.dx;
        let nodes = self.nodes;
        let n = self.x.len();
        let mut grid = std::mem::take(&mut self.grid);
        let mut parts = std::mem::take(&mut self.parts);
        let this = &*self;
        let scatter = |range: std::ops::Range<usize>, grid: &mut [Node<D>]| {
            for p in range {
                let index = this.material[p] as usize;
                let m = &this.materials[index];
                if matches!(m.model, Model::Obstacle) {
                    continue;
                }
                let mass = m.density * this.volume;
                let tau = kirchhoff_stress(m, this.lame[index], &this.f[p], this.j[p]);
                // The stress impulse of MLS-MPM: -dt V 4/dx^2 tau, plus APIC's affine momentum.
                let k = -dt * this.volume * 4.0 * inv_dx * inv_dx;
                let c = &this.c[p];
                let affine: Matrix<D> = std::array::from_fn(|a| {
                    std::array::from_fn(|b| k * tau[a][b] + mass * c[a][b])
                });
                let v = this.v[p];
                Stencil::new(&this.x[p], inv_dx).for_each(nodes, |i, weight, offset| {
                    let d: Vector<D> = std::array::from_fn(|b| offset[b] * this.dx);
                    let node = &mut grid[i];
                    for a in 0..D {
                        let mut momentum = mass * v[a];
                        for b in 0..D {
                            momentum += affine[a][b] * d[b];
                        }
                        node.momentum[a] += weight * momentum;
                    }
                    node.mass += weight * mass;
                });
            }
        };
        grid.fill(Node::ZERO);
        if parts.is_empty() {
            scatter(0..n, &mut grid);
        } else {
            let size = n.div_ceil(PARTS);
            parts.par_iter_mut().enumerate().for_each(|(k, local)| {
                local.fill(Node::ZERO);
                scatter(k * size..((k + 1) * size).min(n), local);
            });
            grid.par_iter_mut().enumerate().for_each(|(i, node)| {
                for local in &parts {
                    for a in 0..D {
                        node.momentum[a] += local[i].momentum[a];
                    }
                    node.mass += local[i].mass;
                }
            });
        }
        self.parts = parts;
        self.grid = grid;
    }

    fn update_grid(&mut self, dt: f64, gravity: &Vector<D>) {
        let nodes = self.nodes;
        let dx = self.dx;
        let s = self.s;
        let solid = &self.solid;
        self.grid.par_iter_mut().enumerate().for_each(|(i, node)| {
            if node.mass <= 0.0 {
                return;
            }
            let mut v: Vector<D> =
                std::array::from_fn(|a| node.momentum[a] / node.mass + dt * gravity[a]);
            if solid[i] {
                v = [0.0; D];
            }
            let mut at = [0.0; D];
            let mut rest = i;
            for a in (0..D).rev() {
                at[a] = (rest % nodes) as f64 * dx;
                rest /= nodes;
            }
            for a in 0..D {
                let [lo, hi] = s.bounds[a];
                let into = (at[a] < lo && v[a] < 0.0) || (at[a] > hi && v[a] > 0.0);
                if at[a] < lo || at[a] > hi {
                    match s.wall {
                        Wall::Sticky => v = [0.0; D],
                        Wall::Slip if into => v[a] = 0.0,
                        Wall::Coulomb(mu) if into => coulomb(&mut v, a, mu),
                        _ => {}
                    }
                }
            }
            // The node now holds velocity.
            node.momentum = v;
        });
    }

    fn grid_to_particles(&mut self, dt: f64) -> Result<()> {
        let inv_dx = 1.0 / self.dx;
        let nodes = self.nodes;
        let dx = self.dx;
        let grid = &self.grid;
        let materials = self.materials;
        let lame = &self.lame;
        let material = &self.material;
        let failure = self
            .x
            .par_iter_mut()
            .zip(self.v.par_iter_mut())
            .zip(self.c.par_iter_mut())
            .zip(self.f.par_iter_mut())
            .zip(self.j.par_iter_mut())
            .enumerate()
            .map(|(p, ((((x, v), c), f), j))| {
                let m = &materials[material[p] as usize];
                if matches!(m.model, Model::Obstacle) {
                    return None;
                }
                let mut new_v = [0.0; D];
                let mut new_c = [[0.0; D]; D];
                Stencil::new(x, inv_dx).for_each(nodes, |i, weight, d| {
                    let node = &grid[i];
                    for a in 0..D {
                        new_v[a] += weight * node.momentum[a];
                        // C = 4/dx^2 sum w v (x_i - x_p)^T, with x_i - x_p = d dx.
                        for b in 0..D {
                            new_c[a][b] += 4.0 * inv_dx * weight * node.momentum[a] * d[b];
                        }
                    }
                });
                *v = new_v;
                *c = new_c;
                // A rigid body's particles move with the body (move_bodies), which also checks them.
                if matches!(m.model, Model::Rigid) {
                    return None;
                }
                for a in 0..D {
                    x[a] += dt * new_v[a];
                }
                let (lambda, mu) = lame[material[p] as usize];
                match m.model {
                    Model::Water { .. } => *j *= 1.0 + dt * trace(&new_c),
                    Model::Sand {
                        friction_angle_deg, ..
                    } => {
                        let trial = deform(f, &new_c, dt);
                        *f = project(&trial, |eps| {
                            let (eps, dilation) =
                                drucker_prager(eps, *j, lambda, mu, friction_angle_deg);
                            *j = dilation;
                            eps
                        });
                    }
                    Model::Goop { yield_stress, .. } => {
                        let trial = deform(f, &new_c, dt);
                        *f = project(&trial, |eps| von_mises(eps, mu, yield_stress));
                    }
                    Model::Obstacle | Model::Rigid => {}
                }
                let finite = x.iter().chain(v.iter()).all(|c| c.is_finite())
                    && f.iter().flatten().all(|c| c.is_finite())
                    && j.is_finite();
                check_particle(p, x, finite, dx)
            })
            .find_first(|e| e.is_some())
            .flatten();
        match failure {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// Projects every rigid body's particle velocities onto a rigid motion and moves the body.
    fn move_bodies(&mut self, dt: f64) -> Result<()> {
        for body in &mut self.bodies {
            body.advance(&mut self.x, &mut self.v, &mut self.c, dt, &self.s.bounds);
            for &p in body.particles() {
                let finite = self.x[p]
                    .iter()
                    .chain(self.v[p].iter())
                    .all(|c| c.is_finite());
                if let Some(e) = check_particle(p, &self.x[p], finite, self.dx) {
                    return Err(e);
                }
            }
        }
        Ok(())
    }
}

/// The error of a particle that became NaN or left the domain, if it did.
fn check_particle(p: usize, x: &[f64], finite: bool, dx: f64) -> Option<Error> {
    if !finite {
        return Some(Error::NonFinite(format!(
            "particle {p} became NaN or infinite"
        )));
    }
    if !inside_grid(x, dx) {
        return Some(Error::Value(format!(
            "particle {p} left the simulation domain (at {x:?}); the walls did not hold it"
        )));
    }
    None
}

/// A Coulomb wall normal to axis `a`: the normal velocity removed, the tangential velocity
/// (the other axes) keeps its direction and loses mu times the removed normal speed, down to
/// zero. The tangential speed is a scaled norm, exactly |v_b| when there is one tangential
/// axis (2D), so 2D keeps sign(v_b) max(|v_b| - mu |v_a|, 0) to the bit.
pub(super) fn coulomb<const D: usize>(v: &mut Vector<D>, a: usize, mu: f64) {
    let normal = v[a].abs();
    v[a] = 0.0;
    let scale = v.iter().fold(0.0, |m: f64, c| m.max(c.abs()));
    if !(scale > 0.0 && scale.is_finite()) {
        return; // no tangential motion (or a NaN, reported after grid to particles)
    }
    let tangential = scale
        * v.iter()
            .map(|c| (c / scale) * (c / scale))
            .sum::<f64>()
            .sqrt();
    let keep = (tangential - mu * normal).max(0.0);
    for b in 0..D {
        if b != a {
            v[b] = v[b] / tangential * keep;
        }
    }
}
