//! The reference simulator: 2D MLS-MPM (moving least squares material point method, Hu et al.
//! 2018) with APIC transfers and quadratic B-splines (docs/reference-simulator.md has its
//! validation against Taichi-Elements). It makes ground truth and is the solver the learned
//! model is timed against.
//!
//! One substep: particles to grid (mass, momentum and the stress impulse), grid update (gravity,
//! walls, obstacles), grid to particles (velocity, affine field C, deformation, plasticity).
//! Substeps per frame come from a CFL bound, recomputed every substep from the fastest particle.
//! Everything is f64; the P2G scatter is split into fixed chunks of particles whose grids are
//! summed in a fixed order, so results do not depend on the number of threads.

use crate::{check_positive, Error, Result};
use rayon::prelude::*;
use std::time::Instant;

type V2 = [f64; 2];
type M2 = [[f64; 2]; 2];

/// The P2G scatter of a run with at least SPLIT_AT particles is split into PARTS fixed ranges of
/// particles, each into its own grid, summed in order: fixed (not per thread) so the
/// summation order, and so the result, never depends on the thread count.
const PARTS: usize = 4;
const SPLIT_AT: usize = 1024;

/// The constitutive model of a material.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Model {
    /// Weakly compressible fluid: Kirchhoff pressure from the volume ratio J, bulk modulus K.
    Water { bulk_modulus: f64 },
    /// Drucker-Prager sand (Klar et al. 2016) on Hencky strain, zero cohesion.
    Sand {
        youngs_modulus: f64,
        poisson_ratio: f64,
        friction_angle_deg: f64,
    },
    /// Elastoplastic "goop": Hencky elasticity with a von Mises yield stress (Pa).
    Goop {
        youngs_modulus: f64,
        poisson_ratio: f64,
        yield_stress: f64,
    },
    /// Static obstacle particles: never move; the grid nodes they cover are sticky walls.
    Obstacle,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    pub density: f64,
    pub model: Model,
}

/// How grid nodes outside the box treat velocity into the wall.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Wall {
    /// Velocity zeroed.
    Sticky,
    /// The normal component into the wall removed, the tangential one kept.
    Slip,
    /// Slip with Coulomb friction: the tangential speed loses mu times the removed normal speed.
    Coulomb(f64),
}

#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// Grid cells per unit length on the [0, 1]^2 domain (dx = 1 / grid).
    pub grid: usize,
    /// The walls: [[x_lo, x_hi], [y_lo, y_hi]], inside the domain by at least 2 dx.
    pub bounds: [[f64; 2]; 2],
    pub wall: Wall,
    pub gravity: V2,
    /// Seconds between saved frames.
    pub frame_dt: f64,
    /// dt_sub <= cfl * dx / (c + |v|max), c the fastest wave speed among the materials.
    pub cfl: f64,
    /// A frame that needs more substeps is an error (the run is unstable or far too stiff).
    pub max_substeps: usize,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            grid: 64,
            bounds: [[0.1, 0.9], [0.1, 0.9]],
            wall: Wall::Coulomb(0.5),
            gravity: [0.0, -9.81],
            frame_dt: 0.0025,
            cfl: 0.4,
            max_substeps: 2000,
        }
    }
}

/// The frames of a run: positions (frames, N, 2) row-major f32 (frame 0 is the initial state),
/// wall-clock seconds and substeps per simulated frame (frames - 1 entries each).
#[derive(Debug, Clone)]
pub struct Output {
    pub positions: Vec<f32>,
    pub seconds: Vec<f64>,
    pub substeps: Vec<u32>,
}

impl Material {
    fn lame(&self) -> (f64, f64) {
        match self.model {
            Model::Sand {
                youngs_modulus: e,
                poisson_ratio: nu,
                ..
            }
            | Model::Goop {
                youngs_modulus: e,
                poisson_ratio: nu,
                ..
            } => (
                e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
                e / (2.0 * (1.0 + nu)),
            ),
            Model::Water { bulk_modulus } => (bulk_modulus, 0.0),
            Model::Obstacle => (0.0, 0.0),
        }
    }

    /// The P-wave speed sqrt((lambda + 2 mu) / rho), which bounds the substep.
    fn wave_speed(&self) -> f64 {
        let (lambda, mu) = self.lame();
        if matches!(self.model, Model::Obstacle) {
            0.0
        } else {
            ((lambda + 2.0 * mu) / self.density).sqrt()
        }
    }

