"""From folders of TensorBoard runs to the thesis's table 5.1 and figures 5.1-5.16, and a P3O-vs-PPO comparison
across games (interquartile mean of human-normalised scores, rliable's protocol).

    uv run python benchmark/results.py runs/ --out results/
    uv run python benchmark/results.py runs/ --out results/ --tag charts/episodic_return --last 100 \
        --table-name train_last100 --no-figures

A run is a folder of `events.out.tfevents.*` files, grouped by the env id and exp name it logged where its name is
that or is not `{env_id}__{exp_name}[__{seed}[__{time}]]`, else by its name (a warning if the two disagree), or by
`--group-regex` with the named groups `env` and `algo`. Runs that cannot be read or grouped, or lack the tag, are
named and skipped. How long the runs took: benchmark/hours.py.
"""

import glob
import logging
import os
import re
import sys
from dataclasses import dataclass

import numpy as np
import pandas as pd
import tyro

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from comparison import ablation_tests, across_games, markdown, mean_se_text, per_game_tests, readme_block  # noqa: E402

# --readme replaces what lies between these two lines of the file with the results table and aggregate line
README_BEGIN = "<!-- begin: written by benchmark/results.py --readme from the committed runs; do not edit by hand -->"
README_END = "<!-- end: written by benchmark/results.py --readme -->"
FIGURES = {  # file suffix: (tag, y label, title)
    "episodic_return": ("charts/episodic_return", "episodic return (game score)", "episodic return, mean ± s.e."),
    "return_last10": ("charts/episodic_return", "mean return of the last 10 games", "last-10-games average"),
    "return_variance": ("charts/episodic_return", "variance across runs (score²)", "across-run variance of return"),
    "entropy": ("losses/entropy", "policy entropy (nats)", "entropy"),
    "explained_variance": ("losses/explained_variance", "explained variance", "explained variance"),
    "policy_loss": ("losses/policy_loss", "policy loss", "policy loss"),
    "value_loss": ("losses/value_loss", "value loss", "value loss"),
    "beta_mean": ("p3o/beta_mean", "mean β", "P3O mean β"),
}
COLUMNS = ["run", "env", "algo", "tag", "step", "value", "wall_time"]
# tags the training scripts and evaluate.py log: one of them that no run has logged yet is said, not refused as a typo
SCRIPT_TAGS = {tag for tag, _, _ in FIGURES.values()} | {"eval/episodic_return", "charts/episodic_length", "p3o/beta"}


@dataclass
class Args:
    roots: tyro.conf.Positional[tuple[str, ...]]
    """folders to search for runs (recursively)"""
    out: str = "results"
    """folder for the tables and figures"""
    tag: str = "eval/episodic_return"
    """the tag the table summarises"""
    last: int = 0
    """per-run statistic: the mean of the run's last K values of the tag (0: of all its values)"""
    above: float | None = None
    """with a histogram tag (P3O's `p3o/beta`): per logged histogram the share of values above this number,
    read from the buckets (linear within the one bucket that straddles it), summarised like a scalar tag"""
    table_name: str = "table"
    """the table is written to OUT/TABLE_NAME.md and .csv"""
    window_steps: int = 0
    """also a table of the tag over training, OUT/TABLE_NAME_windows.md and .csv: per run the mean of its values
    in each window [k·W, (k+1)·W) of W env steps, then mean ± s.e. over runs (0: no such table)"""
    group_regex: str | None = None
    """regex with named groups `env` and `algo`, searched in each run folder's name (instead of the name's parts)"""
    games: tuple[str, ...] = ()
    """only these env ids (default: every game found)"""
    figures: bool = True
    """write the figures"""
    grid_points: int = 200
    """points of the common step grid that curves are interpolated onto"""
    p3o_name: str = "p3o_atari_envpool"
    """the algorithm (exp name) compared against --ppo-name across games"""
    ppo_name: str = "ppo_atari_envpool"
    """the baseline algorithm"""
    ablations: tuple[str, ...] = ()
    """exp names each tested per game against --p3o-name and --ppo-name (Welch, permutation): TABLE_NAME_ablations.md"""
    bootstrap_reps: int = 2000
    """stratified-bootstrap replications for the across-game confidence intervals"""
    seed: int = 0
    """seed of the bootstrap"""
    readme: str | None = None
    """a Markdown file (the README) whose block between the two marker lines (README_BEGIN, README_END) is
    replaced by the results table (with the per-game tests and the thesis's table 5.1) and the across-game line"""


