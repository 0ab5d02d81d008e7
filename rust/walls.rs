//! What a particle sees of the scene's boundaries: clipped distances to the walls of an
//! axis-aligned box (the paper's wall features), and clipped vectors to obstacle shapes
//! (parry) for irregular geometry such as ramps, so a scene need not be lined with particles.

use crate::{check_positive, first_non_finite, Error, Real, Result};
use parry2d_f64 as p2;
use parry3d_f64 as p3;
use rayon::prelude::*;

/// Rows per rayon task; below one task the work runs on the calling thread.
const ROWS_PER_TASK: usize = 2048;

fn check_positions<T: Real>(positions: &[T], dim: usize) -> Result<usize> {
    if dim != 2 && dim != 3 {
        return Err(Error::Shape(format!(
            "positions must have 2 or 3 columns, got {dim}"
        )));
    }
    if positions.len() % dim != 0 {
        return Err(Error::Shape(format!(
            "positions has {} values, not a multiple of dim = {dim}",
            positions.len()
        )));
    }
    if let Some((i, d)) = first_non_finite(positions, dim) {
        return Err(Error::NonFinite(format!(
            "positions[{i}, {d}] is {}; positions must be finite",
            positions[i * dim + d].to_f64()
        )));
    }
    Ok(positions.len() / dim)
}

/// Runs `row(i, out_row)` over rows of `width` values, in parallel for large inputs.
fn for_rows<T: Send>(out: &mut [T], width: usize, row: impl Fn(usize, &mut [T]) + Sync) {
    if width == 0 {
        return;
    }
    if out.len() / width <= ROWS_PER_TASK {
        out.chunks_exact_mut(width)
            .enumerate()
            .for_each(|(i, r)| row(i, r));
    } else {
        out.par_chunks_mut(width * ROWS_PER_TASK)
            .enumerate()
            .for_each(|(t, chunk)| {
                for (k, r) in chunk.chunks_exact_mut(width).enumerate() {
                    row(t * ROWS_PER_TASK + k, r);
                }
            });
    }
}

/// Wall features, shape (N, 2 D): distances to the lower bounds, then to the upper bounds,
/// divided by `radius` and clipped to [-clip, clip] (negative outside the box).
/// `bounds` is (D, 2): [lower, upper] per axis.
pub fn wall_features<T: Real>(
    positions: &[T],
    dim: usize,
    bounds: &[f64],
    radius: f64,
    clip: f64,
) -> Result<Vec<T>> {
    let n = check_positions(positions, dim)?;
    check_positive("radius", radius)?;
    if bounds.len() != 2 * dim {
        return Err(Error::Shape(format!(
            "bounds must be (dim, 2) = ({dim}, 2) pairs [lower, upper], got {} values",
            bounds.len()
        )));
    }
    for d in 0..dim {
        let (lo, hi) = (bounds[2 * d], bounds[2 * d + 1]);
        if !(lo.is_finite() && hi.is_finite() && lo < hi) {
            return Err(Error::Value(format!(
                "bounds[{d}] = [{lo}, {hi}]; expected finite lower < upper"
            )));
        }
    }
    if clip.is_nan() || clip <= 0.0 {
        return Err(Error::Value(format!("clip must be > 0, got {clip}")));
    }
    let mut out = vec![T::from_f64(0.0); n * 2 * dim];
    for_rows(&mut out, 2 * dim, |i, row| {
        for d in 0..dim {
            let x = positions[i * dim + d].to_f64();
            let lower = (x - bounds[2 * d]) / radius;
            let upper = (bounds[2 * d + 1] - x) / radius;
            row[d] = T::from_f64(lower.clamp(-clip, clip));
            row[dim + d] = T::from_f64(upper.clamp(-clip, clip));
        }
    });
    Ok(out)
}

/// A static obstacle in world coordinates.
pub enum Obstacle {
    Shape2(Box<dyn p2::shape::Shape>),
    Shape3(Box<dyn p3::shape::Shape>),
}

/// Obstacle coordinates and the obstacle radius stay within this magnitude: parry measures
/// squared distances, which overflow (and once made it panic) near 1e154.
pub const MAX_OBSTACLE_COORDINATE: f64 = 1e100;

fn check_magnitude(what: &str, values: &[f64]) -> Result<()> {
    match values.iter().find(|v| v.abs() > MAX_OBSTACLE_COORDINATE) {
        Some(v) => Err(Error::Value(format!(
            "{what} has the value {v:e}; obstacle coordinates must lie within \
             +-{MAX_OBSTACLE_COORDINATE:e}"
        ))),
        None => Ok(()),
    }
}

