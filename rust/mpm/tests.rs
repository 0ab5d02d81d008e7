//! 2D tests, and the helpers the 3D tests (tests3d.rs) share.

use super::constitutive::{mul, von_mises};
use super::solver::{Mpm, SPLIT_AT};
use super::*;

fn close(a: Matrix<2>, b: Matrix<2>, tol: f64) -> bool {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .all(|(x, y)| (x - y).abs() < tol)
}

fn transpose(a: Matrix<2>) -> Matrix<2> {
    [[a[0][0], a[1][0]], [a[0][1], a[1][1]]]
}

pub(super) const WATER: Material = Material {
    density: 1000.0,
    model: Model::Water { bulk_modulus: 1e5 },
};

pub(super) const SAND: Material = Material {
    density: 1800.0,
    model: Model::Sand {
        youngs_modulus: 2e6,
        poisson_ratio: 0.3,
        friction_angle_deg: 30.0,
    },
};

pub(super) const RIGID: Material = Material {
    density: 500.0,
    model: Model::Rigid,
};

/// Cell-centred lattice points of spacing `spacing` filling [lo, lo + size], (n, D) row-major,
/// the last axis fastest.
pub(super) fn block<const D: usize>(lo: Vector<D>, size: Vector<D>, spacing: f64) -> Vec<f64> {
    let counts: [usize; D] = std::array::from_fn(|a| (size[a] / spacing).round() as usize);
    let total: usize = counts.iter().product();
    let mut out = Vec::with_capacity(total * D);
    for k in 0..total {
        let mut rest = k;
        let mut point = [0.0; D];
        for a in (0..D).rev() {
            point[a] = lo[a] + ((rest % counts[a]) as f64 + 0.5) * spacing;
            rest /= counts[a];
        }
        out.extend(point);
    }
    out
}

/// A run with every frame on all threads.
pub(super) fn run<const D: usize>(
    s: &Settings<D>,
    materials: &[Material],
    x: &[f64],
    material: &[u32],
    volume: f64,
    frames: usize,
) -> Result<Output>
where
    Dim<D>: Space<D>,
{
    let v = vec![0.0; x.len()];
    simulate(s, materials, x, &v, material, volume, frames, |_, _| {
        Ok(Threads::All)
    })
}

/// The mean of coordinate `axis` of the particles `which` in frame `f` of `out`.
pub(super) fn mean<const D: usize>(out: &Output, f: usize, which: &[usize], axis: usize) -> f64 {
    let n = out.positions.len() / D / (out.seconds.len() + 1);
    which
        .iter()
        .map(|&i| out.positions[(f * n + i) * D + axis] as f64)
        .sum::<f64>()
        / which.len() as f64
}

