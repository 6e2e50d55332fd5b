"""P3O against PPO: per game, Welch's t and the exact permutation test of the difference of means; across games,
rliable's interquartile mean, median and mean of human-normalised scores with stratified-bootstrap CIs, the
probability of improvement with two exact tests of it, and each game's share of the mean's gap. And the README's
results block that sums them up beside the thesis's table 5.1; the one rounding rule and table format of every table
the benchmark tools write. Used by benchmark/results.py."""

import warnings
from itertools import combinations, product
from math import comb

import numpy as np
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
AGGREGATES = ("IQM", "median", "mean")


def number(x: float, like: float | None = None) -> str:
    """The one rounding rule: to 0.01 under 10, else to 0.1; in the README (`like`: the score that x goes with)
    to 1 from 100 on, with thousands separators."""
    decimals = 1 if abs(x if like is None else like) >= 10 else 2
    if like is not None:
        return f"{x:,.{0 if abs(like) >= 100 else decimals}f}"
    return f"{x:.{decimals}f}"


def mean_se_text(mean: float, se: float, n: int, like: float | None = None) -> str:
    """`mean ± s.e.`; a single run has no standard error, so none is written (not ± 0)."""
    like = None if like is None else mean
    return f"{number(mean, like)} ± {number(se, like)}" if n > 1 else number(mean, like)


def markdown(header: list[str], rows: list[list[str]]) -> list[str]:
    """A Markdown table's lines."""
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in rows]


def per_game_scores(statistics, algos) -> dict:
    """env -> algo -> the per-run statistics (in run order), for the algorithms named."""
    per = {}
    for (env, algo), x in statistics.groupby(level=["env", "algo"]):
        if algo in algos:
            per.setdefault(env, {})[algo] = list(x.to_numpy())
    return per


