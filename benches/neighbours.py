"""Radius-graph time per call: gns against scipy's cKDTree and the other peers installed.

    python benches/neighbours.py [--quick]

Cases are uniform points in the unit box with the radius chosen for about 14 neighbours
(self included): 2D r = sqrt(14 / (pi N)), 3D r = cbrt(14 * 3 / (4 pi N)); "clumped" squeezes
half the particles into a box 1/8 as wide per axis (same radius); "far outliers" moves 1% of
them to about 1e6 box lengths away. --quick skips 3D 1M and uses fewer repeats.

Every implementation produces the same thing, the design's output: int64 (2, E) directed edges
(row 0 senders, row 1 receivers) with self-edges, sorted by (receiver, sender). A peer that
lacks a piece gets it in numpy and that time is counted:
- scipy: cKDTree build + query_pairs(r, output_type="ndarray") + symmetrise + self edges + sort.
- sklearn: KDTree build + query_radius (includes self) + concatenate + sort.
- pykdtree: has no radius query; query(k=K, distance_upper_bound=r) with K the largest degree
  (taken from gns's answer, which pykdtree itself cannot know), drop misses, then sort.
  Skipped ("n/a") when N * K would exceed 50M slots.
- vesin: NeighborList(cutoff=r, full_list=True).compute(..., periodic=False) on points padded
  to 3D, box = the unit cell (ignored without periodicity), + self edges + sort.
- matscipy: neighbour_list("ij", cutoff=r, cell=unit cell, pbc=False) on points padded to 3D
  + self edges + sort.
- freud: AABBQuery in a periodic box wide enough that no pair meets through the boundary
  (freud has no pair queries in non-periodic boxes), query(r_max=r, exclude_ii=False) + sort.
The sort is one argsort of receiver * N + sender. Peers run in a forked child each (memory
limit, timeout) so one that blows up on far outliers is reported instead of taking the run down.
Times are medians over repeats; the ratio is peer time / gns time (warm RadiusSearcher,
default threads); ns/edge is per directed edge of the output.
"""

from __future__ import annotations

import os

# OpenBLAS worker threads busy-wait after any numpy call that used them and would take a core
# from gns's threads; no peer's neighbour search uses BLAS, so one BLAS thread is fair to all.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import math
import multiprocessing as mp
import platform
import resource
import signal
import statistics
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata

import gns
import numpy as np
from gns.machine import cpu_name

Edges = np.ndarray  # (2, E) int64
PEER_TIMEOUT = 120.0  # seconds per peer and case
PYKDTREE_MAX_SLOTS = 50_000_000


