//! The Python binding `gns._core`: converts arrays, releases the GIL around every kernel and
//! maps every error to ValueError. No logic lives here; `python/gns/ops.py` fixes dtypes and
//! contiguity before calling in, so this layer can be strict.

use crate::graph::{GraphOptions, Method, Searcher, DEFAULT_MAX_EDGES};
use crate::{euler_step as euler, mpm, walls, Error, Obstacle, Real};
use numpy::{
    Element, PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyTuple;

fn to_py(e: Error) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// A float32 or float64 (N, D) C-contiguous array.
enum Floats<'py> {
    F32(PyReadonlyArray2<'py, f32>),
    F64(PyReadonlyArray2<'py, f64>),
}

impl<'py> Floats<'py> {
    fn extract(name: &str, obj: &Bound<'py, PyAny>) -> PyResult<Self> {
        let floats = if let Ok(a) = obj.cast::<PyArray2<f32>>() {
            Floats::F32(a.readonly())
        } else if let Ok(a) = obj.cast::<PyArray2<f64>>() {
            Floats::F64(a.readonly())
        } else {
            return Err(PyValueError::new_err(format!(
                "{name} must be a 2-D float32 or float64 numpy array, got {}",
                describe(obj)
            )));
        };
        let contiguous = match &floats {
            Floats::F32(a) => a.is_c_contiguous(),
            Floats::F64(a) => a.is_c_contiguous(),
        };
        if !contiguous {
            return Err(PyValueError::new_err(format!(
                "{name} must be C-contiguous (use gns.ops, which converts)"
            )));
        }
        Ok(floats)
    }

    fn dim(&self) -> usize {
        match self {
            Floats::F32(a) => a.shape()[1],
            Floats::F64(a) => a.shape()[1],
        }
    }
}

fn describe(obj: &Bound<'_, PyAny>) -> String {
    match obj
        .getattr("dtype")
        .and_then(|d| d.str().map(|s| s.to_string()))
    {
        Ok(dtype) => {
            let ndim = obj
                .getattr("ndim")
                .map(|n| n.to_string())
                .unwrap_or_default();
            format!("a {ndim}-D array of {dtype}")
        }
        Err(_) => obj
            .get_type()
            .name()
            .map(|n| n.to_string())
            .unwrap_or_default(),
    }
}

fn slice<'a, T: Element>(a: &'a PyReadonlyArray2<'_, T>) -> PyResult<&'a [T]> {
    a.as_slice()
        .map_err(|e| PyValueError::new_err(format!("array is not contiguous: {e}")))
}

fn matrix<T: Element>(
    py: Python<'_>,
    values: Vec<T>,
    rows: usize,
    cols: usize,
) -> PyResult<Py<PyAny>> {
    debug_assert_eq!(values.len(), rows * cols);
    Ok(PyArray1::from_vec(py, values)
        .reshape([rows, cols])?
        .into_any()
        .unbind())
}

/// Runs both passes of a search and hands the result over as numpy arrays without copying.
fn search<'py, T: Real + Element>(
    py: Python<'py>,
    searcher: &mut Searcher,
    positions: &PyReadonlyArray2<'py, T>,
    n_node: Option<&[i64]>,
    opts: &GraphOptions,
    want_shifts: bool,
) -> PyResult<Py<PyAny>> {
    let pos = slice(positions)?;
    let dim = positions.shape()[1];
    let e = py
        .detach(|| searcher.count(pos, dim, n_node, opts, want_shifts))
        .map_err(to_py)?;
    // SAFETY: fill() writes every element before Python sees the arrays.
    let edges = unsafe { PyArray2::<i64>::new(py, [2, e], false) };
    let shifts = want_shifts.then(|| unsafe { PyArray2::<i32>::new(py, [e, dim], false) });
    {
        let mut edges_rw = edges.readwrite();
        let (senders, receivers) = edges_rw.as_slice_mut()?.split_at_mut(e);
        let mut shifts_rw = shifts.as_ref().map(|a| a.readwrite());
        let shifts_out = match shifts_rw.as_mut() {
            Some(w) => Some(w.as_slice_mut()?),
            None => None,
        };
        py.detach(|| searcher.fill(senders, receivers, shifts_out))
            .map_err(to_py)?;
    }
    Ok(match shifts {
        None => edges.into_any().unbind(),
        Some(s) => PyTuple::new(py, [edges.into_any(), s.into_any()])?
            .into_any()
            .unbind(),
    })
}

#[allow(clippy::too_many_arguments)]
fn search_any(
    py: Python<'_>,
    searcher: &mut Searcher,
    positions: &Bound<'_, PyAny>,
    radius: f64,
    n_node: Option<PyReadonlyArray1<'_, i64>>,
    self_edges: bool,
    box_lengths: Option<Vec<f64>>,
    periodic: Option<Vec<bool>>,
    max_edges: Option<u64>,
    method: &str,
    return_shifts: bool,
) -> PyResult<Py<PyAny>> {
    let floats = Floats::extract("positions", positions)?;
    let opts = GraphOptions {
        radius,
        self_edges,
        box_lengths,
        periodic: periodic.unwrap_or_default(),
        max_edges: max_edges.unwrap_or(DEFAULT_MAX_EDGES),
        method: method.parse::<Method>().map_err(to_py)?,
    };
    if return_shifts && opts.box_lengths.is_none() {
        return Err(PyValueError::new_err(
            "return_shifts needs a box: shifts count box lengths",
        ));
    }
    let n_node_slice = match &n_node {
        Some(a) => Some(
            a.as_slice()
                .map_err(|e| PyValueError::new_err(format!("n_node must be contiguous: {e}")))?,
        ),
        None => None,
    };
    match &floats {
        Floats::F32(a) => search(py, searcher, a, n_node_slice, &opts, return_shifts),
        Floats::F64(a) => search(py, searcher, a, n_node_slice, &opts, return_shifts),
    }
}

/// radius_graph(positions, radius, *, n_node=None, self_edges=True, box=None, periodic=None,
/// max_edges=None, method="cells", return_shifts=False)
#[pyfunction]
#[pyo3(signature = (positions, radius, *, n_node=None, self_edges=true, r#box=None,
                    periodic=None, max_edges=None, method="cells", return_shifts=false))]
