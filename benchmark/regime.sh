#!/usr/bin/env bash
# Which part of the update regime does P3O need? Breakout-v5, 250k steps, seeds 1 and 2 (benchmark/README.md,
# "Which part of the regime decides it"). Five factors differ between CleanRL's Atari sizes, where P3O does
# not learn, and the thesis's regime scaled to 16 envs, where it does: learning rate, its annealing, update
# epochs, rollout length and number of envs. Each configuration below moves one of them from one end to
# the other; P3O runs in every configuration, PPO at the two ends and where P3O's result called for a PPO row
# to read it against (CleanRL's sizes with lr 1e-3, the thesis regime with 8 envs: P3O above PPO's end points).
#
# Each configuration is one call of benchmark/p3o_vs_ppo.sh (GROUP=regime/<config>, two runs at a time, one
# core each), so calling this again skips finished runs and resumes unfinished ones from their checkpoints.
# After each configuration the small outputs (event files, training log) are copied to
# OUT/runs/Breakout-v5__<algo>-<config>__<seed>/ to be committed, and the tables are remade.
#
#   bash benchmark/regime.sh                             # every configuration, seeds 1 2
#   CONFIGS="cleanrl_lr thesis_lr" bash benchmark/regime.sh
# Knobs: CONFIGS, SEEDS (1 2), TOTAL_TIMESTEPS (250000), OUT (benchmark/results/regime of this repository),
# PYTHON (as the sweep's).
set -euo pipefail

root=$(cd "$(dirname "$0")/.." && pwd)
if [ "$root" = "$PWD" ]; then base=""; else base="$root/"; fi
PYTHON=${PYTHON:-"uv run --project $root python"}
export PYTHON

# config: which scripts, and the five factors (everything else the scripts' defaults; annealing is on by default)
cleanrl="--num-envs 8 --num-steps 128 --update-epochs 4 --learning-rate 2.5e-4 --num-minibatches 4"
thesis="--num-envs 16 --num-steps 256 --update-epochs 8 --learning-rate 1e-3 --num-minibatches 4 --no-anneal-lr"
declare -A ALGOS_OF=([cleanrl]="ppo p3o" [thesis]="ppo p3o" [cleanrl_lr]="ppo p3o" [thesis_envs]="ppo p3o")
declare -A FLAGS=(
    [cleanrl]="$cleanrl"
    [cleanrl_lr]="--num-envs 8 --num-steps 128 --update-epochs 4 --learning-rate 1e-3 --num-minibatches 4"
    [cleanrl_noanneal]="$cleanrl --no-anneal-lr"
    [cleanrl_epochs]="--num-envs 8 --num-steps 128 --update-epochs 8 --learning-rate 2.5e-4 --num-minibatches 4"
    [cleanrl_steps]="--num-envs 8 --num-steps 256 --update-epochs 4 --learning-rate 2.5e-4 --num-minibatches 4"
    [cleanrl_envs]="--num-envs 16 --num-steps 128 --update-epochs 4 --learning-rate 2.5e-4 --num-minibatches 4"
    [thesis]="$thesis"
    [thesis_lr]="--num-envs 16 --num-steps 256 --update-epochs 8 --learning-rate 2.5e-4 --num-minibatches 4 --no-anneal-lr"
    [thesis_anneal]="--num-envs 16 --num-steps 256 --update-epochs 8 --learning-rate 1e-3 --num-minibatches 4"
    [thesis_epochs]="--num-envs 16 --num-steps 256 --update-epochs 4 --learning-rate 1e-3 --num-minibatches 4 --no-anneal-lr"
    [thesis_steps]="--num-envs 16 --num-steps 128 --update-epochs 8 --learning-rate 1e-3 --num-minibatches 4 --no-anneal-lr"
    [thesis_envs]="--num-envs 8 --num-steps 256 --update-epochs 8 --learning-rate 1e-3 --num-minibatches 4 --no-anneal-lr"
)
ORDER="cleanrl cleanrl_lr cleanrl_noanneal cleanrl_epochs cleanrl_steps cleanrl_envs
       thesis thesis_lr thesis_anneal thesis_epochs thesis_steps thesis_envs"
# unset: the default; set but empty: refused (not taken as the default)
CONFIGS=${CONFIGS-$ORDER}
SEEDS=${SEEDS-"1 2"}
TOTAL_TIMESTEPS=${TOTAL_TIMESTEPS:-250000}
OUT=${OUT:-${base}benchmark/results/regime}
for knob in CONFIGS SEEDS; do
    if [ -z "${!knob// /}" ]; then
        echo "error: $knob is empty." >&2
        exit 1
    fi
done

for config in $CONFIGS; do
    if [ -z "${FLAGS[$config]+set}" ]; then
        echo "error: unknown configuration '$config'; known: $(echo $ORDER)." >&2
        exit 1
    fi
done

# the tables of every copied run: training return, mean beta and the share of beta above 0.5, per 50k steps
tables() {
    local regex='^(?P<env>[^_]+)__(?P<algo>.+)__[0-9]+$'
    $PYTHON "${base}benchmark/results.py" "$OUT/runs" --out "$OUT" --group-regex "$regex" --no-figures \
        --tag charts/episodic_return --table-name return --window-steps 50000
    $PYTHON "${base}benchmark/results.py" "$OUT/runs" --out "$OUT" --group-regex "$regex" --no-figures \
        --tag p3o/beta_mean --table-name beta_mean --window-steps 50000
    $PYTHON "${base}benchmark/results.py" "$OUT/runs" --out "$OUT" --group-regex "$regex" --no-figures \
        --tag p3o/beta --above 0.5 --table-name beta_above_half --window-steps 50000
    $PYTHON "${base}benchmark/hours.py" "$OUT/runs" --out "$OUT" --group-regex "$regex"
}

mkdir -p "$OUT/runs"
for config in $CONFIGS; do
    algos=${ALGOS_OF[$config]:-p3o}
    echo "== $config ($algos): ${FLAGS[$config]}"
    GAMES=Breakout-v5 SEEDS=$SEEDS ALGOS=$algos TOTAL_TIMESTEPS=$TOTAL_TIMESTEPS WORKERS=2 GROUP=regime/$config \
        EXTRA_ARGS="${FLAGS[$config]}" EVAL_EPISODES=0 OMP_NUM_THREADS=1 bash "${base}benchmark/p3o_vs_ppo.sh"
    for seed in $SEEDS; do
        for algo in $algos; do
            run=runs/regime/$config/Breakout-v5__${algo}_atari_envpool__$seed
            copy=$OUT/runs/Breakout-v5__${algo}-${config}__$seed
            rm -rf "$copy"
            mkdir -p "$copy"
            cp "$run"/events.out.tfevents.* "$copy/"
            cp "runs/regime/$config/logs/Breakout-v5__${algo}_atari_envpool__$seed.log" "$copy/train.log"
        done
    done
    tables
done
