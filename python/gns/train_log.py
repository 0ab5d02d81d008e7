"""Training's logs: train.csv / valid.csv and TensorBoard (RunLog), the progress line
(Progress) and the loss-spike report (SpikeReport). Rank 0 writes them; gns.train decides what.
"""

from __future__ import annotations

import csv
import math
import sys
import time
from pathlib import Path

from gns.files import atomic_file

# Spikes printed one line each; later ones are counted and summarised (all go to spikes.csv).
SPIKES_SHOWN = 3


class RunLog:
    """Figures to CSV files and TensorBoard (rank 0 only); on resume, rows past the
    checkpoint's step are dropped, because those steps are about to be trained again."""

    def __init__(self, run_dir: Path, resume_step: int | None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.run_dir = run_dir
        if resume_step is not None:
            for name in ("train.csv", "valid.csv", "spikes.csv"):
                self._truncate(run_dir / name, resume_step)
        purge = None if resume_step is None else resume_step + 1
        self.tensorboard = SummaryWriter(str(run_dir / "tensorboard"), purge_step=purge)

    @staticmethod
    def _truncate(path: Path, step: int) -> None:
        if not path.exists():
            return
        with open(path, newline="") as f:
            rows = list(csv.reader(f))

        def kept_row(row: list[str]) -> bool:
            # Rows of the header's width (a killed run may have left a cut-off last line).
            return len(row) == len(rows[0]) and row[0].isdigit() and int(row[0]) <= step

        kept = rows[:1] + [row for row in rows[1:] if kept_row(row)]
        with atomic_file(path) as tmp, open(tmp, "w", newline="") as f:
            csv.writer(f).writerows(kept)

    def write(self, name: str, step: int, values: dict[str, float]) -> None:
        path = self.run_dir / f"{name}.csv"
        new = not path.exists()
        with open(path, "a", newline="") as f:
            writer = csv.writer(f)
            if new:
                writer.writerow(["step", *values])
            writer.writerow([step, *(f"{v:.9g}" for v in values.values())])
        for key, value in values.items():
            self.tensorboard.add_scalar(f"{name}/{key}", value, step)
        self.tensorboard.flush()

    def spike(self, step: int, loss: float, median: float, windows: str) -> None:
        path = self.run_dir / "spikes.csv"
        new = not path.exists()
        with open(path, "a", newline="") as f:
            writer = csv.writer(f)
            if new:
                writer.writerow(["step", "loss", "recent_median", "windows"])
            writer.writerow([step, f"{loss:.9g}", f"{median:.9g}", windows])

    def close(self) -> None:
        self.tensorboard.close()


class Progress:
    """A one-line progress display on stderr: step, loss, steps/s and time left (the sooner of
    the remaining steps and the remaining time limit, when there is one)."""

    def __init__(
        self, total: int, start: int, enabled: bool, time_limit: float | None = None
    ) -> None:
        self.total, self.start, self.enabled = total, start, enabled
        self.started = time.perf_counter()
        self.time_limit = time_limit
        self.tty = sys.stderr.isatty()
        self.last_shown = 0.0
        self.threads: int | None = None

    def rate(self, step: int) -> float:
        elapsed = time.perf_counter() - self.started
        return (step - self.start) / elapsed if elapsed > 0 else 0.0

    def show(self, step: int, loss: float, force: bool = False, threads: int | None = None) -> None:
        if threads is not None:
            self.threads = threads
        now = time.perf_counter()
        if not self.enabled or (self.tty and not force and now - self.last_shown < 0.5):
            return
        if not self.tty and not force:
            return
        self.last_shown = now
        rate = self.rate(step)
        left = (self.total - step) / rate if rate > 0 else float("nan")
        if self.time_limit is not None:
            left = min(left, max(0.0, self.time_limit - (now - self.started)))
        eta = time.strftime("%H:%M:%S", time.gmtime(left)) if math.isfinite(left) else "--"
        line = f"step {step}/{self.total}  loss {loss:.4g}  {rate:.2f} steps/s  left {eta}"
        if self.threads is not None:  # chosen by timing the steps (gns.threads)
            line += f"  {self.threads} thread{'s' if self.threads > 1 else ''}"
        sys.stderr.write(("\r" + line + "   ") if self.tty else line + "\n")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled and self.tty:
            sys.stderr.write("\n")


class SpikeReport:
    """Loss spikes on stderr without flooding it: the first SPIKES_SHOWN each get a line, the
    rest are only counted (every one is in spikes.csv), and `summarise` ends training with
    their number and the worst. Rank 0 only (enabled)."""

    def __init__(self, enabled: bool, meter: Progress) -> None:
        self.enabled, self.meter = enabled, meter
        self.count = 0
        self.worst: tuple[float, int, float] | None = None  # (times the median, step, loss)

    def _write(self, text: str) -> None:
        newline = "\n" if self.meter.tty and self.meter.enabled else ""  # past \r lines
        sys.stderr.write(f"{newline}{text}\n")

    def add(self, step: int, loss: float, median: float, history: int, windows: str) -> None:
        self.count += 1
        factor = loss / median
        if self.worst is None or factor > self.worst[0]:
            self.worst = (factor, step, loss)
        if not self.enabled or self.count > SPIKES_SHOWN:
            return
        more = (
            "; further spikes are counted, listed in spikes.csv and summarised at the end"
            if self.count == SPIKES_SHOWN
            else ""
        )
        self._write(
            f"loss spike at step {step}: {loss:.4g}, {factor:.1f} times the median "
            f"{median:.4g} of the previous {history} steps, on the batch of windows "
            f"(trajectory:start) {windows}; training goes on{more}"
        )

    def summarise(self, path: Path) -> None:
        if not self.enabled or self.worst is None:
            return
        factor, step, loss = self.worst
        self._write(
            f"{self.count} loss spike{'s' if self.count > 1 else ''} this session (loss above "
            f"the spike factor times the recent median); the worst at step {step}: {loss:.4g}, "
            f"{factor:.1f} times the median; each with its batch in {path}"
        )
