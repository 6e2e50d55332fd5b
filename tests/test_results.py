"""benchmark/results.py on event files written here with SummaryWriter, with known values."""

import csv
import json
import os
import re

import numpy as np
import pytest
from torch.utils.tensorboard import SummaryWriter

from benchmark import comparison, hours, results

P3O, PPO = "p3o_atari_envpool", "ppo_atari_envpool"
# eval returns per (game, algo, seed): 10 games each, known means
EVAL = {
    ("Breakout-v5", P3O): [[10.0] * 10, [20.0] * 10, [30.0] * 10],
    ("Breakout-v5", PPO): [[5.0] * 10, [7.0] * 10, [9.0] * 10],
    ("Qbert-v5", P3O): [list(range(10)), [100.0] * 10, [200.0] * 10],
    ("Qbert-v5", PPO): [[50.0] * 10, [150.0] * 10, [250.0] * 10],
}


def evaluated(run, returns):
    """The run's eval.json, the record that its evaluation is whole (results.py counts eval/ points only beside it)."""
    os.makedirs(run, exist_ok=True)
    with open(os.path.join(run, "eval.json"), "w") as f:
        json.dump({"returns": list(returns)}, f)


def write_run(root, env, algo, seed, eval_returns, step_every):
    run = os.path.join(root, f"{env}__{algo}__{seed}__1700000000")
    writer = SummaryWriter(run)
    for game, ret in enumerate(eval_returns):
        writer.add_scalar("eval/episodic_return", ret, game)
    evaluated(run, eval_returns)
    # a training curve: episodic return = step / 1000 (+ seed), logged every `step_every` steps
    for step in range(step_every, 100_001, step_every):
        writer.add_scalar("charts/episodic_return", step / 1000 + seed, step)
        writer.add_scalar("losses/entropy", 1.0 - step / 200_000, step)
        writer.add_scalar("losses/explained_variance", 0.5, step)
        writer.add_scalar("losses/policy_loss", -0.01, step)
        writer.add_scalar("losses/value_loss", 0.1, step)
        if algo == P3O:
            writer.add_scalar("p3o/beta_mean", 0.4, step)
    writer.close()
    return run


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("runs"))
    for (env, algo), per_seed in EVAL.items():
        for seed, returns in enumerate(per_seed, start=1):
            write_run(root, env, algo, seed, returns, step_every=1000 * seed)  # different logging steps
    # problem runs, reported and skipped
    os.makedirs(os.path.join(root, "Breakout-v5__p3o_atari_envpool__9__1"))
    with open(os.path.join(root, "Breakout-v5__p3o_atari_envpool__9__1", "events.out.tfevents.1.x.1"), "wb") as f:
        f.write(b"\x00\x01garbage, not a record")
    empty = SummaryWriter(os.path.join(root, "Qbert-v5__ppo_atari_envpool__8__1"))
    empty.close()
    no_eval = SummaryWriter(os.path.join(root, "Qbert-v5__p3o_atari_envpool__7__1"))
    no_eval.add_scalar("losses/entropy", 1.0, 1)
    no_eval.close()
    return root


def test_table_means_standard_errors_and_n_are_exact(root, tmp_path, capsys):
    out = str(tmp_path / "out")
    result = results.main(results.Args(roots=(root,), out=out, figures=False, bootstrap_reps=200))
    table = result["table"]
    # per-run means: Breakout P3O 10, 20, 30 -> mean 20, population std sqrt(200/3)
    assert table["Breakout-v5", P3O] == pytest.approx((20.0, np.sqrt(200 / 3) / np.sqrt(3), 3))
    assert table["Breakout-v5", PPO] == pytest.approx((7.0, np.sqrt(8 / 3) / np.sqrt(3), 3))
    assert table["Qbert-v5", P3O] == pytest.approx((np.mean([4.5, 100, 200]), np.std([4.5, 100, 200]) / np.sqrt(3), 3))
    assert table["Qbert-v5", PPO] == pytest.approx((150.0, np.std([50, 150, 250]) / np.sqrt(3), 3))
    with open(os.path.join(out, "table.csv")) as f:
        rows = list(csv.DictReader(f))
    row = next(r for r in rows if r["game"] == "Breakout-v5" and r["algorithm"] == P3O)
    assert float(row["mean"]) == pytest.approx(20.0) and int(row["n"]) == 3
    markdown = open(os.path.join(out, "table.md")).read()
    assert "| Breakout-v5 | 20.0 ± 4.71 (n=3) | 7.00 ± 0.94 (n=3) |" in markdown  # below 10: two decimals
    err = capsys.readouterr().err
    assert "Breakout-v5__p3o_atari_envpool__9__1" in err  # unreadable
    assert "Qbert-v5__ppo_atari_envpool__8__1" in err  # empty
    assert "Qbert-v5__p3o_atari_envpool__7__1: no 'eval/episodic_return' values" in err  # missing tag


def test_last_k_statistic(root, tmp_path):
    result = results.main(
        results.Args(roots=(root,), out=str(tmp_path), tag="charts/episodic_return", last=10, figures=False)
    )
    # seed s logs step/1000 + s every 1000 s steps up to 100000
    expected = [np.mean([step / 1000 + s for step in range(1000 * s, 100_001, 1000 * s)][-10:]) for s in (1, 2, 3)]
    mean, se, n = result["table"]["Breakout-v5", PPO]
    assert (mean, se, n) == pytest.approx((np.mean(expected), np.std(expected) / np.sqrt(3), 3))


def test_window_table_means_per_run_then_over_runs(root, tmp_path):
    out = str(tmp_path / "out")
    args = results.Args(roots=(root,), out=out, tag="charts/episodic_return", window_steps=50_000, figures=False)
    windows = results.main(args)["windows"]["Breakout-v5", PPO]
    # by hand, seed s logging step/1000 + s every 1000 s steps up to 100000, windows [0, 50k), [50k, 100k),
    # [100k, 150k): seed 1 means 26 (49 games), 75.5 (50), 101 (1); seed 2: 27 (24), 76 (25), 102 (1);
    # seed 3: 28.5 (16), 78 (17), none (its last step is 99000)
    expected = [[26, 27, 28.5], [75.5, 76, 78], [101, 102]]
    counts = [89, 92, 2]
    assert len(windows) == 3
    for (mean, se, n, count), x, games in zip(windows, expected, counts, strict=True):
        assert (mean, se, n, count) == pytest.approx((np.mean(x), np.std(x) / np.sqrt(len(x)), len(x), games))
    markdown = open(os.path.join(out, "table_windows.md")).read()
    assert "| game | algorithm | 0–50k | 50k–100k | 100k–150k |" in markdown
    assert (
        f"| Breakout-v5 | {PPO} | 27.2 ± 0.59 (n=3, 89) | 76.5 ± 0.62 (n=3, 92) | 101.5 ± 0.35 (n=2, 2) |" in markdown
    )
    with open(os.path.join(out, "table_windows.csv")) as f:
        rows = [r for r in csv.DictReader(f) if r["game"] == "Breakout-v5" and r["algorithm"] == PPO]
    assert [(int(r["window_start"]), int(r["n"]), int(r["values"])) for r in rows] == [
        (0, 3, 89),
        (50_000, 3, 92),
        (100_000, 2, 2),
    ]
    with pytest.raises(SystemExit, match="--window-steps must be 0 or more"):
        results.main(results.Args(roots=(root,), out=out, window_steps=-1))