def across_games(statistics, tag, last, p3o, ppo, reps, seed, profile=False) -> tuple[str | None, list[str], dict]:
    """The interquartile mean, median and mean of human-normalised scores with stratified-bootstrap 95% CIs, the
    probability that P3O improves on PPO with its two tests, each game's part of the mean's gap, and (with
    `profile`) the performance profile's curves, with rliable (Agarwal et al. 2021)."""
    from rliable import library as rly
    from rliable import metrics

    notes, per = [], {}
    for env, algos in per_game_scores(statistics, (p3o, ppo)).items():
        if env.split("-")[0] not in REFERENCE_SCORES:
            notes.append(f"{env}: no human/random reference score, left out of the across-game comparison")
            continue
        random_score, human_score = REFERENCE_SCORES[env.split("-")[0]]
        per[env] = {algo: [(x - random_score) / (human_score - random_score) for x in xs] for algo, xs in algos.items()}
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
    state, pair = np.random.RandomState(seed), f"{p3o},{ppo}"
    # rliable's StratifiedBootstrap (the IQM, median and mean, and the performance profile) draws its resamples
    # from numpy's global generator, not from the random_state it is given (its update_indices): seeded too, the
    # same --seed gives the same intervals and figure
    np.random.seed(seed)
    aggregates = (metrics.aggregate_iqm, metrics.aggregate_median, metrics.aggregate_mean)
    with warnings.catch_warnings():
        # rliable passes the seeded RandomState on to arch's bootstrap, which warns that the argument is deprecated
        warnings.filterwarnings("ignore", message="random_state is deprecated", category=FutureWarning)
        point, ci = rly.get_interval_estimates(
            scores, lambda x: np.array([f(x) for f in aggregates]), reps=reps, random_state=state
        )
        poi, poi_ci = rly.get_interval_estimates(
            {pair: (scores[p3o], scores[ppo])}, metrics.probability_of_improvement, reps=reps, random_state=state
        )
        if profile:
            taus = np.linspace(min(s.min() for s in scores.values()), max(s.max() for s in scores.values()), 101)
            profiles, profile_cis = rly.create_performance_profile(scores, taus, reps=reps)
    interval = (lambda lo, hi: f"[{lo:.3f}, {hi:.3f}]") if n > 1 else (lambda lo, hi: "–")
    improvement = tuple(float(np.squeeze(x)) for x in (poi[pair], poi_ci[pair][0], poi_ci[pair][1]))
    tests = improvement_tests(scores[p3o], scores[ppo])
    differences = scores[p3o].mean(axis=0) - scores[ppo].mean(axis=0)  # per game: a mean over games decides
    gap = differences.sum() / len(games)
    shares = {env: d / len(games) / gap if gap != 0 else None for env, d in zip(games, differences, strict=True)}
    lines = [
        f"Across {len(games)} game(s) ({', '.join(games)}), {n} run(s) each, `{tag}`"
        + (f" (last {last})" if last else "")
        + f", human-normalised; {reps} stratified-bootstrap replications (rliable). The IQM is over every run of"
        " every game; the median and mean are over the games, of each game's mean over its runs."
        + unequal
        + (
            " With one run per game there is nothing to resample, so no confidence interval is given (a bootstrap"
            " interval would be the point itself)."
            if n == 1  # the bootstrap resamples runs within each game: with one, every replication is the same
            else ""
        ),
        "",
        *markdown(
            ["algorithm", "runs per game", *(x for name in AGGREGATES for x in (name, "95% CI"))],
            [
                [
                    algo,
                    str(n),
                    *(f"{point[algo][k]:.3f} | {interval(ci[algo][0][k], ci[algo][1][k])}" for k in range(3)),
                ]
                for algo in (p3o, ppo)
            ],
        ),
        "",
        f"P({p3o} > {ppo}) = {improvement[0]:.3f}, 95% CI {interval(*improvement[1:])}",
        "",
        f"Two tests of P({p3o} > {ppo}) = 0.5, for two questions. Is there a difference within these {len(games)}"
        f" games? The stratified exact permutation test (runs relabelled within each game; every game's splits, their"
        f" averages combined exactly): p = {tests['stratified']:.3f}. Is {p3o} better across games, the games as the"
        f" units? The exact sign-flip test of the games' P - 0.5: p = {tests['sign_flip']:.3f} (Wilcoxon's signed-rank"
        f" test: p = {tests['wilcoxon']:.3f}). Two-sided p.",
        "",
        f"The mean's gap, {p3o} - {ppo}, is {gap:.3f}; each game's part of it (its difference of means over runs,"
        " divided by the number of games) and share (negative: that game pulls the other way):",
        "",
        *markdown(
            ["game", "difference of means", "part of the gap", "share of the gap"],
            [
                [env, f"{d:.3f}", f"{d / len(games):.3f}", f"{100 * shares[env]:.0f}%" if gap != 0 else "–"]
                for env, d in zip(games, differences, strict=True)
            ],
        ),
    ]
    aggregate = {
        algo: {name: (point[algo][k], ci[algo][0][k], ci[algo][1][k]) for k, name in enumerate(AGGREGATES)}
        for algo in (p3o, ppo)
    }
    numbers = {"games": games, "runs": n, "reps": reps, "aggregates": aggregate, "mean_gap": (float(gap), shares)}
    numbers["profile"] = (profiles, taus, profile_cis) if profile else None
    return (
        "\n".join(lines) + "\n",
        sorted(set(notes)),
        numbers | {"improvement": improvement, "improvement_tests": tests},
    )


def improvement_tests(x, y) -> dict:
    """Two-sided p of P(X > Y) = 0.5, the mean over games of each game's P(X > Y) + P(X = Y) / 2 over its run pairs
    (rliable's probability of improvement), from x and y [runs x games]. `stratified`: the exact permutation test with
    the runs relabelled within each game (each game's every split; the games' statistics are independent under it,
    so the average's distribution is their exact convolution) - no difference within these games. `sign_flip`: the
    exact test with the games as the units (each game's P - 0.5 flipped in sign, every pattern), and `wilcoxon` its
    rank test - better across games."""

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
    """The two-sided p of the difference of means under every split of the pooled runs into groups of len(a) and
    len(b) (scipy's exact permutation test: 252 splits for 5 against 5). Ties count as they fall, unlike the exact
    Mann-Whitney U of scipy, which ignores them."""
    difference = lambda x, y, axis: np.mean(x, axis=axis) - np.mean(y, axis=axis)  # noqa: E731
    test = stats.permutation_test(
        (a, b), difference, permutation_type="independent", vectorized=True, n_resamples=np.inf
    )
    return float(test.pvalue)


