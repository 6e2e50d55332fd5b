#!/usr/bin/env bash
# The GPU visit in one prepared command (the GPU machine is lent for 15 minutes in all, its start included):
# a real run of each training script at the thesis's settings (the scripts' defaults: 256 envs x 256 steps,
# 8 epochs x 8 minibatches) for 1M steps, each read back (the device it trained on, finite losses, its
# evaluation, its steady-state steps/s and its training return: a learning point per script), then
# benchmark/sps.py at the same sizes (raw envpool, the ceiling) and a comparison of the three. Each step runs
# under its own time limit, set from what the first GPU visit measured with about 20% margin, and within one
# budget for the whole check, 540 s (9 minutes): a step gets at most what is left of it. Writes six files to
# OUT (the device tool brings back at most 8): summary.txt (one line per step, "ok" or "FAILED" with the
# reason, then the comparison), gpu_check.log (every step's output), run_ppo.json and run_p3o.json (the
# read-backs), sps_thesis.json (sps.py's own JSON) and runs.tgz (both runs' event files, eval.json and printed
# logs, without checkpoints or models, in folders named as the scripts name a seed-1 run).
#
# On the GPU machine, from the project root (../shared/gpu/README.md: the bundle is built here once with
# `bash ../shared/gpu/envpool-bundle.sh` and carried as .gpu):
#   tar xzf .gpu/site.tgz -C /tmp && export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 && bash benchmark/gpu_check.sh
# Rehearsal on the CPU, the same steps at tiny sizes (tests/test_gpu_check.py runs it):
#   REHEARSAL=1 PYTHON="uv run python" OUT=runs/gpu_rehearsal bash benchmark/gpu_check.sh
# Knobs: OUT ($OUT, else runs/gpu_check), PYTHON (python3), ENV_ID (Breakout-v5), REHEARSAL (0), BUDGET (seconds
# for the whole check: 540, 1500 in the rehearsal).
# Exit status 0 when every step is ok, else 1.
set -uo pipefail

OUT=$(mkdir -p "${OUT:-runs/gpu_check}" && cd "${OUT:-runs/gpu_check}" && pwd)
ENV_ID=${ENV_ID:-Breakout-v5}
REHEARSAL=${REHEARSAL:-0}
root=$(cd "$(dirname "$0")/.." && pwd)
# the interpreter itself, so that the runs (started in a throw-away folder) use it too: "uv run python" finds the
# project's environment only from inside the project
PYTHON=$(cd "$root" && ${PYTHON:-python3} -c 'import sys; print(sys.executable)') || exit 1
work=$(mktemp -d)  # the runs' folders (checkpoints and models stay here, not in OUT)
trap 'rm -rf "$work"' EXIT
: > "$OUT/summary.txt"
: > "$OUT/gpu_check.log"

if [ "$REHEARSAL" = 1 ]; then
    device=cpu  # what the runs must say they trained on
    run=(--num-envs 4 --num-steps 32 --num-minibatches 2 --update-epochs 1 --total-timesteps 384)
    games=1  # the evaluation's (benchmark/evaluate.py --run)
    sps=(--num-envs 4 --num-steps 32 --num-minibatches 2 --update-epochs 1 --iterations 2 --warmup 1)  # the runs' sizes
    limits=(120 300 300 120 60)  # environment, each run, sps.py, each read-back, the archive and the comparison
    budget=${BUDGET:-1500}
else
    device="cuda ("
    # 15 iterations of 65,536 steps: about 110 s at the 8,600-9,400 steps/s a real P3O run logged there
    run=(--total-timesteps 1000000)
    games=2
    sps=(--thesis --iterations 3 --warmup 1)  # about 130 s: raw envpool, then each script started as a user does
    # measured: 10 s; about 130 s a run (start-up and evaluation included); about 130 s; 1 s; under 1 s
    limits=(60 170 160 15 10)
    budget=${BUDGET:-540}  # the whole check: a step gets at most what is left of it, so the call ends within 9 minutes
