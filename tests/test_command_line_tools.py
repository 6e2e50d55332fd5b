"""The benchmark tools' command lines at their edges (tests/test_command_line.py does the training scripts'): each flag
of evaluate.py, results.py and hours.py at each of its edge values on top of a small valid call, on tiny runs written
here. Every outcome is one sentence with `error:` (exit status 1) before any output is written, or the tool's
outputs, complete."""

import os
import tempfile

import numpy as np
import pytest
import tyro
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from torch.utils.tensorboard import SummaryWriter

from benchmark import evaluate, hours, results

INTS = [0, 1, -1, 2, 7, 2**31, 2**62, -(2**62)]
FLOATS = [0.0, -1.0, 0.5, 1e300, float("nan"), float("inf"), float("-inf")]
NAMES = ["", " ", "a b", "é✓", "x__y", "a/b", "../x", "/abs", ".", "x" * 300, "file", "file/sub"]


def edges(args_type, skip=()):
    """flag -> the command-line words of each of its edge values, by the field's type (bools: on and off)."""
    words = {}
    for name, field in args_type.__dataclass_fields__.items():
        if name in skip:
            continue
        flag = "--" + name.replace("_", "-")
        kind = field.type if isinstance(field.type, str) else getattr(field.type, "__name__", str(field.type))
        if "bool" in str(kind):
            words[name] = [[flag], [f"--no-{flag[2:]}"]]
        elif "int" in str(kind) and "str" not in str(kind):
            words[name] = [[f"{flag}={v}"] for v in INTS]
        elif "float" in str(kind):
            words[name] = [[f"{flag}={v}"] for v in FLOATS]
        elif "tuple" in str(kind):
            words[name] = [[flag], [flag, "Breakout-v5", "Breakout-v5"], [flag, *NAMES[:4]]]
        else:
            words[name] = [[f"{flag}={v}"] for v in NAMES]
    return words


@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory):
    """Two tiny training runs of two games, as the scripts log them (hyperparameters, per-iteration points)."""
    root = tmp_path_factory.mktemp("tiny") / "runs"
    for env, seed in (("Breakout-v5", 1), ("Qbert-v5", 1), ("Breakout-v5", 2)):
        for algo in ("p3o_atari_envpool", "ppo_atari_envpool"):
            folder = root / f"{env}__{algo}__{seed}"
            writer = SummaryWriter(str(folder))
            table = f"|param|value|\n|-|-|\n|exp_name|{algo}|\n|env_id|{env}|\n|seed|{seed}|"
            writer.add_text("hyperparameters", table)
            for step in (128, 256, 384):
                for tag in ("charts/SPS", "charts/episodic_return", "losses/value_loss", "p3o/beta_mean"):
                    writer.add_scalar(tag, step / 128 + seed, step)
                writer.add_histogram("p3o/beta", np.array([0.1, 0.6, 0.9]), step)
            for game in range(3):
                writer.add_scalar("eval/episodic_return", game + seed, game)
            writer.close()
            (folder / "eval.json").write_text('{"returns": [1, 2, 3]}')
    return root


def outcome(main, argv, args_type, work, monkeypatch, outputs):
    """The tool's main on argv in a fresh folder (with `file` a file): a refusal must be one sentence and leave
    nothing; otherwise its outputs are there."""
    os.makedirs(work, exist_ok=True)
    open(os.path.join(work, "file"), "w").write("a file where a folder would go")
    monkeypatch.chdir(work)
    try:
        main(tyro.cli(args_type, args=argv))
    except SystemExit as refused:
        assert isinstance(refused.code, str) and refused.code.startswith("error: "), (argv, refused.code)
        assert "\n" not in refused.code.strip(), (argv, refused.code)
        assert sorted(os.listdir(work)) == ["file"], (argv, os.listdir(work))  # nothing written
        return
    assert outputs(work), (" ".join(argv), os.listdir(work))


def tool_call(tool, tiny_runs):
    """results.py or hours.py: its module, a small valid call writing into `o`, its flags' edges, and its check that
    the call wrote its tables."""
    if tool == "results":
        base = [str(tiny_runs), "--out", "o", "--no-figures", "--bootstrap-reps", "10"]
        module, skip = results, ("roots", "figures", "readme")

        def outputs(work):
            return any(name.endswith(".md") for name in os.listdir(os.path.join(work, "o")))

    else:
        base, module, skip = [str(tiny_runs), "--out", "o"], hours, ("roots",)

        def outputs(work):
            return os.path.isfile(os.path.join(work, "o", "hours.md"))

    return module, base, edges(module.Args, skip), outputs


@pytest.mark.parametrize("tool", ["results", "hours"])
def test_results_and_hours_at_every_edge_are_one_sentence_or_their_tables(tool, tiny_runs, tmp_path, monkeypatch):
    module, base, words, outputs = tool_call(tool, tiny_runs)
    for name, values in words.items():
        for words in values:
            if name == "out":  # the output folder itself at its edges
                argv = [str(tiny_runs), *words] + base[3:]
                outputs_here = lambda work, w=words: os.path.isdir(os.path.join(work, w[0].split("=", 1)[1]))  # noqa: E731
            else:
                argv, outputs_here = base + words, outputs
            outcome(module.main, argv, module.Args, tempfile.mkdtemp(dir=tmp_path), monkeypatch, outputs_here)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_results_flags_at_their_edges_together(data, tiny_runs, tmp_path, monkeypatch):
    """Two to four of results.py's flags at edge values at once (hypothesis): still one sentence, or the tables
    (hours.py has one flag besides --out, which the test above takes at each edge)."""
    module, base, words, outputs = tool_call("results", tiny_runs)
    words.pop("out")  # the output folder's edges change what `outputs` looks for: the test above covers them
    chosen = data.draw(st.lists(st.sampled_from(sorted(words)), min_size=2, max_size=4, unique=True))
    argv = base + [word for name in chosen for word in data.draw(st.sampled_from(words[name]), label=name)]
    outcome(module.main, argv, module.Args, tempfile.mkdtemp(dir=tmp_path), monkeypatch, outputs)


@pytest.mark.slow  # plays games (the others of this file are in the quick tier: tests/conftest.py)
def test_evaluate_at_every_edge_is_one_sentence_or_an_evaluation(tmp_path, monkeypatch):
    """evaluate.py's flags at their edges on top of a one-game random-policy evaluation into a new folder."""
    base = ["--random", "--env-id", "Breakout-v5", "--episodes", "1", "--no-cuda", "--run-dir", "e"]

    def outputs(work):
        return os.path.isfile(os.path.join(work, "e", "eval.json")) or not os.path.exists(os.path.join(work, "e"))

    slow = {"episodes", "seed"}  # each value plays a game: one valid value is enough
    for name, values in edges(evaluate.Args, ("cuda",)).items():
        for words in values[:3] if name in slow else values:
            outcome(evaluate.main, base + words, evaluate.Args, tempfile.mkdtemp(dir=tmp_path), monkeypatch, outputs)