def share_above(histogram, threshold: float) -> float:
    """The share of a TensorBoard histogram's values above `threshold`. Bucket i holds the values in
    (limit[i-1], limit[i]] (the first from the histogram's min); the bucket that straddles the threshold
    counts in proportion to the part of it above (values spread evenly within it)."""
    limits = np.array(histogram.bucket_limit, dtype=np.float64)
    counts = np.array(histogram.bucket, dtype=np.float64)
    if histogram.num == 0:
        return float("nan")
    lower = np.concatenate([[histogram.min], limits[:-1]])
    upper = np.minimum(limits, histogram.max)
    width = upper - lower
    above = np.where(width > 0, np.clip((upper - threshold) / np.where(width > 0, width, 1), 0, 1), upper > threshold)
    return float((counts * above).sum() / histogram.num)


def run_group(folder: str, pattern, acc) -> tuple[str, str] | None:
    """(env, algo) of a run: --group-regex's groups in its folder's name; else the env id and exp name it logged
    (the `hyperparameters` text, rows `|name|value|`, a value possibly empty) where its name is that identity, with a
    suffix of another convention (the thesis authors' `{env}__{exp}__{time}_EVALUATE`) or not `{env}__{exp}...`;
    else the name less the seed and start time that follow (an exp name may hold `__`), loudly if it logged another."""
    name = os.path.basename(os.path.normpath(folder))
    if pattern:
        match = pattern.search(name)
        return (match.group("env"), match.group("algo")) if match else None
    parts = name.split("__")
    while len(parts) > 2 and parts[-1].isdigit():
        parts.pop()
    groups = (parts[0], "__".join(parts[1:])) if len(parts) >= 2 else None
    if "hyperparameters/text_summary" not in acc.Tags().get("tensors", []):
        return groups
    text = acc.Tensors("hyperparameters/text_summary")[0].tensor_proto.string_val[0].decode()
    table = dict(line[1:-1].split("|", 1) for line in text.splitlines() if line.count("|") >= 3)
    if "env_id" not in table or "exp_name" not in table:
        return groups
    logged, identity = (table["env_id"], table["exp_name"]), f"{table['env_id']}__{table['exp_name']}"
    if groups is None or name == identity or name.startswith(identity + "__"):
        return logged
    if groups != logged:  # the folder name is what TensorBoard shows and what the user can rename: it decides
        print(
            f"warning: {folder}: the folder name says {groups[0]} / {groups[1]} but the run logged {logged[0]} /"
            f" {logged[1]}; grouped by the folder name",
            file=sys.stderr,
        )
    return groups


def find_runs(roots, group_regex=None, above=None) -> tuple[pd.DataFrame, list[str]]:
    """Every folder under the roots with an event file, read with TensorBoard's own reader into one long table
    (COLUMNS), each tag's points in step order. With `above`, each histogram tag becomes a scalar series: the
    share of its values above that number."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    folders, tables, problems = {}, [], []  # one run per folder, however reached (`runs/x`, `./runs/x`)
    for root in roots:
        if not os.path.isdir(root):
            problems.append(f"{root}: not a folder")
        for path in glob.glob(os.path.join(root, "**", "events.out.tfevents.*"), recursive=True):
            folders.setdefault(os.path.realpath(os.path.dirname(path)), os.path.dirname(path))
    pattern = re.compile(group_regex) if group_regex else None
    # TensorBoard's loader stops at a damaged or incomplete record (a killed write, a full disk, a partial copy) and
    # says so only in a debug line: collected here to name the file
    damaged, logger, handler = [], logging.getLogger("tensorboard"), logging.Handler(logging.DEBUG)
    handler.emit = lambda record: str(record.msg).startswith("Truncated record") and damaged.append(record.args[0])
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        for folder in sorted(folders.values()):
            try:
                guidance = {"scalars": 0, "tensors": 1, "histograms": 0 if above is not None else 1}
                acc = EventAccumulator(folder, size_guidance=guidance)
                acc.Reload()
                points = {t: [(e.step, e.value, e.wall_time) for e in acc.Scalars(t)] for t in acc.Tags()["scalars"]}
                for tag in acc.Tags()["histograms"] if above is not None else []:
                    points[tag] = [
                        (e.step, share_above(e.histogram_value, above), e.wall_time) for e in acc.Histograms(tag)
                    ]
            except Exception as e:  # a foreign file: say which, go on
                problems.append(f"{folder}: unreadable event file ({type(e).__name__}: {e}), skipped")
                continue
            for file in damaged:
                print(
                    f"warning: {file}: a damaged or incomplete record; the records before it are used", file=sys.stderr
                )
            damaged.clear()
            # eval.json, written last, says the evaluation is whole: eval/ points without it are not counted
            if not os.path.isfile(os.path.join(folder, "eval.json")):
                points = {tag: rows for tag, rows in points.items() if not tag.startswith("eval/")}
            groups = run_group(folder, pattern, acc)
            if groups is None or not points:
                why = "no scalar events" if groups else "name does not match --group-regex" if pattern else None
                problems.append(
                    f"{folder}: {why or 'no logged hyperparameters and a name not {env_id}__{exp_name}__...'}, skipped"
                )
                continue
            for tag, rows in points.items():
                step, value, wall_time = np.array(rows, dtype=np.float64).T
                order = np.argsort(step, kind="stable")
                columns = {"step": step[order], "value": value[order], "wall_time": wall_time[order]}
                tables.append(pd.DataFrame({"run": folder, "env": groups[0], "algo": groups[1], "tag": tag} | columns))
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    return pd.concat(tables, ignore_index=True) if tables else pd.DataFrame(columns=COLUMNS), problems


def per_run(frame: pd.DataFrame, tag: str, last: int) -> pd.Series:
    """(env, algo, run) -> the run's statistic of the tag: the mean of its last `last` values (0: of all)."""
    values = frame[frame.tag == tag].groupby(["env", "algo", "run"])["value"]
    return values.agg(lambda v: float(np.mean(v.to_numpy()[-last:] if last else v.to_numpy())))