@dataclass(frozen=True)
class Case:
    name: str
    dim: int
    n: int
    kind: str = "uniform"  # "uniform", "clumped" or "outliers"
    big: bool = False  # skipped with --quick

    def radius(self) -> float:
        if self.dim == 2:
            return math.sqrt(14 / (math.pi * self.n))
        return (14 * 3 / (4 * math.pi * self.n)) ** (1 / 3)

    def positions(self) -> np.ndarray:
        rng = np.random.default_rng(12345)
        x = rng.random((self.n, self.dim))
        if self.kind == "clumped":
            half = self.n // 2
            x[:half] = 0.4 + x[:half] / 8
        elif self.kind == "outliers":
            far = rng.choice(self.n, size=self.n // 100, replace=False)
            x[far] = 1e6 * (2 * rng.random((len(far), self.dim)) - 1)
        return x


CASES = [
    Case("2D 1.1k", 2, 1100),
    Case("2D 10k", 2, 10_000),
    Case("3D 20k", 3, 20_000),
    Case("3D 1M", 3, 1_000_000, big=True),
    Case("2D 10k clumped", 2, 10_000, "clumped"),
    Case("3D 20k clumped", 3, 20_000, "clumped"),
    Case("2D 10k far outliers", 2, 10_000, "outliers"),
]


# ----------------------------------------------------------------------------- shared finishing


def finish(senders, receivers, n: int, add_self: bool) -> Edges:
    """Self edges if missing, then the design's order: by receiver, then sender."""
    senders = np.asarray(senders, dtype=np.int64)
    receivers = np.asarray(receivers, dtype=np.int64)
    if add_self:
        senders = np.concatenate([senders, np.arange(n)])
        receivers = np.concatenate([receivers, np.arange(n)])
    order = np.argsort(receivers * n + senders)
    return np.stack([senders[order], receivers[order]])


def pad3(x: np.ndarray) -> np.ndarray:
    return x if x.shape[1] == 3 else np.column_stack([x, np.zeros(len(x))])


# ----------------------------------------------------------------------------- peers


def scipy_peer(x: np.ndarray, r: float, max_degree: int) -> Edges:
    from scipy.spatial import cKDTree

    pairs = cKDTree(x).query_pairs(r, output_type="ndarray")
    s = np.concatenate([pairs[:, 0], pairs[:, 1]])
    t = np.concatenate([pairs[:, 1], pairs[:, 0]])
    return finish(s, t, len(x), add_self=True)


def sklearn_peer(x: np.ndarray, r: float, max_degree: int) -> Edges:
    from sklearn.neighbors import KDTree

    ind = KDTree(x).query_radius(x, r)
    counts = np.fromiter((len(a) for a in ind), dtype=np.int64, count=len(ind))
    receivers = np.repeat(np.arange(len(x)), counts)
    return finish(np.concatenate(ind), receivers, len(x), add_self=False)


def pykdtree_peer(x: np.ndarray, r: float, max_degree: int) -> Edges:
    from pykdtree.kdtree import KDTree

    if len(x) * max_degree > PYKDTREE_MAX_SLOTS:
        raise RuntimeError(f"k = {max_degree} nearest for {len(x)} points is too many slots")
    _, idx = KDTree(x).query(x, k=max_degree, distance_upper_bound=r)
    idx = idx.reshape(len(x), max_degree)
    hit = idx < len(x)
    receivers = np.broadcast_to(np.arange(len(x))[:, None], idx.shape)[hit]
    return finish(idx[hit], receivers, len(x), add_self=False)


def vesin_peer(x: np.ndarray, r: float, max_degree: int) -> Edges:
    from vesin import NeighborList

    nl = NeighborList(cutoff=r, full_list=True)
    i, j = nl.compute(points=pad3(x), box=np.eye(3), periodic=False, quantities="ij")
    return finish(j, i, len(x), add_self=True)


def matscipy_peer(x: np.ndarray, r: float, max_degree: int) -> Edges:
    from matscipy.neighbours import neighbour_list

    # The nominal unit cell; its default (shrink-wrapped) cell is singular for flat 2D input.
    i, j = neighbour_list("ij", positions=pad3(x), cutoff=r, cell=np.eye(3), pbc=[False] * 3)
    return finish(j, i, len(x), add_self=True)


def freud_peer(x: np.ndarray, r: float, max_degree: int) -> Edges:
    import freud

    # freud does not implement pair queries in a non-periodic box: use a periodic one wide
    # enough that no pair can meet through the boundary.
    lo, hi = x.min(axis=0), x.max(axis=0)
    centre = (lo + hi) / 2
    width = float((hi - lo).max()) * 1.01 + 4 * r
    box = freud.box.Box.square(width) if x.shape[1] == 2 else freud.box.Box.cube(width)
    points = pad3(x - centre)
    query = freud.locality.AABBQuery(box, points)
    nlist = query.query(points, {"r_max": r, "exclude_ii": False}).toNeighborList()
    return finish(nlist.point_indices, nlist.query_point_indices, len(x), add_self=False)


PEERS: dict[str, Callable[[np.ndarray, float, int], Edges]] = {
    "scipy": scipy_peer,
    "sklearn": sklearn_peer,
    "pykdtree": pykdtree_peer,
    "vesin": vesin_peer,
    "matscipy": matscipy_peer,
    "freud": freud_peer,
}
DISTRIBUTIONS = {
    "scipy": "scipy",
    "sklearn": "scikit-learn",
    "pykdtree": "pykdtree",
    "vesin": "vesin",
    "matscipy": "matscipy",
    "freud": "freud-analysis",
}


# ----------------------------------------------------------------------------- timing


def measure(fn: Callable[[], object], repeats: int, budget: float) -> float:
    """Median seconds per call. The first call warms up (buffers, caches) and is only counted
    when it alone takes over half the budget; then up to `repeats` calls within the budget."""
    start = time.perf_counter()
    fn()
    first = time.perf_counter() - start
    if first > budget / 2:
        return first
    times: list[float] = []
    deadline = time.perf_counter() + budget
    while len(times) < repeats and (not times or time.perf_counter() < deadline):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _peer_child(conn, name, x, r, max_degree, repeats, budget):
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        limit = int(total * 0.6)
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
        fn = PEERS[name]
        edges = fn(x, r, max_degree)
        seconds = measure(lambda: fn(x, r, max_degree), repeats, budget)
        conn.send(("ok", seconds, edges.shape[1]))
    except BaseException as e:  # noqa: BLE001 - any failure becomes a table entry
        last = traceback.format_exception_only(type(e), e)[-1].strip()
        conn.send(("error", _short(last), 0))
    finally:
        conn.close()


def _short(text: str, width: int = 60) -> str:
    text = " ".join(text.split())
    return text if len(text) <= width else text[: width - 3] + "..."


def run_peer(name, x, r, max_degree, repeats, budget):
    """(seconds, edge count) or an 'n/a (reason)' string."""
    ctx = mp.get_context("fork")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_peer_child, args=(child, name, x, r, max_degree, repeats, budget))
    proc.start()
    child.close()
    try:
        if not parent.poll(PEER_TIMEOUT):
            proc.kill()
            return f"n/a (timeout > {PEER_TIMEOUT:.0f} s)"
        status, value, count = parent.recv()
    except EOFError:
        status, value, count = "error", None, 0
    finally:
        proc.join(5)
        if proc.is_alive():
            proc.kill()
            proc.join()
    if status == "ok":
        return value, count
    if value is None:
        code = proc.exitcode
        if code is not None and code < 0:
            value = f"crashed: {signal.Signals(-code).name}"
        else:
            value = f"child died, exit code {code}"
    return f"n/a ({value})"


