"""From folders of TensorBoard runs to the thesis's table 5.1 and figures 5.1-5.16, and a P3O-vs-PPO
comparison across games (interquartile mean of human-normalised scores, rliable's protocol).

    uv run python benchmark/results.py runs/ --out results/
    uv run python benchmark/results.py runs/ --out results/ --tag charts/episodic_return --last 100 \
        --table-name train_last100 --no-figures

Runs are folders holding `events.out.tfevents.*` files, read into one long table (run, game, algorithm, tag,
step, value, wall time) and grouped by their folder's name, `{env_id}__{exp_name}[__{seed}[__{time}]]` as the
training scripts name them (a warning when the run logged another env id or exp name; a folder named otherwise,
by `--run-name` or evaluate.py, by the env id and exp name it logged), or by `--group-regex` with named groups
`env` and `algo`. Runs with unreadable files, no events, no name to group by or a missing tag are reported by
name and skipped. How long the runs took: benchmark/hours.py.
"""

import glob
import os
import re
import struct
import sys
import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd
import tyro
from scipy import stats

# Per-game random and human reference scores for human-normalised scores, (score - random) / (human -
# random), as tabulated for the Atari benchmark (Mnih et al. 2015; Badia et al. 2020, Agent57).
REFERENCE_SCORES = {
    "Alien": (227.8, 7127.7),
    "Asterix": (210.0, 8503.3),
    "BeamRider": (363.9, 16926.5),
    "Breakout": (1.7, 30.5),
    "Enduro": (0.0, 860.5),
    "Freeway": (0.0, 29.6),
    "MsPacman": (307.3, 6951.6),
    "Pong": (-20.7, 14.6),
    "Qbert": (163.9, 13455.0),
    "Riverraid": (1338.5, 17118.0),
    "Seaquest": (68.4, 42054.7),
    "SpaceInvaders": (148.0, 1668.7),
}
# The thesis's table 5.1 (20M steps, one trained model per game, 10 evaluation games): P3O, PPO
THESIS_TABLE = {
    "Breakout": (668.6, 363.4),
    "Freeway": (22.9, 22.8),
    "Seaquest": (2552.5, 1806.0),
    "Riverraid": (8898.0, 8096.7),
    "Qbert": (18462.5, 16855.0),
    "MsPacman": (5015.0, 1975.0),
}
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
    bootstrap_reps: int = 2000
    """stratified-bootstrap replications for the across-game confidence intervals"""
    seed: int = 0
    """seed of the bootstrap"""
    readme: str | None = None
    """a Markdown file (the README) whose block between the two marker lines (README_BEGIN, README_END) is
    replaced by the results table (with the per-game tests and the thesis's table 5.1) and the across-game line"""


def logged_identity(acc) -> dict:
    """env_id and exp_name from the `hyperparameters` text the training scripts log (empty if absent). Each row is
    `|name|value|`, split at its first inner bar: a value may be empty (`--wandb-entity=`)."""
    if "hyperparameters/text_summary" not in acc.Tags().get("tensors", []):
        return {}
    text = acc.Tensors("hyperparameters/text_summary")[0].tensor_proto.string_val[0].decode()
    table = dict(line[1:-1].split("|", 1) for line in text.splitlines() if line.count("|") >= 3)
    return {key: table[key] for key in ("env_id", "exp_name") if key in table}


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


def name_groups(name: str, pattern) -> tuple[str, str] | None:
    """(env, algo) from a run folder's name: --group-regex's groups, or `{env_id}__{exp_name}` less the seed and
    start time that follow (an exp name may hold `__` itself). find_runs prefers what the run logged."""
    if pattern:
        match = pattern.search(name)
        return (match.group("env"), match.group("algo")) if match else None
    parts = name.split("__")
    while len(parts) > 2 and parts[-1].isdigit():
        parts.pop()
    return (parts[0], "__".join(parts[1:])) if len(parts) >= 2 else None