def test_group_regex_overrides_grouping(root, tmp_path):
    result = results.main(
        results.Args(
            roots=(root,), out=str(tmp_path), figures=False, group_regex=r"^(?P<env>[A-Za-z]+)-v5__(?P<algo>p..)"
        )
    )
    assert set(result["table"]) == {("Breakout", "p3o"), ("Breakout", "ppo"), ("Qbert", "p3o"), ("Qbert", "ppo")}


def test_interpolation_aligns_runs_logged_at_different_steps():
    a = (np.array([0.0, 10.0, 20.0]), np.array([0.0, 10.0, 20.0]))
    b = (np.array([5.0, 25.0]), np.array([0.0, 40.0]))
    grid, values = results.interpolate([a, b], 4)
    np.testing.assert_allclose(grid, [5.0, 10.0, 15.0, 20.0])  # the steps both runs cover
    np.testing.assert_allclose(values[0], [5.0, 10.0, 15.0, 20.0])
    np.testing.assert_allclose(values[1], [0.0, 10.0, 20.0, 30.0])


def test_curves_of_runs_with_different_logging_steps_average_by_step(root):
    frame, _ = results.find_runs((root,))
    breakout = frame[frame.env == "Breakout-v5"]
    curves = results.figure_curves(breakout, "episodic_return", 50)
    grid, mean, se, n = curves[PPO]
    assert n == "n=3"  # every run reaches the end of the curves: none is cut
    # seeds 1, 2, 3 log step/1000 + seed at every 1000, 2000, 3000 steps: at any common step the mean
    # is step/1000 + 2 and the standard error that of (1, 2, 3); by index they would not line up
    np.testing.assert_allclose(mean, grid / 1000 + 2, rtol=1e-6)
    np.testing.assert_allclose(se, np.std([1, 2, 3]) / np.sqrt(3), rtol=1e-6)
    _, variance, _, _ = results.figure_curves(breakout, "return_variance", 50)[PPO]
    np.testing.assert_allclose(variance, np.var([1, 2, 3]), rtol=1e-6)


def test_last10_average():
    steps = np.arange(12.0)
    _, avg = results.last10_average(steps, np.arange(12.0))
    np.testing.assert_allclose(avg[:3], [0.0, 0.5, 1.0])
    np.testing.assert_allclose(avg[-1], np.mean(np.arange(2, 12)))


def test_figures_are_valid_pngs(root, tmp_path):
    out = str(tmp_path / "figs")
    result = results.main(results.Args(roots=(root,), out=out, bootstrap_reps=200))
    names = {os.path.basename(p) for p in result["figures"]}
    for env in ("Breakout-v5", "Qbert-v5"):
        for kind in results.FIGURES:
            assert f"{env}__{kind}.png" in names
    for path in result["figures"]:
        with open(path, "rb") as f:
            assert f.read(8) == b"\x89PNG\r\n\x1a\n"
        assert os.path.getsize(path) > 10_000


def test_across_games_iqm_and_probability_of_improvement(root, tmp_path):
    result = results.main(results.Args(roots=(root,), out=str(tmp_path), figures=False, bootstrap_reps=500))
    text = result["across_games"]
    assert "Across 2 game(s) (Breakout-v5, Qbert-v5), 3 run(s) each" in text
    assert f"P({P3O} > {PPO}) = " in text
    # Breakout: every P3O run beats every PPO run, Qbert: P3O's runs (4.5, 100, 200) vs (50, 150, 250)
    # win 0 + 1 + 2 = 3 of 9 pairs -> P = (1 + 3/9) / 2
    p = float(text.split(f"P({P3O} > {PPO}) = ")[1].split(",")[0])
    assert p == pytest.approx((1 + 3 / 9) / 2, abs=1e-3)
    assert os.path.isfile(tmp_path / "table_across_games.md")
    # the IQM by hand: human-normalised per-run scores, (score - random) / (human - random), of both games
    # pooled (3 runs x 2 games), the lowest and highest quarter (one value each) dropped, the rest averaged
    for algo, (breakout, qbert) in {P3O: ([10, 20, 30], [4.5, 100, 200]), PPO: ([5, 7, 9], [50, 150, 250])}.items():
        scores = [(x - 1.7) / (30.5 - 1.7) for x in breakout] + [(x - 163.9) / (13455.0 - 163.9) for x in qbert]
        iqm = np.sort(scores)[1:-1].mean()
        row = re.search(rf"\| {algo} \| 3 \| (-?[\d.]+) \| \[(-?[\d.]+), (-?[\d.]+)\] \|", text)
        point, lo, hi = (float(g) for g in row.groups())
        assert point == pytest.approx(iqm, abs=5e-4)
        # a bootstrap IQM averages values drawn from the scores, so the interval lies within their range
        assert min(scores) - 5e-4 <= lo <= point <= hi <= max(scores) + 5e-4 and lo < hi


def test_no_runs_is_a_clear_error(tmp_path):
    with pytest.raises(SystemExit, match="no readable runs"):
        results.main(results.Args(roots=(str(tmp_path),), out=str(tmp_path / "o")))


def test_runs_named_with_run_name_are_grouped_by_their_logged_hyperparameters(tmp_path):
    # folders named as a user names them with --run-name: only the logged hyperparameters say what they are
    for name, env, algo, value in [("breakout_p3o", "Breakout-v5", P3O, 4.0), ("b_ppo_a", "Breakout-v5", PPO, 2.0)]:
        writer = SummaryWriter(str(tmp_path / "runs" / name))
        writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n|exp_name|{algo}|\n|seed|1|\n|env_id|{env}|")
        writer.add_scalar("eval/episodic_return", value, 0)
        writer.close()
        evaluated(tmp_path / "runs" / name, [value])
    # and a run that logged none falls back on its folder name
    writer = SummaryWriter(str(tmp_path / "runs" / f"Qbert-v5__{PPO}__1__1"))
    writer.add_scalar("eval/episodic_return", 7.0, 0)
    writer.close()
    evaluated(tmp_path / "runs" / f"Qbert-v5__{PPO}__1__1", [7.0])
    result = results.main(results.Args(roots=(str(tmp_path / "runs"),), out=str(tmp_path / "o"), figures=False))
    assert result["table"] == {
        ("Breakout-v5", P3O): (4.0, 0.0, 1),
        ("Breakout-v5", PPO): (2.0, 0.0, 1),
        ("Qbert-v5", PPO): (7.0, 0.0, 1),
    }


