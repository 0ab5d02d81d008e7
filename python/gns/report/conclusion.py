"""gns report's conclusion (see gns.report): the table in plain words, computed from the rows."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from gns.report.measure import CONSTANT_VELOCITY, STATIC, Row, _count
from gns.report.render import _format

__all__ = ["conclusion"]


def _times(ratio: float) -> str:
    return f"{ratio:.1f}x" if ratio < 9.95 else f"{ratio:,.0f}x"


def _ms(seconds: float) -> str:
    ms = seconds * 1e3
    return f"{ms:#.2g} ms" if ms < 10 else f"{ms:,.0f} ms"


def _mse_against(mse: float, other: float, name: str) -> str:
    """How an MSE compares with `other`, the MSE of `name`: "3.0x lower MSE than X"."""
    if mse == other:
        return f"the same MSE as {name}"
    direction = "lower" if mse < other else "higher"
    if min(mse, other) == 0:  # no ratio to an exact result
        return f"{direction} MSE than {name} ({_format(mse)} against {_format(other)})"
    return f"{_times(max(mse, other) / min(mse, other))} {direction} MSE than {name}"


def _speed_against(seconds: float, other: float, name: str) -> str:
    """How a time per frame compares with `other`, that of `name`: "3.1x faster than X"."""
    if seconds == other:
        return f"as fast as {name}"
    direction = "faster" if seconds < other else "slower"
    return f"{_times(max(seconds, other) / min(seconds, other))} {direction} than {name}"


def _horizon_phrase(key: str, steps: int) -> str:
    h = key.split("@", 1)[1]
    if h == "full":
        return f"the full {steps}-frame rollouts"
    return "the first predicted frame" if h == "1" else f"the first {h} predicted frames"


def _finite(row: Row, key: str) -> float | None:
    value = row.values.get(key)
    return value if value is not None and math.isfinite(value) else None


def _lowest(rows: Sequence[Row], key: str) -> Row | None:
    """The row of lowest finite value at `key` (the first of equals), or None."""
    scored = [r for r in rows if _finite(r, key) is not None]
    return min(scored, key=lambda r: r.values[key]) if scored else None


def _ratio_text(ratio: float) -> str:
    """A ratio to the truth to two figures: "0.43x", "1.6x", "12x"."""
    if ratio < 1:
        return f"{ratio:.2f}x"
    return f"{ratio:.1f}x" if ratio < 9.95 else _times(ratio)


def _deposit_sentence(
    best: Row, static: Row | None, truth: Mapping[str, float] | None
) -> str | None:
    """Where the best learned row's sand stops and how high it piles against the truth, and
    the static baseline's; None when the figures are not there. The widths and heights are
    means over trajectories; the ratios are the table's (per trajectory, then the mean), which
    the means need not divide to."""
    if truth is None or "runout" not in truth or _finite(best, "runout_ratio") is None:
        return None
    height = "pile_height" in truth and _finite(best, "height_ratio") is not None

    def size(row: Row, against: bool) -> str:
        """ "0.31 wide [against the truth's 0.72] and piles 0.08 high [against 0.05]"."""
        text = f"{_format(row.values['runout'])} wide"
        text += f" against the truth's {_format(truth['runout'])}" if against else ""
        if height and _finite(row, "height_ratio") is not None:
            text += f" and piles {_format(row.values['pile_height'])} high"
            text += f" against {_format(truth['pile_height'])}" if against else ""
        return text

    def ratios(row: Row) -> list[tuple[str, str]]:
        """(figure, "0.43x") for each finite ratio of the row; the density's with its worst
        frame's, "8.5x, 9.1x at its worst frame", as a landing packs more than a pile that
        has relaxed shows."""
        named = {"runout": "runout_ratio", "height": "height_ratio", "density": "density_ratio"}
        out = []
        for name, key in named.items():
            if (value := _finite(row, key)) is None:
                continue
            text = _ratio_text(value)
            if name == "density" and (worst := _finite(row, "density_ratio_max")) is not None:
                text += f", {_ratio_text(worst)} at its worst frame"
            out.append((name, text))
        return out

    ours = ratios(best)
    sentence = (
        f"Where the sand stops (the last frame, means over trajectories): {best.short}'s "
        f"deposit is {size(best, True)}; per trajectory its {ours[0][0]} is {ours[0][1]} the "
        "truth's"
        + "".join(f", its {name} {value}" for name, value in ours[1:])
        + " (the table's ratios)"
    )
    if static is not None and _finite(static, "runout_ratio") is not None:
        theirs = ", ".join(f"{name} {value}" for name, value in ratios(static))
        sentence += f"; the static baseline's is {size(static, False)} ({theirs})"
    return sentence + "."


def _rest_sentence(best: Row) -> str | None:
    """How the best learned row kept the piles held still, when the rest test ran."""
    if best.rest is None:
        return None
    figures, steps = best.rest["mean"], best.rest["steps"]
    held = f"Held still for {_count(steps, 'step')}, the last frames under {best.short}"
    moved = figures.get("max_displacement", math.inf)
    if not math.isfinite(moved):
        return f"{held} diverged (see the rest test)."
    sentence = f"{held} move by at most {_format(moved)}"
    if math.isfinite(speed := figures.get("truth_speed", math.nan)):
        sentence += f" (the data's own last step: at most {_format(speed)})"
    if math.isfinite(density := figures.get("density_ratio", math.nan)):
        sentence += f" and end {_ratio_text(density)} as densely packed as they started"
    return sentence + "."


def _against_all(chosen: Sequence[Row], among: Sequence[Row], yes: str, no: str) -> str:
    """ "yes than every one", "no than every one", or "yes than A, B and no than the other 2"."""
    if len(chosen) == len(among):
        return f"{yes} than every one"
    if not chosen:
        return f"{no} than every one"
    others = len(among) - len(chosen)
    names = ", ".join(r.short for r in chosen)
    return f"{yes} than {names} and {no} than the other {'one' if others == 1 else others}"


def _standing(best: Row, mpm: Sequence[Row], keys: Sequence[str], steps: int, frame: str) -> str:
    """Where the learned row stands against the reference simulator, plainly: faster or slower
    than its settings, lower or higher MSE over the longest horizon, and the regimes (a setting
    and the horizons) where it is both faster and more accurate, if any. The native row of a
    simulator that made the data counts too: exact, it is the accuracy to beat."""
    assert best.seconds_per_frame is not None
    seconds = best.seconds_per_frame
    key = keys[-1]
    faster = [r for r in mpm if seconds < r.seconds_per_frame]  # type: ignore[operator]
    better = [r for r in mpm if (v := _finite(r, key)) is not None and best.values[key] < v]
    times = sorted(r.seconds_per_frame for r in mpm)  # type: ignore[type-var]
    span = _ms(times[0]) if len(times) == 1 else f"{_ms(times[0])} to {_ms(times[-1])}"
    wins = []
    for r in faster:
        won = [
            _horizon_phrase(k, steps)
            for k in keys
            if (ours := _finite(best, k)) is not None
            and (theirs := _finite(r, k)) is not None
            and ours < theirs
        ]
        if len(won) == len(keys):
            wins.append(f"{r.short} at every horizon")
        elif won:
            wins.append(f"{r.short} over {', '.join(won)}")
    regime = (
        "it wins (faster and more accurate) against " + "; ".join(wins)
        if wins
        else "it wins in no regime tried here: every setting is more accurate than it or faster"
    )
    return (
        f"Where it stands against the reference simulator ({len(mpm)} setting"
        f"{'' if len(mpm) == 1 else 's'}, {span} per {frame}): at {_ms(seconds)} per {frame} "
        f"{best.short} is {_against_all(faster, mpm, 'faster', 'slower')}, and over "
        f"{_horizon_phrase(key, steps)} its MSE is "
        f"{_against_all(better, mpm, 'lower', 'higher')}; {regime}."
    )


def conclusion(
    rows: Sequence[Row],
    columns: Sequence[str],
    steps: int,
    truth: Mapping[str, float] | None = None,
    *,
    frame: str = "frame",
    headline: Row | None = None,
) -> list[str]:
    """The table in plain words, computed from it: how the best learned row compares with
    constant velocity (and the static baseline, when there is its row) over the longest horizon
    and at what cost against the reference simulator at its native settings, where its sand
    stops and how high it piles against `truth` (the ground truth's mean deposit, see
    _truth_deposits) and the static baseline's, how it kept a pile held still (when the rest
    test ran), which method has the lowest MSE at each horizon, how the learned model compares
    with the cheaper MPM settings, and which learned rows diverged. One sentence a list entry;
    true for any outcome (a learned model worse than the baseline, every learned row diverged,
    no MPM rows). Times are quoted per `frame`, what the rows' seconds_per_frame are per
    (at a frame stride, one step of the model: "7.5 ms step").

    headline: the learned row to speak of (chosen by the caller on other data, e.g. the
    valid split); default: the lowest MSE over the longest horizon, chosen on these rows. When
    the reference simulator ran, the conclusion opens with where that row stands against it
    (_standing)."""
    keys = [c for c in columns if c.startswith("mse@")]
    learned = [r for r in rows if r.role == "learned"]
    baseline = next((r for r in rows if r.method == CONSTANT_VELOCITY), None)
    static = next((r for r in rows if r.method == STATIC and r.role == "baseline"), None)
    reference = next((r for r in rows if r.native), None)
    # The native MPM on its own data is the ground truth itself (error 0): not a contender.
    exact = reference is not None and reference.same_simulator
    cheaper = [r for r in rows if r.role == "mpm" and not r.native]
    if not keys or baseline is None:
        return []
    sentences = []
    key = keys[-1]  # the longest horizon: what a simulator is for
    horizon = _horizon_phrase(key, steps)
    best = _lowest(learned, key) if headline is None else headline
    timed = [r for r in rows if r.role == "mpm" and r.seconds_per_frame is not None]
    if best is not None and _finite(best, key) is not None and best.seconds_per_frame and timed:
        sentences.append(_standing(best, timed, keys, steps, frame))
    if best is None or _finite(best, key) is None:
        who = (
            "no learned model has a finite MSE (every one diverged, see below)"
            if best is None
            else f"{best.short} has no finite MSE (it diverged, see below)"
        )
        sentences.append(
            f"Over {horizon} {who}; constant velocity's is {_format(baseline.values.get(key))}."
        )
        best = None
    else:
        sentence = (
            f"Over {horizon} {best.short} has "
            f"{_mse_against(best.values[key], baseline.values[key], 'constant velocity')} "
            f"({_format(best.values[key])} against {_format(baseline.values[key])})"
        )
        if static is not None and (held := _finite(static, key)) is not None:
            versus = _mse_against(best.values[key], held, "the static baseline")
            sentence += f" and {versus} ({_format(held)})"
        if best.seconds_per_frame is not None:
            sentence += f" at {_ms(best.seconds_per_frame)} per {frame}"
            if reference is not None and reference.seconds_per_frame is not None:
                sentence += ", " + _speed_against(
                    best.seconds_per_frame,
                    reference.seconds_per_frame,
                    "the reference simulator at its native settings",
                )
                sentence += f" ({_ms(reference.seconds_per_frame)})"
        if reference is None:
            sentence += "; the reference simulator was not run (see Left out)"
        elif reference.seconds_per_frame is None:
            sentence += "; the reference simulator failed at its native settings (see status)"
        sentences.append(sentence + ".")
        for extra in (_deposit_sentence(best, static, truth), _rest_sentence(best)):
            if extra is not None:
                sentences.append(extra)

    winners = []
    for k in keys:
        winner = _lowest([r for r in rows if not (r.native and r.same_simulator)], k)
        if winner is None:
            continue
        text = f"{_horizon_phrase(k, steps)}: {winner.short}"
        if winner.role == "learned":
            text += f", {_mse_against(winner.values[k], baseline.values[k], 'constant velocity')}"
        elif (runner_up := _lowest(learned, k)) is not None:
            text += f", {_mse_against(winner.values[k], runner_up.values[k], runner_up.short)}"
        else:
            text += " (every learned model had diverged)"
        winners.append(text)
    if winners:
        left = ", leaving out the MPM at its native settings (it is the ground truth)"
        sentences.append(f"Lowest MSE{left if exact else ''}: " + "; ".join(winners) + ".")

    if best is not None and cheaper:
        against = []
        for row in cheaper:
            value = _finite(row, key)
            if value is None or row.seconds_per_frame is None:
                against.append(f"{row.short} did not finish (see its status)")
                continue
            text = f"{_mse_against(best.values[key], value, row.short)} ({_format(value)}"
            text += f" at {_ms(row.seconds_per_frame)} per {frame}"
            if best.seconds_per_frame is not None:
                text += ", " + _speed_against(best.seconds_per_frame, row.seconds_per_frame, "it")
            against.append(text + ")")
        sentences.append(
            f"Against the reference simulator at cheaper settings over {horizon}, "
            f"{best.short} has " + "; ".join(against) + "."
        )

    diverged = [r for r in learned if r.diverged]
    for row in diverged:
        sentences.append(
            f"{row.short} diverged: {row.divergence()}; its later frames count as infinitely wrong."
        )
    if learned and not diverged:
        sentences.append("No learned rollout diverged.")
    return sentences