def find_runs(roots, group_regex=None, above=None) -> tuple[pd.DataFrame, list[str]]:
    """Every folder under the roots with an event file, read with TensorBoard's own reader into one long table
    (COLUMNS), each tag's points in step order. With `above`, each histogram tag becomes a scalar series: the
    share of its values above that number."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tables, problems = [], []
    folders = {}  # one run per folder, however it was reached (`runs/x` and `./runs/x`, or a root inside another)
    for root in roots:
        if not os.path.isdir(root):
            problems.append(f"{root}: not a folder")
            continue
        for path in glob.glob(os.path.join(root, "**", "events.out.tfevents.*"), recursive=True):
            folders.setdefault(os.path.realpath(os.path.dirname(path)), os.path.dirname(path))
    pattern = re.compile(group_regex) if group_regex else None
    for folder in sorted(folders.values()):
        name = os.path.basename(os.path.normpath(folder))
        try:
            guidance = {"scalars": 0, "tensors": 1, "histograms": 0 if above is not None else 1}
            acc = EventAccumulator(folder, size_guidance=guidance)
            acc.Reload()
            points = {tag: [(e.step, e.value, e.wall_time) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}
            for tag in acc.Tags()["histograms"] if above is not None else []:
                points[tag] = [
                    (e.step, share_above(e.histogram_value, above), e.wall_time) for e in acc.Histograms(tag)
                ]
        except Exception as e:  # a truncated or foreign file: say which, go on
            problems.append(f"{folder}: unreadable event file ({type(e).__name__}: {e}), skipped")
            continue
        # eval.json, written last, says the evaluation is whole: eval/ points without it are not counted
        if not os.path.isfile(os.path.join(folder, "eval.json")):
            points = {tag: rows for tag, rows in points.items() if not tag.startswith("eval/")}
        groups, logged = name_groups(name, pattern), logged_identity(acc)
        identity = f"{logged.get('env_id')}__{logged.get('exp_name')}"
        # what the run logged, where the folder is named nothing else (a --run-name or evaluate.py folder) or is that
        # identity with a suffix of another convention (the thesis authors' `{env}__{exp}__{time}_EVALUATE`)
        if (
            not pattern
            and len(logged) == 2
            and (groups is None or name == identity or name.startswith(identity + "__"))
        ):
            groups = (logged["env_id"], logged["exp_name"])
        elif groups and not pattern and len(logged) == 2 and groups != (logged["env_id"], logged["exp_name"]):
            # the folder name is what TensorBoard shows and what the user can rename: it decides, loudly
            print(
                f"warning: {folder}: the folder name says {groups[0]} / {groups[1]} but the run logged"
                f" {logged['env_id']} / {logged['exp_name']}; grouped by the folder name",
                file=sys.stderr,
            )
        if groups is None:
            problems.append(
                f"{folder}: name does not match --group-regex, skipped"
                if pattern
                else f"{folder}: no logged hyperparameters and a name not {{env_id}}__{{exp_name}}__..., skipped"
            )
            continue
        if not points:
            problems.append(f"{folder}: no scalar events, skipped")
            continue
        for tag, rows in points.items():
            step, value, wall_time = np.array(rows, dtype=np.float64).T
            order = np.argsort(step, kind="stable")
            table = {"step": step[order], "value": value[order], "wall_time": wall_time[order]}
            tables.append(pd.DataFrame({"run": folder, "env": groups[0], "algo": groups[1], "tag": tag} | table))
        for file in sorted(glob.glob(os.path.join(folder, "events.out.tfevents.*"))):
            damage = truncation(file)
            if damage:
                print(f"warning: {file}: {damage}; the complete records before it are used", file=sys.stderr)
    return pd.concat(tables, ignore_index=True) if tables else pd.DataFrame(columns=COLUMNS), problems


def truncation(path: str) -> str | None:
    """What is wrong with an event file whose records do not fill it exactly (a write cut short: a killed
    process, a full disk, a partial copy), or None. A record is a little-endian uint64 length, its 4-byte CRC,
    the data and the data's 4-byte CRC."""
    size, position, records = os.path.getsize(path), 0, 0
    with open(path, "rb") as f:
        while position < size:
            header = f.read(12)
            length = struct.unpack("<Q", header[:8])[0] if len(header) == 12 else None
            if length is None or position + 16 + length > size:
                return (
                    f"truncated: its last {size - position} bytes are an incomplete record (after {records} complete)"
                )
            f.seek(length + 4, os.SEEK_CUR)
            position += 16 + length
            records += 1
    return None


def per_run(frame: pd.DataFrame, tag: str, last: int) -> pd.Series:
    """(env, algo, run) -> the run's statistic of the tag: the mean of its last `last` values (0: of all)."""
    values = frame[frame.tag == tag].groupby(["env", "algo", "run"])["value"]
    return values.agg(lambda v: float(np.mean(v.to_numpy()[-last:] if last else v.to_numpy())))


def mean_se(x) -> tuple[float, float, int]:
    """Mean, standard error with the population standard deviation (std / sqrt(n), as the thesis's
    table 5.1) and n of per-run statistics."""
    x = np.asarray(x, dtype=np.float64)  # not scipy.stats.sem(ddof=0): for one run it warns and gives nan, not 0
    return float(x.mean()), float(x.std() / np.sqrt(len(x))), len(x)


def per_game_scores(statistics: pd.Series, algos) -> dict:
    """env -> algo -> the per-run statistics (in run order), for the algorithms named."""
    per = {}
    for (env, algo), x in statistics.groupby(level=["env", "algo"]):
        if algo in algos:
            per.setdefault(env, {})[algo] = list(x.to_numpy())
    return per


def number(x: float) -> str:
    return f"{x:.1f}" if abs(x) >= 10 else f"{x:.2f}"  # game scores to 0.1, small ones (β, early returns) to 0.01


def mean_se_text(mean: float, se: float, n: int) -> str:
    """`mean ± s.e.`; a single run has no standard error, so none is written (not ± 0)."""
    return f"{number(mean)} ± {number(se)}" if n > 1 else number(mean)


def markdown(header: list[str], rows: list[list[str]]) -> list[str]:
    """A Markdown table's lines."""
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in rows]


