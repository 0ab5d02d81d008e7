//! 3D tests against analytic cases, on coarse grids so that each runs in about a second.

use super::constitutive::{drucker_prager, mul, von_mises};
use super::solver::SPLIT_AT;
use super::tests::{mean, shape_change, Scene, RIGID, SAND, WATER};
use super::*;

const GOOP: Material = Material {
    density: 1000.0,
    model: Model::Goop {
        youngs_modulus: 3e3,
        poisson_ratio: 0.35,
        yield_stress: 200.0,
    },
};

fn settings(grid: usize) -> Settings<3> {
    Settings {
        grid,
        ..Settings::default()
    }
}

#[test]
fn the_3d_svd_reconstructs_with_rotations_and_flags_inversion() {
    let cases = [
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        [[1.2, 0.3, -0.1], [-0.1, 0.8, 0.2], [0.05, 0.0, 1.1]],
        [[0.5, -2.0, 0.3], [1.5, 0.7, -0.4], [0.2, 0.1, 0.9]],
        // Inverted (det < 0): a reflection of z.
        [[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -0.5]],
        // Two equal singular values.
        [[2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 0.5]],
    ];
    let det = |m: &Matrix<3>| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    for f in cases {
        let (u, sigma, v) = <Dim<3>>::svd(&f);
        let us: Matrix<3> = std::array::from_fn(|i| std::array::from_fn(|k| u[i][k] * sigma[k]));
        let vt: Matrix<3> = std::array::from_fn(|i| std::array::from_fn(|k| v[k][i]));
        let back = mul(&us, &vt);
        for i in 0..3 {
            for k in 0..3 {
                assert!((back[i][k] - f[i][k]).abs() < 1e-12, "{f:?} -> {back:?}");
            }
        }
        assert!((det(&u) - 1.0).abs() < 1e-12 && (det(&v) - 1.0).abs() < 1e-12);
        assert_eq!(sigma[2] < 0.0, det(&f) < 0.0, "{f:?}: {sigma:?}");
        assert!(sigma[0] >= sigma[1] && sigma[1] >= sigma[2].abs() - 1e-12);
    }
    // NaN in, NaN out: never a hang.
    let (_, sigma, _) = <Dim<3>>::svd(&[[f64::NAN, 0.0, 0.0], [0.0; 3], [0.0; 3]]);
    assert!(sigma.iter().all(|s| s.is_nan()));
}

#[test]
fn the_3d_return_mappings_use_the_3d_deviator() {
    // Inside the cone: untouched; expansion: to the tip, remembered.
    let inside = [-0.01, -0.0101, -0.0099];
    assert_eq!(drucker_prager(inside, 0.0, 1.0, 1.0, 30.0), (inside, 0.0));
    assert_eq!(
        drucker_prager([0.01, 0.0, 0.0], 0.0, 1.0, 1.0, 30.0),
        ([0.0; 3], 0.01)
    );
    // Outside: onto the cone |dev| = -(3 lambda + 2 mu) / (2 mu) tr alpha, trace kept.
    let (lambda, mu) = (2.0, 1.0);
    let eps = [-0.001, -0.08, 0.03];
    let (out, _) = drucker_prager(eps, 0.0, lambda, mu, 30.0);
    assert_ne!(out, eps);
    let tr = out.iter().sum::<f64>();
    assert!((tr - (-0.051)).abs() < 1e-12);
    let dev = out.map(|e| e - tr / 3.0);
    let norm = dev.iter().map(|d| d * d).sum::<f64>().sqrt();
    let sin = 30f64.to_radians().sin();
    let alpha = (2.0f64 / 3.0).sqrt() * 2.0 * sin / (3.0 - sin);
    let radius = -(3.0 * lambda + 2.0 * mu) / (2.0 * mu) * tr * alpha;
    assert!((norm - radius).abs() < 1e-12, "{norm} vs {radius}");
    // von Mises: the deviator capped at yield / (2 mu), the mean kept.
    let vm = von_mises([0.1, -0.1, 0.03], 10.0, 1.0);
    let mean = vm.iter().sum::<f64>() / 3.0;
    let norm = vm.iter().map(|e| (e - mean).powi(2)).sum::<f64>().sqrt();
    assert!((norm - 0.05).abs() < 1e-12 && (mean - 0.01).abs() < 1e-15);
}

