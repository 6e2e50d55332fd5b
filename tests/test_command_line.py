"""A property test of the command line (hypothesis): flags drawn from their edge values (0, 1, negative, huge, nan,
inf, empty strings, spaces, unicode, `__`, paths outside runs/ or under a file), a few at a time, on top of a tiny
run, for both training scripts. Every command line either stops with one sentence (`error: ...`, exit status 1)
before any environment starts and with nothing written, or is a run's, which goes on to start its environments
(stopped there: tests/test_end_to_end.py trains real ones)."""

import os
import tempfile

import pytest
import tyro
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import p3o_atari_envpool as p3o
import ppo_atari_envpool as ppo
from helpers import assert_refusal

INTS = [0, 1, -1, 2, 3, 7, 2**31 - 1, 2**31, 2**62, -(2**62)]
FLOATS = [0.0, -0.0, 1.0, -1.0, 0.5, 1e-300, 1e300, float("nan"), float("inf"), float("-inf")]
NAMES = ["", " ", "a b", "é✓", "x__y", "__", "a/b", "../x", "/abs", ".", "a//b", "a\\b", "x" * 300]
NAMES += ["file", "file/run"]  # runs/file is a file
TINY = ["--env-id", "Breakout-v5", "--num-envs", "2", "--num-steps", "8", "--num-minibatches", "2"]
TINY += ["--update-epochs", "1", "--total-timesteps", "16", "--no-cuda"]


def edge_values(module) -> dict:
    """flag -> the command-line words of each of its edge values, by the flag's type."""
    words = {}
    for name in module.INIT:
        flag, default = "--" + name.replace("_", "-"), getattr(module.Args(), name)
        if isinstance(default, bool):
            words[name] = [[flag], [f"--no-{flag[2:]}"]]
        else:
            edges = (
                INTS
                if isinstance(default, int)
                else FLOATS
                if name == "target_kl" or isinstance(default, float)
                else NAMES
            )
            words[name] = [[f"{flag}={v}"] for v in edges]
    for name in ("track", "resume", "auto_resume", "cuda"):  # W&B, checkpoints, GPUs: tests of their own
        words.pop(name)
    return words


def outcome(module, argv, work, monkeypatch) -> None:
    """The command line run in a fresh folder (runs/file a file) whose environments cannot start: a refusal must be one
    sentence with nothing written; anything else must reach the environments."""
    import envpool

    def started(*args, **kwargs):
        raise RuntimeError("the run started its environments")

    monkeypatch.setattr(envpool, "make", started)
    os.makedirs(os.path.join(work, "runs"))
    open(os.path.join(work, "runs", "file"), "w").write("a file where a run folder would go")
    monkeypatch.chdir(work)
    try:
        module.main(tyro.cli(module.Args, args=argv), argv)
    except SystemExit as refused:
        assert isinstance(refused.code, str), (argv, refused.code)
        assert_refusal(refused.code)
        written = sorted(os.path.join(d, f) for d, _, files in os.walk("runs") for f in files)
        assert written == [os.path.join("runs", "file")], (argv, written)  # nothing written
        return
    except RuntimeError as e:
        assert str(e) == "the run started its environments", (argv, e)
        return
    raise AssertionError(f"{argv}: neither refused nor started")


@pytest.mark.parametrize("module", [ppo, p3o], ids=["ppo", "p3o"])
def test_each_flag_at_each_of_its_edges_is_one_sentence_or_a_run(module, tmp_path, monkeypatch):
    for values in edge_values(module).values():
        for words in values:
            outcome(module, TINY + words, tempfile.mkdtemp(dir=tmp_path), monkeypatch)


@pytest.mark.parametrize("module", [ppo, p3o], ids=["ppo", "p3o"])
@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_flags_at_their_edges_together_are_one_sentence_or_a_run(module, data, tmp_path, monkeypatch):
    words = edge_values(module)
    chosen = data.draw(st.lists(st.sampled_from(sorted(words)), min_size=2, max_size=4, unique=True))
    argv = TINY + [word for name in chosen for word in data.draw(st.sampled_from(words[name]), label=name)]
    outcome(module, argv, tempfile.mkdtemp(dir=tmp_path), monkeypatch)
