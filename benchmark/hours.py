"""How long training took, from the runs' event files: OUT/hours.md per game and algorithm, OUT/hours.csv per run.

    uv run python benchmark/hours.py benchmark/results/learning_check/runs --out benchmark/results/learning_check

Runs are found and grouped as benchmark/results.py finds and groups them (one code for both). Per run: the
elapsed time of the processes that trained it (its first start, then each resume from a checkpoint), which
holds every slowdown and pause, and the median time of an iteration (the gaps between its per-iteration
`charts/SPS` points within one process), its usual pace; the evaluation games after training are in neither.
"""

import os
import re
import sys
import time
from dataclasses import dataclass

import numpy as np
import pandas as pd
import tyro

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from results import find_runs, folder_problem, markdown, write  # noqa: E402


@dataclass
class Args:
    roots: tyro.conf.Positional[tuple[str, ...]]
    """folders to search for runs (recursively)"""
    out: str = "results"
    """folder for hours.md and hours.csv"""
    group_regex: str | None = None
    """regex with named groups `env` and `algo`, searched in each run folder's name (as results.py's)"""


def written_by_a_training_process(path: str) -> bool:
    """Whether an event file is one process's part of a training run: the first start's file opens with the
    logged hyperparameters, each resume's with TensorBoard's session start (its purge step). Any other event
    file in the folder (a copy, another tool's) is not a start or a resume of the run."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader
    from tensorboard.compat.proto.event_pb2 import SessionLog

    try:
        for k, event in enumerate(EventFileLoader(path).Load()):
            if event.HasField("session_log") and event.session_log.status == SessionLog.START:
                return True
            if any(value.tag.startswith("hyperparameters") for value in event.summary.value):
                return True
            if k >= 4:  # both come right after the file's version record
                return False
    except Exception:  # unreadable from the start
        return False
    return False


def process_starts(folder: str) -> list[float]:
    """The start times in the names of a run's event files written by its training processes, one per process."""
    starts = []
    for name in sorted(os.listdir(folder)):
        start = re.match(r"events\.out\.tfevents\.(\d+)", name)
        if start and written_by_a_training_process(os.path.join(folder, name)):
            starts.append(float(start[1]))
    return starts


def process_spans(iteration_times, process_starts) -> list[tuple[float, float]]:
    """Per process that trained a run (the run's first start, then each resume from a checkpoint; each wrote
    an event file named for its start time), (its start, the time of its last per-iteration point). The points
    that TensorBoard purges on a resume (iterations after the last checkpoint, run again) end the killed
    process's span early."""
    t = np.sort(np.asarray(iteration_times, dtype=np.float64))
    if not len(t):
        return []
    starts = sorted(s for s in process_starts if s <= t[-1]) or [float(t[0])]  # files renamed: one process
    spans = []
    for k, start in enumerate(starts):
        end = starts[k + 1] if k + 1 < len(starts) else np.inf
        mine = t[(t >= start) & (t < end)]
        if len(mine):
            spans.append((float(start), float(mine[-1])))
    return spans


def union_hours(spans) -> float:
    """Hours covered by at least one of the spans (the machine's wall clock while any run was training)."""
    total, reach = 0.0, -np.inf
    for start, end in sorted(spans):
        if end > reach:
            total += end - max(start, reach)
            reach = end
    return total / 3600


def utc(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(t))


def mean_and_range(x) -> str:
    """A cell of hours.md: the mean of x with its (min–max) where x holds more than one value."""
    if not x:
        return "–"
    return f"{np.mean(x):.2f}" if len(x) == 1 else f"{np.mean(x):.2f} ({min(x):.2f}–{max(x):.2f})"


