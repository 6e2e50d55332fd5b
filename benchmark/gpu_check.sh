#!/usr/bin/env bash
# The first GPU figures in one prepared command (the GPU machine is lent for 15 minutes in all, its start
# included): both scripts train briefly on CUDA and evaluate, then benchmark/sps.py at the thesis's sizes and
# at CleanRL's, each step under its own time limit, at most 8 minutes together. Writes six files to OUT (the
# device tool brings back at most 8): summary.txt (one line per step, "ok" or "FAILED" with the reason, so
# one call tells what to fix), gpu_check.log (every step's output), tiny_ppo.json and tiny_p3o.json (device,
# losses, evaluation of the tiny runs), sps_thesis.json and sps_cleanrl.json (sps.py's own JSON).
#
# On the GPU machine, from the project root (../shared/gpu/README.md: the bundle is built here once with
# `bash ../shared/gpu/envpool-bundle.sh` and carried as .gpu):
#   tar xzf .gpu/site.tgz -C /tmp && export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 && bash benchmark/gpu_check.sh
# Rehearsal on the CPU, the same steps at tiny sizes (tests/test_gpu_check.py runs it):
#   REHEARSAL=1 PYTHON="uv run python" OUT=runs/gpu_rehearsal bash benchmark/gpu_check.sh
# Knobs: OUT ($OUT, else runs/gpu_check), PYTHON (python3), ENV_ID (Breakout-v5), REHEARSAL (0).
# Exit status 0 when every step is ok, else 1.
set -uo pipefail

OUT=$(mkdir -p "${OUT:-runs/gpu_check}" && cd "${OUT:-runs/gpu_check}" && pwd)
PYTHON=${PYTHON:-python3}
ENV_ID=${ENV_ID:-Breakout-v5}
REHEARSAL=${REHEARSAL:-0}
root=$(cd "$(dirname "$0")/.." && pwd)
work=$(mktemp -d)  # the tiny runs' folders (checkpoints stay here, not in OUT)
trap 'rm -rf "$work"' EXIT
: > "$OUT/summary.txt"
: > "$OUT/gpu_check.log"

if [ "$REHEARSAL" = 1 ]; then
    device=cpu  # what the tiny runs must say they trained on
    tiny=(--num-envs 4 --num-steps 32 --num-minibatches 2 --update-epochs 1 --total-timesteps 256 --eval-episodes 1)
    thesis=(--num-envs 4 --num-steps 16 --num-minibatches 2 --update-epochs 1 --iterations 1 --warmup 1)
    cleanrl=(--num-envs 2 --num-steps 16 --num-minibatches 2 --update-epochs 1 --iterations 1 --warmup 1)
    limits=(120 120 300 300)
else
    device="cuda ("
    tiny=(--num-envs 16 --num-steps 64 --num-minibatches 4 --update-epochs 2 --total-timesteps 2048 --eval-episodes 2)
    thesis=(--thesis --iterations 3 --warmup 1)  # 256 envs x 256 steps, 8 epochs x 8 minibatches
    cleanrl=(--iterations 5 --warmup 1)          # sps.py's default sizes: CleanRL's 8 envs x 128 steps, 4 x 4
    limits=(60 60 200 90)  # with 60 s for the environment (10 s measured) and 20 s for each read-back: 510 s at most
fi

# step NAME SECONDS COMMAND...: COMMAND under `timeout`, its output appended to gpu_check.log, a summary line
step() {
    local name=$1 limit=$2 start rc why
    shift 2
    start=$(date +%s)
    timeout "$limit" "$@" > "$work/step.log" 2>&1
    rc=$?
    { echo "=== $name (exit $rc): $*"; cat "$work/step.log"; } >> "$OUT/gpu_check.log"
    if [ "$rc" = 0 ]; then
        echo "ok      $name ($(($(date +%s) - start)) s)" | tee -a "$OUT/summary.txt"
    else
        if [ "$rc" = 124 ]; then why="no result within its $limit s"; else
            why="exit $rc: $(grep -v '^[[:space:]]*$' "$work/step.log" | tail -n 1 | cut -c1-300)"; fi
        echo "FAILED  $name ($(($(date +%s) - start)) s): $why" | tee -a "$OUT/summary.txt"
    fi
}

# after a tiny run: the device it said, finite losses, its eval.json, as OUT/tiny_<algo>.json
read_back() {
    $PYTHON - "$work/runs/$1" "$device" "$OUT/tiny_$1.json" <<'PY'
import json, math, os, sys
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

run, device, out = sys.argv[1:]
if not os.path.isfile(f"{run}/eval.json"):
    sys.exit("nothing to read back: the tiny run wrote no eval.json")
acc = EventAccumulator(run, size_guidance={"scalars": 0})
acc.Reload()
losses = {t: [e.value for e in acc.Scalars(t)] for t in acc.Tags()["scalars"] if t.startswith("losses/")}
report = json.load(open(f"{run}/eval.json"))
summary = {"device": report["device"], "eval_games": len(report["returns"]), "eval_mean": report["mean"]}
summary |= {"losses": losses, "sps": [e.value for e in acc.Scalars("charts/SPS")]}
json.dump(summary, open(out, "w"), indent=2)
# explained variance is nan by definition when the returns do not vary; every loss must be finite
bad = [t for t, values in losses.items() if t != "losses/explained_variance" and not all(map(math.isfinite, values))]
if not report["device"].startswith(device):
    sys.exit(f"it trained on {report['device']}, not {device}...")
if not losses or bad:
    sys.exit(f"non-finite or missing losses: {bad or 'none logged'}")
print(f"device {report['device']}; losses finite; eval.json: {len(report['returns'])} games, mean {report['mean']}")
PY
}

export work device OUT PYTHON
export -f read_back
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
step environment 60 bash -c 'nvidia-smi 2>&1 | head -n 15; $PYTHON -c "$environment" "$REHEARSAL"'
if grep -q '^FAILED  environment' "$OUT/summary.txt"; then
    echo "summary: $OUT/summary.txt (the environment failed, so nothing else ran); its output: $OUT/gpu_check.log"
    exit 1
fi
for algo in ppo p3o; do
    i=$([ "$algo" = ppo ] && echo 0 || echo 1)
    step "tiny_$algo" "${limits[$i]}" bash -c "cd '$work' && $PYTHON '$root/${algo}_atari_envpool.py' --env-id '$ENV_ID' ${tiny[*]} --run-name $algo"
    step "read_back_$algo" 20 bash -c "read_back $algo"
done
cd "$root" || exit 1
step sps_thesis "${limits[2]}" $PYTHON benchmark/sps.py --env-id "$ENV_ID" "${thesis[@]}" --rounds 2 --out "$OUT/sps_thesis.json"
step sps_cleanrl "${limits[3]}" $PYTHON benchmark/sps.py --env-id "$ENV_ID" "${cleanrl[@]}" --rounds 2 --out "$OUT/sps_cleanrl.json"
echo "summary: $OUT/summary.txt; every step's output: $OUT/gpu_check.log"
! grep -q '^FAILED' "$OUT/summary.txt"