/// A water block in the air falls (1/2) g t^2. Symplectic Euler substeps (v += g dt_k, then
/// x += v dt_k) drop it by exactly (1/2) g (t^2 + sum dt_k^2): at least (1/2) g t^2 and, as
/// all but the last substep of a frame of s substeps have the CFL length <= frame_dt / (s - 1),
/// at most (1/2) g t^2 (1 + 1 / ((s_min - 1) frames)). Checked after every frame from the 2nd,
/// to 1e-3 for the f32 output, and the second difference per frame is g frame_dt^2 to 1%.
#[test]
fn a_block_in_the_air_falls_at_g() {
    let mut scene = Scene::new(settings(32), 1.0 / 64.0);
    let stiff = Material {
        density: 1000.0,
        model: Model::Water { bulk_modulus: 1e6 },
    };
    let all = scene.add(stiff, [0.4, 0.6, 0.4], [0.1, 0.1, 0.1], [0.0; 3]);
    let out = scene.run(13).unwrap();
    let y0 = mean::<3>(&out, 0, &all, 1);
    let s_min = *out.substeps.iter().min().unwrap() as f64;
    assert!(s_min >= 5.0, "{:?}", out.substeps);
    let g = 9.81 * scene.s.frame_dt * scene.s.frame_dt;
    for f in 2..13 {
        let t = f as f64 * scene.s.frame_dt;
        let drop = y0 - mean::<3>(&out, f, &all, 1);
        let want = 0.5 * 9.81 * t * t;
        let lag = 1.0 / ((s_min - 1.0) * f as f64);
        assert!(
            drop > want * (1.0 - 1e-3) && drop < want * (1.0 + lag + 1e-3),
            "frame {f}: dropped {drop}, (1/2) g t^2 = {want}"
        );
        let acc = mean::<3>(&out, f, &all, 1) - 2.0 * mean::<3>(&out, f - 1, &all, 1)
            + mean::<3>(&out, f - 2, &all, 1);
        assert!((acc + g).abs() < 1e-2 * g, "frame {f}: {acc} vs {}", -g);
        for axis in [0, 2] {
            let drift = mean::<3>(&out, f, &all, axis) - mean::<3>(&out, 0, &all, axis);
            assert!(drift.abs() < 1e-6, "frame {f}: axis {axis} drifted {drift}");
        }
    }
}

/// Two blocks collide with no gravity, far from the walls: total momentum sum m v is constant
/// to round-off (the quadratic B-spline's sum w (x_i - x_p) = 0 makes the affine and stress
/// terms momentum-free); sand against a rigid cube, so the rigid projection is in the sum.
#[test]
fn momentum_is_conserved_without_walls_and_gravity() {
    let mut scene = Scene::new(
        Settings {
            gravity: [0.0; 3],
            ..settings(32)
        },
        1.0 / 64.0,
    );
    let sand = scene.add(SAND, [0.3, 0.4, 0.4], [0.1, 0.1, 0.1], [2.0, 0.5, 0.0]);
    let cube = scene.add(
        RIGID,
        [0.5, 0.42, 0.42],
        [0.06, 0.06, 0.06],
        [-1.0, 0.0, 0.3],
    );
    let volume = scene.volume();
    let masses: Vec<f64> = scene
        .material
        .iter()
        .map(|&m| scene.materials[m as usize].density * volume)
        .collect();
    let momentum = |v: &[Vector<3>]| -> Vector<3> {
        std::array::from_fn(|a| (0..v.len()).map(|p| masses[p] * v[p][a]).sum())
    };
    let start: Vec<Vector<3>> = scene.v.chunks(3).map(|v| [v[0], v[1], v[2]]).collect();
    let p0 = momentum(&start);
    let scale = p0.iter().map(|p| p.abs()).fold(0.0, f64::max);
    let mut worst = 0.0f64;
    let mut met = f64::INFINITY;
    scene.run_state(40, |_, x, v| {
        let p = momentum(v);
        worst = (0..3).fold(worst, |w, a| w.max((p[a] - p0[a]).abs() / scale));
        let sand_right = sand.iter().map(|&i| x[i][0]).fold(0.0, f64::max);
        let cube_left = cube.iter().map(|&i| x[i][0]).fold(1.0, f64::min);
        met = met.min(cube_left - sand_right);
    });
    assert!(met < 0.02, "the blocks never met (closest {met})");
    assert!(worst < 1e-12, "momentum changed by {worst:e} of its size");
}