#[allow(clippy::too_many_arguments)]
fn radius_graph(
    py: Python<'_>,
    positions: &Bound<'_, PyAny>,
    radius: f64,
    n_node: Option<PyReadonlyArray1<'_, i64>>,
    self_edges: bool,
    r#box: Option<Vec<f64>>,
    periodic: Option<Vec<bool>>,
    max_edges: Option<u64>,
    method: &str,
    return_shifts: bool,
) -> PyResult<Py<PyAny>> {
    search_any(
        py,
        &mut Searcher::default(),
        positions,
        radius,
        n_node,
        self_edges,
        r#box,
        periodic,
        max_edges,
        method,
        return_shifts,
    )
}

/// A radius-graph searcher that keeps its buffers (and optionally its own thread pool).
#[pyclass(module = "gns._core", name = "RadiusSearcher")]
struct PySearcher {
    inner: Searcher,
    #[pyo3(get)]
    num_threads: Option<usize>,
}

#[pymethods]
impl PySearcher {
    #[new]
    #[pyo3(signature = (num_threads=None))]
    fn new(num_threads: Option<usize>) -> PyResult<Self> {
        Ok(PySearcher {
            inner: Searcher::new(num_threads).map_err(to_py)?,
            num_threads,
        })
    }

    #[pyo3(signature = (positions, radius, *, n_node=None, self_edges=true, r#box=None,
                        periodic=None, max_edges=None, method="cells", return_shifts=false))]
    #[allow(clippy::too_many_arguments)]
    fn search(
        &mut self,
        py: Python<'_>,
        positions: &Bound<'_, PyAny>,
        radius: f64,
        n_node: Option<PyReadonlyArray1<'_, i64>>,
        self_edges: bool,
        r#box: Option<Vec<f64>>,
        periodic: Option<Vec<bool>>,
        max_edges: Option<u64>,
        method: &str,
        return_shifts: bool,
    ) -> PyResult<Py<PyAny>> {
        search_any(
            py,
            &mut self.inner,
            positions,
            radius,
            n_node,
            self_edges,
            r#box,
            periodic,
            max_edges,
            method,
            return_shifts,
        )
    }
}

fn floats_out<'py, T: Real + Element>(
    py: Python<'py>,
    a: &PyReadonlyArray2<'py, T>,
    cols_per_dim: usize,
    f: impl FnOnce(&[T], usize) -> crate::Result<Vec<T>> + Send,
) -> PyResult<Py<PyAny>> {
    let x = slice(a)?;
    let dim = a.shape()[1];
    let out = py.detach(|| f(x, dim)).map_err(to_py)?;
    // Rows from the input, not the output: zero obstacles still give N rows of zero width.
    matrix(py, out, x.len() / dim.max(1), cols_per_dim)
}

