"""benchmark/p3o_vs_ppo.sh on a real one-node Slurm (Debian's slurm-wlm and munge): the array job runs every
run, a second sweep submits nothing, and preempted or signalled tasks checkpoint, are requeued and resume to
the same final step with every iteration's TensorBoard points exactly once.

The cluster is started here, in a temporary folder: munged (as the munge user), slurmctld -D and slurmd -D
on a generated slurm.conf naming this host as controller and node, on ports of its own; all stopped at the
end. Run alone with `uv run pytest -m slurm`. Skipped, with the reason in pytest's summary, where Slurm is
not installed or the tests do not run as root (.ci/run installs slurm-wlm and munge with apt-get as root).
"""

import os
import re
import shutil
import socket
import subprocess
import tempfile
import time

import pytest

from helpers import ROOT, python_printing_threads, scalars

pytestmark = pytest.mark.slurm
SWEEP = os.path.join(ROOT, "benchmark", "p3o_vs_ppo.sh")
DAEMONS = ("munged", "slurmctld", "slurmd", "sbatch", "scontrol", "scancel", "sinfo")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def slurm_conf(base: str, host: str) -> str:
    return f"""ClusterName=p3otest
SlurmctldHost={host}(127.0.0.1)
SlurmctldPort={free_port()}
SlurmdPort={free_port()}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={base}/munge/munge.socket,cred_expire=10
StateSaveLocation={base}/state
SlurmdSpoolDir={base}/spool
SlurmctldPidFile={base}/slurmctld.pid
SlurmdPidFile={base}/slurmd.pid
SlurmctldLogFile={base}/log/slurmctld.log
SlurmdLogFile={base}/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SchedulerType=sched/backfill
# A requeued task may start cred_expire + 1 s after its requeue, then waits for a scheduling pass (every 60 s,
# backfill every 30 s, by default): frequent passes keep the preemption test from waiting on them.
SchedulerParameters=sched_interval=2,bf_interval=2
JobCompType=jobcomp/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
ReturnToService=2
JobRequeue=1
PreemptType=preempt/partition_prio
PreemptMode=REQUEUE
KillWait=30
MinJobAge=3600
NodeName={host} NodeAddr=127.0.0.1 CPUs={os.cpu_count()} State=UNKNOWN
PartitionName=test Nodes={host} Default=YES MaxTime=INFINITE State=UP PreemptMode=REQUEUE
"""


@pytest.fixture(scope="module")
def slurm():
    """A running one-node cluster: the environment (SLURM_CONF) its client commands need."""
    missing = [name for name in DAEMONS if shutil.which(name) is None]
    if missing:
        pytest.skip(f"Slurm is not installed ({', '.join(missing)} not found): apt-get install slurm-wlm munge")
    if os.geteuid() != 0:
        pytest.skip("a one-node Slurm needs root here (munged runs as the munge user, slurmd as root)")
    base = tempfile.mkdtemp(prefix="p3o-slurm-", dir="/tmp")
    os.chmod(base, 0o755)  # munged, as the munge user, must reach its socket folder
    for sub in ("munge", "state", "spool", "log"):
        os.makedirs(os.path.join(base, sub))
    shutil.chown(os.path.join(base, "munge"), "munge", "munge")
    os.chmod(os.path.join(base, "munge"), 0o711)
    conf = os.path.join(base, "slurm.conf")
    with open(conf, "w") as f:
        f.write(slurm_conf(base, socket.gethostname().split(".")[0]))
    env = {**os.environ, "SLURM_CONF": conf}
    munge = [f"--socket={base}/munge/munge.socket", f"--pid-file={base}/munge/munged.pid"]
    munge += [f"--log-file={base}/munge/munged.log", f"--seed-file={base}/munge/munged.seed"]
    log = open(os.path.join(base, "log", "daemons.out"), "w")
    daemons = []
    try:
        daemons.append(
            subprocess.Popen(["runuser", "-u", "munge", "--", "munged", "--foreground", *munge], stdout=log, stderr=log)
        )
        time.sleep(1)
        daemons.append(subprocess.Popen(["slurmctld", "-D", "-f", conf], stdout=log, stderr=log, env=env))
        time.sleep(2)
        daemons.append(subprocess.Popen(["slurmd", "-D", "-f", conf], stdout=log, stderr=log, env=env))
        for _ in range(60):
            state = subprocess.run(["sinfo", "-h", "-o", "%T"], env=env, capture_output=True, text=True).stdout
            if state.strip() == "idle":
                break
            time.sleep(1)
        else:
            pytest.fail(f"the one-node Slurm did not come up: {daemon_logs(base)}")
        yield {"SLURM_CONF": conf, "base": base}
    finally:
        for daemon in reversed(daemons):
            daemon.terminate()
        for daemon in daemons:
            try:
                daemon.wait(timeout=30)
            except subprocess.TimeoutExpired:
                daemon.kill()
        log.close()
        shutil.rmtree(base, ignore_errors=True)