def write(out: str, name: str, text: str, csv_rows: list[dict] | None = None) -> str:
    """OUT/NAME.md (and with `csv_rows` OUT/NAME.csv, comma-separated, CRLF lines as Python's csv module writes)."""
    with open(os.path.join(out, f"{name}.md"), "w") as f:
        f.write(text)
    if csv_rows is not None:
        pd.DataFrame(csv_rows).to_csv(os.path.join(out, f"{name}.csv"), index=False, lineterminator="\r\n")
    return text


def write_table(table, out, name, tag, last) -> str:
    envs = sorted({env for env, _ in table})
    algos = sorted({algo for _, algo in table})
    statistic = f"mean of the last {last} values" if last else "mean of all values"
    cell = lambda key: f"{mean_se_text(*table[key])} (n={table[key][2]})" if key in table else "–"  # noqa: E731
    lines = [
        f"`{tag}`, per run the {statistic}; mean ± standard error (population std / √n) over n runs (the mean"
        " alone for one run).",
        "",
        *markdown(["game", *algos], [[env, *(cell((env, algo)) for algo in algos)] for env in envs]),
    ]
    rows = [
        {"game": env, "algorithm": algo, "tag": tag, "last": last, "n": n, "mean": mean, "std_err": se if n > 1 else ""}
        for (env, algo), (mean, se, n) in table.items()
    ]
    return write(out, name, "\n".join(lines) + "\n", rows)