    fn check(&self, index: usize) -> Result<()> {
        let name = |what: &str| format!("materials[{index}]: {what}");
        if !matches!(self.model, Model::Obstacle) {
            check_positive(&name("density"), self.density)?;
        }
        match self.model {
            Model::Water { bulk_modulus } => check_positive(&name("bulk_modulus"), bulk_modulus),
            Model::Sand {
                youngs_modulus: e,
                poisson_ratio: nu,
                friction_angle_deg: phi,
            } => {
                check_elastic(index, e, nu)?;
                if !(phi.is_finite() && phi > 0.0 && phi < 90.0) {
                    return Err(Error::Value(format!(
                        "materials[{index}]: friction_angle_deg must be in (0, 90), got {phi}"
                    )));
                }
                Ok(())
            }
            Model::Goop {
                youngs_modulus: e,
                poisson_ratio: nu,
                yield_stress,
            } => {
                check_elastic(index, e, nu)?;
                if !(yield_stress.is_finite() && yield_stress >= 0.0) {
                    return Err(Error::Value(format!(
                        "materials[{index}]: yield_stress must be a finite number >= 0, got \
                         {yield_stress}"
                    )));
                }
                Ok(())
            }
            _ => Ok(()),
        }
    }
}

fn check_elastic(index: usize, e: f64, nu: f64) -> Result<()> {
    check_positive(&format!("materials[{index}]: youngs_modulus"), e)?;
    if !(nu.is_finite() && (0.0..0.5).contains(&nu)) {
        return Err(Error::Value(format!(
            "materials[{index}]: poisson_ratio must be in [0, 0.5), got {nu}"
        )));
    }
    Ok(())
}

/// What a frame runs on: rayon's current pool (all its threads), or one thread.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Threads {
    All,
    One,
}

/// Runs `frames - 1` frames from the initial positions and velocities ((N, 2) row-major) of
/// particles of the given materials (an index into `materials` per particle), each of volume
/// `particle_volume` (the area it stands for: spacing^2 on a lattice). `after_frame` is called
/// after every frame with its index and its seconds, and says what the next frame runs on (the
/// first runs on all threads): a caller can time the frames and move to one thread when
/// another program holds a core and the pool's second thread stalls every parallel loop. The
/// results do not depend on it. An error from it stops the run. A particle that becomes NaN or
/// leaves the grid, or a frame that needs more than max_substeps, is an error naming the
/// frame: the run is rejected.
// The initial state is four parallel inputs; a struct for them would only be unpacked here.
#[allow(clippy::too_many_arguments)]
pub fn simulate(
    settings: &Settings,
    materials: &[Material],
    positions: &[f64],
    velocities: &[f64],
    material: &[u32],
    particle_volume: f64,
    frames: usize,
    mut after_frame: impl FnMut(usize, f64) -> Result<Threads>,
) -> Result<Output> {
    let n = material.len();
    if frames == 0 {
        return Err(Error::Value(
            "frames must be >= 1 (frame 0 is the initial state)".into(),
        ));
    }
    let mut sim = Mpm::new(
        settings,
        materials,
        positions,
        velocities,
        material,
        particle_volume,
    )?;
    let mut out = Output {
        positions: Vec::with_capacity(frames * n * 2),
        seconds: Vec::with_capacity(frames - 1),
        substeps: Vec::with_capacity(frames - 1),
    };
    sim.record(&mut out.positions);
    let mut threads = Threads::All;
    let mut one_thread: Option<rayon::ThreadPool> = None;
    for frame in 1..frames {
        let start = Instant::now();
        let advanced = match threads {
            Threads::All => sim.advance_frame(),
            Threads::One => {
                if one_thread.is_none() {
                    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build();
                    one_thread = Some(pool.map_err(|e| {
                        Error::Value(format!("cannot start a one-thread pool: {e}"))
                    })?);
                }
                let pool = one_thread.as_ref().expect("made above");
                pool.install(|| sim.advance_frame())
            }
        };
        let substeps = advanced.map_err(|e| match e {
            Error::Value(m) => Error::Value(format!("frame {frame}: {m}")),
            Error::NonFinite(m) => Error::NonFinite(format!("frame {frame}: {m}")),
            other => other,
        })?;
        let seconds = start.elapsed().as_secs_f64();
        out.seconds.push(seconds);
        out.substeps.push(substeps);
        sim.record(&mut out.positions);
        threads = after_frame(frame, seconds)?;
    }
    Ok(out)
}