def test_a_folder_named_for_another_algorithm_than_it_logged_is_grouped_by_its_name_with_a_warning(tmp_path, capsys):
    # a run copied or renamed to `{env_id}__{exp_name}__...`: the name the user sees in TensorBoard decides
    for name, algo, value in [(f"Breakout-v5__{P3O}__1", P3O, 4.0), ("Breakout-v5__p3o-lr1e-3__1", P3O, 6.0)]:
        writer = SummaryWriter(str(tmp_path / "runs" / name))
        writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n|exp_name|{algo}|\n|seed|1|\n|env_id|Breakout-v5|")
        writer.add_scalar("eval/episodic_return", value, 0)
        writer.close()
        evaluated(tmp_path / "runs" / name, [value])
    result = results.main(results.Args(roots=(str(tmp_path / "runs"),), out=str(tmp_path / "o"), figures=False))
    assert result["table"] == {("Breakout-v5", P3O): (4.0, 0.0, 1), ("Breakout-v5", "p3o-lr1e-3"): (6.0, 0.0, 1)}
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning: ")]
    assert warnings == [
        f"warning: {tmp_path}/runs/Breakout-v5__p3o-lr1e-3__1: the folder name says Breakout-v5 / p3o-lr1e-3 but the"
        f" run logged Breakout-v5 / {P3O}; grouped by the folder name"
    ]


def test_above_reads_a_histogram_as_the_share_of_values_above_a_threshold(tmp_path):
    # beta-like values in [0, 1], logged as TensorBoard histograms: the share above 0.5 per iteration, read from
    # the buckets, is the true share to within the one bucket that straddles 0.5 (TensorBoard's ~10% buckets)
    rng = np.random.default_rng(0)
    writer = SummaryWriter(str(tmp_path / "runs" / f"Breakout-v5__{P3O}__1"))
    truth = []
    for i, step in enumerate(range(1000, 11_000, 1000)):
        values = rng.beta(1 + i, 2.0, size=4096)
        values[:10] = [0.0, 1.0, 0.5, 0.5, 0.25, 0.75, 0.49, 0.51, 0.999, 0.001]
        writer.add_histogram("p3o/beta", values, step)
        truth.append((values > 0.5).mean())
    writer.close()
    args = results.Args(roots=(str(tmp_path / "runs"),), out=str(tmp_path / "o"), figures=False)
    args.tag, args.above, args.window_steps, args.table_name = "p3o/beta", 0.5, 5000, "beta_above"
    result = results.main(args)
    frame, _ = results.find_runs(args.roots, above=0.5)
    assert frame.run.nunique() == 1
    steps, shares = frame[frame.tag == "p3o/beta"].step.to_numpy(), frame[frame.tag == "p3o/beta"].value.to_numpy()
    assert list(steps) == list(range(1000, 11_000, 1000))
    np.testing.assert_allclose(shares, truth, atol=0.02)
    assert shares[-1] > shares[0] + 0.3  # the distributions move right, and so does the share
    windows = result["windows"]["Breakout-v5", P3O]
    assert windows[0][0] == pytest.approx(np.mean(shares[:4])) and windows[1][0] == pytest.approx(np.mean(shares[4:9]))
    text = open(tmp_path / "o" / "beta_above_windows.md").read()
    assert text.startswith("`p3o/beta share above 0.5` per window of 5,000 env steps")
    # without --above a histogram is not read: this run has nothing else, so there is nothing to tabulate
    args.above = None
    with pytest.raises(SystemExit, match="no readable runs"):
        results.main(args)


def test_across_games_median_mean_and_the_per_game_tests(root, tmp_path):
    from scipy import stats

    result = results.main(results.Args(roots=(root,), out=str(tmp_path), figures=False, bootstrap_reps=200))
    text = result["across_games"]
    assert "| algorithm | runs per game | IQM | 95% CI | median | 95% CI | mean | 95% CI |" in text
    per_game = {}
    for algo, (breakout, qbert) in {P3O: ([10, 20, 30], [4.5, 100, 200]), PPO: ([5, 7, 9], [50, 150, 250])}.items():
        scores = [(x - 1.7) / (30.5 - 1.7) for x in breakout] + [(x - 163.9) / (13455.0 - 163.9) for x in qbert]
        row = re.search(rf"\| {algo} \|(.*)\|\n", text).group(1).split("|")
        per_game[algo] = [np.mean(scores[:3]), np.mean(scores[3:])]  # rliable: median and mean over game means
        assert int(row[0]) == 3  # the runs per game beside the aggregates
        assert float(row[3]) == pytest.approx(np.median(per_game[algo]), abs=5e-4)
        assert float(row[5]) == pytest.approx(np.mean(per_game[algo]), abs=5e-4)
    # each game's share of the mean's gap: its difference of means / the number of games / the gap
    differences = np.subtract(per_game[P3O], per_game[PPO])
    gap = differences.mean()
    assert f"is {gap:.3f};" in text
    for env, difference in zip(["Breakout-v5", "Qbert-v5"], differences, strict=True):
        share = 100 * difference / 2 / gap
        assert f"| {env} | {difference:.3f} | {difference / 2:.3f} | {share:.0f}% |" in text
    assert round(100 * differences[0] / 2 / gap) > 100 > 0 > round(100 * differences[1] / 2 / gap)  # Qbert pulls back
    tests = result["per_game_tests"]
    assert open(tmp_path / "table_per_game_tests.md").read() == tests
    assert "| game | n | difference of means | Welch 95% CI | Welch p | exact permutation p |" in tests
    assert "smallest possible p is 0.1 for 3 runs against 3" in tests
    # Breakout: P3O (10, 20, 30) against PPO (5, 7, 9): mean difference 13, every P3O run above every PPO run,
    # which 2 of the 20 splits of six runs into three and three reach: exact p = 0.1
    row = re.search(
        r"\| Breakout-v5 \| 3 vs 3 \| 13\.0 \| \[(-?[\d.]+), (-?[\d.]+)\] \| ([\d.]+) \| ([\d.]+) \|", tests
    )
    welch = stats.ttest_ind([10, 20, 30], [5, 7, 9], equal_var=False)
    lo, hi = welch.confidence_interval(0.95)
    assert (float(row.group(1)), float(row.group(2))) == (pytest.approx(lo, abs=0.05), pytest.approx(hi, abs=0.05))
    assert float(row.group(3)) == pytest.approx(welch.pvalue, abs=5e-4) and float(row.group(4)) == 0.1
    assert "| Qbert-v5 | 3 vs 3 | -48.5 | " in tests  # (4.5 + 100 + 200) / 3 - 150