/// A sand layer at rest on the floor, wall to wall (a narrower block would slump at its
/// sides), only settles elastically: its centre moves less than a tenth of a cell in 200 frames.
#[test]
fn a_sand_layer_at_rest_stays() {
    let s = Settings {
        bounds: [[0.1, 0.35], [0.1, 0.9], [0.1, 0.35]],
        ..settings(24)
    };
    let dx = 1.0 / 24.0;
    let mut scene = Scene::new(s, dx / 2.0);
    let all = scene.add(SAND, [0.1, 0.1, 0.1], [0.25, 0.125, 0.25], [0.0; 3]);
    let out = scene.run(200).unwrap();
    for f in [50, 100, 199] {
        for axis in 0..3 {
            let drift = mean::<3>(&out, f, &all, axis) - mean::<3>(&out, 0, &all, axis);
            assert!(
                drift.abs() < 0.1 * dx,
                "frame {f}, axis {axis}: moved {drift}"
            );
        }
    }
}

/// A rigid cube dropped into a water pool: its shape (every pairwise distance of its particles)
/// is kept to 1e-9 relative on the f64 state over 150 frames; it falls at g until it nears the
/// water, enters it (its bottom half a cell below the pool's surface, 0.225) and floats
/// (density 500: half the water's).
#[test]
fn a_rigid_cube_keeps_its_shape_in_water_and_falls_at_g() {
    let s = Settings {
        bounds: [[0.1, 0.5], [0.1, 0.9], [0.1, 0.5]],
        ..settings(24)
    };
    let mut scene = Scene::new(s, 1.0 / 48.0);
    scene.add(WATER, [0.1, 0.1, 0.1], [0.4, 0.125, 0.4], [0.0; 3]);
    let cube = scene.add(RIGID, [0.22, 0.35, 0.25], [0.125, 0.125, 0.125], [0.0; 3]);
    let start = scene.start();
    let (mut worst, mut lowest) = (0.0f64, f64::INFINITY);
    scene.run_state(150, |_, x, _| {
        worst = worst.max(shape_change(&start, x, &cube));
        lowest = lowest.min(cube.iter().map(|&p| x[p][1]).fold(f64::INFINITY, f64::min));
    });
    assert!(
        worst < 1e-9,
        "pairwise distances changed by {worst:e} (relative)"
    );
    assert!(
        lowest < 0.205,
        "the cube never entered the water (lowest {lowest})"
    );
    assert!(lowest > 0.15, "the cube sank (lowest {lowest})");
    // Free fall while it is more than 2 cells above the water (MPM bodies meet on the grid,
    // when their particles' 3-cell stencils overlap).
    let out = scene.run(12).unwrap();
    let g = -9.81 * scene.s.frame_dt * scene.s.frame_dt;
    for f in 2..12 {
        let acc = mean::<3>(&out, f, &cube, 1) - 2.0 * mean::<3>(&out, f - 1, &cube, 1)
            + mean::<3>(&out, f - 2, &cube, 1);
        assert!((acc - g).abs() < 1e-2 * g.abs(), "frame {f}: {acc} vs {g}");
    }
}