/// wall_features(positions, bounds, radius, clip=1.0) -> (N, 2 D)
#[pyfunction]
#[pyo3(signature = (positions, bounds, radius, clip=1.0))]
fn wall_features(
    py: Python<'_>,
    positions: &Bound<'_, PyAny>,
    bounds: PyReadonlyArray2<'_, f64>,
    radius: f64,
    clip: f64,
) -> PyResult<Py<PyAny>> {
    let floats = Floats::extract("positions", positions)?;
    let dim = floats.dim();
    if bounds.shape() != [dim, 2] {
        return Err(PyValueError::new_err(format!(
            "bounds must have shape ({dim}, 2), got {:?}",
            bounds.shape()
        )));
    }
    let b = slice(&bounds)?;
    match &floats {
        Floats::F32(a) => floats_out(py, a, 2 * dim, |x, d| {
            walls::wall_features(x, d, b, radius, clip)
        }),
        Floats::F64(a) => floats_out(py, a, 2 * dim, |x, d| {
            walls::wall_features(x, d, b, radius, clip)
        }),
    }
}

/// A static obstacle (parry shape) for obstacle_features.
#[pyclass(module = "gns._core", name = "Obstacle", frozen)]
struct PyObstacle {
    inner: Obstacle,
    kind: &'static str,
}

#[pymethods]
impl PyObstacle {
    /// A 2D polyline through vertices (K, 2); closed=True joins the last vertex to the first.
    #[staticmethod]
    #[pyo3(signature = (vertices, closed=false))]
    fn polyline(vertices: PyReadonlyArray2<'_, f64>, closed: bool) -> PyResult<Self> {
        if vertices.shape()[1] != 2 {
            return Err(PyValueError::new_err(format!(
                "polyline vertices must have shape (K, 2), got {:?}",
                vertices.shape()
            )));
        }
        Ok(PyObstacle {
            inner: Obstacle::polyline(slice(&vertices)?, closed).map_err(to_py)?,
            kind: "polyline",
        })
    }

    /// An axis-aligned box (2D or 3D) from its centre and half extents.
    #[staticmethod]
    fn cuboid(center: Vec<f64>, half_extents: Vec<f64>) -> PyResult<Self> {
        Ok(PyObstacle {
            inner: Obstacle::cuboid(&center, &half_extents).map_err(to_py)?,
            kind: "cuboid",
        })
    }

    /// A 3D triangle mesh from vertices (V, 3) and triangles (T, 3) of vertex indices.
    #[staticmethod]
    fn trimesh(
        vertices: PyReadonlyArray2<'_, f64>,
        triangles: PyReadonlyArray2<'_, u32>,
    ) -> PyResult<Self> {
        if vertices.shape()[1] != 3 || triangles.shape()[1] != 3 {
            return Err(PyValueError::new_err(format!(
                "trimesh needs vertices (V, 3) and triangles (T, 3), got {:?} and {:?}",
                vertices.shape(),
                triangles.shape()
            )));
        }
        let tris = triangles
            .as_slice()
            .map_err(|e| PyValueError::new_err(format!("triangles: {e}")))?;
        Ok(PyObstacle {
            inner: Obstacle::trimesh(slice(&vertices)?, tris).map_err(to_py)?,
            kind: "trimesh",
        })
    }

    #[getter]
    fn dim(&self) -> usize {
        self.inner.dim()
    }

    fn __repr__(&self) -> String {
        format!("Obstacle.{}({}D)", self.kind, self.inner.dim())
    }
}

/// obstacle_features(positions, obstacles, radius) -> (N, K D)
#[pyfunction]
fn obstacle_features(
    py: Python<'_>,
    positions: &Bound<'_, PyAny>,
    obstacles: Vec<PyRef<'_, PyObstacle>>,
    radius: f64,
) -> PyResult<Py<PyAny>> {
    let floats = Floats::extract("positions", positions)?;
    let shapes: Vec<&Obstacle> = obstacles.iter().map(|o| &o.inner).collect();
    let width = shapes.len() * floats.dim();
    let shapes = &shapes;
    match &floats {
        Floats::F32(a) => floats_out(py, a, width, |x, d| {
            walls::obstacle_features(x, d, shapes, radius)
        }),
        Floats::F64(a) => floats_out(py, a, width, |x, d| {
            walls::obstacle_features(x, d, shapes, radius)
        }),
    }
}