def test_the_exact_permutation_test_counts_ties_and_every_split():
    from itertools import combinations

    # Freeway's three seeds: a 0.0 on each side. Mann-Whitney's exact p ignores the tie (1.0); over all 20 splits
    # the difference of means is at least as far from 0 as the observed 0.3 in 16 of them: p = 0.8
    p3o, ppo = [27.9, 0.0, 28.7], [27.6, 28.1, 0.0]
    assert comparison.exact_permutation_p(p3o, ppo) == pytest.approx(0.8)
    # brute force over every split, two-sided as scipy's (twice the smaller tail)
    pooled, observed = np.array(p3o + ppo), np.mean(p3o) - np.mean(ppo)
    splits = [np.mean(pooled[list(i)]) - np.mean(np.delete(pooled, list(i))) for i in combinations(range(6), 3)]
    tails = (np.mean(np.array(splits) >= observed - 1e-9), np.mean(np.array(splits) <= observed + 1e-9))
    assert comparison.exact_permutation_p(p3o, ppo) == pytest.approx(min(1.0, 2 * min(tails)))
    # five runs against five, every one of one side above the other's: 2 of the 252 splits, p = 0.0079
    assert comparison.exact_permutation_p([6, 7, 8, 9, 10], [1, 2, 3, 4, 5]) == pytest.approx(2 / 252)
    assert comparison.exact_permutation_p([1, 2, 3], [1, 2, 3]) == 1.0


