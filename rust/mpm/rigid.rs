//! Rigid bodies made of particles (BOXBATH-style scenes): the particles of a body take part in
//! particles to grid like any material (mass and momentum, no stress), and after grid to
//! particles their velocities are projected onto the body's rigid motion (linear velocity,
//! angular velocity) as in shape matching. The body keeps its particles' offsets in its own
//! frame and rebuilds their positions as x_c + R r0 every substep, so its shape is kept exactly,
//! up to round-off, however long the run.
//!
//! A body does not enter the walls: the grid's wall nodes slow only the particles that touch
//! them, and averaged over the body that would let it sink into the floor a little every
//! substep; so a body that crosses a wall's bound is put back on it and loses its velocity into
//! the wall (an inelastic contact; friction and torque still come from the wall nodes). Static
//! obstacle particles hold a body only through their sticky nodes, without that correction, so
//! a body resting on an obstacle creeps into it.

use super::constitutive::{identity, mul, mul_vector, sum};
use super::{Dim, Material, Matrix, Model, Space, Vector};

pub(super) struct Body<const D: usize> {
    /// The body's particles in index order, the order of every sum over them.
    particles: Vec<usize>,
    /// Each particle's offset from the centre of mass in the body's frame (its initial one).
    rest: Vec<Vector<D>>,
    /// The centre of mass.
    centre: Vector<D>,
    /// The body's frame: a particle's offset is rotation * rest.
    rotation: Matrix<D>,
}

