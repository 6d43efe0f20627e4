"""What every ``vqtouch evaluate <experiment>`` shares: seeds, mean and spread, the written record.

An experiment repeats a measurement over seeds, then writes three things into its ``--out``
folder: ``<name>.json`` (every per-seed row, the mean/std summary and the provenance: command,
versions, device, wall time), ``<name>.md`` (the tables for people) and one or more PNG figures.
This module knows no model or stage; it only shapes rows of numbers.

Typical use inside an experiment command::

    record = ExperimentRecord("reconstruction", out, seeds=args.seeds, overwrite=args.overwrite)
    rows = [...]                         # one dict per (configuration, seed)
    summary = mean_spread(rows, ("ssim", "psnr"), group=("encoder", "samples"))
    record.write({"rows": rows, "summary": summary}, markdown_lines)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable, Sequence

from vqtouch.plugins.runtime.outputs import output_folder
from vqtouch.plugins.cli.app import seed_int
from vqtouch.core.errors import ConfigError
from vqtouch.core import __version__

#: The seeds an experiment repeats over unless told otherwise (three: the least that gives a spread).
DEFAULT_SEEDS = (0, 1, 2)


def add_experiment_arguments(parser: argparse.ArgumentParser, default_seeds: Sequence[int] = DEFAULT_SEEDS) -> None:
    """``--out``, ``--overwrite`` and ``--seeds``, the flags every experiment takes."""
    parser.add_argument("--out", required=True, help="folder for the experiment's JSON, markdown and PNG files")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="run again into an --out that holds a finished result, training every arm again (without it, an "
        "interrupted run reuses the arms it finished, and one with other settings is refused)",
    )
    parser.add_argument(
        "--seeds",
        type=seed_int,
        nargs="+",
        default=list(default_seeds),
        help=f"seeds to repeat over (default {' '.join(map(str, default_seeds))}); tables give "
        "mean ± standard deviation over them",
    )


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def mean_spread(rows: Iterable[dict[str, Any]], keys: Sequence[str], group: Sequence[str]) -> list[dict[str, Any]]:
    """Rows grouped by the ``group`` columns, each of ``keys`` as its mean over the group's rows
    (the seeds) and ``<key>_std`` its population standard deviation (0.0 for one seed).

    Groups keep their first-seen order.  A key missing or non-finite in some rows is averaged over
    the rows that have it (``<key>_n`` then says over how many); a key no row has is left out.
    """
    grouped: dict[tuple, list[dict[str, Any]]] = {}
    for row in rows:
        grouped.setdefault(tuple(row.get(key) for key in group), []).append(row)
    table = []
    for values, members in grouped.items():
        entry: dict[str, Any] = dict(zip(group, values)) | {"seeds": len(members)}
        for key in keys:
            numbers = [float(row[key]) for row in members if _is_number(row.get(key))]
            if not numbers:
                continue
            entry[key] = round(statistics.fmean(numbers), 6)
            entry[f"{key}_std"] = round(statistics.pstdev(numbers), 6) if len(numbers) > 1 else 0.0
            if len(numbers) != len(members):
                entry[f"{key}_n"] = len(numbers)
        table.append(entry)
    return table


def format_cell(value: Any, spread: Any = None) -> str:
    """A table cell: 4 significant digits (a whole number in full, e.g. 12000 training images),
    ``± spread`` when there is one, ``-`` for nothing."""
    if value is None:
        return "-"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    whole = math.isfinite(value) and float(value).is_integer() and abs(value) < 1e15
    text = str(int(value)) if whole else f"{value:.4g}"
    return text + (f" ± {spread:.2g}" if _is_number(spread) and spread else "")


def markdown_table(
    rows: Sequence[dict[str, Any]], group: Sequence[str], keys: Sequence[str], headers: dict[str, str] | None = None
) -> list[str]:
    """Markdown lines of ``rows`` (e.g. :func:`mean_spread`'s): the ``group`` columns as they are,
    each of ``keys`` as ``mean ± std``.  ``headers`` renames columns for people."""
    headers = headers or {}
    names = [headers.get(column, column) for column in (*group, *keys)]
    lines = ["| " + " | ".join(names) + " |", "|" + "---|" * len(names)]
    for row in rows:
        cells = ["-" if row.get(column) is None else str(row[column]) for column in group]
        cells += [format_cell(row.get(key), row.get(f"{key}_std")) for key in keys]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def gap_verdict(model: dict[str, Any], rival: dict[str, Any], key: str, rival_name: str) -> str:
    """How ``model``'s mean of ``key`` compares with ``rival``'s (rows of :func:`mean_spread`), e.g.
    "beats VQGAN by 0.8": "beats", "is behind" or "is level with", a gap counting only when it
    exceeds the two standard deviations added; the score's direction comes from
    :func:`.directions.lower_is_better`."""
    from .directions import lower_is_better

    sign = -1 if lower_is_better(key) else 1
    gap = sign * (model[key] - rival[key])
    noise = (model.get(f"{key}_std") or 0.0) + (rival.get(f"{key}_std") or 0.0)
    if gap > noise:
        return f"beats {rival_name} by {gap:.3g}"
    if gap < -noise:
        return f"is behind {rival_name} by {-gap:.3g}"
    return f"is level with {rival_name} (gap {gap:+.3g} within the spread {noise:.2g})"


def plot_against_count(
    summary: Sequence[dict[str, Any]],
    *,
    count: str,
    line: str,
    keys: Sequence[str],
    path: Path,
    title: str,
    xlabel: str,
    dashed: Sequence[str] = (),
) -> None:
    """One panel per score of ``keys`` (those some row has): the score's mean against the row's
    ``count`` column on a log axis (ticks at the counts), one line per value of the ``line`` column
    with the seeds' spread as error bars; lines named in ``dashed`` (a no-contact background) grey
    and dashed.  Saved as a PNG at ``path``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from .directions import direction_arrow

    keys = [key for key in keys if any(key in row for row in summary)]
    counts = sorted({row[count] for row in summary})
    figure = Figure(figsize=(5 * max(1, len(keys)), 4), dpi=110)
    FigureCanvasAgg(figure)
    for panel, key in enumerate(keys):
        axes = figure.add_subplot(1, len(keys), panel + 1)
        for name in dict.fromkeys(row[line] for row in summary):
            points = sorted(
                (row[count], row[key], row.get(f"{key}_std") or 0.0)
                for row in summary
                if row[line] == name and key in row
            )
            if not points:
                continue
            xs, ys, errors = zip(*points)
            style = {"linestyle": "--", "color": "grey"} if name in dashed else {"marker": "o"}
            axes.errorbar(xs, ys, yerr=errors, capsize=3, label=name, **style)
        axes.set_xscale("log")
        axes.set_xticks(counts, [str(value) for value in counts])
        axes.minorticks_off()
        axes.set_xlabel(xlabel)
        axes.set_ylabel(f"held-out {key} {direction_arrow(key)}")
        axes.grid(alpha=0.3)
    if keys:
        figure.axes[0].legend(fontsize=7)
    figure.suptitle(title, fontsize=9)
    figure.tight_layout()
    figure.savefig(path)


def refuse_finished(out: str | Path, name: str, what: str, overwrite: bool) -> None:
    """Refuse, in one line, an ``out`` that already holds the experiment's ``<name>.json`` (``what``:
    "a fewshot experiment"), unless ``overwrite``: a finished record is never silently replaced."""
    if not overwrite and (Path(out) / f"{name}.json").is_file():
        raise ConfigError(f"{out} already holds {what}; pass --overwrite to run it again, or choose another --out")


def check_seeds(seeds: Sequence[int]) -> list[int]:
    """``seeds`` as a list, refusing an empty or repeated one (a repeated seed would fake a small spread)."""
    seeds = list(seeds)
    if not seeds:
        raise ConfigError("--seeds needs at least one seed, e.g. --seeds 0 1 2")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds {' '.join(map(str, seeds))} repeats a seed; give distinct seeds")
    return seeds


def provenance() -> dict[str, Any]:
    """Where and how an experiment ran: enough to judge whether two records are comparable."""
    import torch

    return {
        "command": " ".join(["vqtouch", *sys.argv[1:]]) if Path(sys.argv[0]).name == "vqtouch" else " ".join(sys.argv),
        "vqtouch": __version__,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


class ExperimentRecord:
    """The ``--out`` folder of one experiment and its ``<name>.json`` / ``<name>.md``.

    Created at the start (it records the provenance and the start time) and written at the end
    with :meth:`write`; figures go to :meth:`path`.  An ``out`` that holds a finished ``<name>.json``
    is refused unless ``overwrite`` (:func:`refuse_finished`).
    """

    def __init__(self, name: str, out: str | Path, seeds: Sequence[int], *, overwrite: bool = False) -> None:
        self.name = name
        self.out = Path(out)
        self.seeds = check_seeds(seeds)
        refuse_finished(self.out, name, f"a {name.replace('_', '-')} experiment", overwrite)
        self.provenance = provenance()
        self._tic = time.perf_counter()
        output_folder(self.out)

    def path(self, filename: str) -> Path:
        """A file inside the experiment's folder."""
        return self.out / filename

    def write(self, result: dict[str, Any], markdown: Sequence[str]) -> Path:
        """Write ``<name>.json`` (``result`` plus seeds, provenance and wall time) and ``<name>.md``
        (``markdown`` lines under a provenance footer); returns the JSON's path."""
        seconds = round(time.perf_counter() - self._tic, 1)
        record = {
            "experiment": self.name,
            "seeds": self.seeds,
            **result,
            "provenance": {**self.provenance, "wall_seconds": seconds},
        }
        json_path = self.path(f"{self.name}.json")
        json_path.write_text(json.dumps(record, indent=2, default=str) + "\n")
        where = self.provenance["cuda"] or f"{self.provenance['cpu_count']} CPU cores"
        footer = [
            "",
            f"_{len(self.seeds)} seeds ({', '.join(map(str, self.seeds))}); mean ± std over them. "
            f"Ran `{self.provenance['command']}` in {seconds:.0f} s on {where}, "
            f"vqtouch {self.provenance['vqtouch']}, torch {self.provenance['torch']}._",
        ]
        self.path(f"{self.name}.md").write_text("\n".join([*markdown, *footer]) + "\n")
        return json_path