/// nearest_obstacle_features(positions, obstacles, radius, clip) -> (N, D)
#[pyfunction]
fn nearest_obstacle_features(
    py: Python<'_>,
    positions: &Bound<'_, PyAny>,
    obstacles: Vec<PyRef<'_, PyObstacle>>,
    radius: f64,
    clip: f64,
) -> PyResult<Py<PyAny>> {
    let floats = Floats::extract("positions", positions)?;
    let shapes: Vec<&Obstacle> = obstacles.iter().map(|o| &o.inner).collect();
    let width = floats.dim();
    let shapes = &shapes;
    match &floats {
        Floats::F32(a) => floats_out(py, a, width, |x, d| {
            walls::nearest_obstacle_features(x, d, shapes, radius, clip)
        }),
        Floats::F64(a) => floats_out(py, a, width, |x, d| {
            walls::nearest_obstacle_features(x, d, shapes, radius, clip)
        }),
    }
}

fn euler_typed<'py, T: Real + Element>(
    py: Python<'py>,
    x: &PyReadonlyArray2<'py, T>,
    v: &Bound<'py, PyAny>,
    a: &Bound<'py, PyAny>,
    dt: f64,
) -> PyResult<Py<PyAny>> {
    let same = |name: &str, o: &Bound<'py, PyAny>| -> PyResult<PyReadonlyArray2<'py, T>> {
        o.cast::<PyArray2<T>>()
            .map(|arr| arr.readonly())
            .map_err(|_| {
                PyValueError::new_err(format!(
                    "{name} must be a 2-D array of the position's dtype, got {}",
                    describe(o)
                ))
            })
    };
    let (v, a) = (same("velocity", v)?, same("acceleration", a)?);
    for (name, arr) in [("velocity", &v), ("acceleration", &a)] {
        if arr.shape() != x.shape() {
            return Err(PyValueError::new_err(format!(
                "{name} has shape {:?} but position has {:?}; they must match",
                arr.shape(),
                x.shape()
            )));
        }
    }
    let (xs, vs, as_) = (slice(x)?, slice(&v)?, slice(&a)?);
    let dim = x.shape()[1];
    let (nx, nv) = py.detach(|| euler(xs, vs, as_, dim, dt)).map_err(to_py)?;
    let rows = xs.len() / dim.max(1);
    let pair = [matrix(py, nx, rows, dim)?, matrix(py, nv, rows, dim)?];
    Ok(PyTuple::new(py, pair)?.into_any().unbind())
}

/// euler_step(position, velocity, acceleration, dt=1.0) -> (new_position, new_velocity)
#[pyfunction]
#[pyo3(signature = (position, velocity, acceleration, dt=1.0))]
fn euler_step(
    py: Python<'_>,
    position: &Bound<'_, PyAny>,
    velocity: &Bound<'_, PyAny>,
    acceleration: &Bound<'_, PyAny>,
    dt: f64,
) -> PyResult<Py<PyAny>> {
    match &Floats::extract("position", position)? {
        Floats::F32(x) => euler_typed(py, x, velocity, acceleration, dt),
        Floats::F64(x) => euler_typed(py, x, velocity, acceleration, dt),
    }
}

/// One material from Python: (model, density, parameters) with model "water" (bulk_modulus),
/// "sand" (youngs_modulus, poisson_ratio, friction_angle_deg), "goop" (youngs_modulus,
/// poisson_ratio, yield_stress), "obstacle" (none) or "rigid" (none: one rigid body).
fn mpm_material(
    index: usize,
    (model, density, params): (String, f64, Vec<f64>),
) -> PyResult<mpm::Material> {
    let want = match model.as_str() {
        "water" => 1,
        "sand" | "goop" => 3,
        "obstacle" | "rigid" => 0,
        other => {
            return Err(PyValueError::new_err(format!(
                "materials[{index}]: model must be 'water', 'sand', 'goop', 'obstacle' or \
                 'rigid', got {other:?}"
            )))
        }
    };
    if params.len() != want {
        return Err(PyValueError::new_err(format!(
            "materials[{index}]: {model} takes {want} parameters, got {}",
            params.len()
        )));
    }
    let model = match model.as_str() {
        "water" => mpm::Model::Water {
            bulk_modulus: params[0],
        },
        "sand" => mpm::Model::Sand {
            youngs_modulus: params[0],
            poisson_ratio: params[1],
            friction_angle_deg: params[2],
        },
        "goop" => mpm::Model::Goop {
            youngs_modulus: params[0],
            poisson_ratio: params[1],
            yield_stress: params[2],
        },
        "rigid" => mpm::Model::Rigid,
        _ => mpm::Model::Obstacle,
    };
    Ok(mpm::Material { density, model })
}