def hours(frame: pd.DataFrame, out: str) -> str | None:
    """OUT/hours.md and hours.csv from the runs' `charts/SPS` points (their wall times) and event files."""
    rows = []
    for (run, env, algo), points in frame[frame.tag == "charts/SPS"].groupby(["run", "env", "algo"]):
        t = np.sort(points.wall_time.to_numpy())
        starts = process_starts(run)
        spans = process_spans(t, starts)
        gaps = np.concatenate([np.diff(t[(t >= a) & (t <= b)]) for a, b in spans])
        pace = float(np.median(gaps)) if len(gaps) else float("nan")  # nan: one iteration per process
        elapsed = sum(b - a for a, b in spans) / 3600
        # every process after the first is a resume, also one killed in its start-up (no iteration, no span)
        resumes = max(sum(1 for start in starts if start <= t[-1]) - 1, 0)
        rows.append({"run": run, "env": env, "algo": algo, "spans": spans, "iterations": len(t)})
        rows[-1] |= {"pace": pace, "elapsed": elapsed, "resumes": resumes}
    if not rows:
        return None
    runs = pd.DataFrame(rows)
    table = [
        [env, algo, str(len(group))]
        + [mean_and_range([x for x in group[column] if not np.isnan(x)]) for column in ("elapsed", "pace")]
        + [str(group.resumes.sum())]
        for (env, algo), group in runs.groupby(["env", "algo"])
    ]
    spans = [span for run_spans in runs.spans for span in run_spans]
    lines = [
        "How long training took (wall clock, from the event files; the evaluation games after training are not"
        " counted). Per run: the hours its processes ran, from each start to its last iteration, which hold every"
        " slowdown (other work on the cores) and pause, and the median seconds between two of its iterations;"
        " resumes: times it was stopped and resumed from a checkpoint. Means over runs, (min–max).",
        "",
        *markdown(["game", "algorithm", "runs", "hours elapsed", "s per iteration, median", "resumes"], table),
        "",
        f"All {len(runs)} runs: {runs.elapsed.sum():.1f} hours elapsed summed over runs (core-hours for runs"
        f" of one core each); at least one of them was training during {union_hours(spans):.1f} hours of wall"
        f" clock between {utc(min(a for a, _ in spans))} and {utc(max(b for _, b in spans))}.",
    ]
    csv_rows = [
        {"run": os.path.basename(r.run), "game": r.env, "algorithm": r.algo, "iterations": r.iterations}
        | {"hours_elapsed": f"{r.elapsed:.4f}", "seconds_per_iteration": "" if np.isnan(r.pace) else f"{r.pace:.2f}"}
        | {"resumes": r.resumes, "first_start_utc": utc(r.spans[0][0]), "last_iteration_utc": utc(r.spans[-1][1])}
        for r in runs.itertuples()
    ]
    return write(out, "hours", "\n".join(lines) + "\n", csv_rows)


def main(args: Args) -> str:
    if not args.roots:
        sys.exit("error: give the folders of runs to read, e.g. `hours.py runs/ --out results/`.")
    try:
        if args.group_regex and not {"env", "algo"} <= set(re.compile(args.group_regex).groupindex):
            sys.exit("error: --group-regex needs the named groups (?P<env>...) and (?P<algo>...).")
    except re.error as e:
        sys.exit(f"error: --group-regex is not a regular expression ({e}).")
    if folder_problem(args.out):
        sys.exit(f"error: --out {args.out} cannot be a folder for the tables: {folder_problem(args.out)}.")
    frame, problems = find_runs(args.roots, args.group_regex)
    for problem in problems:
        print(f"skipped: {problem}", file=sys.stderr)
    if frame[frame.tag == "charts/SPS"].empty:  # nothing to write: no table, and no folder made for it
        sys.exit(f"error: no training run (per-iteration `charts/SPS` points) under {', '.join(args.roots)}.")
    os.makedirs(args.out, exist_ok=True)
    text = hours(frame, args.out)
    print(f"{text}wrote {os.path.join(args.out, 'hours')}.md and .csv")
    return text


if __name__ == "__main__":
    main(tyro.cli(Args))