fn points<const D: usize>(what: &str, values: &[f64]) -> Result<Vec<[f64; D]>> {
    if values.is_empty() || values.len() % D != 0 {
        return Err(Error::Shape(format!(
            "{what} must be a non-empty (K, {D}) array, got {} values",
            values.len()
        )));
    }
    if let Some((k, d)) = first_non_finite(values, D) {
        return Err(Error::NonFinite(format!(
            "{what}[{k}, {d}] is {}; expected finite coordinates",
            values[k * D + d]
        )));
    }
    check_magnitude(what, values)?;
    Ok(values
        .chunks_exact(D)
        .map(|c| {
            let mut p = [0.0; D];
            p.copy_from_slice(c);
            p
        })
        .collect())
}

impl Obstacle {
    /// A 2D polyline through `vertices` (K, 2); `closed` joins the last vertex to the first.
    pub fn polyline(vertices: &[f64], closed: bool) -> Result<Self> {
        let v = points::<2>("vertices", vertices)?;
        if v.len() < 2 {
            return Err(Error::Shape(format!(
                "a polyline needs at least 2 vertices, got {}",
                v.len()
            )));
        }
        let k = v.len() as u32;
        let mut idx: Vec<[u32; 2]> = (0..k - 1).map(|a| [a, a + 1]).collect();
        if closed && k > 2 {
            idx.push([k - 1, 0]);
        }
        let pts = v.iter().map(|p| p2::math::Point::new(p[0], p[1])).collect();
        Ok(Obstacle::Shape2(Box::new(p2::shape::Polyline::new(
            pts,
            Some(idx),
        ))))
    }

    /// An axis-aligned box (2D or 3D) given by its centre and half extents.
    pub fn cuboid(center: &[f64], half_extents: &[f64]) -> Result<Self> {
        if center.len() != half_extents.len() || !(center.len() == 2 || center.len() == 3) {
            return Err(Error::Shape(format!(
                "center and half_extents must both have 2 or 3 values, got {} and {}",
                center.len(),
                half_extents.len()
            )));
        }
        if let Some(h) = half_extents.iter().find(|h| !(h.is_finite() && **h > 0.0)) {
            return Err(Error::Value(format!(
                "half_extents must be finite and > 0, got {h}"
            )));
        }
        if let Some(c) = center.iter().find(|c| !c.is_finite()) {
            return Err(Error::NonFinite(format!("center must be finite, got {c}")));
        }
        check_magnitude("center", center)?;
        check_magnitude("half_extents", half_extents)?;
        Ok(if center.len() == 2 {
            let shape =
                p2::shape::Cuboid::new(p2::math::Vector::new(half_extents[0], half_extents[1]));
            let iso = p2::math::Isometry::translation(center[0], center[1]);
            Obstacle::Shape2(Box::new(transformed2(shape, iso)))
        } else {
            let shape = p3::shape::Cuboid::new(p3::math::Vector::new(
                half_extents[0],
                half_extents[1],
                half_extents[2],
            ));
            let iso = p3::math::Isometry::translation(center[0], center[1], center[2]);
            Obstacle::Shape3(Box::new(transformed3(shape, iso)))
        })
    }

    /// A 3D triangle mesh: `vertices` (V, 3), `triangles` (T, 3) vertex indices.
    pub fn trimesh(vertices: &[f64], triangles: &[u32]) -> Result<Self> {
        let v = points::<3>("vertices", vertices)?;
        if triangles.is_empty() || triangles.len() % 3 != 0 {
            return Err(Error::Shape(format!(
                "triangles must be a non-empty (T, 3) array, got {} values",
                triangles.len()
            )));
        }
        if let Some(&bad) = triangles.iter().find(|&&t| t as usize >= v.len()) {
            return Err(Error::Value(format!(
                "triangles refer to vertex {bad}, but there are only {} vertices",
                v.len()
            )));
        }
        let pts = v
            .iter()
            .map(|p| p3::math::Point::new(p[0], p[1], p[2]))
            .collect();
        let idx = triangles
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect();
        let mesh = p3::shape::TriMesh::new(pts, idx)
            .map_err(|e| Error::Value(format!("invalid triangle mesh: {e:?}")))?;
        Ok(Obstacle::Shape3(Box::new(mesh)))
    }

    pub fn dim(&self) -> usize {
        match self {
            Obstacle::Shape2(_) => 2,
            Obstacle::Shape3(_) => 3,
        }
    }