/// mpm_simulate(positions, velocities, material, materials, particle_volume, frames, *, grid,
/// bounds, wall, wall_friction, gravity, frame_dt, cfl, max_substeps, progress=None,
/// threads=None, frame_gravity=None) -> (positions (frames, N, D) float32, seconds
/// (frames - 1,), substeps (frames - 1,)). D (2 or 3) is the width of positions; bounds holds
/// D pairs [lo, hi] and gravity D values. progress(frame) after every frame; threads(seconds)
/// after every frame, returning 1 to run the next frame on one thread, anything else for all.
/// frame_gravity: (frames - 1, D) float array whose row k replaces gravity for every substep
/// of frame k -> k + 1 (a shaken container simulated in its own frame).
#[pyfunction]
#[pyo3(signature = (positions, velocities, material, materials, particle_volume, frames, *,
                    grid, bounds, wall, wall_friction, gravity, frame_dt, cfl, max_substeps,
                    progress=None, threads=None, frame_gravity=None))]
#[allow(clippy::too_many_arguments)]
fn mpm_simulate(
    py: Python<'_>,
    positions: PyReadonlyArray2<'_, f64>,
    velocities: PyReadonlyArray2<'_, f64>,
    material: PyReadonlyArray1<'_, u32>,
    materials: Vec<(String, f64, Vec<f64>)>,
    particle_volume: f64,
    frames: usize,
    grid: usize,
    bounds: Vec<Vec<f64>>,
    wall: &str,
    wall_friction: f64,
    gravity: Vec<f64>,
    frame_dt: f64,
    cfl: f64,
    max_substeps: usize,
    progress: Option<Py<PyAny>>,
    threads: Option<Py<PyAny>>,
    frame_gravity: Option<Bound<'_, PyAny>>,
) -> PyResult<Py<PyAny>> {
    let materials = materials
        .into_iter()
        .enumerate()
        .map(|(i, m)| mpm_material(i, m))
        .collect::<PyResult<Vec<_>>>()?;
    let wall = match wall {
        "sticky" => mpm::Wall::Sticky,
        "slip" => mpm::Wall::Slip,
        "coulomb" => mpm::Wall::Coulomb(wall_friction),
        other => {
            return Err(PyValueError::new_err(format!(
                "wall must be 'sticky', 'slip' or 'coulomb', got {other:?}"
            )))
        }
    };
    let dim = positions.shape()[1];
    for (name, a) in [("positions", &positions), ("velocities", &velocities)] {
        if !matches!(a.shape()[1], 2 | 3) || a.shape()[1] != dim {
            return Err(PyValueError::new_err(format!(
                "{name} must have shape (N, 2) or (N, 3), positions and velocities alike; got \
                 {:?} and {:?}",
                positions.shape(),
                velocities.shape()
            )));
        }
    }
    let frame_gravity = match &frame_gravity {
        None => None,
        Some(obj) => {
            let rows = Floats::extract("frame_gravity", obj)?;
            let shape = [frames.saturating_sub(1), dim];
            let (got, values) = match &rows {
                Floats::F32(a) => (a.shape(), slice(a)?.iter().map(|&g| g as f64).collect()),
                Floats::F64(a) => (a.shape(), slice(a)?.to_vec()),
            };
            if got != shape {
                return Err(PyValueError::new_err(format!(
                    "frame_gravity must have shape (frames - 1, D) = ({}, {dim}), one row of D \
                     values (the width of positions) per simulated frame; got ({}, {})",
                    shape[0], got[0], got[1]
                )));
            }
            Some(values)
        }
    };
    let run = MpmRun {
        materials,
        wall,
        grid,
        bounds,
        gravity,
        frame_gravity,
        frame_dt,
        cfl,
        max_substeps,
        positions: slice(&positions)?,
        velocities: slice(&velocities)?,
        material: material
            .as_slice()
            .map_err(|e| PyValueError::new_err(format!("material must be contiguous: {e}")))?,
        particle_volume,
        frames,
    };
    match dim {
        2 => run.simulate::<2>(py, progress, threads),
        _ => run.simulate::<3>(py, progress, threads),
    }
}