/// A rigid body put on the floor settles onto the wall's bound (the lattice starts half a
/// spacing above it) and stays there (the wall nodes alone would let it sink a little every
/// substep), and a spinning one keeps its angular velocity.
#[test]
fn rigid_bodies_rest_on_the_floor_and_spin_freely() {
    let s = Settings {
        wall: Wall::Slip,
        ..settings(24)
    };
    let mut scene = Scene::new(s, 1.0 / 48.0);
    let cube = scene.add(RIGID, [0.3, 0.1, 0.3], [0.125, 0.0625, 0.125], [0.0; 3]);
    let out = scene.run(100).unwrap();
    let low = |f: usize| {
        cube.iter()
            .map(|&p| out.positions[(f * cube.len() + p) * 3 + 1])
            .fold(f32::INFINITY, f32::min)
    };
    for f in 50..100 {
        assert!(
            (low(f) - 0.1).abs() < 1e-7,
            "frame {f}: {} -> {}",
            low(0),
            low(f)
        );
    }
    // Spin about y, no gravity: the velocity field of a rigid rotation is kept.
    let mut scene = Scene::new(
        Settings {
            gravity: [0.0; 3],
            ..settings(24)
        },
        1.0 / 48.0,
    );
    let cube = scene.add(RIGID, [0.4, 0.4, 0.4], [0.125, 0.125, 0.125], [0.0; 3]);
    let start = scene.start();
    let centre = [0.4625, 0.4625, 0.4625];
    let omega = 2.0;
    for (p, x) in start.iter().enumerate() {
        // v = omega e_y x r = omega (r_z, 0, -r_x)
        scene.v[3 * p] = omega * (x[2] - centre[2]);
        scene.v[3 * p + 2] = -omega * (x[0] - centre[0]);
    }
    let frames = 40;
    let mut last = vec![];
    scene.run_state(frames, |_, x, _| last = x.to_vec());
    let angle = omega * (frames - 1) as f64 * scene.s.frame_dt;
    let (sin, cos) = angle.sin_cos();
    for &p in &cube {
        let r = [start[p][0] - centre[0], start[p][2] - centre[2]];
        let want = [cos * r[0] + sin * r[1], -sin * r[0] + cos * r[1]];
        let got = [last[p][0] - centre[0], last[p][2] - centre[2]];
        // APIC carries a rigid rotation through the grid exactly (C = W, set at the start),
        // so the body spins on to round-off.
        assert!(
            (got[0] - want[0]).abs() < 1e-12 && (got[1] - want[1]).abs() < 1e-12,
            "particle {p}: {got:?} vs {want:?}"
        );
    }
}

/// Sand, water, goop and a rigid body in 3D, more particles than SPLIT_AT: one thread, two
/// threads and frames alternating between them give the same bits.
#[test]
fn results_do_not_depend_on_the_thread_count_in_3d() {
    let mut scene = Scene::new(settings(24), 1.0 / 48.0);
    scene.add(SAND, [0.1, 0.1, 0.1], [0.25, 0.125, 0.25], [1.0, 0.0, 0.5]);
    scene.add(WATER, [0.5, 0.1, 0.5], [0.2, 0.1, 0.2], [-1.0, 0.0, 0.0]);
    scene.add(GOOP, [0.5, 0.4, 0.2], [0.1, 0.1, 0.1], [0.0, -1.0, 0.0]);
    scene.add(RIGID, [0.2, 0.5, 0.5], [0.1, 0.1, 0.1], [0.5, 0.0, -0.5]);
    assert!(scene.material.len() > SPLIT_AT);
    let run = |threads: usize, alternate: bool| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let (s, m, volume) = (&scene.s, &scene.materials, scene.volume());
            simulate(
                s,
                m,
                &scene.x,
                &scene.v,
                &scene.material,
                volume,
                8,
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
fn bad_3d_input_and_divergence_are_errors() {
    let mut scene = Scene::new(settings(24), 1.0 / 48.0);
    scene.add(WATER, [0.4, 0.4, 0.4], [0.0625, 0.0625, 0.0625], [0.0; 3]);
    scene.v[5] = f64::NAN;
    let err = scene.run(2).unwrap_err().to_string();
    assert!(
        err.contains("velocities[1, 2] = NaN is not finite"),
        "{err}"
    );
    scene.v[5] = 0.0;
    scene.x[4] = 0.99;
    let err = scene.run(2).unwrap_err().to_string();
    assert!(
        err.contains("particle 1 at [0.4104166666666667, 0.99, 0.43125]")
            && err.contains("outside the simulation domain")
            && err.contains("]^3"),
        "{err}"
    );
    scene.x[4] = 0.41;
    scene.s.max_substeps = 1;
    let err = scene.run(2).unwrap_err().to_string();
    assert!(err.contains("frame 1: more than max_substeps = 1"), "{err}");
    // Positions whose length is not a multiple of 3 per particle.
    scene.s.max_substeps = 100;
    scene.x.pop();
    let err = scene.run(2).unwrap_err().to_string();
    assert!(err.contains("must be (N, 3)"), "{err}");
}
