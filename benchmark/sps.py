"""Steps per second of both training scripts against envpool's own ceiling, in one command.

Each script is measured as a user runs it: started from the command line in its own process (in a
throw-away folder), for `--warmup` + `--iterations` iterations. Its whole-iteration figure is read from
its own event file, the wall time between consecutive `charts/SPS` events over the measured iterations
(so it includes everything a run does each iteration: logging, checkpoints); the rollout and the update
are the `charts/rollout_time` and `charts/update_time` it logs. Raw envpool with random actions at the
same `num_envs` (the rollout's ceiling) runs in a child process of its own. Rates are steps over the
seconds of all measured iterations together, as a run's SPS is; peak host memory (RSS) is each process's own.

    uv run python benchmark/sps.py                 # small CPU settings: 8 envs x 128 steps, 4 x 4
    uv run python benchmark/sps.py --thesis        # thesis settings: 256 x 256, 8 epochs x 8 minibatches
"""

import importlib
import json
import multiprocessing as mp
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)  # the training scripts
SCRIPTS = {"ppo": "ppo_atari_envpool.py", "p3o": "p3o_atari_envpool.py"}


@dataclass
class Args:
    env_id: str = "Breakout-v5"
    """the envpool Atari game"""
    num_envs: int = 8
    """parallel environments"""
    num_steps: int = 128
    """steps per environment per rollout"""
    num_minibatches: int = 4
    """minibatches per epoch"""
    update_epochs: int = 4
    """epochs per update"""
    thesis: bool = False
    """use the thesis's settings instead: 256 envs x 256 steps, 8 epochs x 8 minibatches"""
    iterations: int = 5
    """measured iterations per script (the median is reported)"""
    warmup: int = 1
    """iterations run first and not counted (at least 1: a measured iteration is timed from the end of the one
    before it)"""
    cuda: bool = True
    """train on the GPU when there is one"""
    scripts: tuple[str, ...] = ("ppo", "p3o")
    """which scripts to measure"""
    rounds: int = 1
    """measure each script this many times, the order reversed every other round (so a machine that drifts
    does not favour the script measured first); medians over the rounds"""
    out: str = "runs/sps.json"
    """where the JSON results go"""


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB


def _load(name: str):
    return importlib.import_module(SCRIPTS[name][: -len(".py")])