def peer_available(name: str) -> str | None:
    """None if the peer imports, else the reason."""
    module = {"sklearn": "sklearn.neighbors", "pykdtree": "pykdtree.kdtree"}.get(name, name)
    try:
        __import__(module)
    except Exception as e:  # noqa: BLE001
        return _short(f"{type(e).__name__}: {e}")
    return None


# ----------------------------------------------------------------------------- report


def machine() -> str:
    cpu = cpu_name()
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return f"{cpu}, {os.cpu_count()} logical cores ({affinity} usable), {platform.platform()}"


def versions() -> str:
    out = [f"python {platform.python_version()}", f"numpy {np.__version__}"]
    out.append(f"gns {getattr(gns, '__version__', '?')}")
    for name, dist in DISTRIBUTIONS.items():
        try:
            out.append(f"{name} {metadata.version(dist)}")
        except metadata.PackageNotFoundError:
            out.append(f"{name} (not installed)")
    return ", ".join(out)


def fmt_ms(seconds: float) -> str:
    ms = seconds * 1e3
    return f"{ms:.3f}" if ms < 1 else f"{ms:.2f}" if ms < 100 else f"{ms:.0f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="skip 3D 1M, fewer repeats")
    args = parser.parse_args()
    repeats, budget = (7, 1.0) if args.quick else (21, 3.0)

    print(f"machine: {machine()}")
    print(f"versions: {versions()}")
    threads = os.environ.get("RAYON_NUM_THREADS", "all cores")
    print(f"gns default pool: {threads}; mode: {'quick' if args.quick else 'full'}")
    print()

    missing = {name: peer_available(name) for name in PEERS}
    header = ["case", "N", "edges", "gns ms", "ns/edge", "gns 1 thread ms", "ns/edge", "agrees"]
    header += [f"{name} ms (x gns)" for name in PEERS]
    rows = []
    searcher = gns.RadiusSearcher()
    single = gns.RadiusSearcher(num_threads=1)
    for case in CASES:
        if case.big and args.quick:
            continue
        x, r = case.positions(), case.radius()
        reps, case_budget = (3, budget * 5) if case.big else (repeats, budget)
        edges = searcher(x, r)
        count = edges.shape[1]
        t_gns = measure(lambda x=x, r=r: searcher(x, r), reps, case_budget)
        t_one = measure(lambda x=x, r=r: single(x, r), reps, case_budget)
        max_degree = int(np.bincount(edges[1], minlength=len(x)).max())
        row = [case.name, f"{case.n:,}", f"{count:,}"]
        row += [fmt_ms(t_gns), f"{t_gns / count * 1e9:.2f}"]
        row += [fmt_ms(t_one), f"{t_one / count * 1e9:.2f}"]
        agrees = "?"
        cells = []
        for name in PEERS:
            if missing[name]:
                cells.append(f"n/a ({missing[name]})")
                continue
            result = run_peer(name, x, r, max_degree, max(2, reps // 2), case_budget)
            if isinstance(result, str):
                cells.append(result)
                if name == "scipy":
                    agrees = "no scipy"
                continue
            seconds, peer_count = result
            cell = f"{fmt_ms(seconds)} ({seconds / t_gns:.1f}x)"
            if peer_count != count:
                cell += f" [{peer_count:,} edges]"
            cells.append(cell)
            if name == "scipy":
                agrees = "yes" if peer_count == count else f"NO ({peer_count:,})"
        rows.append(row + [agrees] + cells)
        print(f"  done {case.name}", flush=True)

    print()
    print("| " + " | ".join(header) + " |")
    print("|" + "|".join("---" for _ in header) + "|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    print()
    print("gns ms: warm gns.RadiusSearcher() (default pool); gns 1 thread: RadiusSearcher(1).")
    print("agrees: gns's edge count equals the scipy pipeline's. A peer cell with [n edges]")
    print("produced a different count (for example an exclusive cut-off). pykdtree: k = largest")
    print("degree from gns's answer (it has no radius query), distance_upper_bound = r.")


if __name__ == "__main__":
    main()