def mean_se(x) -> tuple[float, float, int]:
    """Mean, standard error with the population standard deviation (std / sqrt(n), as the thesis's
    table 5.1) and n of per-run statistics."""
    x = np.asarray(x, dtype=np.float64)  # not scipy.stats.sem(ddof=0): for one run it warns and gives nan, not 0
    return float(x.mean()), float(x.std() / np.sqrt(len(x))), len(x)


def write(out: str, name: str, text: str, csv_rows: list[dict] | None = None) -> str:
    """OUT/NAME.md (and with `csv_rows` OUT/NAME.csv, comma-separated, CRLF lines as Python's csv module writes)."""
    with open(os.path.join(out, f"{name}.md"), "w") as f:
        f.write(text)
    if csv_rows is not None:
        pd.DataFrame(csv_rows).to_csv(os.path.join(out, f"{name}.csv"), index=False, lineterminator="\r\n")
    return text


def write_table(table, out, name, tag, last) -> str:
    envs, algos = sorted({env for env, _ in table}), sorted({algo for _, algo in table})
    cell = lambda key: f"{mean_se_text(*table[key])} (n={table[key][2]})" if key in table else "–"  # noqa: E731
    lines = [
        f"`{tag}`, per run the " + (f"mean of the last {last} values" if last else "mean of all values") + "; mean ±"
        " standard error (population std / √n) over n runs (the mean alone for one run).",
        "",
        *markdown(["game", *algos], [[env, *(cell((env, algo)) for algo in algos)] for env in envs]),
    ]
    rows = [
        {"game": env, "algorithm": algo, "tag": tag, "last": last, "n": n, "mean": mean, "std_err": se if n > 1 else ""}
        for (env, algo), (mean, se, n) in table.items()
    ]
    return write(out, name, "\n".join(lines) + "\n", rows)