def per_game_tests(statistics, tag, last, p3o, ppo) -> tuple[str | None, dict]:
    """Per game with two runs or more of each: the difference of the means with Welch's 95% CI and two-sided p (a t
    test: assumes roughly normal run scores), and the exact two-sided permutation test's p (assumes exchangeable
    runs). Returns the table's text and env -> (difference, low, high, Welch p, permutation p)."""
    per = per_game_scores(statistics, (p3o, ppo))
    games = sorted(env for env, algos in per.items() if len(algos.get(p3o, [])) > 1 and len(algos.get(ppo, [])) > 1)
    if not games:
        return None, {}
    tests = {}
    for env in games:
        a, b = np.asarray(per[env][p3o], dtype=np.float64), np.asarray(per[env][ppo], dtype=np.float64)
        welch = stats.ttest_ind(a, b, equal_var=False)
        lo, hi = welch.confidence_interval(0.95)
        tests[env] = (float(a.mean() - b.mean()), float(lo), float(hi), float(welch.pvalue), exact_permutation_p(a, b))
    sizes = sorted({(len(per[env][p3o]), len(per[env][ppo])) for env in games})
    smallest = ", ".join(f"{2 / comb(m + k, m):.3g} for {m} runs against {k}" for m, k in sizes)
    lines = [
        f"`{tag}`" + (f" (last {last})" if last else "") + f": per game, {p3o} against {ppo} over their runs:"
        " the difference of the means; Welch's t test (unequal variances) with its 95% confidence interval of"
        " the difference and two-sided p; and the exact two-sided permutation test of the same difference over"
        f" every split of the game's runs into two groups (ties count; its smallest possible p is {smallest}).",
        "",
        *markdown(
            ["game", "n", "difference of means", "Welch 95% CI", "Welch p", "exact permutation p"],
            [
                [env, f"{len(per[env][p3o])} vs {len(per[env][ppo])}", number(d), f"[{number(lo)}, {number(hi)}]"]
                + [f"{welch_p:.3f}", f"{permutation_p:.3f}"]
                for env, (d, lo, hi, welch_p, permutation_p) in tests.items()
            ],
        ),
    ]
    return "\n".join(lines) + "\n", tests


# An ablation arm is told apart from P3O or PPO where the exact permutation p of their difference is below this; the
# rule for the readings was fixed on 2026-12-07, with 10 of issue 65's 30 runs in and none of them tested 5 against 5
READING_LEVEL = 0.05


def ablation_reading(against_p3o: tuple, against_ppo: tuple) -> str:
    """Whether switching a piece of P3O off takes P3O's lead away (told apart from P3O, not from PPO), keeps it
    (told apart from PPO, not from P3O), or neither; from the arm's (difference, ..., permutation p) against each."""
    (d_p3o, *_, p_p3o), (d_ppo, *_, p_ppo) = against_p3o, against_ppo
    off_p3o, off_ppo = p_p3o < READING_LEVEL, p_ppo < READING_LEVEL
    verdict = {
        (True, False): "takes the lead away" if d_p3o < 0 else "neither",
        (False, True): "keeps the lead" if d_ppo > 0 else "neither",
        (False, False): "cannot tell",
        (True, True): "above both" if min(d_p3o, d_ppo) > 0 else "below both" if max(d_p3o, d_ppo) < 0 else "between",
    }[off_p3o, off_ppo]

    def side(d, p, name, told):
        return (
            f"{'above' if d > 0 else 'below'} {name} (p {p:.3f})" if told else f"not told apart from {name} (p {p:.3f})"
        )

    return f"{verdict}: {side(d_p3o, p_p3o, 'P3O', off_p3o)}, {side(d_ppo, p_ppo, 'PPO', off_ppo)}"


