#!/usr/bin/env bash
# Does it learn? Both scripts on Breakout-v5 on the CPU, 1M steps per seed, each evaluated on 10 full
# games at the end, a random policy measured by the same evaluation, then benchmark/results.py over every
# run committed under benchmark/results/<group>/runs/. A benchmark, not a test.
#
# MODE=thesis (default): the thesis's update regime (table 5.2: 256 steps per rollout, 8 epochs, learning
#   rate 1e-3, not annealed, as in the first million steps of its 20M-step runs) with the environments
#   scaled from 256 to 16 and the minibatches from 8 to 4 so that it fits 2 CPU cores.
# MODE=cleanrl: CleanRL's Atari sizes (8 envs x 128 steps, 4 x 4, learning rate 2.5e-4, annealed), where
#   P3O as specified does not learn (benchmark/README.md, "Does it learn?").
#
# The two scripts of a seed run side by side, one core each (OMP_NUM_THREADS=1), about 3 hours a seed on
# 2 cores. Runs (checkpoints, logs) go under runs/<group>/ in the current folder, as the scripts' do.
# Calling it again skips seeds whose outputs are in OUT/runs/ and resumes unfinished runs from their
# checkpoints.
#
#   bash benchmark/learning_check.sh                          # seeds 1 2 3, thesis regime
#   SEEDS="4 5" bash benchmark/learning_check.sh              # more seeds
#   MODE=cleanrl SEEDS=1 bash benchmark/learning_check.sh     # the CleanRL-size check
# Knobs: MODE, SEEDS, TOTAL_TIMESTEPS (1000000), OUT (benchmark/results/<group> of this repository),
# PYTHON (how to start python; default "uv run python", with --project when run from another folder).
set -euo pipefail

# the tables and figures of every committed run of the group (after each seed, so a session that ends
# between seeds leaves them up to date)
tables() {
    local out=$1 steps=$2
    $PYTHON "${base}benchmark/results.py" "$out/runs" --out "$out"
    # the training return (last 100 games, and per fifth of training) and P3O's mean beta per fifth of training
    $PYTHON "${base}benchmark/results.py" "$out/runs" --out "$out" --tag charts/episodic_return --last 100 \
        --table-name train_last100 --window-steps "$((steps / 5))" --no-figures
    $PYTHON "${base}benchmark/results.py" "$out/runs" --out "$out" --tag p3o/beta_mean --table-name beta \
        --window-steps "$((steps / 5))" --no-figures
    echo "tables: $out/table.md (10-game evaluation), $out/train_last100.md (last 100 training games),"
    echo "        $out/train_last100_windows.md (training return per fifth of training), $out/beta_windows.md"
    echo "figures: $out/*.png; runs: $out/runs/"
}

# this repository, by the shortest path from the current folder
root=$(cd "$(dirname "$0")/.." && pwd)
if [ "$root" = "$PWD" ]; then
    base="" PYTHON=${PYTHON:-"uv run python"}
else
    base="$root/" PYTHON=${PYTHON:-"uv run --project $root python"}
fi

main() {
    local mode=${MODE:-thesis} steps=${TOTAL_TIMESTEPS:-1000000} seeds=${SEEDS:-1 2 3}
    local group sizes
    case "$mode" in
        thesis)
            group=learning_check
            sizes=(--num-envs 16 --num-steps 256 --num-minibatches 4 --update-epochs 8 --learning-rate 1e-3
                --no-anneal-lr) ;;
        cleanrl)
            group=learning_check_cleanrl
            sizes=(--num-envs 8 --num-steps 128 --num-minibatches 4 --update-epochs 4 --learning-rate 2.5e-4) ;;
        *)
            echo "error: MODE must be thesis or cleanrl, got '$mode'." >&2
            exit 1 ;;
    esac
    if ! [[ "$steps" =~ ^[1-9][0-9]*$ ]]; then
        echo "error: TOTAL_TIMESTEPS must be a positive whole number, got '$steps'." >&2
        exit 1
    fi
    for seed in $seeds; do
        if ! [[ "$seed" =~ ^[0-9]+$ ]]; then
            echo "error: SEEDS must be whole numbers, got '$seed'." >&2
            exit 1
        fi
    done
    local out=${OUT:-${base}benchmark/results/$group} logs=runs/$group/logs ran=0
    mkdir -p "$logs" "$out/runs"
    for seed in $seeds; do
        local pids=() algo
        if [ -f "$out/runs/Breakout-v5__ppo_atari_envpool__$seed/eval.json" ] &&
            [ -f "$out/runs/Breakout-v5__p3o_atari_envpool__$seed/eval.json" ]; then
            echo "seed $seed: done (its outputs are in $out/runs/)"
            continue
        fi
        for algo in ppo p3o; do
            local name="$group/Breakout-v5__${algo}_atari_envpool__$seed"
            echo "seed $seed: $algo -> runs/$name (log $logs/${algo}_$seed.log)"
            OMP_NUM_THREADS=1 $PYTHON "${base}${algo}_atari_envpool.py" --env-id Breakout-v5 --seed "$seed" \
                "${sizes[@]}" --total-timesteps "$steps" --eval-episodes 10 --run-name "$name" --auto-resume \
                >>"$logs/${algo}_$seed.log" 2>&1 &
            pids+=($!)
        done
        local failed=0 pid
        for pid in "${pids[@]}"; do wait "$pid" || failed=1; done
        if [ "$failed" = 1 ]; then
            echo "error: a run of seed $seed failed; see $logs/ (calling this again resumes it)." >&2
            exit 1
        fi
        local random_dir="runs/$group/Breakout-v5__random__$seed"
        if [ ! -f "$random_dir/eval.json" ]; then
            $PYTHON "${base}benchmark/evaluate.py" --random --env-id Breakout-v5 --episodes 10 \
                --seed "$((seed + 1000000))" --run-dir "$random_dir"
        fi
        # the small outputs (event files, eval.json, logs) are committed; checkpoints stay in runs/
        for algo in ppo p3o random; do
            local run="Breakout-v5__${algo}_atari_envpool__$seed"
            [ "$algo" = random ] && run="Breakout-v5__random__$seed"
            rm -rf "${out:?}/runs/$run"
            mkdir -p "$out/runs/$run"
            cp "runs/$group/$run"/events.out.tfevents.* "runs/$group/$run/eval.json" "$out/runs/$run/"
            [ "$algo" = random ] || cp "$logs/${algo}_$seed.log" "$out/runs/$run/train.log"
        done
        echo "seed $seed: done; commit $out/ now"
        tables "$out" "$steps"
        ran=1
    done
    if [ "$ran" = 0 ]; then tables "$out" "$steps"; fi
}

main "$@"
