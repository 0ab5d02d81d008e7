//! The reference simulator: MLS-MPM (moving least squares material point method, Hu et al.
//! 2018) with APIC transfers and quadratic B-splines, in 2D and 3D (docs/reference-simulator.md
//! has its validation against Taichi-Elements). It makes ground truth and is the solver the
//! learned model is timed against.
//!
//! One substep: particles to grid (mass, momentum and the stress impulse), grid update (gravity,
//! walls, obstacles), grid to particles (velocity, affine field C, deformation, plasticity), then
//! the rigid bodies' particles are projected onto rigid motions. Substeps per frame come from a
//! CFL bound, recomputed every substep from the fastest particle. Everything is f64; the P2G
//! scatter is split into fixed chunks of particles whose grids are summed in a fixed order, so
//! results do not depend on the number of threads.
//!
//! The code is written once for D = 2 and D = 3 (`const D: usize`); what differs between the
//! two (the SVD, the inertia tensor) is the [`Space`] trait of `space.rs`.
//! - `solver.rs`: the grid, the transfers and the substep loop
//! - `constitutive.rs`: Kirchhoff stress and the return mappings (Hencky strain)
//! - `rigid.rs`: rigid bodies (particles projected onto a rigid motion after every substep)
//! - `space.rs`: the dimension-specific pieces

mod constitutive;
mod rigid;
mod solver;
mod space;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests3d;

use crate::{check_positive, Error, Result};
use solver::Mpm;
use std::time::Instant;

pub use space::{Dim, Space};

/// A point or velocity.
pub type Vector<const D: usize> = [f64; D];
/// A D x D matrix, row-major: `m[row][column]`.
pub type Matrix<const D: usize> = [[f64; D]; D];

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
    /// A rigid body: all particles of this material (one entry of `materials`) form one body.
    /// They scatter mass and momentum like any material (no stress); after grid to particles
    /// their velocities are projected onto the body's rigid motion, and their positions are
    /// rebuilt from the body's centre and rotation, so the body keeps its shape.
    Rigid,
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
    /// Slip with Coulomb friction: the tangential velocity keeps its direction and its speed
    /// loses mu times the removed normal speed (down to zero).
    Coulomb(f64),
}

/// The run's settings in D dimensions (`Settings` alone is 2D).
#[derive(Debug, Clone, PartialEq)]
pub struct Settings<const D: usize = 2> {
    /// Grid cells per unit length on the [0, 1]^D domain (dx = 1 / grid).
    pub grid: usize,
    /// The walls: [[x_lo, x_hi], [y_lo, y_hi], ...], inside the domain by at least 2 dx.
    pub bounds: [[f64; 2]; D],
    pub wall: Wall,
    pub gravity: Vector<D>,
    /// Gravity per frame, replacing `gravity`: row k is used for every substep of frame
    /// k -> k + 1, so `simulate` wants frames - 1 rows. A container shaken with acceleration
    /// a_c(t) is simulated in its own frame, where its walls are at rest and the fictitious
    /// force adds -a_c(t) to gravity. None: `gravity` for every frame.
    pub frame_gravity: Option<Vec<Vector<D>>>,
    /// Seconds between saved frames.
    pub frame_dt: f64,
    /// dt_sub <= cfl * dx / (c + |v|max), c the fastest wave speed among the materials.
    pub cfl: f64,
    /// A frame that needs more substeps is an error (the run is unstable or far too stiff).
    pub max_substeps: usize,
}

impl<const D: usize> Default for Settings<D>
where
    Dim<D>: Space<D>,
{
    /// Grid 64, walls at [0.1, 0.9] on every axis, Coulomb walls (mu 0.5), gravity -9.81 along
    /// y (axis 1, up in the DeepMind datasets), frames of 2.5 ms.
    fn default() -> Self {
        let mut gravity = [0.0; D];
        gravity[1] = -9.81;
        Settings {
            grid: 64,
            bounds: [[0.1, 0.9]; D],
            wall: Wall::Coulomb(0.5),
            gravity,
            frame_gravity: None,
            frame_dt: 0.0025,
            cfl: 0.4,
            max_substeps: 2000,
        }
    }
}

impl<const D: usize> Settings<D> {
    /// The gravity of frame k -> k + 1.
    fn gravity_of(&self, k: usize) -> Vector<D> {
        self.frame_gravity
            .as_ref()
            .map_or(self.gravity, |rows| rows[k])
    }
}

/// The frames of a run: positions (frames, N, D) row-major f32 (frame 0 is the initial state),
/// wall-clock seconds and substeps per simulated frame (frames - 1 entries each).
#[derive(Debug, Clone)]
pub struct Output {
    pub positions: Vec<f32>,
    pub seconds: Vec<f64>,
    pub substeps: Vec<u32>,
}

