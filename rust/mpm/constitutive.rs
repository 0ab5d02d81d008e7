//! The materials' constitutive models in D dimensions: Kirchhoff stress from Hencky strain
//! (the log of F's singular values) and the return mappings of sand (Drucker-Prager) and goop
//! (von Mises). Every sum runs in index order from its first term, as the 2D-only simulator's
//! written-out expressions did, so 2D results are bit-identical to it.

use super::{Dim, Material, Matrix, Model, Space, Vector};

/// term(0) + term(1) + ... + term(D - 1), in that order.
#[inline]
pub(super) fn sum<const D: usize>(term: impl Fn(usize) -> f64) -> f64 {
    let mut total = term(0);
    for k in 1..D {
        total += term(k);
    }
    total
}

pub(super) fn identity<const D: usize>() -> Matrix<D> {
    std::array::from_fn(|i| std::array::from_fn(|j| if i == j { 1.0 } else { 0.0 }))
}

pub(super) fn mul<const D: usize>(a: &Matrix<D>, b: &Matrix<D>) -> Matrix<D> {
    std::array::from_fn(|i| std::array::from_fn(|j| sum::<D>(|k| a[i][k] * b[k][j])))
}

pub(super) fn mul_vector<const D: usize>(a: &Matrix<D>, x: &Vector<D>) -> Vector<D> {
    std::array::from_fn(|i| sum::<D>(|k| a[i][k] * x[k]))
}

pub(super) fn trace<const D: usize>(a: &Matrix<D>) -> f64 {
    sum::<D>(|k| a[k][k])
}

/// The Kirchhoff stress tau = P F^T of a particle of material `m` with Lame parameters
/// (lambda, mu), deformation gradient `f` and `j` (water's volume ratio).
pub(super) fn kirchhoff_stress<const D: usize>(
    m: &Material,
    (lambda, mu): (f64, f64),
    f: &Matrix<D>,
    j: f64,
) -> Matrix<D>
where
    Dim<D>: Space<D>,
{
    match m.model {
        Model::Water { .. } => {
            let pressure = lambda * j * (j - 1.0);
            std::array::from_fn(|a| std::array::from_fn(|b| if a == b { pressure } else { 0.0 }))
        }
        Model::Sand { .. } | Model::Goop { .. } => {
            // Hencky: tau = U (2 mu eps + lambda tr(eps) I) U^T with eps = log(sigma).
            let (u, sigma, _) = <Dim<D>>::svd(f);
            let eps: Vector<D> = std::array::from_fn(|a| sigma[a].ln());
            let tr = sum::<D>(|a| eps[a]);
            let d: Vector<D> = std::array::from_fn(|a| 2.0 * mu * eps[a] + lambda * tr);
            // U diag(d) U^T
            std::array::from_fn(|i| std::array::from_fn(|k| sum::<D>(|a| u[i][a] * d[a] * u[k][a])))
        }
        Model::Obstacle | Model::Rigid => [[0.0; D]; D],
    }
}

/// F' = (I + dt C) F.
pub(super) fn deform<const D: usize>(f: &Matrix<D>, c: &Matrix<D>, dt: f64) -> Matrix<D> {
    let a = std::array::from_fn(|i| {
        std::array::from_fn(|k| {
            if i == k {
                1.0 + dt * c[i][k]
            } else {
                dt * c[i][k]
            }
        })
    });
    mul(&a, f)
}

/// Applies a return mapping on the Hencky strain (log of the singular values) of F.
pub(super) fn project<const D: usize>(
    f: &Matrix<D>,
    map: impl FnOnce(Vector<D>) -> Vector<D>,
) -> Matrix<D>
where
    Dim<D>: Space<D>,
{
    let (u, sigma, v) = <Dim<D>>::svd(f);
    let eps = map(std::array::from_fn(|a| sigma[a].max(1e-12).ln()));
    let d: Vector<D> = std::array::from_fn(|a| eps[a].exp());
    // U diag(d) V^T
    std::array::from_fn(|i| std::array::from_fn(|k| sum::<D>(|a| u[i][a] * d[a] * v[k][a])))
}

/// Klar et al. (2016), cohesionless, in D dimensions, with the volume correction of Tampubolon
/// et al. (2017): `dilation` (log volume gained by separating) adds to the volumetric strain.
/// Expansion goes to the cone's tip (stress-free) and is remembered; in compression the
/// deviatoric strain beyond the friction cone is removed. Returns (new strain, new dilation).
pub(super) fn drucker_prager<const D: usize>(
    eps: Vector<D>,
    dilation: f64,
    lambda: f64,
    mu: f64,
    friction_angle_deg: f64,
) -> (Vector<D>, f64) {
    let d = D as f64;
    let tr = sum::<D>(|a| eps[a]) + dilation;
    if tr >= 0.0 {
        return ([0.0; D], tr);
    }
    let dev: Vector<D> = std::array::from_fn(|a| eps[a] - tr / d);
    let norm = sum::<D>(|a| dev[a] * dev[a]).sqrt();
    let sin = friction_angle_deg.to_radians().sin();
    // Klar et al.'s fit of the Mohr-Coulomb cone, the same in 2D (plane strain) and 3D.
    let alpha = (2.0f64 / 3.0).sqrt() * 2.0 * sin / (3.0 - sin);
    // The plastic multiplier: the deviator's excess over the cone, (d lambda + 2 mu) / (2 mu)
    // converting the volumetric strain into the cone's radius.
    let gamma = norm + (d * lambda + 2.0 * mu) / (2.0 * mu) * tr * alpha;
    if gamma <= 0.0 || norm == 0.0 {
        return (eps, 0.0);
    }
    (std::array::from_fn(|a| eps[a] - gamma * dev[a] / norm), 0.0)
}

/// von Mises: the deviatoric strain is capped at yield_stress / (2 mu).
pub(super) fn von_mises<const D: usize>(eps: Vector<D>, mu: f64, yield_stress: f64) -> Vector<D> {
    let mean = sum::<D>(|a| eps[a]) / D as f64;
    let dev: Vector<D> = std::array::from_fn(|a| eps[a] - mean);
    let norm = sum::<D>(|a| dev[a] * dev[a]).sqrt();
    let limit = yield_stress / (2.0 * mu);
    if norm <= limit {
        return eps;
    }
    let scale = limit / norm;
    std::array::from_fn(|a| mean + scale * dev[a])
}
