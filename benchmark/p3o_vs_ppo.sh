#!/usr/bin/env bash
# The thesis's grid: 6 games x 10 seeds x {PPO, P3O}, 20M steps each (thesis section 5.1), locally or
# as one Slurm job array. Runs go under runs/ in the current folder, as the training scripts' do.
# Every run has a fixed name, runs/$GROUP/{env_id}__{exp_name}__{seed}, and is started with --auto-resume; once it
# has trained, benchmark/evaluate.py --run plays its evaluation (EVAL_EPISODES games) into its folder. Running the
# sweep again leaves out the runs whose checkpoint says they finished and whose eval.json is there (nothing is
# started or submitted for them), continues unfinished ones from their checkpoints and evaluates trained ones that
# lack their evaluation; a requeued Slurm task does the same.
#
#   bash benchmark/p3o_vs_ppo.sh                        # local: WORKERS runs at a time, a log per run
#   SLURM=1 bash benchmark/p3o_vs_ppo.sh                # one sbatch --array job, one task per run
#   DRY_RUN=1 bash benchmark/p3o_vs_ppo.sh              # print the commands (and the sbatch script)
#
# Knobs (environment variables):
#   GAMES            envpool ids (default: the thesis's six games)
#   SEEDS            seeds (default: 1 2 ... 10)
#   ALGOS            which scripts: ppo, p3o or both (default: "ppo p3o"), or a P3O ablation of
#                    benchmark/p3o_ablation.py: p3o-gae, p3o-value-beta-one, p3o-batch-minmax (runs named p3o_gae, ...)
#   TOTAL_TIMESTEPS  steps per run (default: 20000000)
#   EVAL_EPISODES    games each run's evaluation plays after training (default: 10; 0: no evaluation)
#   EXTRA_ARGS       more flags for both scripts, e.g. "--num-envs 64", split at spaces (no quotes); not the
#                    flags the sweep sets per run (--env-id, --seed, --total-timesteps, --run-name, --exp-name,
#                    --ewma-alpha, --resume, --auto-resume): they would make runs differ from their names
#   DRY_RUN, SLURM   1 (or true) or 0 (or false); GAMES, SEEDS and ALGOS, when set, must be non-empty and
#                    name each entry once. Runs already in runs/$GROUP made with other settings are named and
#                    refused (give another GROUP), never skipped as done or resumed.
#   WORKERS          runs at a time: local processes, or the array's % limit under Slurm (default: 1)
#   OMP_NUM_THREADS  torch's threads per run (default: the cores / WORKERS locally when WORKERS > 1, the task's
#                    --cpus-per-task under Slurm): runs that each take every core slow one another down
#   GROUP            folder under runs/ (default: p3o_vs_ppo)
#   PYTHON           how to start python (default: "uv run python", with --project when run elsewhere)
#   SBATCH_ARGS      extra sbatch options (default: "--gres=gpu:1 --cpus-per-task=16 --time=24:00:00")
#   SIGNAL_SECONDS   Slurm signals SIGTERM this long before the time limit (default: 300)
set -euo pipefail

# unset: the default; set but empty: refused below (an empty SEEDS is a mistake, not "every seed")
GAMES=${GAMES-"Breakout-v5 Freeway-v5 Seaquest-v5 Riverraid-v5 Qbert-v5 MsPacman-v5"}
SEEDS=${SEEDS-"1 2 3 4 5 6 7 8 9 10"}
ALGOS=${ALGOS-"ppo p3o"}
TOTAL_TIMESTEPS=${TOTAL_TIMESTEPS:-20000000}
EVAL_EPISODES=${EVAL_EPISODES:-10}
EXTRA_ARGS=${EXTRA_ARGS:-}
WORKERS=${WORKERS:-1}
GROUP=${GROUP:-p3o_vs_ppo}
# the training scripts, by the shortest path from here
root=$(cd "$(dirname "$0")/.." && pwd)
if [ "$root" = "$PWD" ]; then scripts=""; else scripts="$root/"; fi
if [ "$root" = "$PWD" ]; then PYTHON=${PYTHON:-"uv run python"}; else PYTHON=${PYTHON:-"uv run --project $root python"}; fi
SBATCH_ARGS=${SBATCH_ARGS-"--gres=gpu:1 --cpus-per-task=16 --time=24:00:00"}
SIGNAL_SECONDS=${SIGNAL_SECONDS:-300}