impl Material {
    /// (lambda, mu); for water (K, 0).
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
            Model::Obstacle | Model::Rigid => (0.0, 0.0),
        }
    }

    /// The P-wave speed sqrt((lambda + 2 mu) / rho), which bounds the substep.
    fn wave_speed(&self) -> f64 {
        let (lambda, mu) = self.lame();
        if matches!(self.model, Model::Obstacle | Model::Rigid) {
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

/// Runs `frames - 1` frames from the initial positions and velocities ((N, D) row-major) of
/// particles of the given materials (an index into `materials` per particle), each of volume
/// `particle_volume` (spacing^D on a lattice). `after_frame` is called after every frame with
/// its index and its seconds, and says what the next frame runs on (the first runs on all
/// threads): a caller can time the frames and move to one thread when another program holds a
/// core and the pool's second thread stalls every parallel loop. The results do not depend on
/// it. An error from it stops the run. A particle that becomes NaN or leaves the grid, or a
/// frame that needs more than max_substeps, is an error naming the frame: the run is rejected.
// The initial state is four parallel inputs; a struct for them would only be unpacked here.
#[allow(clippy::too_many_arguments)]
pub fn simulate<const D: usize>(
    settings: &Settings<D>,
    materials: &[Material],
    positions: &[f64],
    velocities: &[f64],
    material: &[u32],
    particle_volume: f64,
    frames: usize,
    mut after_frame: impl FnMut(usize, f64) -> Result<Threads>,
) -> Result<Output>
where
    Dim<D>: Space<D>,
{
    let n = material.len();
    if frames == 0 {
        return Err(Error::Value(
            "frames must be >= 1 (frame 0 is the initial state)".into(),
        ));
    }
    check_inputs(
        settings,
        materials,
        positions,
        velocities,
        material,
        particle_volume,
    )?;
    check_frame_gravity(settings, frames)?;
    let mut sim = Mpm::new(
        settings,
        materials,
        positions,
        velocities,
        material,
        particle_volume,
    );
    let mut out = Output {
        positions: Vec::with_capacity(frames * n * D),
        seconds: Vec::with_capacity(frames - 1),
        substeps: Vec::with_capacity(frames - 1),
    };
    sim.record(&mut out.positions);
    let mut threads = Threads::All;
    let mut one_thread: Option<rayon::ThreadPool> = None;
    for frame in 1..frames {
        let start = Instant::now();
        let gravity = settings.gravity_of(frame - 1);
        let advanced = match threads {
            Threads::All => sim.advance_frame(gravity),
            Threads::One => {
                if one_thread.is_none() {
                    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build();
                    one_thread = Some(pool.map_err(|e| {
                        Error::Value(format!("cannot start a one-thread pool: {e}"))
                    })?);
                }
                let pool = one_thread.as_ref().expect("made above");
                pool.install(|| sim.advance_frame(gravity))
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

fn check_inputs<const D: usize>(
    s: &Settings<D>,
    materials: &[Material],
    positions: &[f64],
    velocities: &[f64],
    material: &[u32],
    particle_volume: f64,
) -> Result<()> {
    let n = material.len();
    if positions.len() != D * n || velocities.len() != D * n {
        return Err(Error::Shape(format!(
            "positions and velocities must be (N, {D}) with N = {n} (the length of material), \
             got {} and {} values",
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
                k / D,
                k % D,
                a[k]
            )));
        }
    }
    for (i, p) in positions.chunks_exact(D).enumerate() {
        if !inside_grid(p, dx) {
            return Err(Error::Value(format!(
                "particle {i} at {p:?} is outside the simulation domain [{}, {}]^{D}",
                1.5 * dx,
                1.0 - 1.5 * dx
            )));
        }
    }
    Ok(())
}

/// frame_gravity, when given: one finite row per simulated frame.
fn check_frame_gravity<const D: usize>(s: &Settings<D>, frames: usize) -> Result<()> {
    let Some(rows) = &s.frame_gravity else {
        return Ok(());
    };
    if rows.len() != frames - 1 {
        return Err(Error::Shape(format!(
            "frame_gravity must have frames - 1 = {} rows (row k the gravity of frame k -> k + \
             1), got {}",
            frames - 1,
            rows.len()
        )));
    }
    for (k, row) in rows.iter().enumerate() {
        if let Some(a) = row.iter().position(|g| !g.is_finite()) {
            return Err(Error::NonFinite(format!(
                "frame_gravity[{k}, {a}] = {} is not finite (row {k}: {row:?})",
                row[a]
            )));
        }
    }
    Ok(())
}

/// Whether the 3^D stencil of a particle at p lies on the grid's nodes 0..=grid.
fn inside_grid(p: &[f64], dx: f64) -> bool {
    p.iter().all(|&c| c >= 1.5 * dx && c <= 1.0 - 1.5 * dx)
}