def write_window_table(frame, out, name, tag, window, label) -> dict:
    """Per (env, algo) and window k of steps [k·window, (k+1)·window): `mean_se` over the runs with values there of
    each run's mean in the window, and the number of values in all (None: no run has values there); written."""
    rows = frame[frame.tag == tag]
    rows = rows.assign(k=(rows.step.to_numpy() // window).astype(int))
    per = rows.groupby(["env", "algo", "run", "k"])["value"].agg(
        mean=lambda v: float(np.mean(v.to_numpy())), count="size"
    )
    table = {}
    for key, group in per.groupby(level=["env", "algo"]):
        cells = {k: (*mean_se(g["mean"]), int(g["count"].sum())) for k, g in group.groupby(level="k")}
        table[key] = [cells.get(k) for k in range(max(cells) + 1)]
    windows = max(len(cells) for cells in table.values())
    steps = lambda s: "0" if s == 0 else f"{s / 1e6:g}M" if s >= 1_000_000 else f"{s / 1e3:g}k"  # noqa: E731
    lines = [
        f"`{label}` per window of {window:,} env steps: per run the mean of its values in the window; mean ± standard"
        " error (population std / √n) over n runs (the mean alone for one run), and in brackets the number of"
        " values (games for episodic returns, iterations for losses and β).",
        "",
        *markdown(
            ["game", "algorithm", *(f"{steps(k * window)}–{steps((k + 1) * window)}" for k in range(windows))],
            [
                [env, algo, *(f"{mean_se_text(*c[:3])} (n={c[2]}, {c[3]})" if c else "–" for c in cells)]
                + ["–"] * (windows - len(cells))
                for (env, algo), cells in table.items()
            ],
        ),
    ]
    csv_rows = [
        {"game": env, "algorithm": algo, "tag": label, "window_start": k * window, "window_end": (k + 1) * window}
        | {"n": c[2], "mean": c[0], "std_err": c[1] if c[2] > 1 else "", "values": c[3]}
        for (env, algo), cells in table.items()
        for k, c in enumerate(cells)
        if c
    ]
    print(write(out, f"{name}_windows", "\n".join(lines) + "\n", csv_rows))
    return table


def interpolate(curves, grid_points):
    """Curves logged at different steps, aligned by linear interpolation onto one common step grid that spans the
    steps every curve covers (never by index). Returns (grid, [runs x grid] values)."""
    curves = [(s, v) for s, v in curves if len(s) > 0]
    lo, hi = max((s[0] for s, _ in curves), default=0), min((s[-1] for s, _ in curves), default=-1)
    if hi < lo:
        return None, None
    grid = np.linspace(lo, hi, grid_points) if hi > lo else np.array([lo])
    return grid, np.stack([np.interp(grid, s, v) for s, v in curves])


def last10_average(steps, values):
    """At each logged game, the average return of the last 10 games (thesis fig. 5.5)."""
    cumulative, index = np.concatenate([[0.0], np.cumsum(values)]), np.arange(1, len(values) + 1)
    start = np.maximum(index - 10, 0)
    return steps, (cumulative[index] - cumulative[start]) / (index - start)


def figure_curves(frame, kind, grid_points):
    """For one game's rows and one figure: algo -> (grid, centre, band or None, runs); the runs' count says "cut"
    where the shortest run cut the others by more than 5% of the longest."""
    rows, curves = frame[frame.tag == FIGURES[kind][0]], {}
    for algo in sorted(frame.algo.unique()):
        series = [(g.step.to_numpy(), g.value.to_numpy()) for _, g in rows[rows.algo == algo].groupby("run")]
        if kind == "return_last10":
            series = [last10_average(s, v) for s, v in series]
        grid, values = interpolate(series, grid_points)
        if grid is None:
            continue
        longest = max(s[-1] for s, _ in series if len(s))
        n = f"n={len(values)}" if longest - grid[-1] <= 0.05 * (longest - grid[0]) else f"n={len(values)}, cut"
        if kind == "return_variance":
            curves[algo] = (grid, values.var(axis=0), None, n)
        else:
            se = values.std(axis=0) / np.sqrt(len(values))
            curves[algo] = (grid, values.mean(axis=0), se if len(values) > 1 else None, n)
        if n.endswith("cut") and kind == "episodic_return":
            print(
                f"warning: {rows.env.iloc[0]} {algo}: its curves end at step {grid[-1]:,.0f}, where its shortest run"
                f" does; its longest goes on to {longest:,.0f}",
                file=sys.stderr,
            )
    return curves


def plot_curves(ax, curves, title, ylabel, fontsize=None) -> None:
    """One game's curves on `ax`: each algorithm's centre line (its run count in the legend) and ± band."""
    for algo, (grid, centre, band, n) in curves.items():
        (line,) = ax.plot(grid, centre, label=f"{algo} ({n})", marker="o" if len(grid) == 1 else None)
        if band is not None:
            ax.fill_between(grid, centre - band, centre + band, color=line.get_color(), alpha=0.25)
    ax.set_xlabel("environment steps")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=fontsize)


def save_figure(path: str, panels: list, draw, size: tuple[float, float], dpi: int = 120, title=None) -> str:
    """The one plotting helper: `draw(ax, panel)` for each panel, three to a row of `size` each, written to `path`."""
    import matplotlib

    matplotlib.use("Agg")  # files only, whatever display the machine has
    import matplotlib.pyplot as plt

    cols = min(3, len(panels))
    fig, axes = plt.subplots(
        -(-len(panels) // cols), cols, figsize=(size[0] * cols, size[1] * -(-len(panels) // cols)), squeeze=False
    )
    for ax, panel in zip(axes.flat, panels, strict=False):
        draw(ax, panel)
    for ax in axes.flat[len(panels) :]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def draw_profile(ax, aggregate) -> None:
    """rliable's performance profile (the fraction of runs above each human-normalised score) with its bands."""
    from rliable import plot_utils

    profiles, taus, cis = aggregate["profile"]
    plot_utils.plot_performance_profiles(profiles, taus, performance_profile_cis=cis, ax=ax)
    ax.set_title(f"performance profile over {len(aggregate['games'])} game(s), {aggregate['runs']} run(s) each")
    ax.legend(loc="upper right")  # rliable labels each line: a list of names would label a line and its band


def write_figures(frame, out, grid_points) -> list[str]:
    """Per game, one figure per FIGURES entry (thesis figs. 5.1-5.16), and with two games or more every game's training
    return side by side (figs. 5.1/5.5); mean ± s.e. over runs."""
    written = []
    for env, env_frame in frame.groupby("env"):
        for kind, (_, ylabel, title) in FIGURES.items():
            curves = figure_curves(env_frame, kind, grid_points)
            draw = lambda ax, c, t=f"{env}: {title}", y=ylabel: plot_curves(ax, c, t, y)  # noqa: E731
            written += (
                [save_figure(os.path.join(out, f"{env}__{kind}.png"), [curves], draw, (6.4, 4.2))] if curves else []
            )
    envs = sorted(frame[frame.tag == "charts/episodic_return"].env.unique())
    if len(envs) > 1:
        panels = [(env, figure_curves(frame[frame.env == env], "episodic_return", grid_points)) for env in envs]
        draw = lambda ax, p: plot_curves(ax, p[1], p[0], "episodic return", fontsize="small")  # noqa: E731
        title = "training return (full games), mean ± s.e. over runs"
        written.append(
            save_figure(os.path.join(out, "games__episodic_return.png"), panels, draw, (4.6, 3.4), 110, title)
        )
    return written


def folder_problem(path: str) -> str | None:
    """Why a folder could not be made (or written) at `path`, or None: checked before any work, so that a bad
    output folder is one sentence up front, not a traceback after the work (benchmark/evaluate.py uses it too)."""
    if not path.strip():  # an unset variable in a script: `--out ""` would be the current folder, silently
        return "an empty name is no folder"
    if any(len(part.encode()) > 255 for part in path.split(os.sep)):  # the file systems' limit on one name
        return "a name in it is longer than 255 bytes"
    probe = os.path.abspath(path)
    while not os.path.exists(probe):  # the nearest part of the path that exists must be a writable folder
        probe = os.path.dirname(probe)
    if not os.path.isdir(probe):
        return "it is a file" if probe == os.path.abspath(path) else f"{probe} is a file, not a folder"
    return None if os.access(probe, os.W_OK | os.X_OK) else f"{probe} is not writable"


def refusal(args: Args) -> str | None:
    """What is wrong with the command line, in one sentence, before anything is read or written; or None."""
    if not args.roots:
        return "give the folders of runs to read, e.g. `results.py runs/ --out results/`."
    if min(args.last, args.window_steps) < 0 or not (2 <= args.grid_points <= 1e5 and 1 <= args.bootstrap_reps <= 1e6):
        return (
            "--last and --window-steps must be 0 or more, --grid-points in [2, 100000] and --bootstrap-reps in"
            " [1, 1000000]."
        )
    if not 0 <= args.seed < 2**32:
        return f"--seed must lie in [0, 2^32 - 1] (numpy's seeds), got {args.seed}."
    try:
        if args.group_regex and not {"env", "algo"} <= set(re.compile(args.group_regex).groupindex):
            return "--group-regex needs the named groups (?P<env>...) and (?P<algo>...)."
    except re.error as e:
        return f"--group-regex is not a regular expression ({e})."
    if folder_problem(args.out):
        return f"--out {args.out} cannot be a folder for the tables: {folder_problem(args.out)}."
    if not args.table_name.strip() or "/" in args.table_name or len(args.table_name.encode()) > 200:
        return f"--table-name {args.table_name!r} must be a file name (not empty, no '/', 200 bytes at most)."
    if args.readme is None:
        return None
    try:
        text = open(args.readme).read()
    except OSError as e:
        return f"--readme {args.readme} cannot be read ({e.strerror})."
    if not text.count(README_BEGIN) == text.count(README_END) == 1 or text.index(README_BEGIN) > text.index(README_END):
        return f"--readme {args.readme} needs the line {README_BEGIN!r} and, after it, {README_END!r}, once each."
    return None


def main(args: Args) -> dict:
    if problem := refusal(args):
        sys.exit(f"error: {problem}")
    frame, problems = find_runs(args.roots, args.group_regex, args.above)
    frame = frame[frame.env.isin(args.games)] if args.games else frame
    for problem in problems:
        print(f"skipped: {problem}", file=sys.stderr)
    if frame.empty:
        sys.exit(f"error: no readable runs under {', '.join(args.roots)}.")
    roots, logged = ", ".join(args.roots), sorted(set(frame.tag))
    if args.tag not in logged and args.tag in SCRIPT_TAGS:  # no game over yet, in short runs: nothing to write
        print(f"no run under {roots} has logged {args.tag} yet; no table written", file=sys.stderr)
        return {"runs": frame.run.nunique(), "table": {}, "windows": {}, "across_games": None, "figures": []}
    if args.tag not in logged:  # a typo or an empty name: nothing to summarise, said before anything is written
        sys.exit(
            f"error: --tag {args.tag!r}: no run under {roots} logged it (they logged {', '.join(logged[:8])}, ...)."
        )
    if args.above is not None and args.tag in set(find_runs(args.roots, args.group_regex)[0].tag):
        sys.exit(f"error: --above reads a histogram tag (P3O's `p3o/beta`), but {args.tag} is a scalar tag.")
    os.makedirs(args.out, exist_ok=True)
    out, name = args.out, args.table_name
    label = args.tag if args.above is None else f"{args.tag} share above {args.above:g}"
    statistics = per_run(frame, args.tag, args.last)
    for run in sorted(set(frame.run) - set(statistics.index.get_level_values("run"))):
        print(f"skipped: {run}: no '{args.tag}' values, left out of the table", file=sys.stderr)
    table = {key: mean_se(x) for key, x in statistics.groupby(level=["env", "algo"])}
    print(write_table(table, out, name, label, args.last))
    print(f"wrote {os.path.join(out, name)}.md and .csv")
    windows = write_window_table(frame, out, name, args.tag, args.window_steps, label) if args.window_steps else {}
    if windows:
        print(f"wrote {os.path.join(out, name)}_windows.md and .csv")
    comparison, notes, aggregate = across_games(
        statistics, args.tag, args.last, args.p3o_name, args.ppo_name, args.bootstrap_reps, args.seed, args.figures
    )
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    profile = os.path.join(out, f"{name}_performance_profile.png")
    if comparison and args.figures:
        save_figure(profile, [aggregate], draw_profile, (6.4, 4.2))
        # named relative to the table, which sits in the same folder, so the committed text holds no machine's path
        comparison += "\nPerformance profile (fraction of runs above each human-normalised score):"
        comparison += f" `{os.path.basename(profile)}`\n"
    if comparison:
        print(write(out, f"{name}_across_games", comparison))
    tests_text, tests = per_game_tests(statistics, args.tag, args.last, args.p3o_name, args.ppo_name)
    if tests_text:
        print(write(out, f"{name}_per_game_tests", tests_text))
    ablations = ablation_tests(statistics, args.tag, args.last, args.ablations, args.p3o_name, args.ppo_name)
    if ablations:  # with fewer than two runs a side in every game, the file says so
        print(write(out, f"{name}_ablations", ablations))
    result = {"runs": frame.run.nunique(), "table": table, "windows": windows, "across_games": comparison}
    result |= {"per_game_tests": tests_text, "ablations": ablations, "figures": []}
    if args.readme is not None:
        block = readme_block(frame, table, tests, label, args.last, args.p3o_name, args.ppo_name, aggregate)
        before, rest = open(args.readme).read().split(README_BEGIN)
        path = os.path.realpath(args.readme)  # a symlink's file is written, not the link replaced by a file
        with open(f"{path}.tmp", "w") as f:  # written whole, then renamed: never half a README
            f.write(f"{before}{README_BEGIN}\n{block}{README_END}{rest.split(README_END)[1]}")
        os.replace(f"{path}.tmp", path)
        print(f"wrote the results block of {args.readme}")
        result["readme_block"] = block
    if args.figures:
        result["figures"] = write_figures(frame, out, args.grid_points) + ([profile] if comparison else [])
        print(f"wrote {len(result['figures'])} figures to {out}/")
        for path in result["figures"]:
            print(f"  {path}")
    return result


if __name__ == "__main__":
    main(tyro.cli(Args))
