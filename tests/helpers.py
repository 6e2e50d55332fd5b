"""What several test files share: the repository's root, a run's TensorBoard output read back, and a benchmark
driver run with its knobs."""

import os
import subprocess
import sys

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run_driver(script, cwd, knobs, timeout) -> subprocess.CompletedProcess:
    """A benchmark shell script run in cwd with its knobs as environment variables and this Python as PYTHON."""
    env = os.environ | {"PYTHON": sys.executable} | knobs
    return subprocess.run(["bash", script], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def python_printing_threads(folder) -> str:
    """A PYTHON for the sweep that first prints, to stderr (a run's log), the OMP_NUM_THREADS it starts with."""
    path = os.path.join(folder, "python-printing-threads")
    with open(path, "w") as f:
        f.write(f'#!/bin/sh\necho "OMP_NUM_THREADS=${{OMP_NUM_THREADS-unset}}" >&2\nexec {sys.executable} "$@"\n')
    os.chmod(path, 0o755)
    return path


def events(run_dir) -> EventAccumulator:
    """Every scalar, histogram and text a run folder holds, as TensorBoard shows it (purged points left out)."""
    acc = EventAccumulator(str(run_dir), size_guidance={"scalars": 0, "histograms": 0, "tensors": 0})
    acc.Reload()
    return acc


def scalars(run_dir) -> dict[str, list[tuple[int, float]]]:
    """tag -> [(step, value), ...] for every scalar the run logged."""
    acc = events(run_dir)
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def hyperparameters(run_dir) -> str:
    """The `|name|value|` table the scripts log as text, as CleanRL does."""
    return events(run_dir).Tensors("hyperparameters/text_summary")[0].tensor_proto.string_val[0].decode()


def assert_logged(run_dir, *rows: str) -> None:
    """Each `name|value` row is in the run's logged hyperparameters table."""
    text = hyperparameters(run_dir)
    missing = [row for row in rows if f"|{row}|" not in text]
    assert not missing, (str(run_dir), missing)


def assert_refusal(message: str, *fragments: str) -> None:
    """A refusal of bad input: one line that starts with `error:`, no traceback, and each fragment in it (the
    flag, the value, what to do instead): its content, not its exact wording."""
    message = message.removesuffix("\n")
    assert message.startswith("error: ") and "\n" not in message and "Traceback" not in message, message
    missing = [fragment for fragment in fragments if fragment not in message]
    assert not missing, (message, missing)