fn check_inputs(
    s: &Settings,
    materials: &[Material],
    positions: &[f64],
    velocities: &[f64],
    material: &[u32],
    particle_volume: f64,
) -> Result<()> {
    let n = material.len();
    if positions.len() != 2 * n || velocities.len() != 2 * n {
        return Err(Error::Shape(format!(
            "positions and velocities must be (N, 2) with N = {n} (the length of material), got \
             {} and {} values",
            positions.len(),
            velocities.len()
        )));
    }
    for (i, m) in materials.iter().enumerate() {
        m.check(i)?;
    }
    if let Some(k) = material.iter().position(|&m| m as usize >= materials.len()) {
        return Err(Error::Value(format!(
            "material[{k}] = {} but there are {} materials",
            material[k],
            materials.len()
        )));
    }
    check_positive("particle_volume", particle_volume)?;
    if s.grid < 8 {
        return Err(Error::Value(format!(
            "grid must be >= 8 cells, got {}",
            s.grid
        )));
    }
    let dx = 1.0 / s.grid as f64;
    for (a, [lo, hi]) in s.bounds.iter().enumerate() {
        if !(lo.is_finite()
            && hi.is_finite()
            && 2.0 * dx <= *lo
            && lo < hi
            && *hi <= 1.0 - 2.0 * dx)
        {
            return Err(Error::Value(format!(
                "bounds[{a}] = [{lo}, {hi}] must satisfy 2 dx <= lo < hi <= 1 - 2 dx with dx = {dx}"
            )));
        }
    }
    check_positive("frame_dt", s.frame_dt)?;
    check_positive("cfl", s.cfl)?;
    if s.cfl > 1.0 {
        return Err(Error::Value(format!("cfl must be <= 1, got {}", s.cfl)));
    }
    if s.max_substeps == 0 {
        return Err(Error::Value("max_substeps must be >= 1".into()));
    }
    if !s.gravity.iter().all(|g| g.is_finite()) {
        return Err(Error::NonFinite(format!(
            "gravity must be finite, got {:?}",
            s.gravity
        )));
    }
    if let Wall::Coulomb(mu) = s.wall {
        if !(mu.is_finite() && mu >= 0.0) {
            return Err(Error::Value(format!(
                "wall friction must be finite and >= 0, got {mu}"
            )));
        }
    }
    for (name, a) in [("positions", positions), ("velocities", velocities)] {
        if let Some(k) = a.iter().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite(format!(
                "{name}[{}, {}] = {} is not finite",
                k / 2,
                k % 2,
                a[k]
            )));
        }
    }
    for i in 0..n {
        let p = [positions[2 * i], positions[2 * i + 1]];
        if !inside_grid(p, dx) {
            return Err(Error::Value(format!(
                "particle {i} at {p:?} is outside the simulation domain [{}, {}]^2",
                1.5 * dx,
                1.0 - 1.5 * dx
            )));
        }
    }
    Ok(())
}

/// Whether the 3x3 stencil of a particle at p lies on the grid's nodes 0..=grid.
fn inside_grid(p: V2, dx: f64) -> bool {
    p.iter().all(|&c| c >= 1.5 * dx && c <= 1.0 - 1.5 * dx)
}

struct Mpm<'a> {
    s: &'a Settings,
    materials: &'a [Material],
    lame: Vec<(f64, f64)>,
    dx: f64,
    nodes: usize,
    x: Vec<V2>,
    v: Vec<V2>,
    c: Vec<M2>,
    f: Vec<M2>,
    /// Water: the volume ratio J (F is not kept for a fluid). Sand: the log of the volume
    /// gained by separating (Tampubolon et al. 2017), which must be recompressed before the
    /// grains carry stress again, as Taichi-Elements does.
    j: Vec<f64>,
    material: Vec<u32>,
    volume: f64,
    wave_speed: f64,
    /// Grid nodes covered by obstacle particles (sticky), fixed for the run.
    solid: Vec<bool>,
    /// (momentum x, momentum y, mass) per node.
    grid: Vec<[f64; 3]>,
    /// The PARTS grids of a split scatter (empty below SPLIT_AT particles), kept between substeps.
    parts: Vec<Vec<[f64; 3]>>,
}

