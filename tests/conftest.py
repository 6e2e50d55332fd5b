import os
import sys

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


def pytest_collection_modifyitems(items):
    """Collect the slow files first, each file's tests in their order (a stable sort); the rest keep theirs."""
    rank = {name: i for i, name in enumerate(SLOWEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