# the thesis's EWMA alpha per game (section 5.1.2): 0.75 for MsPacman, 0.6 for Riverraid, 0.9 otherwise
alpha_for() {
    case "$1" in
        MsPacman-*) echo 0.75 ;;
        Riverraid-*) echo 0.6 ;;
        *) echo 0.9 ;;
    esac
}

# the knobs, before anything starts or is submitted: one sentence and exit status 1 for the first bad one
knob_error() { echo "error: $1" >&2; exit 1; }
[ -n "${GAMES// /}" ] || knob_error "GAMES is empty."
[ -n "${SEEDS// /}" ] || knob_error "SEEDS is empty."
[ -n "${ALGOS// /}" ] || knob_error "ALGOS is empty."
# a seed is a number written one way (`seq -w`'s 01 would be a second run of seed 1, in a folder of its own)
for seed in $SEEDS; do
    [[ "$seed" =~ ^(0|[1-9][0-9]*)$ ]] || knob_error "SEEDS must be whole numbers without leading zeros, got '$seed'."
done
for knob in GAMES SEEDS ALGOS; do  # a repeated entry would start the same run twice
    repeated=$(tr -s ' ' '\n' <<<"${!knob}" | sed '/^$/d' | sort | uniq -d | head -n 1)
    [ -z "$repeated" ] || knob_error "$knob names '$repeated' twice."
done
# 1/true/yes or 0/false/no (or unset); anything else is refused, never taken as 0 (a dry run that trains)
for knob in DRY_RUN SLURM; do
    case "${!knob:-0}" in
        1 | true | yes) printf -v "$knob" 1 ;;
        0 | false | no) printf -v "$knob" 0 ;;
        *) knob_error "$knob must be 1 (or true) or 0 (or false), got '${!knob}'." ;;
    esac
done
# the runs are started by splitting the command at spaces, locally and under Slurm alike: no quoting
case "$EXTRA_ARGS$GROUP" in
    *[\'\"\\]*) knob_error "EXTRA_ARGS and GROUP are split at spaces and cannot hold quotes or backslashes." ;;
esac
[[ "$GROUP" =~ ^[^[:space:]]+$ ]] || knob_error "GROUP must be one folder name without spaces, got '$GROUP'."
[[ "$TOTAL_TIMESTEPS" =~ ^[1-9][0-9]*$ ]] || knob_error "TOTAL_TIMESTEPS must be a positive whole number, got '$TOTAL_TIMESTEPS'."
[[ "$WORKERS" =~ ^[1-9][0-9]*$ ]] || knob_error "WORKERS must be a whole number of at least 1, got '$WORKERS'."
[[ "$SIGNAL_SECONDS" =~ ^[0-9]+$ ]] || knob_error "SIGNAL_SECONDS must be a whole number, got '$SIGNAL_SECONDS'."
[[ "$EVAL_EPISODES" =~ ^[0-9]+$ ]] || knob_error "EVAL_EPISODES must be a whole number, got '$EVAL_EPISODES'."
for algo in $ALGOS; do
    case "$algo" in
        ppo | p3o | p3o-gae | p3o-value-beta-one | p3o-batch-minmax) ;;
        *) knob_error "ALGOS must be ppo, p3o or P3O ablations (p3o-gae, p3o-value-beta-one, p3o-batch-minmax), got '$algo'." ;;
    esac
done