/// Quadratic B-spline weights and the base node of a particle at p.
#[inline]
fn stencil(p: V2, inv_dx: f64) -> ([usize; 2], V2, [[f64; 3]; 2]) {
    let mut base = [0usize; 2];
    let mut fx = [0.0; 2];
    let mut w = [[0.0; 3]; 2];
    for a in 0..2 {
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
    (base, fx, w)
}

impl<'a> Mpm<'a> {
    fn new(
        s: &'a Settings,
        materials: &'a [Material],
        positions: &[f64],
        velocities: &[f64],
        material: &[u32],
        volume: f64,
    ) -> Result<Self> {
        check_inputs(s, materials, positions, velocities, material, volume)?;
        let n = material.len();
        let nodes = s.grid + 1;
        let dx = 1.0 / s.grid as f64;
        let pair = |a: &[f64], i: usize| [a[2 * i], a[2 * i + 1]];
        let wave_speed = material
            .iter()
            .map(|&m| materials[m as usize].wave_speed())
            .fold(0.0, f64::max);
        let mut solid = vec![false; nodes * nodes];
        for i in 0..n {
            if matches!(materials[material[i] as usize].model, Model::Obstacle) {
                let (base, _, _) = stencil(pair(positions, i), s.grid as f64);
                for di in 0..3 {
                    for dj in 0..3 {
                        solid[(base[0] + di) * nodes + base[1] + dj] = true;
                    }
                }
            }
        }
        Ok(Mpm {
            s,
            materials,
            lame: materials.iter().map(Material::lame).collect(),
            dx,
            nodes,
            x: (0..n).map(|i| pair(positions, i)).collect(),
            v: (0..n).map(|i| pair(velocities, i)).collect(),
            c: vec![[[0.0; 2]; 2]; n],
            f: vec![[[1.0, 0.0], [0.0, 1.0]]; n],
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
            grid: vec![[0.0; 3]; nodes * nodes],
            parts: if n >= SPLIT_AT {
                vec![vec![[0.0; 3]; nodes * nodes]; PARTS]
            } else {
                vec![]
            },
        })
    }

    fn record(&self, out: &mut Vec<f32>) {
        for p in &self.x {
            out.push(p[0] as f32);
            out.push(p[1] as f32);
        }
    }

    /// Advances one frame; returns the number of substeps it took.
    fn advance_frame(&mut self) -> Result<u32> {
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
            self.substep(dt)?;
            t += dt;
            substeps += 1;
        }
        Ok(substeps)
    }

    fn max_speed(&self) -> f64 {
        self.v
            .par_iter()
            .map(|v| (v[0] * v[0] + v[1] * v[1]).sqrt())
            .reduce(|| 0.0, f64::max)
    }

    fn substep(&mut self, dt: f64) -> Result<()> {
        self.particles_to_grid(dt);
        self.update_grid(dt);
        self.grid_to_particles(dt)
    }

    fn particles_to_grid(&mut self, dt: f64) {
        let inv_dx = 1.0 / self.dx;
        let nodes = self.nodes;
        let n = self.x.len();
        let mut grid = std::mem::take(&mut self.grid);
        let mut parts = std::mem::take(&mut self.parts);
        let this = &*self;
        let scatter = |range: std::ops::Range<usize>, grid: &mut [[f64; 3]]| {
            for p in range {
                let m = &this.materials[this.material[p] as usize];
                if matches!(m.model, Model::Obstacle) {
                    continue;
                }
                let mass = m.density * this.volume;
                let tau = this.kirchhoff_stress(p);
                // The stress impulse of MLS-MPM: -dt V 4/dx^2 tau, plus APIC's affine momentum.
                let k = -dt * this.volume * 4.0 * inv_dx * inv_dx;
                let c = &this.c[p];
                let affine = [
                    [
                        k * tau[0][0] + mass * c[0][0],
                        k * tau[0][1] + mass * c[0][1],
                    ],
                    [
                        k * tau[1][0] + mass * c[1][0],
                        k * tau[1][1] + mass * c[1][1],
                    ],
                ];
                let (base, fx, w) = stencil(this.x[p], inv_dx);
                let v = this.v[p];
                for di in 0..3 {
                    for dj in 0..3 {
                        let weight = w[0][di] * w[1][dj];
                        let d = [(di as f64 - fx[0]) * this.dx, (dj as f64 - fx[1]) * this.dx];
                        let node = &mut grid[(base[0] + di) * nodes + base[1] + dj];
                        node[0] +=
                            weight * (mass * v[0] + affine[0][0] * d[0] + affine[0][1] * d[1]);
                        node[1] +=
                            weight * (mass * v[1] + affine[1][0] * d[0] + affine[1][1] * d[1]);
                        node[2] += weight * mass;
                    }
                }
            }
        };
        grid.fill([0.0; 3]);
        if parts.is_empty() {
            scatter(0..n, &mut grid);
        } else {
            let size = n.div_ceil(PARTS);
            parts.par_iter_mut().enumerate().for_each(|(k, local)| {
                local.fill([0.0; 3]);
                scatter(k * size..((k + 1) * size).min(n), local);
            });
            grid.par_iter_mut().enumerate().for_each(|(i, node)| {
                for local in &parts {
                    for a in 0..3 {
                        node[a] += local[i][a];
                    }
                }
            });
        }
        self.parts = parts;
        self.grid = grid;
    }

    /// tau = P F^T of the particle's material (Kirchhoff stress).
    fn kirchhoff_stress(&self, p: usize) -> M2 {
        let (lambda, mu) = self.lame[self.material[p] as usize];
        match self.materials[self.material[p] as usize].model {
            Model::Water { .. } => {
                let j = self.j[p];
                let pressure = lambda * j * (j - 1.0);
                [[pressure, 0.0], [0.0, pressure]]
            }
            Model::Sand { .. } | Model::Goop { .. } => {
                // Hencky: tau = U (2 mu eps + lambda tr(eps) I) U^T with eps = log(sigma).
                let (u, sigma, _) = svd(self.f[p]);
                let eps = [sigma[0].ln(), sigma[1].ln()];
                let tr = eps[0] + eps[1];
                let d = [
                    2.0 * mu * eps[0] + lambda * tr,
                    2.0 * mu * eps[1] + lambda * tr,
                ];
                rotate_diagonal(u, d)
            }
            Model::Obstacle => [[0.0; 2]; 2],
        }
    }

    fn update_grid(&mut self, dt: f64) {
        let nodes = self.nodes;
        let dx = self.dx;
        let s = self.s;
        let solid = &self.solid;
        self.grid.par_iter_mut().enumerate().for_each(|(i, node)| {
            if node[2] <= 0.0 {
                return;
            }
            let mut v = [
                node[0] / node[2] + dt * s.gravity[0],
                node[1] / node[2] + dt * s.gravity[1],
            ];
            if solid[i] {
                v = [0.0, 0.0];
            }
            let at = [(i / nodes) as f64 * dx, (i % nodes) as f64 * dx];
            for a in 0..2 {
                let [lo, hi] = s.bounds[a];
                let into = (at[a] < lo && v[a] < 0.0) || (at[a] > hi && v[a] > 0.0);
                if at[a] < lo || at[a] > hi {
                    match s.wall {
                        Wall::Sticky => v = [0.0, 0.0],
                        Wall::Slip if into => v[a] = 0.0,
                        Wall::Coulomb(mu) if into => {
                            let normal = v[a].abs();
                            let b = 1 - a;
                            let tangential = v[b].abs();
                            v[a] = 0.0;
                            v[b] = v[b].signum() * (tangential - mu * normal).max(0.0);
                        }
                        _ => {}
                    }
                }
            }
            // The node now holds velocity (mass kept for the weights' normalisation).
            node[0] = v[0];
            node[1] = v[1];
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
                let (base, fx, w) = stencil(*x, inv_dx);
                let mut new_v = [0.0; 2];
                let mut new_c = [[0.0; 2]; 2];
                for di in 0..3 {
                    for dj in 0..3 {
                        let weight = w[0][di] * w[1][dj];
                        let d = [di as f64 - fx[0], dj as f64 - fx[1]];
                        let node = &grid[(base[0] + di) * nodes + base[1] + dj];
                        for a in 0..2 {
                            new_v[a] += weight * node[a];
                            // C = 4/dx^2 sum w v (x_i - x_p)^T, with x_i - x_p = d dx.
                            for b in 0..2 {
                                new_c[a][b] += 4.0 * inv_dx * weight * node[a] * d[b];
                            }
                        }
                    }
                }
                *v = new_v;
                *c = new_c;
                x[0] += dt * new_v[0];
                x[1] += dt * new_v[1];
                let (lambda, mu) = lame[material[p] as usize];
                match m.model {
                    Model::Water { .. } => *j *= 1.0 + dt * (new_c[0][0] + new_c[1][1]),
                    Model::Sand {
                        friction_angle_deg, ..
                    } => {
                        let trial = deform(*f, new_c, dt);
                        *f = project(trial, |eps| {
                            let (eps, dilation) =
                                drucker_prager(eps, *j, lambda, mu, friction_angle_deg);
                            *j = dilation;
                            eps
                        });
                    }
                    Model::Goop { yield_stress, .. } => {
                        let trial = deform(*f, new_c, dt);
                        *f = project(trial, |eps| von_mises(eps, mu, yield_stress));
                    }
                    Model::Obstacle => {}
                }
                let finite = x.iter().chain(v.iter()).all(|c| c.is_finite())
                    && f.iter().flatten().all(|c| c.is_finite())
                    && j.is_finite();
                if !finite {
                    return Some(Error::NonFinite(format!(
                        "particle {p} became NaN or infinite"
                    )));
                }
                if !inside_grid(*x, dx) {
                    return Some(Error::Value(format!(
                        "particle {p} left the simulation domain (at {:?}); the walls did not \
                         hold it",
                        *x
                    )));
                }
                None
            })
            .find_first(|e| e.is_some())
            .flatten();
        match failure {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }
}

/// F' = (I + dt C) F.
fn deform(f: M2, c: M2, dt: f64) -> M2 {
    let a = [
        [1.0 + dt * c[0][0], dt * c[0][1]],
        [dt * c[1][0], 1.0 + dt * c[1][1]],
    ];
    mul(a, f)
}

/// Applies a return mapping on the Hencky strain (log of the singular values) of F.
fn project(f: M2, mut map: impl FnMut([f64; 2]) -> [f64; 2]) -> M2 {
    let (u, sigma, v) = svd(f);
    let eps = map([sigma[0].max(1e-12).ln(), sigma[1].max(1e-12).ln()]);
    let d = [eps[0].exp(), eps[1].exp()];
    // U diag(d) V^T
    mul(
        [
            [u[0][0] * d[0], u[0][1] * d[1]],
            [u[1][0] * d[0], u[1][1] * d[1]],
        ],
        transpose(v),
    )
}

/// Klar et al. (2016), cohesionless, with the volume correction of Tampubolon et al. (2017):
/// `dilation` (log volume gained by separating) adds to the volumetric strain. Expansion goes
/// to the cone's tip (stress-free) and is remembered; in compression the deviatoric strain
/// beyond the friction cone is removed. Returns (new strain, new dilation).
fn drucker_prager(
    eps: [f64; 2],
    dilation: f64,
    lambda: f64,
    mu: f64,
    friction_angle_deg: f64,
) -> ([f64; 2], f64) {
    let tr = eps[0] + eps[1] + dilation;
    if tr >= 0.0 {
        return ([0.0, 0.0], tr);
    }
    let dev = [eps[0] - 0.5 * tr, eps[1] - 0.5 * tr];
    let norm = (dev[0] * dev[0] + dev[1] * dev[1]).sqrt();
    let sin = friction_angle_deg.to_radians().sin();
    let alpha = (2.0f64 / 3.0).sqrt() * 2.0 * sin / (3.0 - sin);
    // d = 2 in the plastic multiplier (d lambda + 2 mu) / (2 mu).
    let gamma = norm + (2.0 * lambda + 2.0 * mu) / (2.0 * mu) * tr * alpha;
    if gamma <= 0.0 || norm == 0.0 {
        return (eps, 0.0);
    }
    (
        [
            eps[0] - gamma * dev[0] / norm,
            eps[1] - gamma * dev[1] / norm,
        ],
        0.0,
    )
}

/// von Mises: the deviatoric strain is capped at yield_stress / (2 mu).
fn von_mises(eps: [f64; 2], mu: f64, yield_stress: f64) -> [f64; 2] {
    let mean = 0.5 * (eps[0] + eps[1]);
    let dev = [eps[0] - mean, eps[1] - mean];
    let norm = (dev[0] * dev[0] + dev[1] * dev[1]).sqrt();
    let limit = yield_stress / (2.0 * mu);
    if norm <= limit {
        return eps;
    }
    let scale = limit / norm;
    [mean + scale * dev[0], mean + scale * dev[1]]
}

fn mul(a: M2, b: M2) -> M2 {
    let mut out = [[0.0; 2]; 2];
    for i in 0..2 {
        for j in 0..2 {
            out[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j];
        }
    }
    out
}

fn transpose(a: M2) -> M2 {
    [[a[0][0], a[1][0]], [a[0][1], a[1][1]]]
}

/// U diag(d) U^T.
fn rotate_diagonal(u: M2, d: [f64; 2]) -> M2 {
    let mut out = [[0.0; 2]; 2];
    for i in 0..2 {
        for j in 0..2 {
            out[i][j] = u[i][0] * d[0] * u[j][0] + u[i][1] * d[1] * u[j][1];
        }
    }
    out
}

/// F = U diag(sigma) V^T in closed form via the polar decomposition F = R S: R is the rotation
/// of F, S = R^T F is symmetric and its eigen-decomposition gives V and sigma; U = R V. U and V
/// are rotations; sigma[1] is negative when F is inverted (det F < 0).
pub fn svd(f: M2) -> (M2, [f64; 2], M2) {
    let theta = (f[1][0] - f[0][1]).atan2(f[0][0] + f[1][1]);
    let (s, c) = theta.sin_cos();
    let r = [[c, -s], [s, c]];
    let sym = mul(transpose(r), f);
    let (a, b, d) = (sym[0][0], 0.5 * (sym[0][1] + sym[1][0]), sym[1][1]);
    let phi = 0.5 * (2.0 * b).atan2(a - d);
    let (sp, cp) = phi.sin_cos();
    let v = [[cp, -sp], [sp, cp]];
    let mean = 0.5 * (a + d);
    let radius = (0.25 * (a - d) * (a - d) + b * b).sqrt();
    let sigma = [mean + radius, mean - radius];
    (mul(r, v), sigma, v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: M2, b: M2, tol: f64) -> bool {
        a.iter()
            .flatten()
            .zip(b.iter().flatten())
            .all(|(x, y)| (x - y).abs() < tol)
    }

    #[test]
    fn svd_reconstructs_and_is_orthogonal() {
        let cases = [
            [[1.0, 0.0], [0.0, 1.0]],
            [[1.2, 0.3], [-0.1, 0.8]],
            [[0.5, -2.0], [1.5, 0.7]],
            [[0.9, 0.9], [0.9, 0.9 + 1e-9]],
            [[2.0, 0.0], [0.0, 0.5]],
        ];
        for f in cases {
            let (u, sigma, v) = svd(f);
            let back = mul(
                [
                    [u[0][0] * sigma[0], u[0][1] * sigma[1]],
                    [u[1][0] * sigma[0], u[1][1] * sigma[1]],
                ],
                transpose(v),
            );
            assert!(close(back, f, 1e-12), "{f:?} -> {back:?}");
            assert!(close(mul(u, transpose(u)), [[1.0, 0.0], [0.0, 1.0]], 1e-12));
            assert!(sigma[0] >= sigma[1].abs() - 1e-12);
        }
    }

    #[test]
    fn return_mappings_respect_their_yield_surfaces() {
        // Expansion goes to the tip; a compressive state inside the cone is untouched.
        assert_eq!(
            drucker_prager([0.01, 0.0], 0.0, 1.0, 1.0, 30.0),
            ([0.0, 0.0], 0.01)
        );
        let inside = [-0.01, -0.0101];
        assert_eq!(drucker_prager(inside, 0.0, 1.0, 1.0, 30.0), (inside, 0.0));
        // Remembered dilation must be recompressed first: stress-free until then.
        assert_eq!(
            drucker_prager(inside, 0.03, 1.0, 1.0, 30.0).1,
            0.03 - 0.0201
        );
        // Outside: projected onto the cone, volume strain unchanged.
        let (out, _) = drucker_prager([-0.001, -0.05], 0.0, 1.0, 1.0, 30.0);
        assert!((out[0] + out[1] - (-0.051)).abs() < 1e-12);
        let dev = 0.5 * (out[0] - out[1]).abs() * 2f64.sqrt();
        let sin = 30f64.to_radians().sin();
        let alpha = (2.0f64 / 3.0).sqrt() * 2.0 * sin / (3.0 - sin);
        assert!((dev - 2.0 * -(out[0] + out[1]) * alpha).abs() < 1e-12);
        // von Mises caps the deviator at yield / (2 mu) and keeps the mean.
        let vm = von_mises([0.1, -0.1], 10.0, 1.0);
        let norm = ((vm[0] - 0.0).powi(2) + (vm[1] - 0.0).powi(2)).sqrt();
        assert!((norm - 0.05).abs() < 1e-12 && (vm[0] + vm[1]).abs() < 1e-15);
    }

    fn block(lo: V2, size: V2, spacing: f64) -> Vec<f64> {
        let mut out = vec![];
        let nx = (size[0] / spacing).round() as usize;
        let ny = (size[1] / spacing).round() as usize;
        for i in 0..nx {
            for j in 0..ny {
                out.push(lo[0] + (i as f64 + 0.5) * spacing);
                out.push(lo[1] + (j as f64 + 0.5) * spacing);
            }
        }
        out
    }

    #[test]
    fn free_fall_drops_by_g_dt_squared_per_frame_squared() {
        let s = Settings::default();
        let water = [Material {
            density: 1000.0,
            model: Model::Water { bulk_modulus: 1e5 },
        }];
        let x = block([0.4, 0.6], [0.1, 0.1], 0.01);
        let n = x.len() / 2;
        let out = simulate(
            &s,
            &water,
            &x,
            &vec![0.0; 2 * n],
            &vec![0; n],
            1e-4,
            11,
            |_, _| Ok(Threads::All),
        )
        .unwrap();
        let mean_y = |f: usize| {
            (0..n)
                .map(|i| out.positions[(f * n + i) * 2 + 1] as f64)
                .sum::<f64>()
                / n as f64
        };
        let g = -9.81 * s.frame_dt * s.frame_dt;
        for f in 2..11 {
            let acc = mean_y(f) - 2.0 * mean_y(f - 1) + mean_y(f - 2);
            assert!((acc - g).abs() < 1e-3 * g.abs(), "frame {f}: {acc} vs {g}");
        }
    }

    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        let s = Settings::default();
        let sand = [Material {
            density: 1800.0,
            model: Model::Sand {
                youngs_modulus: 2e6,
                poisson_ratio: 0.3,
                friction_angle_deg: 30.0,
            },
        }];
        let x = block([0.3, 0.1], [0.25, 0.2], 0.006);
        let n = x.len() / 2;
        assert!(n > SPLIT_AT);
        // Frames on every thread of a pool of `threads`, or alternating with one thread.
        let run = |threads: usize, alternate: bool| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                simulate(
                    &s,
                    &sand,
                    &x,
                    &vec![0.0; 2 * n],
                    &vec![0; n],
                    6.4e-5,
                    6,
                    |frame, _| match alternate && frame % 2 == 1 {
                        true => Ok(Threads::One),
                        false => Ok(Threads::All),
                    },
                )
                .unwrap()
                .positions
            })
        };
        let one = run(1, false);
        assert_eq!(one, run(2, false));
        assert_eq!(one, run(2, true));
    }

    #[test]
    fn bad_input_and_divergence_are_errors() {
        let s = Settings::default();
        let water = [Material {
            density: 1000.0,
            model: Model::Water { bulk_modulus: 1e5 },
        }];
        let x = vec![0.5, 0.5];
        let err = simulate(&s, &water, &x, &[0.0, 0.0], &[1], 1e-4, 2, |_, _| {
            Ok(Threads::All)
        })
        .unwrap_err();
        assert!(err.to_string().contains("material[0] = 1"), "{err}");
        let err = simulate(
            &s,
            &water,
            &[0.0, 0.5],
            &[0.0, 0.0],
            &[0],
            1e-4,
            2,
            |_, _| Ok(Threads::All),
        )
        .unwrap_err();
        assert!(
            err.to_string().contains("outside the simulation domain"),
            "{err}"
        );
        let tight = Settings {
            max_substeps: 2,
            ..Settings::default()
        };
        let err = simulate(&tight, &water, &x, &[0.0, 0.0], &[0], 1e-4, 2, |_, _| {
            Ok(Threads::All)
        })
        .unwrap_err();
        assert!(
            err.to_string()
                .contains("frame 1: more than max_substeps = 2"),
            "{err}"
        );
    }
}
