"""The one error type of `gns.data`: a ValueError that says where the problem is."""

from __future__ import annotations

import os


class DatasetError(ValueError):
    """A dataset file is missing, damaged or inconsistent.

    The message always names the file and, when one is involved, the trajectory, so a user with
    hundreds of files knows which one to look at.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        problem: str,
        trajectory: int | str | None = None,
    ) -> None:
        self.path = os.fspath(path)
        self.trajectory = trajectory
        self.problem = problem
        where = self.path if trajectory is None else f"{self.path}: trajectory {trajectory}"
        super().__init__(f"{where}: {problem}")