def daemon_logs(base):
    text = ""
    for name in ("log/daemons.out", "log/slurmctld.log", "log/slurmd.log", "munge/munged.log"):
        path = os.path.join(base, name)
        if os.path.exists(path):
            text += f"\n--- {name}\n" + "".join(open(path).readlines()[-15:])
    return text


def sweep(slurm, cwd, **knobs):
    drop = ("GAMES", "SEEDS", "EXTRA_ARGS", "DRY_RUN", "OMP_NUM_THREADS", "EVAL_EPISODES")
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env |= {"SLURM": "1", "SLURM_CONF": slurm["SLURM_CONF"], "PYTHON": python_printing_threads(cwd), **knobs}
    env["SBATCH_ARGS"] = "--cpus-per-task=1 --time=30"  # no GPU here
    return subprocess.run(["bash", SWEEP], env=env, cwd=cwd, capture_output=True, text=True, timeout=300)


def tasks(slurm, job):
    """task id -> (state, restarts) of an array job, from `scontrol show job`."""
    out = subprocess.run(
        ["scontrol", "show", "job", str(job)], env={**os.environ, "SLURM_CONF": slurm["SLURM_CONF"]},
        capture_output=True, text=True,
    ).stdout  # fmt: skip
    found = {}
    for record in out.split("\n\n"):
        task = re.search(r"ArrayTaskId=(\d+)\s", record)
        if task:
            state = re.search(r"JobState=(\w+)", record).group(1)
            found[int(task.group(1))] = (state, int(re.search(r"Restarts=(\d+)", record).group(1)))
    return found


def wait_for(slurm, job, done, timeout=600):
    start = time.time()
    while time.time() - start < timeout:
        states = tasks(slurm, job)
        if states and done(states):
            return states
        time.sleep(2)
    pytest.fail(f"job {job} did not get there in {timeout} s: {tasks(slurm, job)}{daemon_logs(slurm['base'])}")


def submitted(proc):
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return int(re.search(r"Submitted batch job (\d+)", proc.stdout).group(1))


def iteration_steps(run_dir, tag="losses/value_loss"):
    return [step for step, _ in scalars(run_dir)[tag]]


TINY = "--num-envs 4 --num-steps 32 --num-minibatches 2 --update-epochs 1 --no-cuda"