commands=()
names=()
evals=()
for game in $GAMES; do
    for seed in $SEEDS; do
        for algo in $ALGOS; do
            case "$algo" in  # the script, and the exp name it logs (the run's name)
                ppo | p3o) script="${scripts}${algo}_atari_envpool.py" exp="${algo}_atari_envpool" ;;
                *) script="${scripts}benchmark/p3o_ablation.py ${algo#p3o-}" exp="p3o_${algo#p3o-}" exp=${exp//-/_} ;;
            esac
            name="$GROUP/${game}__${exp}__${seed}"
            cmd="$PYTHON $script --env-id $game --seed $seed --total-timesteps $TOTAL_TIMESTEPS"
            if [ "$algo" != ppo ]; then cmd+=" --ewma-alpha $(alpha_for "$game")"; fi
            cmd+=" --run-name $name --auto-resume"
            if [ -n "$EXTRA_ARGS" ]; then cmd+=" $EXTRA_ARGS"; fi
            commands+=("$cmd")
            names+=("$name")
            if [ "$EVAL_EPISODES" -gt 0 ]; then
                evals+=("$PYTHON ${scripts}benchmark/evaluate.py --run runs/$name --episodes $EVAL_EPISODES")
            else
                evals+=("")
            fi
        done
    done
done

logs="runs/$GROUP/logs"

# every command's arguments, checked by the training script's own parser and checks (games, seed ranges,
# EXTRA_ARGS, run names), so that a bad grid stops here instead of in its first run; EXTRA_ARGS may not change
# what names a run (its game, seed, steps, folder, alpha); and a run already in runs/$GROUP must have been made
# with the same experiment arguments, or the sweep would skip or resume a different experiment
$PYTHON - "$root" "$EXTRA_ARGS" "${commands[@]}" <<'PY' || exit 1
import contextlib, importlib, io, os, shlex, sys

sys.path.insert(0, sys.argv[1])
import tyro

extra = sys.argv[2].split()
owner = {"env_id": "GAMES", "seed": "SEEDS", "total_timesteps": "TOTAL_TIMESTEPS", "run_name": "GROUP"}
owner |= {"exp_name": "the run names", "ewma_alpha": "the thesis's alpha per game"}
owner |= {"auto_resume": "every run", "resume": "every run"}
for command in sys.argv[3:]:
    words = shlex.split(command)
    at = next(i for i, w in enumerate(words) if w.endswith(("_atari_envpool.py", "p3o_ablation.py")))
    ablation = words[at].endswith("p3o_ablation.py")  # then the change comes first, and the script is P3O's
    script = importlib.import_module("p3o_atari_envpool" if ablation else words[at].rsplit("/", 1)[-1][:-3])
    at += ablation
    base = words[at + 1 : len(words) - len(extra)]
    # parsed as resumes, which Args leaves unchecked (the check comes below, after the sweep's own knobs): the
    # command without EXTRA_ARGS need not be a valid run by itself (a short TOTAL_TIMESTEPS is one once EXTRA_ARGS
    # shrinks the batch); a --resume in EXTRA_ARGS comes later and wins
    unchecked = ["--resume", "(unchecked)"]
    try:  # tyro's own message is a box of many lines: one sentence instead
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            args = tyro.cli(script.Args, args=unchecked + base + extra, prog=words[at], console_outputs=False)
    except SystemExit:
        sys.exit(f"error: EXTRA_ARGS '{sys.argv[2]}' holds a flag or value that {os.path.basename(words[at])} does not take (see its --help).")
    given = vars(tyro.cli(script.Args, args=unchecked + base, prog=words[at]))
    for name, knob in owner.items():
        if name in given and given[name] != getattr(args, name):
            flag = "--" + name.replace("_", "-")
            sys.exit(f"error: EXTRA_ARGS sets {flag} ({getattr(args, name)}), which the sweep sets for {knob}.")
    made = {"resume": None} | ({"exp_name": "p3o_" + words[at].replace("-", "_")} if ablation else {})  # as the tool
    args = script.Args(**{n: getattr(args, n) for n in script.INIT} | made)  # now checked, as a run's
    path = os.path.join("runs", args.run_name, "checkpoint.pt")
    if os.path.isfile(path):
        try:
            saved = script.torch.load(path, map_location="cpu", weights_only=True, mmap=True)["args"]
        except Exception:  # unreadable: the run itself says why when it starts
            continue
        differ = [n for n in script.INIT if n not in script.RUN_FLAGS and n in saved and saved[n] != getattr(args, n)]
        if differ:
            was = ", ".join(f"--{n.replace('_', '-')} {saved[n]} (now {getattr(args, n)})" for n in differ)
            sys.exit(
                f"error: runs/{args.run_name} was made with {was}; give this sweep another GROUP, or remove that run."
            )
PY

# leave out finished runs (their checkpoint says so) that are evaluated (their eval.json is there, or EVAL_EPISODES
# is 0); one python call reads every checkpoint that exists
if [ -d "runs/$GROUP" ]; then
    # shellcheck disable=SC2086
    finished=$($PYTHON - "$EVAL_EPISODES" "${names[@]}" <<'PY'
import os, sys, torch
for name in sys.argv[2:]:
    path = os.path.join("runs", name, "checkpoint.pt")
    evaluated = sys.argv[1] == "0" or os.path.isfile(os.path.join("runs", name, "eval.json"))
    try:
        if evaluated and torch.load(path, map_location="cpu", weights_only=True, mmap=True)["finished"]:
            print(name)
    except Exception:  # missing or unreadable: not known to be finished, so it runs (and the script says why not)
        pass
PY
)
    todo_commands=()
    todo_names=()
    todo_evals=()
    for i in "${!names[@]}"; do
        if ! grep -qxF "${names[$i]}" <<<"$finished"; then
            todo_commands+=("${commands[$i]}")
            todo_names+=("${names[$i]}")
            todo_evals+=("${evals[$i]}")
        fi
    done
    if [ "${#todo_names[@]}" -lt "${#names[@]}" ]; then
        echo "$((${#names[@]} - ${#todo_names[@]})) of ${#names[@]} runs already finished; left out"
    fi
    if [ "${#todo_names[@]}" = 0 ]; then
        echo "nothing to run: every run in runs/$GROUP has finished"
        exit 0
    fi
    commands=("${todo_commands[@]}")
    names=("${todo_names[@]}")
    evals=("${todo_evals[@]}")
fi

sbatch_script() {
    cat <<SBATCH
#!/usr/bin/env bash
#SBATCH --job-name=$GROUP
#SBATCH --array=0-$((${#commands[@]} - 1))%$WORKERS
#SBATCH --requeue
#SBATCH --signal=B:TERM@$SIGNAL_SECONDS
#SBATCH --output=$PWD/$logs/slurm-%A_%a.log
#SBATCH --open-mode=append
set -uo pipefail
cd "$PWD"
commands=(
$(printf '    %q\n' "${commands[@]}")
)
evals=(
$(printf '    %q\n' "${evals[@]}")
)
echo "task \$SLURM_ARRAY_TASK_ID (restart \${SLURM_RESTART_COUNT:-0}) on \$(hostname): \${commands[\$SLURM_ARRAY_TASK_ID]}"
# torch's threads: the task's CPUs, not the node's (tasks sharing a node would otherwise slow one another down)
export OMP_NUM_THREADS=\${OMP_NUM_THREADS:-\${SLURM_CPUS_PER_TASK:-1}}
# SIGTERM (preemption, or SIGNAL_SECONDS before the time limit) goes to the training script, which writes a
# checkpoint and exits (or to the evaluation, which writes nothing); the task then requeues itself and continues
# with --auto-resume (or evaluates again).
run() {
    bash -c "exec \$1" &
    child=\$!
    wait \$child
}
trap 'kill -TERM \$child; wait \$child; scontrol requeue "\${SLURM_ARRAY_JOB_ID}_\${SLURM_ARRAY_TASK_ID}"; exit 0' TERM
run "\${commands[\$SLURM_ARRAY_TASK_ID]}" || exit
if [ -n "\${evals[\$SLURM_ARRAY_TASK_ID]}" ]; then run "\${evals[\$SLURM_ARRAY_TASK_ID]}"; fi
SBATCH
}

if [ "$DRY_RUN" = 1 ]; then
    printf '%s\n' "${commands[@]}"
    [ "$EVAL_EPISODES" = 0 ] || echo "# then, for each run: $PYTHON ${scripts}benchmark/evaluate.py --run runs/RUN --episodes $EVAL_EPISODES"
    if [ "$SLURM" = 1 ]; then
        echo "# sbatch $SBATCH_ARGS runs/$GROUP/slurm/$GROUP.sbatch, with:"
        sbatch_script
    fi
    exit 0
fi

mkdir -p "$logs"
if [ "$SLURM" = 1 ]; then
    mkdir -p "runs/$GROUP/slurm"
    sbatch_script > "runs/$GROUP/slurm/$GROUP.sbatch"
    # shellcheck disable=SC2086
    sbatch $SBATCH_ARGS "runs/$GROUP/slurm/$GROUP.sbatch"
    exit 0
fi

# local mode: at most WORKERS runs at a time, each appending to its own log. With torch's default of a thread per
# core, runs side by side slow one another down (two 4-environment runs on 2 cores: 55 steps/s each, 300 with one
# thread each; benchmark/README.md), so each gets its share of the cores unless OMP_NUM_THREADS says otherwise.
if [ "$WORKERS" -gt 1 ] && [ -z "${OMP_NUM_THREADS:-}" ]; then
    threads=$(($(nproc) / WORKERS))
    export OMP_NUM_THREADS=$((threads > 0 ? threads : 1))
fi
failed=0
for i in "${!commands[@]}"; do
    log="$logs/$(basename "${names[$i]}").log"
    printf '%s\0%s\0%s\0' "${commands[$i]}" "$log" "${evals[$i]:-true}"
done | xargs -0 -n 3 -P "$WORKERS" bash -c 'echo "start: $0"; if $0 >> "$1" 2>&1 && $2 >> "$1" 2>&1; then echo "done:  $0"; else echo "FAILED (see $1): $0"; exit 1; fi' || failed=1
echo "logs in $logs/, runs in runs/$GROUP/"
exit $failed
