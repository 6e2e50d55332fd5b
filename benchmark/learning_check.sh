#!/usr/bin/env bash
# Does it learn? Both scripts on the thesis's six games (or GAMES) on the CPU, 1M steps per (game, seed),
# each run evaluated on 10 full games at the end, a random policy measured by the same evaluation, then
# benchmark/results.py over every run committed under benchmark/results/<group>/runs/. A benchmark, not a test.
#
# MODE=thesis (default): the thesis's update regime (table 5.2: 256 steps per rollout, 8 epochs, learning
#   rate 1e-3, not annealed, as in the first million steps of its 20M-step runs) with the environments
#   scaled from 256 to 16 and the minibatches from 8 to 4 so that it fits 2 CPU cores.
# MODE=cleanrl: CleanRL's Atari sizes (8 envs x 128 steps, 4 x 4, learning rate 2.5e-4, annealed), where
#   P3O as specified does not learn (benchmark/README.md, "Does it learn?").
# MODE=ablation: the thesis regime's runs of P3O with GBAE switched off (p3o-gae) and with the value loss's beta set
#   to 1 (p3o-value-beta-one), benchmark/p3o_ablation.py, on the games P3O leads (Breakout, Seaquest, Qbert), seeds
#   1-5, into OUT=benchmark/results/ablation (benchmark/README.md, "Which piece of P3O carries its lead"); the
#   committed P3O and PPO runs of benchmark/results/learning_check are the other two arms, and no random policy runs.
#
# Order: seed 1 of every game, then seed 2, and so on. The two runs of a (game, seed) go side by side, one core
# each (OMP_NUM_THREADS=1), through benchmark/p3o_vs_ppo.sh (which gives P3O the thesis's alpha of the game and
# evaluates each run with benchmark/evaluate.py --run): 2.5-3 hours a pair on 2 cores of the machine seeds 1-3 ran
# on, 4-5.5 hours on a slower one (OUT/hours.md has every run's). Runs (checkpoints, logs) go under runs/<group>/
# in the current folder, as the scripts' do. After each pair its small outputs (event files, eval.json, the
# training log) are copied to OUT/runs/ to be committed and the tables remade; calling this again skips
# pairs whose outputs are there and resumes unfinished runs from their checkpoints. It commits nothing itself.
#
#   bash benchmark/learning_check.sh                                   # 6 games x seeds 1 2 3, thesis regime
#   GAMES=Breakout-v5 SEEDS="4 5" bash benchmark/learning_check.sh     # more seeds of one game
#   MODE=cleanrl GAMES=Breakout-v5 SEEDS=1 bash benchmark/learning_check.sh   # the CleanRL-size check
#   MODE=ablation bash benchmark/learning_check.sh                     # GBAE and the beta-weighted value loss off
# Knobs: MODE, GAMES, SEEDS, TOTAL_TIMESTEPS (1000000), OUT (benchmark/results/<group> of this repository),
# PYTHON (how to start python; default "uv run python", with --project when run from another folder).
set -euo pipefail

# the tables and figures of every committed run of the group (after each pair, so a session that ends
# between pairs leaves them up to date)
tables() {
    local out=$1 steps=$2 readme=()
    if [ "$mode" = ablation ]; then  # the four arms: the two ablations, and the committed P3O and PPO of their games
        # the four arms' table and curves, and each ablation against P3O and against PPO: Welch and permutation p
        local arms=("$out/runs" "$out/../learning_check/runs") four=(--games $games --ablations p3o_gae p3o_value_beta_one)
        $PYTHON "${base}benchmark/results.py" "${arms[@]}" --out "$out" "${four[@]}"
        $PYTHON "${base}benchmark/results.py" "${arms[@]}" --out "$out" "${four[@]}" --tag charts/episodic_return \
            --last 100 --table-name train_last100 --window-steps "$((steps / 5))" --no-figures
        $PYTHON "${base}benchmark/hours.py" "$out/runs" --out "$out"
        echo "tables: $out/table.md (the four arms' 10-game evaluation), $out/table_ablations.md (the tests),"
        echo "        $out/train_last100*.md (training); figures: $out/*.png (the four arms' training curves);"
        echo "        hours: $out/hours.md"
        return
    fi
    # the thesis regime's tables in a repository's benchmark/results/learning_check/ also rewrite the results
    # block of that repository's README (tests/test_results.py checks the README against the committed runs)
    if [ "$mode" = thesis ] &&
        grep -qF "<!-- begin: written by benchmark/results.py --readme" "$out/../../../README.md" 2>/dev/null; then
        readme=(--readme "$(cd "$out/../../.." && pwd)/README.md")
    fi
    $PYTHON "${base}benchmark/results.py" "$out/runs" --out "$out" "${readme[@]}"
    # the training return (last 100 games, and per fifth of training) and P3O's mean beta per fifth of training
    $PYTHON "${base}benchmark/results.py" "$out/runs" --out "$out" --tag charts/episodic_return --last 100 \
        --table-name train_last100 --window-steps "$((steps / 5))" --no-figures
    $PYTHON "${base}benchmark/results.py" "$out/runs" --out "$out" --tag p3o/beta_mean --table-name beta \
        --window-steps "$((steps / 5))" --no-figures
    $PYTHON "${base}benchmark/hours.py" "$out/runs" --out "$out"
    echo "tables: $out/table.md (10-game evaluation), $out/train_last100.md (last 100 training games),"
    echo "        $out/train_last100_windows.md (training return per fifth of training), $out/beta_windows.md"
    echo "figures: $out/*.png; hours of training: $out/hours.md; runs: $out/runs/"
}