/// The largest relative change of a pairwise distance among `which` between two states.
pub(super) fn shape_change<const D: usize>(
    a: &[Vector<D>],
    b: &[Vector<D>],
    which: &[usize],
) -> f64 {
    let distance = |x: &[Vector<D>], p: usize, q: usize| {
        (0..D)
            .map(|k| (x[p][k] - x[q][k]).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    let mut worst = 0.0f64;
    for (k, &p) in which.iter().enumerate() {
        for &q in &which[k + 1..] {
            let d0 = distance(a, p, q);
            worst = worst.max((distance(b, p, q) - d0).abs() / d0);
        }
    }
    worst
}

/// A scene built block by block on a lattice of one spacing (particle volume spacing^D); every
/// block is its own entry of materials, so every Rigid block is its own body.
pub(super) struct Scene<const D: usize> {
    pub s: Settings<D>,
    pub spacing: f64,
    pub materials: Vec<Material>,
    pub x: Vec<f64>,
    pub v: Vec<f64>,
    pub material: Vec<u32>,
}

impl<const D: usize> Scene<D>
where
    Dim<D>: Space<D>,
{
    pub fn new(s: Settings<D>, spacing: f64) -> Self {
        Scene {
            s,
            spacing,
            materials: vec![],
            x: vec![],
            v: vec![],
            material: vec![],
        }
    }

    /// Adds a block; returns the indices of its particles.
    pub fn add(&mut self, m: Material, lo: Vector<D>, size: Vector<D>, v: Vector<D>) -> Vec<usize> {
        let first = self.material.len();
        let points = block(lo, size, self.spacing);
        let n = points.len() / D;
        self.x.extend(points);
        for _ in 0..n {
            self.v.extend(v);
            self.material.push(self.materials.len() as u32);
        }
        self.materials.push(m);
        (first..first + n).collect()
    }

    pub fn volume(&self) -> f64 {
        self.spacing.powi(D as i32)
    }

    pub fn run(&self, frames: usize) -> Result<Output> {
        let (s, m, v) = (&self.s, &self.materials, self.volume());
        simulate(s, m, &self.x, &self.v, &self.material, v, frames, |_, _| {
            Ok(Threads::All)
        })
    }

    /// Runs on the f64 state (the output is f32), calling `each(frame, positions, velocities)`
    /// after every frame.
    pub fn run_state(
        &self,
        frames: usize,
        mut each: impl FnMut(usize, &[Vector<D>], &[Vector<D>]),
    ) {
        let (s, m, volume) = (&self.s, &self.materials, self.volume());
        check_inputs(s, m, &self.x, &self.v, &self.material, volume).unwrap();
        let mut sim = Mpm::new(s, m, &self.x, &self.v, &self.material, volume);
        for frame in 1..frames {
            sim.advance_frame(s.gravity_of(frame - 1)).unwrap();
            each(frame, &sim.x, &sim.v);
        }
    }

    pub fn start(&self) -> Vec<Vector<D>> {
        self.x
            .chunks(D)
            .map(|p| std::array::from_fn(|a| p[a]))
            .collect()
    }
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
        let (u, sigma, v) = <Dim<2>>::svd(&f);
        let back = mul(
            &[
                [u[0][0] * sigma[0], u[0][1] * sigma[1]],
                [u[1][0] * sigma[0], u[1][1] * sigma[1]],
            ],
            &transpose(v),
        );
        assert!(close(back, f, 1e-12), "{f:?} -> {back:?}");
        assert!(close(
            mul(&u, &transpose(u)),
            [[1.0, 0.0], [0.0, 1.0]],
            1e-12
        ));
        assert!(sigma[0] >= sigma[1].abs() - 1e-12);
    }
}

#[test]
fn return_mappings_respect_their_yield_surfaces() {
    use super::constitutive::drucker_prager;
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

#[test]
fn free_fall_drops_by_g_dt_squared_per_frame_squared() {
    let s: Settings = Settings::default();
    let x = block([0.4, 0.6], [0.1, 0.1], 0.01);
    let n = x.len() / 2;
    let out = run(&s, &[WATER], &x, &vec![0; n], 1e-4, 11).unwrap();
    let all: Vec<usize> = (0..n).collect();
    let g = -9.81 * s.frame_dt * s.frame_dt;
    for f in 2..11 {
        let acc = mean::<2>(&out, f, &all, 1) - 2.0 * mean::<2>(&out, f - 1, &all, 1)
            + mean::<2>(&out, f - 2, &all, 1);
        assert!((acc - g).abs() < 1e-3 * g.abs(), "frame {f}: {acc} vs {g}");
    }
}

#[test]
fn results_do_not_depend_on_the_thread_count() {
    let s: Settings = Settings::default();
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
                &[SAND],
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
    let s: Settings = Settings::default();
    let water = [WATER];
    let x = vec![0.5, 0.5];
    let err = run(&s, &water, &x, &[1], 1e-4, 2).unwrap_err();
    assert!(err.to_string().contains("material[0] = 1"), "{err}");
    let err = run(&s, &water, &[0.0, 0.5], &[0], 1e-4, 2).unwrap_err();
    assert!(
        err.to_string().contains("outside the simulation domain"),
        "{err}"
    );
    let tight: Settings = Settings {
        max_substeps: 2,
        ..Settings::default()
    };
    let err = run(&tight, &water, &x, &[0], 1e-4, 2).unwrap_err();
    assert!(
        err.to_string()
            .contains("frame 1: more than max_substeps = 2"),
        "{err}"
    );
}

/// Per-frame gravity equal to the constant one is the constant-gravity run to the bit (the
/// substeps read the frame's row where they read `gravity`), in 2D with a wall-bound block
/// thrown at a wall and a rigid body; a row that changes is what the frame falls by.
#[test]
fn frame_gravity_equal_to_gravity_is_the_same_run_and_each_row_drives_its_frame() {
    let s: Settings = Settings {
        grid: 32,
        ..Settings::default()
    };
    let mut scene = Scene::new(s.clone(), 1.0 / 64.0);
    scene.add(WATER, [0.1, 0.1], [0.3, 0.15], [-1.0, 0.5]);
    scene.add(RIGID, [0.6, 0.3], [0.125, 0.125], [0.5, 0.0]);
    let frames = 30;
    let constant = scene.run(frames).unwrap();
    scene.s.frame_gravity = Some(vec![s.gravity; frames - 1]);
    let per_frame = scene.run(frames).unwrap();
    assert_eq!(constant.positions, per_frame.positions);
    assert_eq!(constant.substeps, per_frame.substeps);

    // Free fall (a block far from the walls): frame k -> k + 1 changes the mean velocity by
    // row k times frame_dt (momentum is conserved by the transfers and the stress, so only
    // gravity changes it), whatever the other rows are.
    let mut free = Scene::new(s.clone(), 1.0 / 64.0);
    free.add(WATER, [0.4, 0.5], [0.1, 0.1], [0.0; 2]);
    let rows: Vec<Vector<2>> = (0..8)
        .map(|k| [3.0 * (k as f64 * 0.7).sin(), -9.81 + k as f64])
        .collect();
    free.s.frame_gravity = Some(rows.clone());
    let mut before = [0.0; 2];
    free.run_state(9, |frame, _, v| {
        let now: Vector<2> =
            std::array::from_fn(|a| v.iter().map(|p| p[a]).sum::<f64>() / v.len() as f64);
        for a in 0..2 {
            let expected = rows[frame - 1][a] * s.frame_dt;
            assert!(
                (now[a] - before[a] - expected).abs() < 1e-12,
                "frame {frame}, axis {a}: {} vs {expected}",
                now[a] - before[a]
            );
        }
        before = now;
    });
}

#[test]
fn bad_frame_gravity_is_refused_by_name() {
    let x = block([0.4, 0.5], [0.05, 0.05], 0.01);
    let n = x.len() / 2;
    let mut s: Settings = Settings {
        frame_gravity: Some(vec![[0.0, -9.81]; 3]),
        ..Settings::default()
    };
    let err = run(&s, &[WATER], &x, &vec![0; n], 1e-4, 5).unwrap_err();
    assert!(
        err.to_string()
            .contains("frame_gravity must have frames - 1 = 4 rows"),
        "{err}"
    );
    assert!(err.to_string().contains("got 3"), "{err}");
    s.frame_gravity = Some(vec![[0.0, -9.81], [f64::NAN, -9.81], [0.0, -9.81]]);
    let err = run(&s, &[WATER], &x, &vec![0; n], 1e-4, 4).unwrap_err();
    assert!(
        matches!(err, Error::NonFinite(_)) && err.to_string().contains("frame_gravity[1, 0] = NaN"),
        "{err}"
    );
}

#[test]
fn coulomb_walls_keep_the_sign_and_lose_mu_times_the_normal_speed() {
    use super::solver::coulomb;
    let mut v = [-2.0, 3.0];
    coulomb(&mut v, 0, 0.5);
    assert_eq!(v, [0.0, 2.0]);
    let mut v = [1.0, -0.3];
    coulomb(&mut v, 1, 0.5);
    assert_eq!(v, [0.85, 0.0]);
    let mut v = [4.0, 0.1];
    coulomb(&mut v, 0, 0.5);
    assert_eq!(v, [0.0, 0.0]);
    // 3D: the tangential vector keeps its direction; its length loses mu |v_n|.
    let mut v = [3.0, -1.0, 4.0];
    coulomb(&mut v, 1, 1.0);
    assert!((v[0] - 2.4).abs() < 1e-15 && v[1] == 0.0 && (v[2] - 3.2).abs() < 1e-15);
}

/// A rigid square falling into a water pool, in 2D: shape kept to round-off on the f64 state,
/// free fall at g before it reaches the water.
#[test]
fn a_rigid_square_keeps_its_shape_and_falls_at_g() {
    let s: Settings = Settings {
        grid: 32,
        ..Settings::default()
    };
    let mut scene = Scene::new(s, 1.0 / 64.0);
    scene.add(WATER, [0.1, 0.1], [0.8, 0.125], [0.0; 2]);
    let body = scene.add(RIGID, [0.4, 0.32], [0.125, 0.125], [0.0; 2]);
    let start = scene.start();
    let mut worst = 0.0f64;
    let mut lowest = f64::INFINITY;
    scene.run_state(100, |_, now, _| {
        worst = worst.max(shape_change(&start, now, &body));
        lowest = lowest.min(
            body.iter()
                .map(|&p| now[p][1])
                .fold(f64::INFINITY, f64::min),
        );
    });
    assert!(
        worst < 1e-9,
        "pairwise distances changed by {worst:e} (relative)"
    );
    assert!(
        lowest < 0.22,
        "the square never reached the water (lowest {lowest})"
    );
    // Free fall: its first frames, before it reaches the water, at g.
    let out = scene.run(8).unwrap();
    let g = -9.81 * scene.s.frame_dt * scene.s.frame_dt;
    for f in 2..8 {
        let acc = mean::<2>(&out, f, &body, 1) - 2.0 * mean::<2>(&out, f - 1, &body, 1)
            + mean::<2>(&out, f - 2, &body, 1);
        assert!((acc - g).abs() < 1e-2 * g.abs(), "frame {f}: {acc} vs {g}");
    }
}