def _measure_script(name: str, settings: dict, warmup: int, iterations: int, cuda: bool) -> dict:
    """Run the script from the command line as a user does and read its own event file back."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    batch = settings["num_envs"] * settings["num_steps"]
    cmd = [sys.executable, os.path.join(ROOT, SCRIPTS[name])]
    cmd += [f"--{key.replace('_', '-')}={value}" for key, value in settings.items()]
    cmd += [f"--total-timesteps={batch * (warmup + iterations)}", "--seed=1", "--run-name=sps"]
    cmd += [] if cuda else ["--no-cuda"]
    started = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        with open(f"{tmp}/out.log", "w") as log:
            proc = subprocess.Popen(cmd, cwd=tmp, stdout=log, stderr=subprocess.STDOUT)
            _, status, usage = os.wait4(proc.pid, 0)  # this process's own peak memory
        output = open(f"{tmp}/out.log").read().splitlines()
        if os.waitstatus_to_exitcode(status) != 0:
            sys.exit(f"error: {SCRIPTS[name]} failed during the measurement: {(output or ['no output'])[-1]}")
        events = EventAccumulator(f"{tmp}/runs/sps", size_guidance={"scalars": 0})
        events.Reload()
        ends = [e.wall_time for e in events.Scalars("charts/SPS")]
        rollout = [e.value for e in events.Scalars("charts/rollout_time")][warmup:]
        update = [e.value for e in events.Scalars("charts/update_time")][warmup:]
    measured = batch * iterations
    return {
        "iteration_sps": measured / (ends[-1] - ends[warmup - 1]),
        "rollout_sps": measured / sum(rollout),
        "update_sps": measured / sum(update),
        "peak_rss_mb": usage.ru_maxrss / 1024,  # Linux reports KiB
        "started": started,  # unix time, so the order of the measurements can be checked
        "device": next(line for line in output if line.startswith("device: "))[len("device: ") :],
    }


def _measure_raw_env(settings: dict, warmup: int, iterations: int, queue) -> None:
    import numpy as np

    module = _load("ppo")
    envs = module.make_env(settings["env_id"], settings["num_envs"], seed=1)
    n, steps = settings["num_envs"], settings["num_steps"]
    actions = np.random.default_rng(0).integers(0, envs.action_space.n, size=(steps, n)).astype(np.int32)
    envs.reset()
    seconds = []
    for _ in range(warmup + iterations):
        start = time.perf_counter()
        for t in range(steps):
            envs.step(actions[t])
        seconds.append(time.perf_counter() - start)
    envs.close()
    queue.put({"rollout_sps": n * steps * iterations / sum(seconds[warmup:]), "peak_rss_mb": _peak_rss_mb()})


def _in_child(target, *args):
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=target, args=(*args, queue))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def main(args: Args) -> dict:
    if args.thesis:
        args.num_envs, args.num_steps, args.num_minibatches, args.update_epochs = 256, 256, 8, 8
    if args.iterations < 1 or args.warmup < 1 or args.rounds < 1:
        sys.exit("error: --iterations, --warmup and --rounds must be at least 1.")
    unknown = set(args.scripts) - set(SCRIPTS)
    if unknown or not args.scripts:
        sys.exit(f"error: --scripts must name one or more of {sorted(SCRIPTS)}, got {sorted(args.scripts)}.")
    # where the results go, checked before minutes of measuring (on a GPU machine, minutes of a lent device)
    from benchmark.results import folder_problem  # the same check as results.py --out

    out = "folder" if os.path.isdir(args.out) else "file" if os.path.isfile(args.out) else None  # a file: replaced
    problem = "it is a folder" if out == "folder" else None if out == "file" else folder_problem(args.out)
    if problem:
        sys.exit(f"error: --out {args.out} cannot be written: {problem}.")
    settings = {
        "env_id": args.env_id,
        "num_envs": args.num_envs,
        "num_steps": args.num_steps,
        "num_minibatches": args.num_minibatches,
        "update_epochs": args.update_epochs,
    }
    _load("ppo").Args(**settings, total_timesteps=args.num_envs * args.num_steps)  # its checks refuse bad sizes

    import torch  # its version for the report; the parent never touches the GPU

    print(
        f"{args.env_id}: {args.num_envs} envs x {args.num_steps} steps, {args.update_epochs} epochs x "
        f"{args.num_minibatches} minibatches; {args.warmup} warm-up + {args.iterations} measured iterations, "
        f"{args.rounds} round(s); {platform.processor() or 'CPU'}, {os.cpu_count()} CPU cores, "
        f"torch {torch.__version__}",
        flush=True,
    )
    results = {"raw_env": _in_child(_measure_raw_env, settings, args.warmup, args.iterations)}
    rounds = {name: [] for name in args.scripts}
    for r in range(args.rounds):
        for name in args.scripts if r % 2 == 0 else reversed(args.scripts):
            rounds[name].append(_measure_script(name, settings, args.warmup, args.iterations, args.cuda))
    for name, measured in rounds.items():
        numbers = [key for key in measured[0] if key not in ("started", "device")]
        results[name] = {key: statistics.median(m[key] for m in measured) for key in numbers}
        results[name]["rounds"] = measured
    device = rounds[args.scripts[0]][0]["device"]
    raw = results["raw_env"]["rollout_sps"]
    ratios = {}
    for name in args.scripts:
        ratios[f"{name}_rollout/raw_env"] = results[name]["rollout_sps"] / raw
        ratios[f"{name}_iteration/raw_env"] = results[name]["iteration_sps"] / raw
    if {"ppo", "p3o"} <= set(args.scripts):
        ratios["p3o/ppo_iteration"] = results["p3o"]["iteration_sps"] / results["ppo"]["iteration_sps"]
        ratios["p3o/ppo_rollout"] = results["p3o"]["rollout_sps"] / results["ppo"]["rollout_sps"]
        ratios["p3o/ppo_update"] = results["p3o"]["update_sps"] / results["ppo"]["update_sps"]
    report = {"settings": asdict(args), "device": device, "torch": torch.__version__, "results": results}
    report |= {"ratios": ratios, "unix_time": int(time.time())}
    # the measurements are written before anything is printed: a reader gone (`| tee` ended by Ctrl-C) loses nothing
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=2)
    print(f"device: {device}")
    print("\n| what | iteration steps/s | rollout steps/s | update steps/s | peak RSS MB |")
    print("|---|---|---|---|---|")
    print(f"| raw envpool, random actions | | {raw:,.0f} | | {results['raw_env']['peak_rss_mb']:,.0f} |")
    for name in args.scripts:
        r = results[name]
        print(
            f"| {SCRIPTS[name]} | {r['iteration_sps']:,.0f} | {r['rollout_sps']:,.0f} | "
            f"{r['update_sps']:,.0f} | {r['peak_rss_mb']:,.0f} |"
        )
    print()
    for key, value in ratios.items():
        print(f"{key}: {value:.3f}")
    print(f"\nwrote {args.out}")
    return report


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args))