def test_the_array_job_runs_every_run_and_a_second_sweep_submits_nothing(slurm, tmp_path):
    knobs = {"GAMES": "Breakout-v5 Qbert-v5", "SEEDS": "1", "TOTAL_TIMESTEPS": "256", "WORKERS": "2", "GROUP": "grid"}
    knobs |= {"EXTRA_ARGS": TINY, "EVAL_EPISODES": "1"}
    commands = sweep(slurm, tmp_path, DRY_RUN="1", **knobs).stdout.splitlines()[:4]
    assert not any(command.startswith("#") for command in commands)
    job = submitted(sweep(slurm, tmp_path, **knobs))
    states = wait_for(
        slurm, job, lambda s: len(s) == 4 and all(state in ("COMPLETED", "FAILED") for state, _ in s.values())
    )
    logs = tmp_path / "runs" / "grid" / "logs"
    print(f"grid: job {job}, tasks (state, restarts): {states}")
    assert states == {i: ("COMPLETED", 0) for i in range(4)}, [
        (logs / f"slurm-{job}_{i}.log").read_text() for i in range(4)
    ]
    for i, command in enumerate(commands):
        # task i ran the i-th run of the grid, to its end, with its evaluation
        log = (logs / f"slurm-{job}_{i}.log").read_text()
        assert f"task {i} (restart 0) on " in log and log.splitlines()[0].endswith(command)
        assert "iteration 2/2 global_step=256" in log and "eval: 1 games" in log
        assert "OMP_NUM_THREADS=1\n" in log  # the task's one CPU (--cpus-per-task=1), not the node's
        name = re.search(r"--run-name (\S+)", command).group(1)
        assert iteration_steps(tmp_path / "runs" / name) == [128, 256]
        assert (tmp_path / "runs" / name / "eval.json").is_file()
    again = sweep(slurm, tmp_path, **knobs)
    assert again.returncode == 0 and "Submitted batch job" not in again.stdout
    assert again.stdout.endswith("nothing to run: every run in runs/grid has finished\n")


def test_preempted_and_signalled_tasks_checkpoint_requeue_and_resume(slurm, tmp_path):
    iterations = 16
    knobs = {"GAMES": "Breakout-v5", "SEEDS": "1", "TOTAL_TIMESTEPS": str(128 * iterations), "WORKERS": "2"}
    knobs |= {"GROUP": "long", "EXTRA_ARGS": TINY, "EVAL_EPISODES": "0"}
    job = submitted(sweep(slurm, tmp_path, **knobs))
    logs = tmp_path / "runs" / "long" / "logs"
    env = {**os.environ, "SLURM_CONF": slurm["SLURM_CONF"]}

    def printed(task, text):
        path = logs / f"slurm-{job}_{task}.log"
        return path.exists() and text in path.read_text()

    # task 0 (PPO) is preempted: Slurm signals it itself and requeues it. Task 1 (P3O) gets what
    # `--signal=B:TERM@...` sends before a time limit: SIGTERM to its batch shell, which passes it on to the
    # training script and requeues the task itself. Each as soon as it has printed its third iteration, so
    # neither can finish first however far apart the two start.
    stop = {0: ["scontrol", "requeue", f"{job}_0"], 1: ["scancel", "--signal=TERM", "--batch", f"{job}_1"]}
    start = time.time()
    while stop:
        assert time.time() - start < 300, f"tasks {sorted(stop)} did not start"
        for task in [task for task in stop if printed(task, "iteration 3/")]:
            subprocess.run(stop.pop(task), env=env, check=True)
        time.sleep(0.1)
    states = wait_for(
        slurm, job, lambda s: all(state == "COMPLETED" and restarts >= 1 for state, restarts in s.values())
    )
    print(f"preemption: job {job}, tasks (state, restarts): {states}")
    assert states == {0: ("COMPLETED", 1), 1: ("COMPLETED", 1)}
    for task, algo in enumerate(("ppo", "p3o")):
        name = f"long/Breakout-v5__{algo}_atari_envpool__1"
        log = (logs / f"slurm-{job}_{task}.log").read_text()
        keep = ("task ", "stopped by", "resuming", "slurmstepd", f"iteration {iterations}/")
        print(f"--- slurm-{job}_{task}.log, the lines that tell the story:")
        print("\n".join(line for line in log.splitlines() if line.startswith(keep)))
        stopped = re.search(rf"stopped by signal 15 after iteration (\d+); continue with --resume runs/{name}\n", log)
        assert stopped, log
        assert f"resuming runs/{name} after iteration {stopped.group(1)} " in log, log
        assert f"task {task} (restart 1) on " in log and log.count(f"iteration {iterations}/{iterations} ") == 1
        assert f"iteration {iterations}/{iterations} global_step={128 * iterations} " in log
        # every iteration's points exactly once, as an uninterrupted run has them
        for tag in ("losses/value_loss", "charts/learning_rate", "charts/SPS"):
            assert iteration_steps(tmp_path / "runs" / name, tag) == [128 * i for i in range(1, iterations + 1)], tag