fi

# step NAME SECONDS COMMAND...: COMMAND under `timeout` (SECONDS, or what is left of the budget if less), its output
# appended to gpu_check.log, a summary line
deadline=$(($(date +%s) + budget))
step() {
    local name=$1 limit=$2 start rc why
    shift 2
    start=$(date +%s)
    if [ "$limit" -gt $((deadline - start)) ]; then limit=$((deadline - start)); fi
    if [ "$limit" -gt 0 ]; then
        timeout "$limit" "$@" > "$work/step.log" 2>&1
        rc=$?
    else
        echo "no time left of the check's $budget s" > "$work/step.log"
        rc=1
    fi
    { echo "=== $name (exit $rc): $*"; cat "$work/step.log"; } >> "$OUT/gpu_check.log"
    if [ "$rc" = 0 ]; then
        echo "ok      $name ($(($(date +%s) - start)) s)" | tee -a "$OUT/summary.txt"
    else
        if [ "$rc" = 124 ]; then why="no result within its $limit s"; else
            why="exit $rc: $(grep -v '^[[:space:]]*$' "$work/step.log" | tail -n 1 | cut -c1-300)"; fi
        echo "FAILED  $name ($(($(date +%s) - start)) s): $why" | tee -a "$OUT/summary.txt"
    fi
}

# after a run: the device it said, finite losses, its eval.json, its steady-state speed (the wall time between
# its first and last charts/SPS events) and its training return over the last quarter of its steps
read_back() {
    $PYTHON - "$work/runs/$1" "$device" "$OUT/run_$2.json" <<'PY'
import json, math, os, sys
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

run, device, out = sys.argv[1:]
if not os.path.isfile(f"{run}/eval.json"):
    sys.exit("nothing to read back: the run wrote no eval.json")
acc = EventAccumulator(run, size_guidance={"scalars": 0})
acc.Reload()
scalars = {t: acc.Scalars(t) for t in acc.Tags()["scalars"]}
losses = {t: [e.value for e in events] for t, events in scalars.items() if t.startswith("losses/")}
report = json.load(open(f"{run}/eval.json"))
sps = scalars["charts/SPS"]
steps = sps[-1].step
batch = sps[0].step
returns = [e.value for e in scalars.get("charts/episodic_return", []) if e.step > 0.75 * steps]
summary = {
    "device": report["device"],
    "eval_games": len(report["returns"]),
    "eval_mean": report["mean"],
    "steps": steps,
    "iterations": len(sps),
    # every iteration after the first (start-up), logging and checkpoints included: what the run gets
    "steady_sps": (steps - batch) / (sps[-1].wall_time - sps[0].wall_time) if len(sps) > 1 else None,
    "logged_sps": [e.value for e in sps],  # the scripts' own SPS, cumulative from the start
    "rollout_s": [e.value for e in scalars["charts/rollout_time"]],
    "update_s": [e.value for e in scalars["charts/update_time"]],
    "train_return_last_quarter": {"mean": sum(returns) / len(returns) if returns else None, "games": len(returns)},
    "losses": losses,
}
json.dump(summary, open(out, "w"), indent=2)
# explained variance is nan by definition when the returns do not vary; every loss must be finite
bad = [t for t, values in losses.items() if t != "losses/explained_variance" and not all(map(math.isfinite, values))]
if not report["device"].startswith(device):
    sys.exit(f"it trained on {report['device']}, not {device}...")
if not losses or bad:
    sys.exit(f"non-finite or missing losses: {bad or 'none logged'}")
if summary["steady_sps"] is None:
    sys.exit("it logged one iteration: no steady-state speed to read")
print(
    f"device {report['device']}; losses finite; eval.json: {len(report['returns'])} games, mean {report['mean']}; "
    f"{summary['steady_sps']:,.0f} steps/s after its first iteration (logged at its end: {sps[-1].value:,.0f}); "
    f"training return {summary['train_return_last_quarter']['mean']} over the last quarter of its steps"
)
PY
}