def test_the_games_figure_and_the_performance_profile(root, tmp_path, monkeypatch):
    import matplotlib.figure
    from matplotlib.colors import to_hex
    from matplotlib.lines import Line2D

    legends, save = [], matplotlib.figure.Figure.savefig

    def read_legend(fig, path, *args, **kwargs):  # the profile's legend, read as it is saved
        if str(path).endswith("_performance_profile.png"):
            ax = fig.axes[0]
            lines = {line.get_label(): to_hex(line.get_color()) for line in ax.get_lines()}
            legend = ax.get_legend()
            entries = zip(legend.get_texts(), legend.legend_handles, strict=True)
            legends.append((lines, [(text.get_text(), handle) for text, handle in entries]))
        return save(fig, path, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", read_legend)
    result = results.main(results.Args(roots=(root,), out=str(tmp_path), bootstrap_reps=200))
    names = {os.path.basename(p) for p in result["figures"]}
    assert {"games__episodic_return.png", "table_performance_profile.png"} <= names
    for name in ("games__episodic_return.png", "table_performance_profile.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and (tmp_path / name).stat().st_size > 10_000
    # the committed table names the figure beside it, never this machine's folder
    text = (tmp_path / "table_across_games.md").read_text()
    assert "`table_performance_profile.png`" in text and str(tmp_path) not in text
    # the legend names each algorithm beside its own line, in that line's colour (not a line and its band)
    [(lines, entries)] = legends
    assert [name for name, _ in entries] == ["p3o_atari_envpool", "ppo_atari_envpool"]
    for name, handle in entries:
        assert isinstance(handle, Line2D) and to_hex(handle.get_color()) == lines[name]
    assert lines["p3o_atari_envpool"] != lines["ppo_atari_envpool"]


def test_the_bootstrap_intervals_and_the_performance_profile_are_the_same_for_the_same_seed(root, tmp_path):
    # the across-game CIs and the profile's bands are bootstrapped: the same --seed gives the same table and
    # figure (rliable resamples from numpy's global generator, whatever random_state it is given), another
    # seed other ones
    made = []
    for seed, out in [(1, "a"), (1, "b"), (2, "c")]:
        args = results.Args(roots=(root,), out=str(tmp_path / out), bootstrap_reps=200, seed=seed, grid_points=2)
        results.main(args)
        table = (tmp_path / out / "table_across_games.md").read_text()
        made.append((table, (tmp_path / out / "table_performance_profile.png").read_bytes()))
    assert made[0] == made[1]
    assert made[2][0] != made[0][0] and made[2][1] != made[0][1]


def test_a_single_run_has_no_standard_error(tmp_path):
    """One run's spread is unknown: the tables write its mean alone (not `± 0.00`) and the CSVs leave the
    standard error empty, while a group of three keeps its `±`."""
    root = str(tmp_path / "runs")
    write_run(root, "Freeway-v5", P3O, 1, [27.0] * 10, step_every=1000)
    for seed in (1, 2, 3):
        write_run(root, "Freeway-v5", PPO, seed, [20.0 + seed] * 10, step_every=1000)
    out = str(tmp_path / "out")
    results.main(results.Args(roots=(root,), out=out, figures=False, bootstrap_reps=50))
    assert "| Freeway-v5 | 27.0 (n=1) | 22.0 ± 0.47 (n=3) |" in open(os.path.join(out, "table.md")).read()
    with open(os.path.join(out, "table.csv")) as f:
        rows = {r["algorithm"]: r for r in csv.DictReader(f)}
    assert rows[P3O]["std_err"] == "" and float(rows[PPO]["std_err"]) == pytest.approx(
        np.std([21, 22, 23]) / np.sqrt(3)
    )
    args = results.Args(roots=(root,), out=out, tag="charts/episodic_return", window_steps=50_000, figures=False)
    results.main(args)
    # seed 1 logs step / 1000 + 1 every 1000 steps: 49 games below 50k with mean 26
    markdown = open(os.path.join(out, "table_windows.md")).read()
    assert f"| Freeway-v5 | {P3O} | 26.0 (n=1, 49) |" in markdown and "± 0.00" not in markdown
    with open(os.path.join(out, "table_windows.csv")) as f:
        assert all(r["std_err"] == "" for r in csv.DictReader(f) if r["algorithm"] == P3O)


def test_games_with_more_runs_than_others_say_in_the_table_which_runs_the_comparison_used(tmp_path):
    """rliable's stratified bootstrap needs as many runs of every game: while a sweep is under way (Breakout
    three seeds, Freeway one) the committed across-game table names the counts and that only each game's first
    run in folder-name order (seed 1 here) is used, and its scores are those runs'."""
    root = str(tmp_path / "runs")
    for seed in (1, 2, 3):
        write_run(root, "Breakout-v5", P3O, seed, [10.0 * seed] * 10, step_every=1000)
        write_run(root, "Breakout-v5", PPO, seed, [5.0 * seed] * 10, step_every=1000)
    write_run(root, "Freeway-v5", P3O, 1, [27.0] * 10, step_every=1000)
    write_run(root, "Freeway-v5", PPO, 1, [21.0] * 10, step_every=1000)
    out = str(tmp_path / "out")
    results.main(results.Args(roots=(root,), out=out, figures=False, bootstrap_reps=50))
    text = open(os.path.join(out, "table_across_games.md")).read()
    assert "Across 2 game(s) (Breakout-v5, Freeway-v5), 1 run(s) each" in text
    assert (
        f"Runs per game differ ({P3O}/{PPO}: Breakout-v5 3/3, Freeway-v5 1/1): only the first 1 of each game and"
        " algorithm, in folder-name order, are used here." in text
    )
    # one run per game: the IQM of two values is their mean; seed 1's Breakout (10 and 5), not 20 or 30
    for algo, breakout, freeway in ((P3O, 10.0, 27.0), (PPO, 5.0, 21.0)):
        expected = ((breakout - 1.7) / (30.5 - 1.7) + (freeway - 0.0) / (29.6 - 0.0)) / 2
        row = re.search(rf"\| {algo} \| 1 \| (-?[\d.]+) \|", text)
        assert float(row.group(1)) == pytest.approx(expected, abs=5e-4)
    # one run per game: the bootstrap has nothing to resample, so no interval (not [x, x])
    assert "With one run per game there is nothing to resample, so no confidence interval is given" in text
    assert re.search(rf"\| {P3O} \| 1 \| [\d.]+ \| – \| [\d.]+ \| – \| [\d.]+ \| – \|", text)
    assert re.search(rf"P\({P3O} > {PPO}\) = [\d.]+, 95% CI –", text)


def write_process(folder, start, iterations, every, purge_step=None):
    """One training process of a run: per-iteration `charts/SPS` points every `every` seconds after 100 s of
    start-up, in an event file named for `start` as SummaryWriter names it (`events.out.tfevents.<start>...`)."""
    scratch = f"{folder}.process"
    writer = SummaryWriter(scratch, purge_step=purge_step)
    if purge_step is None:  # a first start logs its hyperparameters first, as the training scripts do
        writer.add_text("hyperparameters", "|param|value|\n|-|-|\n|seed|1|", walltime=start)
    for k, iteration in enumerate(iterations, start=1):
        writer.add_scalar("charts/SPS", 100.0, iteration * 4096, walltime=start + 100 + every * k)
    writer.close()
    os.makedirs(folder, exist_ok=True)
    (name,) = os.listdir(scratch)
    os.rename(os.path.join(scratch, name), os.path.join(folder, f"events.out.tfevents.{int(start)}.host.1.0"))
    os.rmdir(scratch)


def test_hours_are_the_elapsed_time_of_each_process_and_the_union_over_runs(tmp_path):
    """hours.md: a run killed after iteration 10 (checkpoint after 8), resumed, killed again in its start-up
    and resumed ten hours later counts the time of its two training processes, without the pause and without
    the purged iterations 9-10 of the first, and two resumes; the
    machine's wall clock is the union over runs; a run with no training points (the random policy) is not in
    it."""
    t0 = 1_700_000_000  # 2023-11-14 22:13:20 UTC
    root = str(tmp_path / "runs")
    p3o = os.path.join(root, f"Breakout-v5__{P3O}__1")
    write_process(p3o, t0, range(1, 11), every=300)
    write_process(p3o, t0 + 30_000, [], every=300, purge_step=8 * 4096 + 1)  # killed in its start-up
    write_process(p3o, t0 + 36_000, range(9, 21), every=300, purge_step=8 * 4096 + 1)
    # a stray event file in the run's folder (a copy, another tool's writer): neither a start nor a resume
    stray = SummaryWriter(str(tmp_path / "stray"))
    stray.add_text("note", "not a training process", walltime=t0 + 20_000)
    stray.close()
    (name,) = os.listdir(tmp_path / "stray")
    os.rename(tmp_path / "stray" / name, os.path.join(p3o, f"events.out.tfevents.{t0 + 20_000}.other.2.0"))
    write_process(os.path.join(root, f"Breakout-v5__{PPO}__1"), t0, range(1, 21), every=200)
    write_run(root, "Breakout-v5", "random", 1, [1.0] * 10, step_every=50_000)
    out = str(tmp_path / "out")
    hours.main(hours.Args(roots=(root,), out=out))
    with open(os.path.join(out, "hours.csv")) as f:
        rows = {r["algorithm"]: r for r in csv.DictReader(f)}
    assert set(rows) == {P3O, PPO}
    # P3O: (100 + 8 × 300) + (100 + 12 × 300) = 6,200 s; PPO: 100 + 20 × 200 = 4,100 s
    assert (rows[P3O]["iterations"], rows[P3O]["resumes"], rows[P3O]["seconds_per_iteration"]) == ("20", "2", "300.00")
    assert float(rows[P3O]["hours_elapsed"]) == pytest.approx(6200 / 3600, abs=1e-4)
    assert float(rows[PPO]["hours_elapsed"]) == pytest.approx(4100 / 3600, abs=1e-4)
    assert (rows[PPO]["first_start_utc"], rows[P3O]["last_iteration_utc"]) == (
        "2023-11-14 22:13 UTC",
        "2023-11-15 09:15 UTC",  # t0 + 36,000 + 3,700
    )
    markdown = open(os.path.join(out, "hours.md")).read()
    assert f"| Breakout-v5 | {P3O} | 1 | 1.72 | 300.00 | 2 |" in markdown
    assert f"| Breakout-v5 | {PPO} | 1 | 1.14 | 200.00 | 0 |" in markdown
    # union: [t0, t0 + 4,100] and [t0 + 36,000, t0 + 39,700] = 7,800 s
    assert "All 2 runs: 2.9 hours elapsed summed over runs" in markdown
    assert "training during 2.2 hours of wall clock between 2023-11-14 22:13 UTC and 2023-11-15 09:15 UTC" in markdown


def test_readme_replaces_only_the_block_between_its_markers(root, tmp_path):
    readme = tmp_path / "README.md"
    text = f"# title\n\nbefore\n{results.README_BEGIN}\nstale table\n{results.README_END}\nafter\n"
    readme.write_text(text)
    result = results.main(
        results.Args(roots=(root,), out=str(tmp_path / "out"), figures=False, bootstrap_reps=200, readme=str(readme))
    )
    written = readme.read_text()
    assert written.startswith("# title\n\nbefore\n" + results.README_BEGIN + "\n")
    assert written.endswith(results.README_END + "\nafter\n") and "stale table" not in written
    block = result["readme_block"]
    assert written == text.replace("stale table\n", block)
    # per game: mean ± s.e. (n), the two tests, the thesis's table 5.1; then the across-game line
    assert "| Breakout | 20.0 ± 4.7 (3) | 7.00 ± 0.94 (3) | +13.0; " in block  # population std / √3
    welch = float(re.search(r"\| Breakout \|.*\+13\.0; ([\d.]+), ([\d.]+) \|", block).group(1))
    from scipy import stats

    assert welch == pytest.approx(stats.ttest_ind([10, 20, 30], [5, 7, 9], equal_var=False).pvalue, abs=5e-4)
    assert "| 668.6 / 363.4 |" in block and "| 18,462.5 / 16,855.0 |" in block
    assert "**Across the 2 games** (3 runs each" in block and "P(P3O > PPO) = " in block


def test_a_readme_without_its_markers_is_refused_before_any_work(root, tmp_path, capsys):
    readme = tmp_path / "README.md"
    readme.write_text("# a README with no results block\n")
    for path in (readme, tmp_path / "missing.md"):
        with pytest.raises(SystemExit) as stop:
            results.main(results.Args(roots=(root,), out=str(tmp_path / "out"), readme=str(path)))
        assert str(stop.value).startswith(f"error: --readme {path}") and str(path) in str(stop.value)
    assert not (tmp_path / "out").exists()  # refused before reading a run or writing a file
    assert readme.read_text() == "# a README with no results block\n"


def test_the_readme_results_block_is_what_results_py_writes_from_the_committed_runs(tmp_path):
    """README.md's table and across-game line come from the committed learning-check runs; when a run is added
    or results.py changes, rewrite them with the command below instead of by hand."""
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    readme = tmp_path / "README.md"
    readme.write_text(open(os.path.join(repo, "README.md")).read())
    runs = os.path.join(repo, "benchmark", "results", "learning_check", "runs")
    results.main(results.Args(roots=(runs,), out=str(tmp_path), figures=False, readme=str(readme)))
    assert readme.read_text() == open(os.path.join(repo, "README.md")).read(), (
        "README.md's results block is not what the committed runs give; rewrite it with `uv run python"
        " benchmark/results.py benchmark/results/learning_check/runs --out benchmark/results/learning_check"
        " --readme README.md`"
    )


@pytest.mark.parametrize(
    "against_p3o, against_ppo, reading",
    [
        ((-300.0, 0.008), (-20.0, 0.69), "takes the lead away: below P3O (p 0.008), not told apart from PPO (p 0.690)"),
        ((-10.0, 0.55), (250.0, 0.016), "keeps the lead: not told apart from P3O (p 0.550), above PPO (p 0.016)"),
        (
            (-90.0, 0.095),
            (60.0, 0.19),
            "cannot tell: not told apart from P3O (p 0.095), not told apart from PPO (p 0.190)",
        ),
        ((600.0, 0.008), (880.0, 0.008), "above both: above P3O (p 0.008), above PPO (p 0.008)"),
        ((-460.0, 0.008), (-190.0, 0.032), "below both: below P3O (p 0.008), below PPO (p 0.032)"),
        ((-100.0, 0.016), (120.0, 0.024), "between: below P3O (p 0.016), above PPO (p 0.024)"),
        ((200.0, 0.040), (300.0, 0.10), "neither: above P3O (p 0.040), not told apart from PPO (p 0.100)"),
        ((-0.5, 0.049), (-0.2, 0.050), "takes the lead away: below P3O (p 0.049), not told apart from PPO (p 0.050)"),
    ],
)
def test_an_ablation_reading_follows_the_fixed_rule(against_p3o, against_ppo, reading):
    """Told apart means an exact permutation p below 0.05 (p 0.050 is not); the direction of the differences picks
    the words."""
    (d_p3o, p_p3o), (d_ppo, p_ppo) = against_p3o, against_ppo
    as_tested = (d_p3o, 0.0, 0.0, 0.0, p_p3o), (d_ppo, 0.0, 0.0, 0.0, p_ppo)  # (difference, lo, hi, Welch p, perm p)
    assert comparison.ablation_reading(*as_tested) == reading


def test_one_folder_given_twice_or_under_two_roots_is_one_run(root, tmp_path):
    single = results.main(results.Args(roots=(root,), out=str(tmp_path / "a"), figures=False, bootstrap_reps=10))
    dotted = os.path.join(os.path.relpath(root), ".")  # the same folder by another path
    inner = os.path.join(root, f"Breakout-v5__{P3O}__1__1700000000")
    twice = results.main(
        results.Args(roots=(root, dotted, inner), out=str(tmp_path / "b"), figures=False, bootstrap_reps=10)
    )
    assert twice["runs"] == single["runs"] and twice["table"] == single["table"]
    assert twice["table"]["Breakout-v5", P3O][2] == 3


def test_an_exp_name_with_double_underscores_is_not_split_at_them(tmp_path, capsys):
    """Two experiments `my__a` and `my__b`, named by the scripts' default folder name, stay two groups (not
    one `my` group), and no rename warning is printed; a folder renamed to another algorithm still wins."""
    root = str(tmp_path / "runs")
    for exp, value in (("my__a", 10.0), ("my__b", 20.0)):
        for seed in (1, 2):
            writer = SummaryWriter(os.path.join(root, f"Breakout-v5__{exp}__{seed}__1700000000"))
            table = f"|param|value|\n|-|-|\n|exp_name|{exp}|\n|env_id|Breakout-v5|\n|seed|{seed}|"
            writer.add_text("hyperparameters", table)
            writer.add_scalar("eval/episodic_return", value, 0)
            writer.close()
            evaluated(os.path.join(root, f"Breakout-v5__{exp}__{seed}__1700000000"), [value])
    result = results.main(results.Args(roots=(root,), out=str(tmp_path / "out"), figures=False))
    assert set(result["table"]) == {("Breakout-v5", "my__a"), ("Breakout-v5", "my__b")}
    assert result["table"]["Breakout-v5", "my__a"][:3] == (10.0, 0.0, 2)
    assert "warning" not in capsys.readouterr().err


def test_a_truncated_event_file_is_named_and_its_complete_records_used(tmp_path, capsys):
    root = str(tmp_path / "runs")
    run = write_run(root, "Breakout-v5", P3O, 1, [7.0] * 10, step_every=50_000)
    (name,) = [f for f in os.listdir(run) if f.startswith("events.out.tfevents.")]
    path = os.path.join(run, name)
    results.main(results.Args(roots=(root,), out=str(tmp_path / "out"), figures=False))
    assert "damaged" not in capsys.readouterr().err  # a whole file: no warning
    with open(path, "ab") as f:  # a write cut short: a record's header and part of its data
        f.write((1000).to_bytes(8, "little") + b"\x00" * 4 + b"partial")
    result = results.main(results.Args(roots=(root,), out=str(tmp_path / "out"), figures=False))
    err = capsys.readouterr().err  # TensorBoard's loader found the cut record; results.py names the file
    assert f"warning: {path}: a damaged or incomplete record; the records before it are used" in err
    assert result["table"]["Breakout-v5", P3O][:3] == (7.0, 0.0, 1)  # the complete records are still read


def logged_run(folder, env, exp, eval_returns=None, rows=""):
    """A run folder as the scripts write it: the hyperparameters table (with `rows` more) and eval points."""
    writer = SummaryWriter(str(folder))
    writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n|exp_name|{exp}|\n|env_id|{env}|\n|seed|1|{rows}")
    for game, value in enumerate(eval_returns or []):
        writer.add_scalar("eval/episodic_return", value, game)
    writer.close()
    if eval_returns:
        evaluated(folder, eval_returns)


def test_an_empty_cell_among_the_logged_hyperparameters_is_read(tmp_path, capsys):
    """`--wandb-entity=` (an unset variable in a sweep) logs the row `|wandb_entity||`: the folder is still read and
    grouped by what it logged, with the others."""
    logged_run(tmp_path / "runs" / "mine", "Breakout-v5", P3O, [3.0], rows="\n|wandb_entity||\n|run_name||")
    logged_run(tmp_path / "runs" / "other", "Breakout-v5", P3O, [5.0])
    result = results.main(results.Args(roots=(str(tmp_path / "runs"),), out=str(tmp_path / "o"), figures=False))
    assert result["table"] == {("Breakout-v5", P3O): (4.0, pytest.approx(1 / np.sqrt(2)), 2)}
    assert "skipped" not in capsys.readouterr().err


def test_runs_named_by_another_convention_group_by_what_they_logged(tmp_path, capsys):
    """The thesis authors' evaluation runs are `{env}__{exp}__{time}_EVALUATE`: the logged identity with a suffix,
    one group for all of them and no warning; a folder that names another algorithm still warns."""
    for seed, value in ((1, 10.0), (2, 20.0)):
        logged_run(tmp_path / "runs" / f"Breakout-v5__p3o__170000000{seed}_EVALUATE", "Breakout-v5", "p3o", [value])
    result = results.main(results.Args(roots=(str(tmp_path / "runs"),), out=str(tmp_path / "o"), figures=False))
    assert result["table"] == {("Breakout-v5", "p3o"): (15.0, pytest.approx(5 / np.sqrt(2)), 2)}
    assert "warning" not in capsys.readouterr().err


def test_eval_points_count_only_beside_their_eval_json(tmp_path):
    """eval.json is written last, once an evaluation is whole: points of one that failed before it are not a run's
    evaluation, so the table leaves them out rather than average two evaluations or a half one."""
    logged_run(tmp_path / "runs" / "whole", "Breakout-v5", P3O, [4.0])
    logged_run(tmp_path / "runs" / "half", "Breakout-v5", P3O)
    writer = SummaryWriter(str(tmp_path / "runs" / "half"), filename_suffix=".eval")
    writer.add_scalar("eval/episodic_return", 100.0, 0)
    writer.close()
    result = results.main(results.Args(roots=(str(tmp_path / "runs"),), out=str(tmp_path / "o"), figures=False))
    assert result["table"] == {("Breakout-v5", P3O): (4.0, 0.0, 1)}


def test_a_readme_given_as_a_symlink_has_its_file_written(root, tmp_path):
    readme = tmp_path / "docs" / "README.md"
    readme.parent.mkdir()
    readme.write_text(f"# x\n{results.README_BEGIN}\nold\n{results.README_END}\ntail\n")
    (tmp_path / "README.md").symlink_to(readme)
    args = results.Args(roots=(root,), out=str(tmp_path / "o"), figures=False, readme=str(tmp_path / "README.md"))
    results.main(args)
    assert (tmp_path / "README.md").is_symlink() and "old" not in readme.read_text()
    assert readme.read_text().startswith(f"# x\n{results.README_BEGIN}\n") and readme.read_text().endswith("tail\n")


@pytest.mark.parametrize(
    "flags,sentence",
    [
        ([], "error: give the folders of runs to read"),
        (["{root}", "--tag", "charts/episodic_return", "--above", "0.5"], "error: --above reads a histogram tag"),
    ],
)
def test_no_folder_and_above_on_a_scalar_tag_are_one_sentence(flags, sentence, root, tmp_path):
    import subprocess
    import sys

    script = os.path.join(os.path.dirname(results.__file__), "results.py")
    flags = [f.format(root=root) for f in flags]
    proc = subprocess.run(
        [sys.executable, script, *flags, "--out", str(tmp_path / "o")], capture_output=True, text=True
    )
    assert proc.returncode == 1 and proc.stderr.splitlines()[-1].startswith(sentence), proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "o").exists()


def test_a_run_much_shorter_than_the_others_is_said_where_it_cuts_the_curves(tmp_path, capsys):
    """Curves of a group are drawn over the steps all its runs cover: one short run among long ones cuts them, and
    the legend and a warning say so; a curve of a single common step is a marker, not an empty line."""
    root = tmp_path / "runs"
    for seed, last in ((1, 100_000), (2, 100_000), (3, 20_000)):
        writer = SummaryWriter(str(root / f"Breakout-v5__{PPO}__{seed}"))
        for step in range(1000, last + 1, 1000):
            writer.add_scalar("charts/episodic_return", step / 1000, step)
        writer.close()
    frame, _ = results.find_runs((str(root),))
    grid, _, _, n = results.figure_curves(frame, "episodic_return", 50)[PPO]
    assert n == "n=3, cut" and grid[-1] == 20_000
    assert "Breakout-v5 ppo_atari_envpool: its curves end at step 20,000" in capsys.readouterr().err
    single = SummaryWriter(str(root / f"Breakout-v5__{PPO}__4"))
    single.add_scalar("charts/episodic_return", 1.0, 1000)
    single.close()
    frame, _ = results.find_runs((str(root),))
    grid, centre, _, n = results.figure_curves(frame, "episodic_return", 50)[PPO]
    assert len(grid) == 1 and n == "n=4, cut"
    written = results.write_figures(frame, str(tmp_path), 50)
    assert os.path.getsize(written[0]) > 0


@pytest.mark.parametrize(
    "flags,sentence",
    [
        ([], "error: give the folders of runs to read"),
        (["{missing}"], "error: no training run (per-iteration `charts/SPS` points) under"),
        (["{empty}"], "error: no training run (per-iteration `charts/SPS` points) under"),
        (["{empty}", "--group-regex", "(?P<env>"], "error: --group-regex is not a regular expression"),
    ],
)
def test_hours_refuses_what_it_cannot_count_in_one_sentence_and_makes_no_folder(flags, sentence, tmp_path):
    import subprocess
    import sys

    (tmp_path / "empty").mkdir()
    flags = [f.format(missing=tmp_path / "missing", empty=tmp_path / "empty") for f in flags]
    script = os.path.join(os.path.dirname(results.__file__), "hours.py")
    proc = subprocess.run(
        [sys.executable, script, *flags, "--out", str(tmp_path / "o")], capture_output=True, text=True
    )
    assert proc.returncode == 1 and proc.stderr.splitlines()[-1].startswith(sentence), proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "o").exists()