def ablation_tests(statistics, tag, last, arms, p3o, ppo) -> str | None:
    """Each ablation arm against P3O and against PPO, per game with two runs or more of each side: per_game_tests's
    difference, Welch's CI and p and the exact permutation p, one row per (game, arm, other), in one table; then
    ablation_reading per (game, arm) tested against both; None without arms."""
    if not arms:
        return None
    rows, readings, sizes = [], [], set()
    per = per_game_scores(statistics, (p3o, ppo, *arms))
    tested = {
        (arm, other): per_game_tests(statistics, tag, last, arm, other)[1] for arm in arms for other in (p3o, ppo)
    }
    for env in sorted(per):
        for (arm, other), tests in tested.items():
            if env in tests:
                d, lo, hi, welch_p, permutation_p = tests[env]
                sizes.add((len(per[env][arm]), len(per[env][other])))
                rows.append([env, arm, other, f"{len(per[env][arm])} vs {len(per[env][other])}", number(d)])
                rows[-1] += [f"[{number(lo)}, {number(hi)}]", f"{welch_p:.3f}", f"{permutation_p:.3f}"]
        for arm in arms:
            if env in tested[arm, p3o] and env in tested[arm, ppo]:
                readings.append([env, arm, ablation_reading(tested[arm, p3o][env], tested[arm, ppo][env])])
    if not rows:
        return (
            f"`{tag}`: no game has two runs or more of an ablation arm ({', '.join(arms)}) and of {p3o} or {ppo} yet.\n"
        )
    smallest = ", ".join(f"{2 / comb(m + k, m):.3g} for {m} runs against {k}" for m, k in sorted(sizes))
    lines = [
        f"`{tag}`" + (f" (last {last})" if last else "") + ": per game, each ablation arm against the full P3O"
        f" ({p3o}) and against PPO ({ppo}): the arm's mean minus the other's; Welch's t test (unequal variances) with"
        " its 95% confidence interval of the difference and two-sided p; the exact two-sided permutation test of the"
        f" same difference over every split of the two arms' runs (its smallest possible p is {smallest}). A large"
        " p says only that these runs cannot tell the two apart.",
        "",
        *markdown(
            ["game", "arm", "against", "n", "difference", "Welch 95% CI", "Welch p", "exact permutation p"], rows
        ),
    ]
    if readings:
        lines += [
            "",
            f"Reading (a rule fixed before the runs were all in): an arm is told apart from P3O or PPO where the exact"
            f" permutation p is below {READING_LEVEL}. Switching the piece off takes P3O's lead away where the arm is"
            " below P3O and not told apart from PPO; keeps it where it is above PPO and not told apart from P3O;"
            " cannot tell where it is told apart from neither (which says only that these runs cannot, not that"
            " the arms are equal); neither where it is told apart only from P3O and above it, or only from PPO and"
            " below it; else it is above both, below both or between the two.",
            "",
            *markdown(["game", "arm", "reading"], readings),
        ]
    return "\n".join(lines) + "\n"


def readme_block(frame, table, tests, tag, last, p3o, ppo, aggregate) -> str:
    """The README's results from the tables written: per game the mean ± s.e. (n) of each algorithm and the random
    policy, the two per-game tests, the thesis's table 5.1; then the across-game aggregates in one line."""
    order = {game: i for i, game in enumerate(THESIS_TABLE)}  # the thesis's games first, in its order
    envs = sorted({env for env, _ in table}, key=lambda env: (order.get(env.split("-")[0], 99), env))
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
        cells = [
            f"{mean_se_text(*table[env, a], like=True)} ({table[env, a][2]})" if (env, a) in table else "–"
            for a in [p3o, ppo, *others]
        ]
        if env in tests:
            difference, _, _, welch_p, permutation_p = tests[env]
            like = max(abs(table[env, p3o][0]), abs(table[env, ppo][0]))
            cells.append(
                f"{'+' if difference > 0 else ''}{number(difference, like)}; {welch_p:.3f}, {permutation_p:.3f}"
            )
        else:
            cells.append("–")
        thesis = THESIS_TABLE.get(env.split("-")[0])
        cells.append(f"{thesis[0]:,.1f} / {thesis[1]:,.1f}" if thesis else "–")
        lines.append(f"| {env.split('-')[0]} | " + " | ".join(cells) + " |")
    if aggregate:
        k, (poi, lo, hi), p = aggregate["aggregates"], aggregate["improvement"], aggregate["improvement_tests"]
        parts = [
            f"{name} {k[p3o][name][0]:.3f} [{k[p3o][name][1]:.3f}, {k[p3o][name][2]:.3f}] against"
            f" {k[ppo][name][0]:.3f} [{k[ppo][name][1]:.3f}, {k[ppo][name][2]:.3f}]"
            for name in AGGREGATES
        ]
        lines += [
            "",
            f"**Across the {len(aggregate['games'])} games** ({aggregate['runs']} runs each, human-normalised, 95%"
            f" stratified-bootstrap CIs over {aggregate['reps']:,} replications, rliable), P3O against PPO: "
            + "; ".join(parts)
            + f"; P(P3O > PPO) = {poi:.3f} [{lo:.3f}, {hi:.3f}]: a difference within these games, p ="
            f" {p['stratified']:.3f} (stratified exact permutation test); P3O better across games, p ="
            f" {p['sign_flip']:.3f} (exact sign-flip test, games as the units).",
        ]
        gap, shares = aggregate["mean_gap"]
        if gap != 0:
            parts = [
                f"{env.split('-')[0]} {100 * s:.0f}%" for env, s in sorted(shares.items(), key=lambda x: -abs(x[1]))
            ]
            lines[-1] += f" Each game's share of the mean's gap ({gap:.3f}): " + ", ".join(parts) + "."
    return "\n".join(lines) + "\n"