/// mpm_simulate's inputs, converted; `simulate::<D>` checks the D-sized settings and runs.
struct MpmRun<'a> {
    materials: Vec<mpm::Material>,
    wall: mpm::Wall,
    grid: usize,
    bounds: Vec<Vec<f64>>,
    gravity: Vec<f64>,
    /// (frames - 1, D) row-major, its shape checked.
    frame_gravity: Option<Vec<f64>>,
    frame_dt: f64,
    cfl: f64,
    max_substeps: usize,
    positions: &'a [f64],
    velocities: &'a [f64],
    material: &'a [u32],
    particle_volume: f64,
    frames: usize,
}

impl MpmRun<'_> {
    fn simulate<const D: usize>(
        self,
        py: Python<'_>,
        progress: Option<Py<PyAny>>,
        threads: Option<Py<PyAny>>,
    ) -> PyResult<Py<PyAny>>
    where
        mpm::Dim<D>: mpm::Space<D>,
    {
        let pairs = self.bounds.iter().all(|b| b.len() == 2);
        let bounds: [[f64; 2]; D] = match (pairs, <[Vec<f64>; D]>::try_from(self.bounds.clone())) {
            (true, Ok(b)) => b.map(|pair| [pair[0], pair[1]]),
            _ => {
                return Err(PyValueError::new_err(format!(
                    "bounds must be {D} pairs [lo, hi], one per axis of positions (N, {D}); got \
                     {:?}",
                    self.bounds
                )))
            }
        };
        let gravity = <[f64; D]>::try_from(self.gravity.as_slice()).map_err(|_| {
            PyValueError::new_err(format!(
                "gravity must have {D} values, one per axis of positions (N, {D}); got {:?}",
                self.gravity
            ))
        })?;
        let settings = mpm::Settings::<D> {
            grid: self.grid,
            bounds,
            wall: self.wall,
            gravity,
            frame_gravity: self.frame_gravity.as_ref().map(|values| {
                values
                    .chunks_exact(D)
                    .map(|row| std::array::from_fn(|a| row[a]))
                    .collect()
            }),
            frame_dt: self.frame_dt,
            cfl: self.cfl,
            max_substeps: self.max_substeps,
        };
        let n = self.material.len();
        let frames = self.frames;
        // A Python exception from the progress callback (e.g. KeyboardInterrupt) is re-raised as is.
        let mut raised: Option<PyErr> = None;
        let result = py.detach(|| {
            mpm::simulate(
                &settings,
                &self.materials,
                self.positions,
                self.velocities,
                self.material,
                self.particle_volume,
                frames,
                |frame, seconds| {
                    Python::attach(|py| {
                        let call = match &progress {
                            Some(f) => f.call1(py, (frame,)).map(|_| ()),
                            None => py.check_signals(),
                        };
                        let next = call.and_then(|()| match &threads {
                            Some(f) => f.call1(py, (seconds,))?.extract::<i64>(py),
                            None => Ok(0),
                        });
                        match next {
                            Ok(1) => Ok(mpm::Threads::One),
                            Ok(_) => Ok(mpm::Threads::All),
                            Err(e) => {
                                raised = Some(e);
                                Err(Error::Value("stopped by a callback".into()))
                            }
                        }
                    })
                },
            )
        });
        if let Some(err) = raised {
            return Err(err);
        }
        let out = result.map_err(to_py)?;
        let steps = out.seconds.len();
        let frames_array = PyArray1::from_vec(py, out.positions).reshape([frames, n, D])?;
        let parts = [
            frames_array.into_any(),
            PyArray1::from_vec(py, out.seconds).into_any(),
            PyArray1::from_vec(py, out.substeps).into_any(),
        ];
        debug_assert_eq!(steps + 1, frames);
        Ok(PyTuple::new(py, parts)?.into_any().unbind())
    }
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(radius_graph, m)?)?;
    m.add_function(wrap_pyfunction!(wall_features, m)?)?;
    m.add_function(wrap_pyfunction!(obstacle_features, m)?)?;
    m.add_function(wrap_pyfunction!(nearest_obstacle_features, m)?)?;
    m.add_function(wrap_pyfunction!(euler_step, m)?)?;
    m.add_function(wrap_pyfunction!(mpm_simulate, m)?)?;
    m.add_class::<PySearcher>()?;
    m.add_class::<PyObstacle>()?;
    m.add("DEFAULT_MAX_EDGES", DEFAULT_MAX_EDGES)?;
    Ok(())
}
