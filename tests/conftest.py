import os
import sys

import pytest

# The whole suite runs on the CPU whatever the host has: the pinned numbers were recorded on the CPU, and a
# GPU would run TF32 convolutions. Set before torch initialises CUDA, and inherited by the scripts the tests
# start as subprocesses.
os.environ["CUDA_VISIBLE_DEVICES"] = ""
# wandb in the tests is offline and quiet, never the network
os.environ["WANDB_MODE"] = "offline"
os.environ["WANDB_SILENT"] = "true"

from helpers import ROOT  # noqa: E402  (after the environment above)

if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

# The test files that take longest, longest first (the suite run behind stop 40's CI on this 2-core machine, 2026-12-03:
# test_resume.py about 10 minutes, the next three 5-8, the rest 3 or less; test_learning_check.py has since trained
# two pairs instead of four, about half its time, and moved down). pytest-xdist hands whole files to the
# workers in collection order (`--dist loadfile --no-loadscope-reorder`, pyproject.toml), each worker taking the next
# file as it finishes one: long files first, so that the workers end together and none waits alone at the end
# for a long file started last (by its default order, the most tests first, one worker finished 5 minutes early).
SLOWEST_FIRST = (
    "test_resume.py",
    "test_end_to_end.py",
    "test_slurm.py",
    "test_learning_check.py",
    "test_sweep.py",
    "test_gpu_check.py",
    "test_video_wandb.py",
)


# the quick tier, `uv run pytest -m "not slow"`: the maths and the refusals of bad input, in-process (their tests
# that start a script are marked slow one by one); every test of the other files trains or starts programs
QUICK_FILES = ("test_maths.py", "test_bad_input.py", "test_command_line.py", "test_command_line_tools.py")


def pytest_ignore_collect(collection_path, config):
    """With `-m "not slow"`, the other files are not even imported (every test in them is slow): the quick tier
    is not kept waiting for torch's, envpool's and TensorBoard's imports in files it would deselect."""
    if config.getoption("markexpr", "").replace(" ", "") == "notslow" and collection_path.suffix == ".py":
        return collection_path.name.startswith("test_") and collection_path.name not in QUICK_FILES
    return None


def pytest_xdist_auto_num_workers(config):
    """`-n auto` (pyproject.toml) for the quick tier: one process, since starting workers takes longer than its
    tests; the full suite: one worker per CPU (at most 4, pyproject.toml), as pytest-xdist counts them."""
    if config.getoption("markexpr", "").replace(" ", "") == "notslow":
        return 0
    return None


def pytest_collection_modifyitems(items):
    """Collect the slow files first, each file's tests in their order (a stable sort); the rest keep theirs.
    Every test outside QUICK_FILES is marked slow."""
    rank = {name: i for i, name in enumerate(SLOWEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
    for item in items:
        if item.path.name not in QUICK_FILES:
            item.add_marker(pytest.mark.slow)
