"""Per-trajectory npz folders described by a manifest.json (e.g. the sand2d-taichi dataset).

The folder has no metadata.json: the manifest gives bounds, frame spacing and, per file, the
friction angle and initial velocity. Each trajectory gets the friction angle as a global feature,
the paper's CONTINUOUS setup, represented as tan(friction angle) (the Mohr-Coulomb friction
coefficient; dimensionless, O(1), and what geoelements' material_property uses):

    step_context       (T, 1) float32, tan(angle) repeated on every frame
    material_property  ()     float32, the same tan(angle)

Split, deterministic and independent of file order: trajectories are grouped by friction angle
(ascending, k = 0, 1, ...) and, inside a group, split into "at rest" (zero initial velocity) and
"thrown", each sorted by file name. Per angle, `test` takes the last at-rest and the last thrown
one, `valid` takes the last remaining at-rest one for even k and the last remaining thrown one
for odd k, and `train` takes the rest. For sand2d-taichi (4 angles x (3 at rest + 3 thrown)) that
is train 12 (sand_x0, x1, x3 for 20/35 deg; x0, x1, x2 for 25/40 deg), valid 4 (sand_02, 13, 32,
43) and test 8 (sand_x4, x5). No angle is held out entirely: the data has no 30 degree run, so
30 degrees is the natural unseen angle for a generalisation check.

Statistics are computed on the train split when the folder is opened (cached per process).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gns.data.errors import DatasetError
from gns.data.metadata import Metadata
from gns.data.npz import NpzSource
from gns.data.stats import compute_statistics
from gns.data.trajectory import Trajectory

SPLITS = ("train", "valid", "test")
# Not in the manifest: the paper's 2D connectivity radius, which gives 10-20 neighbours here.
CONNECTIVITY_RADIUS = 0.015

_STATS_CACHE: dict[tuple[str, tuple[int, ...]], Metadata] = {}


def split_entries(entries: Sequence[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Assign manifest entries to train / valid / test by the rule in the module docstring."""
    by_angle: dict[float, list[dict[str, Any]]] = {}
    for entry in entries:
        by_angle.setdefault(float(entry["friction_angle_deg"]), []).append(entry)
    out: dict[str, list[dict[str, Any]]] = {name: [] for name in SPLITS}
    for k, angle in enumerate(sorted(by_angle)):
        group = sorted(by_angle[angle], key=lambda e: str(e["file"]))
        rest = [e for e in group if not any(float(v) for v in e.get("initial_velocity", [0]))]
        thrown = [e for e in group if e not in rest]
        test = [kind.pop() for kind in (rest, thrown) if kind]
        preferred = (rest, thrown) if k % 2 == 0 else (thrown, rest)
        valid = next(([kind.pop()] for kind in preferred if kind), [])
        out["test"] += test
        out["valid"] += valid
        out["train"] += rest + thrown
    for name in SPLITS:
        out[name].sort(key=lambda e: str(e["file"]))
    return out


class ManifestSource:
    """One split of a manifest folder: one npz per trajectory, read on demand."""

    layout = "manifest"

    def __init__(self, folder: str | os.PathLike[str], split: str) -> None:
        self.folder = Path(folder)
        self.manifest_path = self.folder / "manifest.json"
        try:
            self.manifest = json.loads(self.manifest_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as err:
            raise DatasetError(self.manifest_path, f"cannot read manifest: {err}") from err
        if split not in SPLITS:
            raise DatasetError(self.folder, f"unknown split {split!r}; expected one of {SPLITS}")
        try:
            self.entries = split_entries(self.manifest["trajectories"])[split]
        except (KeyError, TypeError, ValueError) as err:
            raise DatasetError(self.manifest_path, f"malformed trajectory entries: {err}") from err
        self.split = split

    def __len__(self) -> int:
        return len(self.entries)

    def read(self, index: int) -> Trajectory:
        entry = self.entries[index]
        path = self.folder / str(entry["file"])
        source = NpzSource(path)
        if len(source) != 1:
            raise DatasetError(path, f"expected one trajectory per file, found {len(source)}")
        raw = source.read(0)
        tan_angle = np.float32(math.tan(math.radians(float(entry["friction_angle_deg"]))))
        context = np.full((raw.num_frames, 1), tan_angle, dtype=np.float32)
        return Trajectory(
            raw.positions,
            raw.particle_type,
            context,
            np.asarray(tan_angle),
            key=index,
            source=str(path),
        )

    @property
    def files(self) -> list[Path]:
        return [self.folder / str(e["file"]) for e in self.entries]

    def metadata(self) -> Metadata:
        """Metadata from the manifest, with statistics of the train split."""
        m = self.manifest
        try:
            bounds = [list(map(float, pair)) for pair in m["bounds"]]
            raw = {
                "bounds": bounds,
                "dim": len(bounds),
                "dt": float(m["frame_dt_s"]),
                "sequence_length": int(m["frames"]) - 1,
                "default_connectivity_radius": CONNECTIVITY_RADIUS,
                "material_feature_len": 1,
                "step_context_description": "tan(friction angle), constant per trajectory",
            }
        except (KeyError, TypeError, ValueError) as err:
            raise DatasetError(self.manifest_path, f"manifest lacks or mangles {err}") from err
        metadata = Metadata.from_dict(raw, self.manifest_path)
        train = ManifestSource(self.folder, "train")
        try:
            stamp = tuple(p.stat().st_mtime_ns for p in [self.manifest_path, *train.files])
        except OSError as err:
            raise DatasetError(self.folder, f"cannot read a training file: {err}") from err
        cache_key = (str(self.folder.resolve()), stamp)
        if cache_key not in _STATS_CACHE:
            stats = compute_statistics(
                (train.read(i) for i in range(len(train))),
                metadata.kinematic_particle_types,
                metadata.period,
            )
            _STATS_CACHE[cache_key] = stats.apply_to(metadata)
        return _STATS_CACHE[cache_key]