impl<const D: usize> Body<D>
where
    Dim<D>: Space<D>,
{
    /// One body per Rigid material that has particles, in material order; all particles of a
    /// material have the same mass, so the centre of mass is the mean position.
    pub(super) fn all(materials: &[Material], material: &[u32], x: &[Vector<D>]) -> Vec<Self> {
        let mut bodies = vec![];
        for (index, m) in materials.iter().enumerate() {
            if !matches!(m.model, Model::Rigid) {
                continue;
            }
            let particles: Vec<usize> = (0..material.len())
                .filter(|&p| material[p] as usize == index)
                .collect();
            if particles.is_empty() {
                continue;
            }
            let count = particles.len() as f64;
            let mut centre = [0.0; D];
            for &p in &particles {
                for a in 0..D {
                    centre[a] += x[p][a];
                }
            }
            centre = centre.map(|c| c / count);
            let rest = particles
                .iter()
                .map(|&p| std::array::from_fn(|a| x[p][a] - centre[a]))
                .collect();
            bodies.push(Body {
                particles,
                rest,
                centre,
                rotation: identity(),
            });
        }
        bodies
    }

    pub(super) fn particles(&self) -> &[usize] {
        &self.particles
    }

    /// Makes the initial velocities `v` a rigid motion (the one with their linear and angular
    /// momentum) and sets C to its velocity gradient: with C = 0 the first particles to grid
    /// would smear a spinning body's velocity field and lose a quarter of its spin (3 cells
    /// wide, measured).
    pub(super) fn start(&self, v: &mut [Vector<D>], c: &mut [Matrix<D>]) {
        let (velocity, spin) = self.rigid_motion(v);
        for (&p, rest) in self.particles.iter().zip(&self.rest) {
            let spun = mul_vector(&spin, rest);
            v[p] = std::array::from_fn(|a| velocity[a] + spun[a]);
            c[p] = spin;
        }
    }

    /// The rigid motion (V, W) with the linear momentum (V = sum m v / M) and angular momentum
    /// (omega = I^-1 sum m r x v, W r = omega x r) of the particle velocities `v` about the
    /// centre of mass.
    fn rigid_motion(&self, v: &[Vector<D>]) -> (Vector<D>, Matrix<D>) {
        let count = self.particles.len() as f64;
        let mut velocity = [0.0; D];
        for &p in &self.particles {
            for a in 0..D {
                velocity[a] += v[p][a];
            }
        }
        velocity = velocity.map(|s| s / count);
        // Second moment S = sum r r^T and angular momentum A = sum (v r^T - r v^T), per unit
        // mass (the mass cancels in I^-1 L); v relative to V, which sum r = 0 makes the same
        // but with less cancellation.
        let mut second_moment = [[0.0; D]; D];
        let mut angular_momentum = [[0.0; D]; D];
        for (&p, rest) in self.particles.iter().zip(&self.rest) {
            let r = mul_vector(&self.rotation, rest);
            let u: Vector<D> = std::array::from_fn(|a| v[p][a] - velocity[a]);
            for i in 0..D {
                for j in 0..D {
                    second_moment[i][j] += r[i] * r[j];
                    angular_momentum[i][j] += u[i] * r[j] - r[i] * u[j];
                }
            }
        }
        let spin = <Dim<D>>::angular_velocity(&second_moment, &angular_momentum);
        (velocity, spin)
    }

    /// From the particles' grid velocities `v`: the rigid motion with the same linear and
    /// angular momentum (rigid_motion); then the body moves by dt and every particle gets
    /// x = x_c + R r0, v = V + omega x r and C = W = skew(omega), the rigid motion's velocity
    /// gradient (F stays I).
    pub(super) fn advance(
        &mut self,
        x: &mut [Vector<D>],
        v: &mut [Vector<D>],
        c: &mut [Matrix<D>],
        dt: f64,
        bounds: &[[f64; 2]; D],
    ) {
        let (mut velocity, spin) = self.rigid_motion(v);
        for a in 0..D {
            self.centre[a] += dt * velocity[a];
        }
        let turn = spin.map(|row| row.map(|w| dt * w));
        self.rotation = orthonormal(mul(&exponential(&turn), &self.rotation));
        self.keep_inside(bounds, &mut velocity);
        for (&p, rest) in self.particles.iter().zip(&self.rest) {
            let r = mul_vector(&self.rotation, rest);
            let spun = mul_vector(&spin, &r);
            x[p] = std::array::from_fn(|a| self.centre[a] + r[a]);
            v[p] = std::array::from_fn(|a| velocity[a] + spun[a]);
            c[p] = spin;
        }
    }

    /// Moves the body back inside `bounds` where it crossed one, and removes its velocity into
    /// that wall.
    fn keep_inside(&mut self, bounds: &[[f64; 2]; D], velocity: &mut Vector<D>) {
        let mut low = [f64::INFINITY; D];
        let mut high = [f64::NEG_INFINITY; D];
        for rest in &self.rest {
            let r = mul_vector(&self.rotation, rest);
            for a in 0..D {
                low[a] = low[a].min(self.centre[a] + r[a]);
                high[a] = high[a].max(self.centre[a] + r[a]);
            }
        }
        for a in 0..D {
            let [lo, hi] = bounds[a];
            if low[a] < lo && high[a] <= hi {
                self.centre[a] += lo - low[a];
                velocity[a] = velocity[a].max(0.0);
            } else if high[a] > hi && low[a] >= lo {
                self.centre[a] += hi - high[a];
                velocity[a] = velocity[a].min(0.0);
            }
        }
    }
}

/// exp(K) of a skew matrix K (a rotation by |omega| dt), by Rodrigues' formula
/// I + sin(t)/t K + (1 - cos t)/t^2 K^2 with t^2 = sum over i < j of K_ij^2, which holds in 2D
/// and 3D; (1 - cos t)/t^2 written as (sin(t/2)/(t/2))^2 / 2, free of cancellation.
fn exponential<const D: usize>(k: &Matrix<D>) -> Matrix<D> {
    let mut t2 = 0.0;
    for i in 0..D {
        for j in i + 1..D {
            t2 += k[i][j] * k[i][j];
        }
    }
    let t = t2.sqrt();
    if t == 0.0 {
        return identity();
    }
    let a = t.sin() / t;
    let half = 0.5 * t;
    let b = 0.5 * (half.sin() / half).powi(2);
    let k2 = mul(k, k);
    let mut out = identity();
    for i in 0..D {
        for j in 0..D {
            out[i][j] += a * k[i][j] + b * k2[i][j];
        }
    }
    out
}