# this repository, by the shortest path from the current folder
root=$(cd "$(dirname "$0")/.." && pwd)
if [ "$root" = "$PWD" ]; then
    base="" PYTHON=${PYTHON:-"uv run python"}
else
    base="$root/" PYTHON=${PYTHON:-"uv run --project $root python"}
fi
export PYTHON

main() {
    mode=${MODE:-thesis}
    # unset: the default; set but empty: refused by the sweep's check (not taken as the default)
    local steps=${TOTAL_TIMESTEPS-1000000} seeds=${SEEDS-1 2 3}
    local games=${GAMES-Breakout-v5 Freeway-v5 Seaquest-v5 Riverraid-v5 Qbert-v5 MsPacman-v5}
    local group sizes batch algos="ppo p3o" random=1
    local thesis="--num-envs 16 --num-steps 256 --num-minibatches 4 --update-epochs 8 --learning-rate 1e-3 --no-anneal-lr"
    case "$mode" in
        thesis)
            group=learning_check batch=$((16 * 256)) sizes=$thesis ;;
        ablation)
            group=ablation batch=$((16 * 256)) sizes=$thesis algos="p3o-gae p3o-value-beta-one" random=0
            seeds=${SEEDS-1 2 3 4 5} games=${GAMES-Breakout-v5 Seaquest-v5 Qbert-v5} ;;
        cleanrl)
            group=learning_check_cleanrl batch=$((8 * 128))
            sizes="--num-envs 8 --num-steps 128 --num-minibatches 4 --update-epochs 4 --learning-rate 2.5e-4" ;;
        *)
            echo "error: MODE must be thesis, cleanrl or ablation, got '$mode'." >&2
            exit 1 ;;
    esac
    # each algorithm's runs are named by the exp name it logs
    local exps="" algo
    for algo in $algos; do
        case "$algo" in
            ppo | p3o) exps+=" ${algo}_atari_envpool" ;;
            *) exps+=" ${algo//-/_}" ;;
        esac
    done
    # every knob (games, seeds, steps) is checked by the sweep, for the whole grid, before anything runs
    local sweep=(env GROUP="$group" TOTAL_TIMESTEPS="$steps" EXTRA_ARGS="$sizes" EVAL_EPISODES=10 WORKERS=2
        ALGOS="$algos" OMP_NUM_THREADS=1 bash "${base}benchmark/p3o_vs_ppo.sh")
    GAMES=$games SEEDS=$seeds DRY_RUN=1 "${sweep[@]}" >/dev/null
    local out=${OUT:-${base}benchmark/results/$group} ran=0 seed game algo
    # committed runs made for another number of steps would be skipped as done and tabulated with this one's
    # windows: name the first one instead (a run of S steps ends at the last whole batch, as eval.json says)
    $PYTHON - "$out/runs" "$((steps / batch * batch))" "$games" "$seeds" "$exps" <<'PY' || exit 1
import json, os, sys

folder, final, games, seeds = sys.argv[1], int(sys.argv[2]), sys.argv[3].split(), sys.argv[4].split()
for game in games:
    for seed in seeds:
        for exp in sys.argv[5].split():
            path = os.path.join(folder, f"{game}__{exp}__{seed}", "eval.json")
            try:
                made = json.load(open(path)).get("global_step") if os.path.isfile(path) else None
            except (ValueError, AttributeError):  # not JSON, or JSON but not an object
                sys.exit(f"error: {path} is not an eval.json these tools wrote; mend it or remove that run's folder.")
            if made is not None and made != final:
                sys.exit(
                    f"error: {os.path.dirname(path)} was trained for {made:,} steps, not the {final:,} that"
                    f" TOTAL_TIMESTEPS={os.environ.get('TOTAL_TIMESTEPS', '1000000')} gives; use another OUT."
                )
PY
    mkdir -p "$out/runs"
    for seed in $seeds; do
        for game in $games; do
            local done=1 exp
            for exp in $exps; do
                [ -f "$out/runs/${game}__${exp}__$seed/eval.json" ] || done=0
            done
            if [ "$done" = 1 ]; then
                echo "$game seed $seed: done (its outputs are in $out/runs/)"
                continue
            fi
            echo "$game seed $seed: ${algos// / and } -> runs/$group/ (logs in runs/$group/logs/)"
            if ! GAMES=$game SEEDS=$seed "${sweep[@]}"; then
                echo "error: a run of $game seed $seed failed; see runs/$group/logs/ (calling this again resumes it)." >&2
                exit 1
            fi
            local random_dir="runs/$group/${game}__random__$seed"
            if [ "$random" = 1 ] && [ ! -f "$random_dir/eval.json" ]; then
                $PYTHON "${base}benchmark/evaluate.py" --random --env-id "$game" --episodes 10 \
                    --seed "$((seed + 1000000))" --run-dir "$random_dir"
            fi
            # the small outputs (event files, eval.json, logs) are committed; checkpoints stay in runs/
            for exp in $exps $([ "$random" = 1 ] && echo random); do
                local run="${game}__${exp}__$seed"
                rm -rf "${out:?}/runs/$run"
                mkdir -p "$out/runs/$run"
                cp "runs/$group/$run"/events.out.tfevents.* "runs/$group/$run/eval.json" "$out/runs/$run/"
                [ "$exp" = random ] || cp "runs/$group/logs/$run.log" "$out/runs/$run/train.log"
            done
            echo "$game seed $seed: done; commit $out/ now"
            tables "$out" "$steps"
            ran=1
        done
    done
    if [ "$ran" = 0 ]; then tables "$out" "$steps"; fi
}

main "$@"
