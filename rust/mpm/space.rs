//! What differs between 2D and 3D: the SVD of a deformation gradient and the inverse of a rigid
//! body's inertia tensor. Everything else in the simulator is written once over `const D`.
//!
//! 2D keeps its closed-form SVD (the results of 2D runs are bit-identical to those of the
//! 2D-only simulator this grew from); 3D uses nalgebra's (through parry3d's re-export, so the
//! crate has one nalgebra) with the signs fixed so that U and V are rotations.

use super::{Matrix, Vector};
use parry3d_f64::na;

/// The dimension marker: the simulator runs for the D with `Dim<D>: Space<D>` (2 and 3).
pub struct Dim<const D: usize>;

pub trait Space<const D: usize> {
    /// F = U diag(sigma) V^T with U and V rotations, |sigma| in decreasing order; the last
    /// sigma is negative when F is inverted (det F < 0). NaN in, NaN out (never a hang).
    fn svd(f: &Matrix<D>) -> (Matrix<D>, Vector<D>, Matrix<D>);

    /// The angular velocity omega = I^-1 L of a rigid body, as the skew matrix W with
    /// W r = omega x r, from its second moment S = sum m r r^T and its angular momentum as the
    /// skew matrix A = sum m (v r^T - r v^T) (A[1][0] = L_z), r the offsets from the centre of
    /// mass. I is singular for a body without extent along some axis (one particle, a line of
    /// particles in 3D): there the pseudo-inverse, which gives no spin about that axis.
    fn angular_velocity(second_moment: &Matrix<D>, angular_momentum: &Matrix<D>) -> Matrix<D>;
}

impl Space<2> for Dim<2> {
    /// In closed form via the polar decomposition F = R S: R is the rotation of F,
    /// S = R^T F is symmetric and its eigen-decomposition gives V and sigma; U = R V.
    fn svd(f: &Matrix<2>) -> (Matrix<2>, Vector<2>, Matrix<2>) {
        let theta = (f[1][0] - f[0][1]).atan2(f[0][0] + f[1][1]);
        let (s, c) = theta.sin_cos();
        let r = [[c, -s], [s, c]];
        let sym = mul2(transpose2(r), *f);
        let (a, b, d) = (sym[0][0], 0.5 * (sym[0][1] + sym[1][0]), sym[1][1]);
        let phi = 0.5 * (2.0 * b).atan2(a - d);
        let (sp, cp) = phi.sin_cos();
        let v = [[cp, -sp], [sp, cp]];
        let mean = 0.5 * (a + d);
        let radius = (0.25 * (a - d) * (a - d) + b * b).sqrt();
        let sigma = [mean + radius, mean - radius];
        (mul2(r, v), sigma, v)
    }

    /// I = sum m |r|^2 = tr S, a scalar; omega = L / I.
    fn angular_velocity(second_moment: &Matrix<2>, angular_momentum: &Matrix<2>) -> Matrix<2> {
        let inertia = second_moment[0][0] + second_moment[1][1];
        let omega = if inertia > 0.0 {
            angular_momentum[1][0] / inertia
        } else {
            0.0
        };
        [[0.0, -omega], [omega, 0.0]]
    }
}

impl Space<3> for Dim<3> {
    fn svd(f: &Matrix<3>) -> (Matrix<3>, Vector<3>, Matrix<3>) {
        let nan = ([[f64::NAN; 3]; 3], [f64::NAN; 3], [[f64::NAN; 3]; 3]);
        if !f.iter().flatten().all(|x| x.is_finite()) {
            return nan;
        }
        let m = na::Matrix3::from_fn(|i, j| f[i][j]);
        // Bounded iterations: a matrix the SVD cannot handle is reported as NaN, never a hang.
        let Some(svd) = na::linalg::SVD::try_new(m, true, true, f64::EPSILON, 1000) else {
            return nan;
        };
        let (Some(mut u), Some(v_t)) = (svd.u, svd.v_t) else {
            return nan;
        };
        let mut sigma = svd.singular_values;
        let mut v = v_t.transpose();
        // nalgebra's U and V may be reflections; a reflection moved into the smallest singular
        // value makes them rotations, and that value negative when F is inverted.
        if u.determinant() < 0.0 {
            u.column_mut(2).neg_mut();
            sigma[2] = -sigma[2];
        }
        if v.determinant() < 0.0 {
            v.column_mut(2).neg_mut();
            sigma[2] = -sigma[2];
        }
        let back =
            |a: &na::Matrix3<f64>| std::array::from_fn(|i| std::array::from_fn(|j| a[(i, j)]));
        (back(&u), [sigma[0], sigma[1], sigma[2]], back(&v))
    }

    /// I = sum m (|r|^2 Id - r r^T) = tr(S) Id - S, inverted on its eigenvectors.
    fn angular_velocity(second_moment: &Matrix<3>, angular_momentum: &Matrix<3>) -> Matrix<3> {
        let a = angular_momentum;
        let l = na::Vector3::new(a[2][1], a[0][2], a[1][0]);
        let s = na::Matrix3::from_fn(|i, j| second_moment[i][j]);
        let inertia = na::Matrix3::identity() * s.trace() - s;
        let nan = [[f64::NAN; 3]; 3];
        if !(inertia.iter().all(|x| x.is_finite()) && l.iter().all(|x| x.is_finite())) {
            return nan;
        }
        let Some(eigen) = na::linalg::SymmetricEigen::try_new(inertia, f64::EPSILON, 1000) else {
            return nan;
        };
        let largest = eigen.eigenvalues.max();
        let mut omega = na::Vector3::zeros();
        for k in 0..3 {
            let lambda = eigen.eigenvalues[k];
            // Below this the body has no extent about that axis (round-off of a line or point).
            if lambda > 1e-12 * largest {
                let q = eigen.eigenvectors.column(k);
                omega += q * (q.dot(&l) / lambda);
            }
        }
        [
            [0.0, -omega[2], omega[1]],
            [omega[2], 0.0, -omega[0]],
            [-omega[1], omega[0], 0.0],
        ]
    }
}

fn mul2(a: Matrix<2>, b: Matrix<2>) -> Matrix<2> {
    let mut out = [[0.0; 2]; 2];
    for i in 0..2 {
        for j in 0..2 {
            out[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j];
        }
    }
    out
}

fn transpose2(a: Matrix<2>) -> Matrix<2> {
    [[a[0][0], a[1][0]], [a[0][1], a[1][1]]]
}