def test_the_two_tests_of_the_probability_of_improvement_by_brute_force():
    """improvement_tests against an enumeration written out here: every joint relabelling of the runs within each of
    two games (C(6,3)^2 = 400) for the stratified test, every sign pattern of the games' effects for the other."""
    from itertools import combinations, product

    x = np.array([[3.0, 10.0], [5.0, 10.0], [9.0, 12.0]])  # [runs x games], ties across the groups included
    y = np.array([[1.0, 10.0], [4.0, 8.0], [5.0, 7.0]])

    def poi(a, b):
        return np.mean([(u > v) + 0.5 * (u == v) for u in a for v in b])

    observed = np.mean([poi(x[:, g], y[:, g]) for g in range(2)])
    averages = []
    for split0, split1 in product(combinations(range(6), 3), repeat=2):
        per_game = []
        for g, chosen in enumerate((split0, split1)):
            pooled = np.concatenate([x[:, g], y[:, g]])
            per_game.append(poi(pooled[list(chosen)], np.delete(pooled, list(chosen))))
        averages.append(np.mean(per_game))
    stratified = np.mean([abs(a - 0.5) >= abs(observed - 0.5) - 1e-12 for a in averages])
    effects = np.array([poi(x[:, g], y[:, g]) - 0.5 for g in range(2)])
    sign_flip = np.mean([abs((effects * s).mean()) >= abs(effects.mean()) - 1e-12 for s in product([1, -1], repeat=2)])
    tests = comparison.improvement_tests(x, y)
    assert tests["stratified"] == pytest.approx(stratified) and 0 < stratified < 1
    assert tests["sign_flip"] == pytest.approx(sign_flip)