def summarise_windows(frame, tag, window) -> dict:
    """(env, algo) -> per window k of steps [k·window, (k+1)·window): `mean_se` over the runs with values
    there of each run's mean in the window, and the number of values in all; None for a window no run has
    values in."""
    rows = frame[frame.tag == tag]
    rows = rows.assign(k=(rows.step.to_numpy() // window).astype(int))
    per = rows.groupby(["env", "algo", "run", "k"])["value"].agg(
        mean=lambda v: float(np.mean(v.to_numpy())), count="size"
    )
    table = {}
    for key, group in per.groupby(level=["env", "algo"]):
        by_k = group.groupby(level="k")
        cells = {k: (*mean_se(g["mean"]), int(g["count"].sum())) for k, g in by_k}
        table[key] = [cells.get(k) for k in range(max(cells) + 1)]
    return table


def steps_label(steps: int) -> str:
    return "0" if steps == 0 else f"{steps / 1e6:g}M" if steps >= 1_000_000 else f"{steps / 1e3:g}k"


def write_window_table(table, out, name, tag, window) -> str:
    windows = max(len(cells) for cells in table.values())
    labels = [f"{steps_label(k * window)}–{steps_label((k + 1) * window)}" for k in range(windows)]
    rows = [
        [env, algo, *(f"{mean_se_text(*c[:3])} (n={c[2]}, {c[3]})" if c else "–" for c in cells)]
        + ["–"] * (windows - len(cells))
        for (env, algo), cells in table.items()
    ]
    lines = [
        f"`{tag}` per window of {window:,} env steps: per run the mean of its values in the window; mean ± standard"
        " error (population std / √n) over n runs (the mean alone for one run), and in brackets the number of"
        " values (games for episodic returns, iterations for losses and β).",
        "",
        *markdown(["game", "algorithm", *labels], rows),
    ]
    csv_rows = [
        {"game": env, "algorithm": algo, "tag": tag, "window_start": k * window, "window_end": (k + 1) * window}
        | {"n": c[2], "mean": c[0], "std_err": c[1] if c[2] > 1 else "", "values": c[3]}
        for (env, algo), cells in table.items()
        for k, c in enumerate(cells)
        if c
    ]
    return write(out, f"{name}_windows", "\n".join(lines) + "\n", csv_rows)


def last10_average(steps, values):
    """At each logged game, the average return of the last 10 games (thesis fig. 5.5)."""
    cumulative = np.concatenate([[0.0], np.cumsum(values)])
    index = np.arange(1, len(values) + 1)
    start = np.maximum(index - 10, 0)
    return steps, (cumulative[index] - cumulative[start]) / (index - start)


def interpolate(curves, grid_points):
    """Curves logged at different steps, aligned by linear interpolation onto one common step grid that
    spans the steps every curve covers (never by index). Returns (grid, [runs x grid] values); where that cuts
    more than 5% of the longest curve, figure_curves says so in the legend and write_figures on stderr."""
    curves = [(s, v) for s, v in curves if len(s) > 0]
    if not curves:
        return None, None
    lo = max(s[0] for s, _ in curves)
    hi = min(s[-1] for s, _ in curves)
    if hi < lo:
        return None, None
    grid = np.linspace(lo, hi, grid_points) if hi > lo else np.array([lo])
    return grid, np.stack([np.interp(grid, s, v) for s, v in curves])


def figure_curves(frame, kind, grid_points):
    """For one game's rows and one figure: algo -> (grid, centre, band or None, runs)."""
    rows = frame[frame.tag == FIGURES[kind][0]]
    curves = {}
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


def pyplot():
    import matplotlib

    matplotlib.use("Agg")  # files only, whatever display the machine has
    import matplotlib.pyplot as plt

    return plt


def plot(ax, curves, title, ylabel, fontsize=None) -> None:
    """One game's curves on `ax`: each algorithm's centre line (its run count in the legend) and ± band."""
    for algo, (grid, centre, band, n) in curves.items():  # n: the runs, and "cut" where the shortest cut them
        (line,) = ax.plot(grid, centre, label=f"{algo} ({n})", marker="o" if len(grid) == 1 else None)
        if band is not None:
            ax.fill_between(grid, centre - band, centre + band, color=line.get_color(), alpha=0.25)
    ax.set_xlabel("environment steps")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=fontsize)


def write_figures(frame, out, grid_points) -> list[str]:
    """Per game, one figure per FIGURES entry (thesis figs. 5.1-5.16), mean ± s.e. over runs."""
    plt, written = pyplot(), []
    for env, env_frame in frame.groupby("env"):
        for kind, (_, ylabel, title) in FIGURES.items():
            curves = figure_curves(env_frame, kind, grid_points)
            if not curves:
                continue
            fig, ax = plt.subplots(figsize=(6.4, 4.2))
            plot(ax, curves, f"{env}: {title}", ylabel)
            fig.tight_layout()
            written.append(os.path.join(out, f"{env}__{kind}.png"))
            fig.savefig(written[-1], dpi=120)
            plt.close(fig)
    return written


def write_games_figure(frame, out, grid_points, name) -> str | None:
    """One figure of every game's training return curves side by side (mean ± s.e. over runs), as the
    thesis's figures 5.1/5.5."""
    envs = sorted(frame[frame.tag == "charts/episodic_return"].env.unique())
    if len(envs) < 2:
        return None
    plt = pyplot()
    cols = min(3, len(envs))
    rows = -(-len(envs) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.4 * rows), squeeze=False)
    for ax, env in zip(axes.flat, envs, strict=False):
        curves = figure_curves(frame[frame.env == env], "episodic_return", grid_points)
        plot(ax, curves, env, "episodic return", fontsize="small")
    for ax in axes.flat[len(envs) :]:
        ax.set_visible(False)
    fig.suptitle("training return (full games), mean ± s.e. over runs")
    fig.tight_layout()
    path = os.path.join(out, f"{name}.png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def human_normalised(score, env):
    game = env.split("-")[0]
    random_score, human_score = REFERENCE_SCORES[game]
    return (score - random_score) / (human_score - random_score)


def mean_gap_shares(scores, games, p3o, ppo) -> tuple[str, float, dict]:
    """Per game, its part of the gap between the two algorithms' human-normalised means (the mean over games
    of each game's mean over runs, as rliable's): (P3O's game mean - PPO's) / the number of games, and that
    as a share of the whole gap, so that a reader sees when one game decides the mean."""
    per_game = scores[p3o].mean(axis=0) - scores[ppo].mean(axis=0)  # [games]
    gap = per_game.sum() / len(games)
    lines = [
        f"The mean's gap, {p3o} - {ppo}, is {gap:.3f}; each game's part of it (its difference of means over runs,"
        " divided by the number of games) and share (negative: that game pulls the other way):",
        "",
        "| game | difference of means | part of the gap | share of the gap |",
        "|---|---|---|---|",
    ]
    shares = {
        env: difference / len(games) / gap if gap != 0 else None
        for env, difference in zip(games, per_game, strict=True)
    }
    for env, difference in zip(games, per_game, strict=True):
        share = f"{100 * shares[env]:.0f}%" if gap != 0 else "–"
        lines.append(f"| {env} | {difference:.3f} | {difference / len(games):.3f} | {share} |")
    return "\n".join(lines), float(gap), shares


def across_games(statistics, tag, last, p3o, ppo, reps, seed, figure_path=None) -> tuple[str | None, list[str], dict]:
    """The interquartile mean, median and mean of human-normalised scores with stratified-bootstrap 95% CIs,
    the probability that P3O improves on PPO, and (with `figure_path`) the performance profile, with rliable
    (Agarwal et al. 2021)."""
    from rliable import library as rly
    from rliable import metrics

    notes = []
    per = {}
    for env, algos in per_game_scores(statistics, (p3o, ppo)).items():
        if env.split("-")[0] not in REFERENCE_SCORES:
            notes.append(f"{env}: no human/random reference score, left out of the across-game comparison")
            continue
        per[env] = {algo: [human_normalised(x, env) for x in stats] for algo, stats in algos.items()}
    games = sorted(env for env, algos in per.items() if p3o in algos and ppo in algos)
    if not games:
        return None, sorted(set(notes)), {}
    n = min(len(per[env][algo]) for env in games for algo in (p3o, ppo))
    unequal = ""
    if any(len(per[env][algo]) != n for env in games for algo in (p3o, ppo)):
        # rliable's stratified bootstrap needs as many runs of every game; the table says what it left out
        counts = ", ".join(f"{env} {len(per[env][p3o])}/{len(per[env][ppo])}" for env in games)
        unequal = (
            f" Runs per game differ ({p3o}/{ppo}: {counts}): only the first {n} of each game and algorithm,"
            " in folder-name order, are used here."
        )
        notes.append(unequal.strip())
    scores = {algo: np.array([[per[env][algo][i] for env in games] for i in range(n)]) for algo in (p3o, ppo)}
    state = np.random.RandomState(seed)
    # rliable's StratifiedBootstrap (the IQM, median and mean, and the performance profile) draws its resamples
    # from numpy's global generator, not from the random_state it is given (its update_indices): seeded too, the
    # same --seed gives the same intervals and figure
    np.random.seed(seed)
    pair = f"{p3o},{ppo}"
    aggregates = [
        ("IQM", metrics.aggregate_iqm),
        ("median", metrics.aggregate_median),
        ("mean", metrics.aggregate_mean),
    ]
    with warnings.catch_warnings():
        # rliable passes the seeded RandomState on to arch's bootstrap, which warns that the argument is deprecated
        warnings.filterwarnings("ignore", message="random_state is deprecated", category=FutureWarning)
        point, ci = rly.get_interval_estimates(
            scores, lambda x: np.array([f(x) for _, f in aggregates]), reps=reps, random_state=state
        )
        poi, poi_ci = rly.get_interval_estimates(
            {pair: (scores[p3o], scores[ppo])}, metrics.probability_of_improvement, reps=reps, random_state=state
        )
        if figure_path:
            taus = np.linspace(min(s.min() for s in scores.values()), max(s.max() for s in scores.values()), 101)
            profiles, profile_cis = rly.create_performance_profile(scores, taus, reps=reps)
    lines = [
        f"Across {len(games)} game(s) ({', '.join(games)}), {n} run(s) each, `{tag}`"
        + (f" (last {last})" if last else "")
        + f", human-normalised; {reps} stratified-bootstrap replications (rliable). The IQM is over every run of"
        " every game; the median and mean are over the games, of each game's mean over its runs." + unequal,
        "",
        "| algorithm | runs per game | " + " | ".join(f"{name} | 95% CI" for name, _ in aggregates) + " |",
        "|---|---|" + "---|---|" * len(aggregates),
    ]
    if n == 1:  # the bootstrap resamples runs within each game: with one, every replication is the same
        lines[0] += (
            " With one run per game there is nothing to resample, so no confidence interval is given (a bootstrap"
            " interval would be the point itself)."
        )
    interval = (lambda lo, hi: f"[{lo:.3f}, {hi:.3f}]") if n > 1 else (lambda lo, hi: "–")
    for algo in (p3o, ppo):
        cells = [f"{point[algo][k]:.3f} | {interval(ci[algo][0][k], ci[algo][1][k])}" for k in range(len(aggregates))]
        lines.append(f"| {algo} | {n} | " + " | ".join(cells) + " |")
    poi_interval = interval(float(np.squeeze(poi_ci[pair][0])), float(np.squeeze(poi_ci[pair][1])))
    lines += ["", f"P({p3o} > {ppo}) = {float(np.squeeze(poi[pair])):.3f}, 95% CI {poi_interval}"]
    tests = improvement_tests(scores[p3o], scores[ppo])
    lines += [
        "",
        f"Two tests of P({p3o} > {ppo}) = 0.5, for two questions. Is there a difference within these {len(games)}"
        f" games? The stratified exact permutation test (runs relabelled within each game; every game's splits, their"
        f" averages combined exactly): p = {tests['stratified']:.3f}. Is {p3o} better across games, the games as the"
        f" units? The exact sign-flip test of the games' P - 0.5: p = {tests['sign_flip']:.3f} (Wilcoxon's signed-rank"
        f" test: p = {tests['wilcoxon']:.3f}). Two-sided p.",
    ]
    shares_text, gap, shares = mean_gap_shares(scores, games, p3o, ppo)
    lines += ["", shares_text]
    if figure_path:
        from rliable import plot_utils

        plt = pyplot()

        fig, ax = plt.subplots(figsize=(6.4, 4.2))
        plot_utils.plot_performance_profiles(profiles, taus, performance_profile_cis=profile_cis, ax=ax)
        ax.set_title(f"performance profile over {len(games)} game(s), {n} run(s) each")
        # rliable labels each algorithm's line; a list of names would label the first artists (a line and its band)
        ax.legend(loc="upper right")
        fig.tight_layout()
        fig.savefig(figure_path, dpi=120)
        plt.close(fig)
        # named relative to the table, which sits in the same folder, so the committed text holds no machine's path
        name = os.path.basename(figure_path)
        lines += ["", f"Performance profile (fraction of runs above each human-normalised score): `{name}`"]
    numbers = {
        "games": games,
        "runs": n,
        "reps": reps,
        "aggregates": {
            algo: {name: (point[algo][k], ci[algo][0][k], ci[algo][1][k]) for k, (name, _) in enumerate(aggregates)}
            for algo in (p3o, ppo)
        },
        "mean_gap": (gap, shares),
        "improvement": tuple(float(np.squeeze(x)) for x in (poi[pair], poi_ci[pair][0], poi_ci[pair][1])),
        "improvement_tests": tests,
    }
    return "\n".join(lines) + "\n", sorted(set(notes)), numbers


def improvement_tests(x, y) -> dict:
    """Two-sided p of P(X > Y) = 0.5, the mean over games of each game's P(X > Y) + P(X = Y) / 2 over its run pairs
    (rliable's probability of improvement), from x and y [runs x games]. `stratified`: the exact permutation test with
    the runs relabelled within each game (each game's every split; the games' statistics are independent under it,
    so the average's distribution is their exact convolution) - no difference within these games. `sign_flip`: the
    exact test with the games as the units (each game's P - 0.5 flipped in sign, every pattern), and `wilcoxon` its
    rank test - better across games."""
    from itertools import combinations, product

    def pairs(a, b):  # 2 * (the pairs with a > b, plus half the ties), an integer
        return int(2 * (a[:, None] > b[None, :]).sum() + (a[:, None] == b[None, :]).sum())

    games, m, k = x.shape[1], len(x), len(y)
    observed = sum(pairs(x[:, g], y[:, g]) for g in range(games))
    distribution = np.ones(1)  # the sum over no games: 0
    for g in range(games):  # each game's exact distribution over its splits, convolved into the sum's
        pooled = np.concatenate([x[:, g], y[:, g]])
        counts = np.zeros(2 * m * k + 1)
        for chosen in combinations(range(m + k), m):
            rest = [i for i in range(m + k) if i not in chosen]
            counts[pairs(pooled[list(chosen)], pooled[rest])] += 1
        distribution = np.convolve(distribution, counts / counts.sum())
    centre = games * m * k  # the sum when P = 0.5
    stratified = distribution[np.abs(np.arange(len(distribution)) - centre) >= abs(observed - centre) - 1e-9].sum()
    effects = np.array([pairs(x[:, g], y[:, g]) / (2 * m * k) - 0.5 for g in range(games)])
    flips = [abs((effects * np.array(s)).mean()) >= abs(effects.mean()) - 1e-12 for s in product([1, -1], repeat=games)]
    wilcoxon = stats.wilcoxon(effects).pvalue if np.any(effects) else 1.0
    return {"stratified": float(min(stratified, 1.0)), "sign_flip": float(np.mean(flips)), "wilcoxon": float(wilcoxon)}


def exact_permutation_p(a, b) -> float:
    """The two-sided p of the difference of means under every split of the pooled runs into groups of
    len(a) and len(b) (scipy's exact permutation test: 20 splits for 3 against 3, 252 for 5 against 5).
    Ties count as they fall, unlike the exact Mann-Whitney U of scipy, which ignores them."""

    def difference(x, y, axis):
        return np.mean(x, axis=axis) - np.mean(y, axis=axis)

    test = stats.permutation_test(
        (a, b), difference, permutation_type="independent", vectorized=True, n_resamples=np.inf
    )
    return float(test.pvalue)


def per_game_tests(statistics, tag, last, p3o, ppo) -> str | None:
    """Per game, whether P3O and PPO can be told apart: the difference of the means with Welch's 95% CI and
    two-sided p (a t test: assumes roughly normal run scores), and the exact two-sided permutation test of
    the difference of means (assumes nothing but exchangeable runs)."""
    from math import comb

    per = per_game_scores(statistics, (p3o, ppo))
    games = sorted(env for env, algos in per.items() if len(algos.get(p3o, [])) > 1 and len(algos.get(ppo, [])) > 1)
    if not games:
        return None
    sizes = sorted({(len(per[env][p3o]), len(per[env][ppo])) for env in games})
    smallest = ", ".join(f"{2 / comb(m + k, m):.3g} for {m} runs against {k}" for m, k in sizes)
    lines = [
        f"`{tag}`" + (f" (last {last})" if last else "") + f": per game, {p3o} against {ppo} over their runs:"
        " the difference of the means; Welch's t test (unequal variances) with its 95% confidence interval of"
        " the difference and two-sided p; and the exact two-sided permutation test of the same difference over"
        f" every split of the game's runs into two groups (ties count; its smallest possible p is {smallest}).",
        "",
        "| game | n | difference of means | Welch 95% CI | Welch p | exact permutation p |",
        "|---|---|---|---|---|---|",
    ]
    for env in games:
        difference, lo, hi, welch_p, permutation_p = compare(per[env][p3o], per[env][ppo])
        lines.append(
            f"| {env} | {len(per[env][p3o])} vs {len(per[env][ppo])} | {number(difference)} |"
            f" [{number(lo)}, {number(hi)}] | {welch_p:.3f} | {permutation_p:.3f} |"
        )
    return "\n".join(lines) + "\n"


def compare(a, b) -> tuple[float, float, float, float, float]:
    """mean(a) - mean(b), Welch's 95% CI of it and its two-sided p, and the exact permutation test's p."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    welch = stats.ttest_ind(a, b, equal_var=False)
    lo, hi = welch.confidence_interval(0.95)
    return float(a.mean() - b.mean()), float(lo), float(hi), float(welch.pvalue), exact_permutation_p(a, b)


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
    if not os.access(probe, os.W_OK | os.X_OK):
        return f"{probe} is not writable"
    return None


def readme_markers(path: str) -> str:
    """The file's text, or one sentence and exit 1 when it lacks the two marker lines, in order."""
    try:
        text = open(path).read()
    except OSError as e:
        sys.exit(f"error: --readme {path} cannot be read ({e.strerror}).")
    if (
        text.count(README_BEGIN) != 1
        or text.count(README_END) != 1
        or text.index(README_BEGIN) > text.index(README_END)
    ):
        sys.exit(f"error: --readme {path} needs the line {README_BEGIN!r} and, after it, {README_END!r}, once each.")
    return text


def rounded(x: float, like: float) -> str:
    """x to the precision that suits `like` (a game score to 1, a return under 100 to 0.1, under 10 to 0.01)."""
    decimals = 0 if abs(like) >= 100 else 1 if abs(like) >= 10 else 2
    return f"{x:,.{decimals}f}"


def readme_block(frame, statistics, table, tag, last, p3o, ppo, aggregate) -> str:
    """The README's results: per game the mean ± s.e. (n) of each algorithm and the random policy, the two
    per-game tests, the thesis's table 5.1; then the across-game aggregates in one line."""
    per = per_game_scores(statistics, (p3o, ppo))
    envs = sorted(
        {env for env, _ in table},
        key=lambda env: (list(THESIS_TABLE).index(env.split("-")[0]) if env.split("-")[0] in THESIS_TABLE else 99, env),
    )
    others = sorted({algo for _, algo in table} - {p3o, ppo})
    games = list(frame[frame.tag == tag].groupby("run").size())
    each = f"the mean of its {games[0]} values" if len(set(games)) == 1 else "the mean of its values"
    lines = [
        f"Per game: mean ± standard error over n runs (n in brackets), each run's score being {each} of `{tag}`"
        + (f" (the last {last})" if last else "")
        + "; the standard error is the population standard deviation over the runs / √n, as in the thesis's"
        " table 5.1. Tests of the difference: Welch's t and the exact permutation test (two-sided p).",
        "",
        "| game | P3O | PPO | "
        + " | ".join(f"{algo} policy" if algo == "random" else algo for algo in others)
        + (" | " if others else "")
        + "P3O − PPO: difference; Welch p, permutation p | thesis table 5.1 (20M): P3O / PPO |",
        "|---|---|---|" + "---|" * len(others) + "---|---|",
    ]
    for env in envs:
        cells = []
        for algo in [p3o, ppo, *others]:
            if (env, algo) in table:
                mean, se, n = table[env, algo]
                cells.append(
                    f"{rounded(mean, mean)} ± {rounded(se, mean)} ({n})" if n > 1 else f"{rounded(mean, mean)} (1)"
                )
            else:
                cells.append("–")
        a, b = per.get(env, {}).get(p3o, []), per.get(env, {}).get(ppo, [])
        if len(a) > 1 and len(b) > 1:
            difference, _, _, welch_p, permutation_p = compare(a, b)
            sign = "+" if difference > 0 else ""
            like = max(abs(np.mean(a)), abs(np.mean(b)))
            cells.append(f"{sign}{rounded(difference, like)}; {welch_p:.3f}, {permutation_p:.3f}")
        else:
            cells.append("–")
        thesis = THESIS_TABLE.get(env.split("-")[0])
        cells.append(f"{thesis[0]:,.1f} / {thesis[1]:,.1f}" if thesis else "–")
        lines.append(f"| {env.split('-')[0]} | " + " | ".join(cells) + " |")
    if aggregate:
        k = aggregate["aggregates"]
        parts = [
            f"{name} {k[p3o][name][0]:.3f} [{k[p3o][name][1]:.3f}, {k[p3o][name][2]:.3f}] against"
            f" {k[ppo][name][0]:.3f} [{k[ppo][name][1]:.3f}, {k[ppo][name][2]:.3f}]"
            for name in ("IQM", "median", "mean")
        ]
        poi, lo, hi = aggregate["improvement"]
        lines += [
            "",
            f"**Across the {len(aggregate['games'])} games** ({aggregate['runs']} runs each, human-normalised, 95%"
            f" stratified-bootstrap CIs over {aggregate['reps']:,} replications, rliable), P3O against PPO: "
            + "; ".join(parts)
            + f"; P(P3O > PPO) = {poi:.3f} [{lo:.3f}, {hi:.3f}]: a difference within these games, p ="
            f" {aggregate['improvement_tests']['stratified']:.3f} (stratified exact permutation test); P3O better"
            f" across games, p = {aggregate['improvement_tests']['sign_flip']:.3f} (exact sign-flip test, games as"
            " the units).",
        ]
        gap, shares = aggregate["mean_gap"]
        if gap != 0:
            parts = [
                f"{env.split('-')[0]} {100 * share:.0f}%"
                for env, share in sorted(shares.items(), key=lambda x: -abs(x[1]))
            ]
            lines[-1] += f" Each game's share of the mean's gap ({gap:.3f}): " + ", ".join(parts) + "."
    return "\n".join(lines) + "\n"


def main(args: Args) -> dict:
    if not args.roots:
        sys.exit("error: give the folders of runs to read, e.g. `results.py runs/ --out results/`.")
    if (
        args.last < 0
        or args.window_steps < 0
        or not 2 <= args.grid_points <= 100_000
        or not 1 <= args.bootstrap_reps <= 10**6
    ):
        sys.exit(
            "error: --last and --window-steps must be 0 or more, --grid-points in [2, 100000] and --bootstrap-reps in"
            " [1, 1000000]."
        )
    if not 0 <= args.seed < 2**32:
        sys.exit(f"error: --seed must lie in [0, 2^32 - 1] (numpy's seeds), got {args.seed}.")
    if args.group_regex:
        try:
            if not {"env", "algo"} <= set(re.compile(args.group_regex).groupindex):
                sys.exit("error: --group-regex needs the named groups (?P<env>...) and (?P<algo>...).")
        except re.error as e:
            sys.exit(f"error: --group-regex is not a regular expression ({e}).")
    if folder_problem(args.out):
        sys.exit(f"error: --out {args.out} cannot be a folder for the tables: {folder_problem(args.out)}.")
    if not args.table_name.strip() or "/" in args.table_name or len(args.table_name.encode()) > 200:
        sys.exit(f"error: --table-name {args.table_name!r} must be a file name (not empty, no '/', 200 bytes at most).")
    readme = readme_markers(args.readme) if args.readme else None
    frame, problems = find_runs(args.roots, args.group_regex, args.above)
    frame = frame[frame.env.isin(args.games)] if args.games else frame
    for problem in problems:
        print(f"skipped: {problem}", file=sys.stderr)
    if frame.empty:
        sys.exit(f"error: no readable runs under {', '.join(args.roots)}.")
    if args.tag not in set(frame.tag):  # a typo or an empty name: nothing to summarise, said before anything is written
        logged = ", ".join(sorted(set(frame.tag))[:8])
        sys.exit(
            f"error: --tag {args.tag!r}: no run under {', '.join(args.roots)} logged it (they logged {logged}, ...)."
        )
    if args.above is not None and args.tag in set(find_runs(args.roots, args.group_regex)[0].tag):
        sys.exit(f"error: --above reads a histogram tag (P3O's `p3o/beta`), but {args.tag} is a scalar tag.")
    os.makedirs(args.out, exist_ok=True)
    label = args.tag if args.above is None else f"{args.tag} share above {args.above:g}"
    statistics = per_run(frame, args.tag, args.last)
    for run in sorted(set(frame.run) - set(statistics.index.get_level_values("run"))):
        print(f"skipped: {run}: no '{args.tag}' values, left out of the table", file=sys.stderr)
    table = {key: mean_se(x) for key, x in statistics.groupby(level=["env", "algo"])}
    result = {"runs": frame.run.nunique(), "table": table, "figures": [], "across_games": None}
    if table:
        print(write_table(table, args.out, args.table_name, label, args.last))
        print(f"wrote {os.path.join(args.out, args.table_name)}.md and .csv")
    else:
        print(f"no run has '{args.tag}'; no table written", file=sys.stderr)
    result["windows"] = summarise_windows(frame, args.tag, args.window_steps) if args.window_steps else {}
    if result["windows"]:
        print(write_window_table(result["windows"], args.out, args.table_name, label, args.window_steps))
        print(f"wrote {os.path.join(args.out, args.table_name)}_windows.md and .csv")
    profile = os.path.join(args.out, f"{args.table_name}_performance_profile.png") if args.figures else None
    comparison, notes, aggregate = across_games(
        statistics, args.tag, args.last, args.p3o_name, args.ppo_name, args.bootstrap_reps, args.seed, profile
    )
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    if comparison:
        print(write(args.out, f"{args.table_name}_across_games", comparison))
        result["across_games"] = comparison
    tests = per_game_tests(statistics, args.tag, args.last, args.p3o_name, args.ppo_name)
    if tests:
        print(write(args.out, f"{args.table_name}_per_game_tests", tests))
    result["per_game_tests"] = tests
    if readme is not None:
        block = readme_block(frame, statistics, table, label, args.last, args.p3o_name, args.ppo_name, aggregate)
        before, rest = readme.split(README_BEGIN)
        after = rest.split(README_END)[1]
        path = os.path.realpath(args.readme)  # a symlink's file is written, not the link replaced by a file
        with open(f"{path}.tmp", "w") as f:  # written whole, then renamed: never half a README
            f.write(f"{before}{README_BEGIN}\n{block}{README_END}{after}")
        os.replace(f"{path}.tmp", path)
        print(f"wrote the results block of {args.readme}")
        result["readme_block"] = block
    if args.figures:
        result["figures"] = write_figures(frame, args.out, args.grid_points)
        games = write_games_figure(frame, args.out, args.grid_points, "games__episodic_return")
        result["figures"] += [games] if games else []
        result["figures"] += [profile] if comparison else []
        print(f"wrote {len(result['figures'])} figures to {args.out}/")
        for path in result["figures"]:
            print(f"  {path}")
    return result


if __name__ == "__main__":
    main(tyro.cli(Args))