    /// The obstacle's bounding box, (lower, upper) corners (the third axis 0 in 2D).
    fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        match self {
            Obstacle::Shape2(s) => {
                let b = s.compute_local_aabb();
                ([b.mins.x, b.mins.y, 0.0], [b.maxs.x, b.maxs.y, 0.0])
            }
            Obstacle::Shape3(s) => {
                let b = s.compute_local_aabb();
                (
                    [b.mins.x, b.mins.y, b.mins.z],
                    [b.maxs.x, b.maxs.y, b.maxs.z],
                )
            }
        }
    }

    /// The point of the obstacle's surface nearest to x (a point inside a solid obstacle is
    /// projected onto its surface, so penetration still points the way out).
    fn nearest(&self, x: &[f64]) -> [f64; 3] {
        match self {
            Obstacle::Shape2(s) => {
                let p = s
                    .project_local_point(&p2::math::Point::new(x[0], x[1]), false)
                    .point;
                [p.x, p.y, 0.0]
            }
            Obstacle::Shape3(s) => {
                let p = s
                    .project_local_point(&p3::math::Point::new(x[0], x[1], x[2]), false)
                    .point;
                [p.x, p.y, p.z]
            }
        }
    }
}

// parry's shapes are defined about their own origin; a box placed elsewhere is a compound of
// one shape at an isometry.
fn transformed2(shape: p2::shape::Cuboid, iso: p2::math::Isometry<f64>) -> p2::shape::Compound {
    p2::shape::Compound::new(vec![(iso, p2::shape::SharedShape::new(shape))])
}

fn transformed3(shape: p3::shape::Cuboid, iso: p3::math::Isometry<f64>) -> p3::shape::Compound {
    p3::shape::Compound::new(vec![(iso, p3::shape::SharedShape::new(shape))])
}

fn check_obstacles(dim: usize, obstacles: &[&Obstacle], reach: f64) -> Result<()> {
    if reach > MAX_OBSTACLE_COORDINATE {
        return Err(Error::Value(format!(
            "radius = {reach:e}; obstacle features need a radius of at most \
             {MAX_OBSTACLE_COORDINATE:e}"
        )));
    }
    for (k, o) in obstacles.iter().enumerate() {
        if o.dim() != dim {
            return Err(Error::Shape(format!(
                "obstacle {k} is {}D but the positions are {dim}D",
                o.dim()
            )));
        }
    }
    Ok(())
}

/// Farther than `reach` from the obstacle's bounding box along some axis. Besides saving the
/// projection, this keeps far particles (at any finite coordinate) out of parry's squared
/// distances.
fn beyond(bounds: &([f64; 3], [f64; 3]), x: &[f64], reach: f64) -> bool {
    let (lo, hi) = bounds;
    (0..x.len()).any(|d| lo[d] - x[d] > reach || x[d] - hi[d] > reach)
}

/// Obstacle features, shape (N, K D): for each obstacle k, (nearest point - x) / radius when
/// that point is within `radius` of the particle, else zeros.
pub fn obstacle_features<T: Real>(
    positions: &[T],
    dim: usize,
    obstacles: &[&Obstacle],
    radius: f64,
) -> Result<Vec<T>> {
    let n = check_positions(positions, dim)?;
    check_positive("radius", radius)?;
    check_obstacles(dim, obstacles, radius)?;
    let width = obstacles.len() * dim;
    let mut out = vec![T::from_f64(0.0); n * width];
    let boxes: Vec<_> = obstacles.iter().map(|o| o.bounds()).collect();
    for_rows(&mut out, width, |i, row| {
        let x: Vec<f64> = (0..dim).map(|d| positions[i * dim + d].to_f64()).collect();
        for (k, o) in obstacles.iter().enumerate() {
            if beyond(&boxes[k], &x, radius) {
                continue;
            }
            let p = o.nearest(&x);
            let v: Vec<f64> = (0..dim).map(|d| (p[d] - x[d]) / radius).collect();
            if v.iter().map(|c| c * c).sum::<f64>() <= 1.0 {
                for d in 0..dim {
                    row[k * dim + d] = T::from_f64(v[d]);
                }
            }
        }
    });
    Ok(out)
}

