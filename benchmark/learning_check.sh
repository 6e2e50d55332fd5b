#!/usr/bin/env bash
# Does it learn? Both scripts on Breakout-v5 on the CPU at CleanRL's Atari sizes (8 envs x 128 steps,
# 4 minibatches x 4 epochs, learning rate 2.5e-4, everything else the scripts' defaults), 1M steps,
# seed 1, each evaluated on 10 full games at the end; a random policy measured by the same evaluation;
# then benchmark/results.py on those runs. Runs one script after the other and resumes where a
# previous call stopped (checkpoints). A benchmark, not a test: about 1.5 hours on 2 cores.
#
#   bash benchmark/learning_check.sh            # TOTAL_TIMESTEPS=... and SEED=... override
set -euo pipefail

main() {
    cd "$(dirname "$0")/.."
    local steps=${TOTAL_TIMESTEPS:-1000000} seed=${SEED:-1}
    local group=learning_check out=benchmark/results/learning_check
    local sizes=(--num-envs 8 --num-steps 128 --num-minibatches 4 --update-epochs 4 --learning-rate 2.5e-4)
    for algo in ppo p3o; do
        local name="$group/Breakout-v5__${algo}_atari_envpool__$seed"
        local start=(--run-name "$name")
        if [ -f "runs/$name/checkpoint.pt" ]; then start=(--resume "runs/$name"); fi
        uv run python "${algo}_atari_envpool.py" --env-id Breakout-v5 --seed "$seed" "${sizes[@]}" \
            --total-timesteps "$steps" --eval-episodes 10 "${start[@]}"
    done
    uv run python benchmark/evaluate.py --random --env-id Breakout-v5 --episodes 10 --seed "$seed" \
        --run-dir "runs/$group/Breakout-v5__random__$seed"
    uv run python benchmark/results.py "runs/$group" --out "$out"
    uv run python benchmark/results.py "runs/$group" --out "$out" --tag charts/episodic_return --last 100 \
        --table-name train_last100 --no-figures
    echo "table: $out/table.md (10-game evaluation), $out/train_last100.md (last 100 training games)"
    echo "figures: $out/*.png"
}

main "$@"
