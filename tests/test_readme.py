"""The README's first screen as a new user meets it (issue 66 #19): its "does it work" commands, the short run and
its evaluation, run as written (only `uv run python` is this interpreter, and the two files are named by their paths
in the repository, since the commands run in a folder of their own), their outputs read back."""

import json
import os
import re
import shlex
import subprocess
import sys

from helpers import ROOT, scalars


def first_screen_commands() -> list[list[str]]:
    """The `uv run python ...` commands of the README's first bash block, continuation lines joined, comments cut."""
    text = open(os.path.join(ROOT, "README.md")).read()
    block = re.search(r"```bash\n(.*?)```", text, re.S).group(1).replace("\\\n", " ")
    return [shlex.split(line, comments=True) for line in block.splitlines() if line.startswith("uv run python ")]


def test_the_first_screens_short_run_and_its_evaluation_work_as_written(tmp_path):
    commands = first_screen_commands()
    assert [c[3] for c in commands] == ["p3o_atari_envpool.py", "benchmark/evaluate.py"], commands
    for command in commands:
        argv = [sys.executable, os.path.join(ROOT, command[3]), *command[4:]]
        proc = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=900)
        assert proc.returncode == 0, (command, proc.stdout[-2000:], proc.stderr[-2000:])
    run_dir = tmp_path / "runs" / "quick"  # the --run-name the first command gives and the second reads
    total = int(commands[0][commands[0].index("--total-timesteps") + 1])
    steps = [step for step, _ in scalars(str(run_dir))["charts/SPS"]]
    assert steps and max(steps) == total  # every iteration of the short run logged
    report = json.loads((run_dir / "eval.json").read_text())
    assert len(report["returns"]) == int(commands[1][commands[1].index("--episodes") + 1])
    assert report["global_step"] == total