def test_a_tag_the_scripts_log_but_no_run_has_yet_is_said_and_a_typo_refused(tmp_path, capsys):
    """One iteration of MsPacman ends no game: `charts/episodic_return` is a tag the scripts log, not yet logged, so
    the learning check's table of it is skipped with a line (exit 0, nothing written); a misspelt tag is refused."""
    root = tmp_path / "runs"
    writer = SummaryWriter(str(root / f"MsPacman-v5__{PPO}__1"))
    writer.add_scalar("charts/SPS", 100.0, 4096)
    writer.close()
    out = tmp_path / "out"
    result = results.main(results.Args(roots=(str(root),), out=str(out), tag="charts/episodic_return"))
    assert result["table"] == {} and not out.exists()
    assert f"no run under {root} has logged charts/episodic_return yet; no table written" in capsys.readouterr().err
    with pytest.raises(SystemExit) as refused:
        results.main(results.Args(roots=(str(root),), out=str(out), tag="charts/episodic_retrun"))
    assert str(refused.value.code).startswith("error: --tag 'charts/episodic_retrun': no run under")
    assert not out.exists()


def test_each_ablation_arm_is_tested_against_p3o_and_ppo_in_one_table(tmp_path):
    from scipy import stats

    arms = {"p3o_gae": [[6.0] * 10, [8.0] * 10, [10.0] * 10], "p3o_value_beta_one": [[25.0] * 10, [35.0] * 10]}
    for algo, per_seed in [(P3O, EVAL["Breakout-v5", P3O]), (PPO, EVAL["Breakout-v5", PPO]), *arms.items()]:
        for seed, returns in enumerate(per_seed, start=1):
            write_run(tmp_path / "runs", "Breakout-v5", algo, seed, returns, step_every=50_000)
    write_run(tmp_path / "runs", "Qbert-v5", "p3o_gae", 1, [1.0] * 10, step_every=50_000)  # one run: not tested
    args = dict(roots=(str(tmp_path / "runs"),), out=str(tmp_path / "out"), figures=False, bootstrap_reps=10)
    text = results.main(results.Args(**args, ablations=tuple(arms)))["ablations"]
    assert open(tmp_path / "out" / "table_ablations.md").read() == text
    assert "smallest possible p is 0.2 for 2 runs against 3, 0.1 for 3 runs against 3" in text
    rows = re.findall(
        r"\| (\S+) \| (\S+) \| (\S+) \| (\d) vs (\d) \| (\S+) \| \[(\S+), (\S+)\] \| (\S+) \| (\S+) \|", text
    )
    assert [row[:3] for row in rows] == [
        ("Breakout-v5", arm, other) for arm in arms for other in (P3O, PPO)
    ]  # Qbert's single p3o_gae run has nothing to be tested against
    scores = {P3O: [10, 20, 30], PPO: [5, 7, 9], "p3o_gae": [6, 8, 10], "p3o_value_beta_one": [25, 35]}
    for _, arm, other, n_arm, n_other, d, lo, hi, welch_p, permutation_p in rows:
        a, b = scores[arm], scores[other]
        welch = stats.ttest_ind(a, b, equal_var=False)
        assert (int(n_arm), int(n_other)) == (len(a), len(b))
        assert float(d) == pytest.approx(np.mean(a) - np.mean(b), abs=0.05)
        assert [float(lo), float(hi)] == pytest.approx(list(welch.confidence_interval(0.95)), abs=0.05)
        assert float(welch_p) == pytest.approx(welch.pvalue, abs=5e-4)
        assert float(permutation_p) == pytest.approx(comparison.exact_permutation_p(a, b), abs=5e-4)
    # p3o_gae (6, 8, 10) against PPO (5, 7, 9): +1; 7 of the 20 splits of the six runs into three and three give the
    # arm's side a sum of 24 or more, so the two-sided p is twice 7/20
    assert re.search(r"\| Breakout-v5 \| p3o_gae \| ppo_atari_envpool \| 3 vs 3 \| 1\.00 \| .* \| 0\.700 \|\n", text)
    # each arm tested against both gets the reading; three runs a side or fewer (smallest p 0.1) tell nothing apart
    readings = re.findall(r"\| Breakout-v5 \| (\S+) \| (.+) \|\n", text.split("| game | arm | reading |")[1])
    assert readings == [
        ("p3o_gae", "cannot tell: not told apart from P3O (p 0.200), not told apart from PPO (p 0.700)"),
        ("p3o_value_beta_one", "cannot tell: not told apart from P3O (p 0.400), not told apart from PPO (p 0.200)"),
    ]
    # without arms nothing is written; with arms but one run a side, the file says there is nothing to test yet
    assert results.main(results.Args(**args | {"out": str(tmp_path / "none")}))["ablations"] is None
    assert not (tmp_path / "none" / "table_ablations.md").exists()
    few = results.main(results.Args(**args | {"games": ("Qbert-v5",)}, ablations=("p3o_gae",)))["ablations"]
    assert few.startswith("`eval/episodic_return`: no game has two runs or more of an ablation arm (p3o_gae)")