# the runs' speed against sps.py's for the same script and sizes, and against raw envpool
compare() {
    $PYTHON - "$OUT" <<'PY'
import json, os, sys

out = sys.argv[1]
missing = [f for f in ("sps_thesis.json", "run_ppo.json", "run_p3o.json") if not os.path.isfile(f"{out}/{f}")]
if missing:
    sys.exit(f"nothing to compare: {', '.join(missing)} missing (its step failed)")
sps = json.load(open(f"{out}/sps_thesis.json"))["results"]
raw = sps["raw_env"]["rollout_sps"]
runs = {algo: json.load(open(f"{out}/run_{algo}.json"))["steady_sps"] for algo in ("ppo", "p3o")}
for algo, run in runs.items():
    measured = sps[algo]["iteration_sps"]
    print(f"{algo}: run {run:,.0f} steps/s = {run / raw:.2f} x raw envpool ({raw:,.0f}); sps.py {measured:,.0f} = "
          f"{measured / run:.2f} x the run")
print(f"p3o/ppo: runs {runs['p3o'] / runs['ppo']:.3f}, sps.py {sps['p3o']['iteration_sps'] / sps['ppo']['iteration_sps']:.3f}")
PY
}

export work device OUT PYTHON
export -f read_back compare
# torch and envpool, and on the GPU machine a usable GPU: without one every later step would train on the CPU and
# read "ok", so the check stops here, naming it
export REHEARSAL
environment='import sys, torch, envpool
cuda = torch.cuda.is_available()
print("torch", torch.__version__, "CUDA", torch.version.cuda, "available", cuda,
      torch.cuda.get_device_name(0) if cuda else "", "envpool", envpool.__version__)
if not cuda and sys.argv[1] != "1":
    sys.exit(f"torch {torch.__version__} finds no usable GPU (CUDA {torch.version.cuda}), so nothing would run on one")'
export environment
step environment "${limits[0]}" bash -c 'nvidia-smi 2>&1 | head -n 15; $PYTHON -c "$environment" "$REHEARSAL"'
if grep -q '^FAILED  environment' "$OUT/summary.txt"; then
    echo "summary: $OUT/summary.txt (the environment failed, so nothing else ran); its output: $OUT/gpu_check.log"
    exit 1
fi
for algo in ppo p3o; do
    name="${ENV_ID}__${algo}_atari_envpool__1"  # as the scripts name a seed-1 run, so that results.py groups it
    step "run_$algo" "${limits[1]}" bash -c "cd '$work' && $PYTHON '$root/${algo}_atari_envpool.py' --env-id '$ENV_ID' \
        ${run[*]} --seed 1 --run-name '$name' > '$work/$algo.log' 2>&1 && $PYTHON '$root/benchmark/evaluate.py' \
        --run 'runs/$name' --episodes $games >> '$work/$algo.log' 2>&1; rc=\$?; tail -n 3 '$work/$algo.log'; exit \$rc"
    cp "$work/$algo.log" "$work/runs/$name/train.log" 2> /dev/null
    step "read_back_$algo" "${limits[3]}" bash -c "read_back '$name' $algo"
done
cd "$root" || exit 1
step sps_thesis "${limits[2]}" $PYTHON benchmark/sps.py --env-id "$ENV_ID" "${sps[@]}" --out "$OUT/sps_thesis.json"
step runs_tgz "${limits[4]}" bash -c "cd '$work/runs' && tar czf '$OUT/runs.tgz' --exclude='*.pt' --exclude='*.cleanrl_model' --exclude=.lock */"
step compare "${limits[4]}" bash -c compare
sed -n '/^=== compare (exit 0)/,$p' "$OUT/gpu_check.log" | tail -n +2 | sed 's/^/        /' >> "$OUT/summary.txt"
echo "summary: $OUT/summary.txt; every step's output: $OUT/gpu_check.log"
! grep -q '^FAILED' "$OUT/summary.txt"
