//! The paper's semi-implicit Euler update, v' = v + dt a, then x' = x + dt v' (the new velocity
//! moves the particle), for callers with arrays (`gns.euler_step`). The learned model applies
//! the same update in torch (LearnedSimulator.decoder_postprocess), where gradients flow
//! through it and the tensors stay on the model's device; this is not on its path.

use crate::{check_positive, first_non_finite, Error, Real, Result};

/// Returns (new position, new velocity), each the shape of the inputs. Computed in f64 and
/// rounded once to the input precision. Non-finite inputs or results are errors naming the
/// first bad particle, so a diverging rollout stops where it diverges.
pub fn euler_step<T: Real>(
    position: &[T],
    velocity: &[T],
    acceleration: &[T],
    dim: usize,
    dt: f64,
) -> Result<(Vec<T>, Vec<T>)> {
    if dim == 0 || position.len() % dim != 0 {
        return Err(Error::Shape(format!(
            "position has {} values, not a multiple of dim = {dim}",
            position.len()
        )));
    }
    for (name, a) in [("velocity", velocity), ("acceleration", acceleration)] {
        if a.len() != position.len() {
            return Err(Error::Shape(format!(
                "{name} has {} values but position has {}; they must have the same shape",
                a.len(),
                position.len()
            )));
        }
    }
    check_positive("dt", dt)?;
    for (name, a) in [
        ("position", position),
        ("velocity", velocity),
        ("acceleration", acceleration),
    ] {
        if let Some((i, d)) = first_non_finite(a, dim) {
            return Err(Error::NonFinite(format!(
                "{name}[{i}, {d}] is {}; expected finite values",
                a[i * dim + d].to_f64()
            )));
        }
    }
    let mut new_velocity = Vec::with_capacity(position.len());
    let mut new_position = Vec::with_capacity(position.len());
    for k in 0..position.len() {
        let v = T::from_f64(velocity[k].to_f64() + dt * acceleration[k].to_f64());
        new_velocity.push(v);
        new_position.push(T::from_f64(position[k].to_f64() + dt * v.to_f64()));
    }
    for (name, a) in [("velocity", &new_velocity), ("position", &new_position)] {
        if let Some((i, d)) = first_non_finite(a, dim) {
            return Err(Error::NonFinite(format!(
                "the new {name} of particle {i} (axis {d}) overflows to {}; the acceleration \
                 {:e} is too large for this precision",
                a[i * dim + d].to_f64(),
                acceleration[i * dim + d].to_f64()
            )));
        }
    }
    Ok((new_position, new_velocity))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_acceleration_matches_the_closed_form_of_semi_implicit_euler() {
        // x_n = x_0 + n dt v_0 + dt^2 a n (n + 1) / 2 for v' = v + dt a, x' = x + dt v'.
        let (a, dt) = (-9.81, 0.01);
        let (mut x, mut v) = (vec![1.0f64], vec![0.5f64]);
        for _ in 0..100 {
            (x, v) = euler_step(&x, &v, &[a], 1, dt).unwrap();
        }
        let n = 100.0;
        let want = 1.0 + n * dt * 0.5 + dt * dt * a * n * (n + 1.0) / 2.0;
        assert!((x[0] - want).abs() < 1e-12, "{} vs {want}", x[0]);
    }

    #[test]
    fn non_finite_inputs_and_overflow_are_errors() {
        assert!(euler_step(&[0.0f64], &[0.0], &[f64::NAN], 1, 1.0).is_err());
        let e = euler_step(&[0.0f32], &[0.0], &[1e38], 1, 10.0).unwrap_err();
        assert!(e.to_string().contains("overflows"), "{e}");
        assert!(euler_step(&[0.0f64, 0.0], &[0.0], &[0.0], 1, 1.0).is_err());
        assert!(euler_step(&[0.0f64], &[0.0], &[0.0], 1, 0.0).is_err());
    }
}