/// The nearest obstacle of a set, shape (N, D): the unit vector from the particle towards the
/// nearest surface point of all `obstacles`, scaled by 1 - d / reach (reach = clip * radius):
/// 1 at contact, 0 at `reach` and beyond. One D-vector whatever the number of shapes, so one
/// model serves scenes with different obstacles (1-3 ramps, a floor of any number of
/// segments); zero at the reach and growing towards contact, so the feature is continuous
/// and a particle sees nothing of an obstacle beyond it, as with boundary particles.
pub fn nearest_obstacle_features<T: Real>(
    positions: &[T],
    dim: usize,
    obstacles: &[&Obstacle],
    radius: f64,
    clip: f64,
) -> Result<Vec<T>> {
    let n = check_positions(positions, dim)?;
    check_positive("radius", radius)?;
    check_positive("clip", clip)?;
    let reach = clip * radius;
    check_obstacles(dim, obstacles, reach)?;
    let mut out = vec![T::from_f64(0.0); n * dim];
    let boxes: Vec<_> = obstacles.iter().map(|o| o.bounds()).collect();
    for_rows(&mut out, dim, |i, row| {
        let x: Vec<f64> = (0..dim).map(|d| positions[i * dim + d].to_f64()).collect();
        let mut best: Option<(f64, [f64; 3])> = None;
        for (k, o) in obstacles.iter().enumerate() {
            if beyond(&boxes[k], &x, reach) {
                continue;
            }
            let p = o.nearest(&x);
            let d2: f64 = (0..dim).map(|d| (p[d] - x[d]).powi(2)).sum();
            if best.is_none_or(|(b, _)| d2 < b) {
                best = Some((d2, p));
            }
        }
        if let Some((d2, p)) = best {
            let d = d2.sqrt();
            // On the surface itself the direction is undefined: the feature is left at zero.
            if d < reach && d > 0.0 {
                let scale = (1.0 - d / reach) / d;
                for c in 0..dim {
                    row[c] = T::from_f64((p[c] - x[c]) * scale);
                }
            }
        }
    });
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wall_features_are_the_clipped_distances_lower_then_upper() {
        let pos = [0.1f64, 0.5, 0.95, 0.02, 1.2, -0.3];
        let bounds = [0.0, 1.0, 0.0, 1.0];
        let f = wall_features(&pos, 2, &bounds, 0.1, 1.0).unwrap();
        let want = [
            [1.0, 1.0, 1.0, 1.0],
            [1.0, 0.2, 0.5, 1.0],
            [1.0, -1.0, -1.0, 1.0],
        ];
        for (row, w) in f.chunks(4).zip(want) {
            for (a, b) in row.iter().zip(w) {
                assert!((a - b).abs() < 1e-12, "{row:?} vs {w:?}");
            }
        }
        assert!(wall_features(&pos, 2, &[1.0, 0.0, 0.0, 1.0], 0.1, 1.0).is_err());
        assert!(wall_features(&pos, 2, &bounds, 0.1, f64::NAN).is_err());
    }

    #[test]
    fn obstacle_vectors_point_to_the_nearest_surface_point_within_the_radius() {
        // A ramp from (0, 0) to (1, 1); the particle at (0.5, 0.4) is 0.1 / sqrt(2) away.
        let ramp = Obstacle::polyline(&[0.0, 0.0, 1.0, 1.0], false).unwrap();
        let f = obstacle_features(&[0.5f64, 0.4, 0.5, -0.5], 2, &[&ramp], 0.1).unwrap();
        assert!(
            (f[0] - (-0.5)).abs() < 1e-9 && (f[1] - 0.5).abs() < 1e-9,
            "{f:?}"
        );
        assert_eq!(&f[2..], &[0.0, 0.0]);
        // Inside a box the vector points to the nearest face.
        let b = Obstacle::cuboid(&[0.0, 0.0, 0.0], &[1.0, 1.0, 1.0]).unwrap();
        let f = obstacle_features(&[0.0f64, 0.0, 0.95], 3, &[&b], 0.1).unwrap();
        assert!((f[2] - 0.5).abs() < 1e-9 && f[0].abs() < 1e-12, "{f:?}");
        assert!(obstacle_features(&[0.0f64, 0.0], 2, &[&b], 0.1).is_err());
        assert!(Obstacle::trimesh(&[0.0; 9], &[0, 1, 3]).is_err());
    }

    #[test]
    fn far_particles_and_huge_obstacles_neither_panic_nor_overflow() {
        // Found by fuzzing: parry's projection panicked on a particle at 3.7e221.
        let ramp = Obstacle::polyline(&[0.1, 0.1, 0.9, 0.3], false).unwrap();
        let far = [-3.7e221f64, -4.9e15, 1e300, 1e300, 0.5, 0.25];
        let f = obstacle_features(&far, 2, &[&ramp], 4e16).unwrap();
        assert_eq!(&f[..4], &[0.0; 4]);
        assert!(
            f[4].abs() < 1e-15 && (f[5] / f[4] + 4.0).abs() < 1e-9,
            "{f:?}"
        );
        let big = |r: Result<Vec<f64>>| r.unwrap_err().to_string();
        assert!(big(obstacle_features(&far, 2, &[&ramp], 1e200)).contains("radius = 1e200"));
        let err = Obstacle::polyline(&[0.0, 0.0, 1e200, 0.0], false)
            .err()
            .unwrap();
        assert!(err.to_string().contains("1e200"), "{err}");
        assert!(Obstacle::cuboid(&[1e101, 0.0], &[1.0, 1.0]).is_err());
    }
}