/// The rotation nearest a product of rotations, by Gram-Schmidt on its columns: keeps the
/// round-off of thousands of substeps from accumulating into shear or scale.
fn orthonormal<const D: usize>(mut r: Matrix<D>) -> Matrix<D> {
    for j in 0..D {
        for k in 0..j {
            let dot = sum::<D>(|i| r[i][j] * r[i][k]);
            for i in 0..D {
                r[i][j] -= dot * r[i][k];
            }
        }
        let norm = sum::<D>(|i| r[i][j] * r[i][j]).sqrt();
        for i in 0..D {
            r[i][j] /= norm;
        }
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_exponential_of_a_skew_matrix_is_the_rotation_by_its_angle() {
        let (w, dt) = (3.0, 0.1);
        let r = exponential(&[[0.0, -w * dt], [w * dt, 0.0]]);
        let (s, c) = (w * dt).sin_cos();
        let want = [[c, -s], [s, c]];
        for i in 0..2 {
            for j in 0..2 {
                assert!((r[i][j] - want[i][j]).abs() < 1e-15, "{r:?}");
            }
        }
        // 3D about z: the same rotation in the xy block, z fixed.
        let k = [[0.0, -0.3, 0.0], [0.3, 0.0, 0.0], [0.0, 0.0, 0.0]];
        let r = exponential(&k);
        assert!((r[0][0] - c).abs() < 1e-15 && (r[1][0] - s).abs() < 1e-15);
        assert!((r[2][2] - 1.0).abs() < 1e-15 && r[0][2] == 0.0);
        // About an arbitrary axis: orthogonal and the axis fixed.
        let axis = [0.3, -0.5, 0.8];
        let k = [
            [0.0, -axis[2], axis[1]],
            [axis[2], 0.0, -axis[0]],
            [-axis[1], axis[0], 0.0],
        ];
        let r = exponential(&k);
        for i in 0..3 {
            for j in 0..3 {
                let dot = sum::<3>(|a| r[a][i] * r[a][j]);
                assert!((dot - if i == j { 1.0 } else { 0.0 }).abs() < 1e-14);
            }
        }
        let moved = mul_vector(&r, &axis);
        assert!(
            (0..3).all(|a| (moved[a] - axis[a]).abs() < 1e-15),
            "{moved:?}"
        );
    }

    #[test]
    fn the_inertia_inverse_gives_back_a_rigid_spin() {
        // Particles of a rigid motion with omega: the projection finds omega again, in 3D for
        // a lopsided cloud (a full inertia tensor) and for a line (the pseudo-inverse).
        let omega = [0.7, -1.1, 0.4];
        let skew = [
            [0.0, -omega[2], omega[1]],
            [omega[2], 0.0, -omega[0]],
            [-omega[1], omega[0], 0.0],
        ];
        let cloud = [
            [0.1, 0.0, 0.02],
            [-0.05, 0.08, 0.0],
            [0.0, -0.03, -0.09],
            [-0.05, -0.05, 0.07],
        ];
        // The second moment and angular momentum of points moving with the spin `skew`.
        let moments = |points: &[[f64; 3]]| {
            let (mut s, mut l) = ([[0.0; 3]; 3], [[0.0; 3]; 3]);
            for r in points {
                let v = mul_vector(&skew, r);
                for i in 0..3 {
                    for j in 0..3 {
                        s[i][j] += r[i] * r[j];
                        l[i][j] += v[i] * r[j] - r[i] * v[j];
                    }
                }
            }
            (s, l)
        };
        let (s, l) = moments(&cloud);
        let w = <Dim<3>>::angular_velocity(&s, &l);
        for i in 0..3 {
            for j in 0..3 {
                assert!((w[i][j] - skew[i][j]).abs() < 1e-12, "{w:?}");
            }
        }
        // A line along x: spin about x is undetermined and left out; the rest is found.
        let line = [[-0.1, 0.0, 0.0], [0.0, 0.0, 0.0], [0.1, 0.0, 0.0]];
        let (s, l) = moments(&line);
        let w = <Dim<3>>::angular_velocity(&s, &l);
        assert!(w[2][1].abs() < 1e-12, "{w:?}"); // omega_x
        assert!((w[0][2] - omega[1]).abs() < 1e-12 && (w[1][0] - omega[2]).abs() < 1e-12);
        // 2D: omega = L / I.
        let w = <Dim<2>>::angular_velocity(&[[2.0, 0.5], [0.5, 3.0]], &[[0.0, -10.0], [10.0, 0.0]]);
        assert_eq!(w, [[0.0, -2.0], [2.0, 0.0]]);
    }
}
